//! Whole rendered passes posted as EXR (written by an independent writer, OpenEXR's Python
//! package) with `splatd post` give exactly the frame the same values give posted as records;
//! a pass with invalid samples is refused by name and changes nothing.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::{runtime, Server};
use exr::prelude::f16;
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Batch, Client, ClientError, Record};

const W: u32 = 29;
const H: u32 = 17;
const PASSES: usize = 3;

fn write_passes(dir: &Path) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/write_passes.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(dir)
        .args(["--width", &W.to_string(), "--height", &H.to_string()])
        .args(["--passes", &PASSES.to_string(), "--seed", "11"])
        .output()
        .expect("running python3 (tests/run.sh installs numpy and OpenEXR)");
    assert!(
        out.status.success(),
        "write_passes.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The raw values beside a pass file (`pass0.half.exr` -> `pass0.half.f32`).
fn raw_values(exr: &Path) -> Vec<[f32; 3]> {
    let bytes = std::fs::read(exr.with_extension("f32")).unwrap();
    bytes
        .chunks_exact(12)
        .map(|c| {
            let f = |i: usize| f32::from_le_bytes(c[i..i + 4].try_into().unwrap());
            [f(0), f(4), f(8)]
        })
        .collect()
}

#[test]
fn passes_posted_as_exr_equal_the_same_samples_posted_as_records() {
    let dir = tempfile::tempdir().unwrap();
    write_passes(dir.path());
    let mut files: Vec<PathBuf> = Vec::new();
    for i in 0..PASSES {
        files.push(dir.path().join(format!("pass{i}.half.exr")));
        files.push(dir.path().join(format!("pass{i}.uint.exr")));
    }

    let server = Server::start(&[]);
    let status = Command::new(env!("CARGO_BIN_EXE_splatd"))
        .args([
            "post",
            "--url",
            &server.url,
            "--frame",
            "passes",
            "--create",
        ])
        .args(&files)
        .status()
        .unwrap();
    assert!(status.success(), "splatd post failed");
    let post = |frame: &str, worker: Option<&str>, files: &[PathBuf]| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_splatd"));
        cmd.args(["post", "--url", &server.url, "--frame", frame, "--create"]);
        if let Some(worker) = worker {
            cmd.args(["--worker", worker]);
        }
        assert!(
            cmd.args(files).status().unwrap().success(),
            "splatd post failed"
        );
    };
    // Rerunning posts nothing twice, with or without a worker id.
    for _ in 0..2 {
        post("again", Some("77"), &files);
        post("again-default", None, &files);
    }
    // A rerun with the same worker id on other files adds them all: passes are numbered by
    // their content, not by their position on the command line.
    let (first, rest) = files.split_at(files.len() / 2);
    post("split", Some("78"), first);
    post("split", Some("78"), rest);

    // The same values as records, into a second frame. Half files hold the values rounded to
    // half precision; uint files hold integers.
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    rt.block_on(client.create_frame(&CreateFrame::new("records", W, H)))
        .unwrap();
    for (seq, file) in files.iter().enumerate() {
        let half = file.to_str().unwrap().ends_with(".half.exr");
        let records: Vec<Record> = raw_values(file)
            .into_iter()
            .enumerate()
            .map(|(i, rgb)| {
                let rgb = if half {
                    rgb.map(|v| f16::from_f32(v).to_f32())
                } else {
                    rgb
                };
                Record::new(i as u32 % W, i as u32 / W, rgb)
            })
            .collect();
        let batch = Batch::new("records", 5, seq as u64, records).unwrap();
        rt.block_on(client.post_batch(&batch)).unwrap();
    }

    let image = |id: &str| {
        rt.block_on(client.image(id, &ImageQuery::default()))
            .unwrap()
    };
    let from_records = image("records");
    assert!(image("passes") == from_records, "passes and records differ");
    for (frame, what) in [
        ("again", "a rerun counted passes twice"),
        (
            "again-default",
            "a rerun without --worker counted passes twice",
        ),
        (
            "split",
            "a second run with the same worker dropped new passes",
        ),
    ] {
        assert!(image(frame) == from_records, "{what}");
    }
    let info = rt.block_on(client.frame_info("passes")).unwrap();
    let n = files.len() as u64;
    assert_eq!((info.spp_min, info.spp_max, info.batches), (n, n, n));

    // A float pass holds negative, NaN and infinite samples: refused, naming the sample.
    let bad = std::fs::read(dir.path().join("pass0.float.exr")).unwrap();
    let err = rt
        .block_on(client.post_pass("passes", 9, 0, bad.into()))
        .unwrap_err();
    match err {
        ClientError::Rejected { status: 422, body } => {
            assert!(
                ["negative_sample", "non_finite_sample"].contains(&body.error.as_str()),
                "{body}"
            );
            assert!(body.message.starts_with("record "), "{body}");
        }
        other => panic!("expected a 422, got {other}"),
    }
    // A pass of the wrong size, and a file that is not an EXR.
    let lum = std::fs::read(dir.path().join("luminance.exr")).unwrap();
    let err = rt
        .block_on(client.post_pass("passes", 9, 1, lum.into()))
        .unwrap_err();
    assert!(
        matches!(&err, ClientError::Rejected { status: 422, body } if body.error == "invalid_pass" && body.message.contains("Y")),
        "{err}"
    );
    let err = rt
        .block_on(client.post_pass("passes", 9, 2, b"not an exr".to_vec().into()))
        .unwrap_err();
    assert!(
        matches!(&err, ClientError::Rejected { status: 422, .. }),
        "{err}"
    );
    assert!(
        image("passes") == from_records,
        "a refused pass changed the frame"
    );
}
