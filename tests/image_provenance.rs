//! A served `image.exr` says in its header how it was made: software and version, the estimator
//! and its parameters (the frame's, or the request's overrides), and the sample counts, read back
//! with OpenEXR's own Python package (and `oiiotool --info -v` where OpenImageIO is installed).

use std::process::Command;

use crate::common::{read_exr_attributes_with_python, runtime, Server};
use serde_json::json;
use splatd_proto::api::{CascadeParams, CreateFrame, ImageQuery, ResolveParams, Variant};
use splatd_proto::{Batch, Client, Record};

const W: u32 = 5;
const H: u32 = 3;

#[test]
fn resolved_exrs_carry_their_provenance() {
    let server = Server::start(&[]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    let luminance = [0.25, 0.5, 0.25];
    let create = CreateFrame {
        cascades: CascadeParams {
            base: 4.0,
            cascades: 5,
            lowest_scale: 0.25,
            luminance,
        },
        resolve: ResolveParams {
            variant: Variant::Shader,
            kappa: 2.5,
            kappa_min: 1.0,
            kappa_exponent: 0.25,
        },
        ..CreateFrame::new("prov", W, H)
    };
    rt.block_on(client.create_or_get(&create)).unwrap();
    // One sample everywhere, then three more at (0, 0) and one more at (4, 2).
    let mut spp = vec![0u64; (W * H) as usize];
    let mut every = Vec::new();
    for i in 0..W * H {
        every.push(Record::new(i % W, i / W, [0.5, 0.25, 0.125]));
    }
    let extra = vec![
        Record::new(0, 0, [1.0, 1.0, 1.0]),
        Record::new(0, 0, [90.0, 2.0, 1.0]),
        Record::new(0, 0, [0.0, 0.0, 0.0]),
        Record::new(4, 2, [3.0, 3.0, 3.0]),
    ];
    for (seq, records) in [every, extra].into_iter().enumerate() {
        for r in &records {
            spp[(r.y * W + r.x) as usize] += 1;
        }
        let batch = Batch::new("prov", 1, seq as u64, records).unwrap();
        rt.block_on(client.post_batch(&batch)).unwrap();
    }
    let samples: u64 = spp.iter().sum();
    let (min, max) = (*spp.iter().min().unwrap(), *spp.iter().max().unwrap());
    assert_eq!((samples, min, max), (19, 1, 4));

    let dir = tempfile::tempdir().unwrap();
    let fetch = |query: &ImageQuery, name: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, rt.block_on(client.image("prov", query)).unwrap()).unwrap();
        path
    };
    let as_f32 = |v: f64| f64::from(v as f32);
    let counts = json!({
        "splatd:samples": samples as f64,
        "splatd:sppMin": min as f64,
        "splatd:sppMax": max as f64,
        "splatd:sppMean": samples as f64 / f64::from(W * H),
    });
    let expect = |estimator: &str, kappa: f64| {
        let mut want = json!({
            "software": format!("splatd {}", env!("CARGO_PKG_VERSION")),
            "splatd:estimator": estimator,
            "splatd:kappa": kappa,
            "splatd:kappaMin": 1.0,
            "splatd:kappaExponent": 0.25,
            "splatd:cascadeBase": 4.0,
            "splatd:cascades": 5,
            "splatd:cascadeLowestScale": 0.25,
            "splatd:luminance": luminance.map(as_f32),
        });
        want.as_object_mut()
            .unwrap()
            .extend(counts.as_object().unwrap().clone());
        want
    };

    // The frame's own parameters.
    let path = fetch(&ImageQuery::default(), "frame.exr");
    let got = read_exr_attributes_with_python(&path);
    assert_eq!(got, expect("shader", 2.5), "{}", path.display());
    // A request's overrides are what the image was resolved with.
    let query = ImageQuery {
        variant: Some(Variant::Off),
        kappa: Some(3.0),
        ..ImageQuery::default()
    };
    let path = fetch(&query, "off.exr");
    assert_eq!(read_exr_attributes_with_python(&path), expect("off", 3.0));
    // The counts agree with what the server reports.
    let info = rt.block_on(client.frame_info("prov")).unwrap();
    assert_eq!(
        (info.samples, info.spp_min, info.spp_max),
        (samples, min, max)
    );

    // OpenImageIO, when the machine has it, lists the same attributes.
    match Command::new("oiiotool")
        .args(["--info", "-v"])
        .arg(&path)
        .output()
    {
        Ok(out) => {
            assert!(out.status.success(), "oiiotool --info -v failed");
            let text = String::from_utf8_lossy(&out.stdout);
            for needle in [
                "splatd:estimator: \"off\"",
                "splatd:kappa: 3",
                "splatd:sppMax: 4",
            ] {
                assert!(
                    text.contains(needle),
                    "oiiotool does not show {needle}:\n{text}"
                );
            }
        }
        Err(e) => eprintln!("oiiotool not run ({e}); OpenEXR's Python package checked the header"),
    }
}
