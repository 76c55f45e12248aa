//! `GET /v1/frames/{id}/need` of a real server: the EXR form, read back by OpenEXR's own Python
//! bindings (an independent reader), holds the JSON form's tiles, one pixel each.

use crate::common::{read_exr_with_python, runtime, Server};
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Client, Record};
use splatd_scenes::synth::FireflyScene;

#[test]
fn the_need_map_as_exr_holds_the_json_maps_tiles() {
    let server = Server::start(&[]);
    let (w, h) = (40u32, 20u32);
    let scene = FireflyScene::new(w, h, 5);
    let client = Client::new(&server.url).unwrap();
    let (json, exr) = runtime().block_on(async {
        client
            .create_frame(&CreateFrame::new("n", w, h))
            .await
            .unwrap();
        for pass in 0..8 {
            let records = scene
                .pass(pass)
                .map(|(x, y, rgb)| Record::new(x, y, rgb))
                .collect();
            client
                .post_batch(&Batch::new("n", 1, pass, records).unwrap())
                .await
                .unwrap();
        }
        let json = client.need("n", Some(8)).await.unwrap();
        let exr = reqwest::get(format!("{}/v1/frames/n/need?tile=8&format=exr", server.url))
            .await
            .unwrap();
        assert_eq!(exr.status(), 200);
        assert_eq!(exr.headers()["content-type"], "image/x-exr");
        (json, exr.bytes().await.unwrap())
    });
    assert_eq!((json.tile, json.tiles_x, json.tiles_y), (8, 5, 3));
    assert_eq!(json.samples, u64::from(w * h) * 8);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("need.exr");
    std::fs::write(&path, &exr).unwrap();
    let (width, height, channels) = read_exr_with_python(&path);
    assert_eq!((width, height), (5, 3), "one pixel per tile");
    let names: Vec<&str> = channels.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names,
        ["deficit.Y", "need.Y", "removed.Y", "spp.Y", "spp_min.Y"]
    );
    let channel = |name: &str| &channels.iter().find(|(n, _)| n == name).unwrap().1;
    // 32-bit floats of the JSON's numbers (to within their last bit).
    let same = |exr: &[f64], json: &[f64]| {
        exr.len() == json.len()
            && exr
                .iter()
                .zip(json)
                .all(|(a, b)| (a - b).abs() <= 1e-6 * b.abs())
    };
    assert!(same(channel("need.Y"), &json.need), "{channels:?}");
    assert!(same(channel("removed.Y"), &json.removed_fraction));
    assert!(same(channel("deficit.Y"), &json.deficit_fraction));
    // The last row of tiles is 4 pixels high: still 8 spp.
    assert_eq!(channel("spp.Y"), &vec![8.0; 15]);
    assert_eq!(channel("spp_min.Y"), &vec![8.0; 15]);
    assert!(json.need.iter().all(|&n| n > 0.0));
}
