//! `/metrics` of a real server in the Prometheus text format, counting what happened.

mod common;

use std::collections::HashMap;

use common::{runtime, Server};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Batch, Client, Record};

/// `name{labels} value` lines into a map (comments skipped).
fn parse(text: &str) -> HashMap<String, f64> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let (name, value) = l.rsplit_once(' ').expect("name and value");
            (name.to_owned(), value.parse().expect("a number"))
        })
        .collect()
}

#[test]
fn metrics_count_ingest_rejections_frames_and_resolves() {
    let server = Server::start(&[]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    rt.block_on(async {
        client
            .create_frame(&CreateFrame::new("m", 8, 8))
            .await
            .unwrap();
        for seq in 0..3 {
            let records = vec![Record::new(1, 2, [1.0; 3]); 10];
            client
                .post_batch(&Batch::new("m", 1, seq, records).unwrap())
                .await
                .unwrap();
        }
        // A duplicate and a refused batch.
        let records = vec![Record::new(1, 2, [1.0; 3]); 10];
        client
            .post_batch(&Batch::new("m", 1, 0, records).unwrap())
            .await
            .unwrap();
        let bad = vec![Record::new(9, 2, [1.0; 3])];
        assert!(client
            .post_batch(&Batch::new("m", 1, 3, bad).unwrap())
            .await
            .is_err());
        client.image("m", &ImageQuery::default()).await.unwrap();
        client.image("m", &ImageQuery::default()).await.unwrap();
    });
    let response = reqwest::blocking::get(format!("{}/metrics", server.url)).unwrap();
    assert_eq!(response.status(), 200);
    let content_type = response.headers()["content-type"]
        .to_str()
        .unwrap()
        .to_owned();
    assert!(content_type.starts_with("text/plain"), "{content_type}");
    let text = response.text().unwrap();
    let m = parse(&text);
    let get = |k: &str| *m.get(k).unwrap_or_else(|| panic!("no {k} in:\n{text}"));
    assert_eq!(get("splatd_samples_ingested_total"), 30.0);
    assert_eq!(get("splatd_batches_ingested_total"), 3.0);
    assert_eq!(get("splatd_batches_duplicate_total"), 1.0);
    assert_eq!(
        get("splatd_batches_rejected_total{reason=\"samples\"}"),
        1.0
    );
    assert_eq!(get("splatd_samples_rejected_total"), 1.0);
    assert_eq!(get("splatd_frames"), 1.0);
    assert_eq!(get("splatd_resolve_seconds_count"), 2.0);
    assert!(get("splatd_resolve_seconds_bucket{le=\"+Inf\"}") == 2.0);
    assert!(get("splatd_ingest_bytes_total") > 5.0 * 200.0);
    assert!(
        text.contains("# TYPE splatd_resolve_seconds histogram"),
        "{text}"
    );
    // The frame's convergence: 30 samples, all in pixel (1, 2) of 64.
    let frame = |name: &str| get(&format!("{name}{{frame=\"m\"}}"));
    assert_eq!(frame("splatd_frame_spp_min"), 0.0);
    assert_eq!(frame("splatd_frame_spp_mean"), 30.0 / 64.0);
    assert_eq!(frame("splatd_frame_spp_max"), 30.0);
    assert_eq!(
        frame("splatd_frame_converged"),
        0.0,
        "63 pixels have no samples"
    );
    assert_eq!(frame("splatd_frame_converged_below"), 0.01);
    // 30 identical samples of one pixel: fully supported, nothing removed.
    assert_eq!(frame("splatd_frame_removed_fraction"), 0.0);
    assert!(frame("splatd_frame_samples_per_second") >= 0.0);
    assert!(
        text.contains("# TYPE splatd_frame_removed_fraction gauge"),
        "{text}"
    );
}
