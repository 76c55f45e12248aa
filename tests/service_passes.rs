//! Whole rendered passes posted as EXR (written by an independent writer, OpenEXR's Python
//! package) with `splatd post` give exactly the frame the same values give posted as records;
//! a pass with invalid samples is refused by name and changes nothing.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common::{runtime, Server};
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

const WRITE: &str = "w-passes-0123456789abcdef";
const READ: &str = "r-passes-0123456789abcdef";

/// `splatd post` from a farm worker holding only a `write` token: `--create` makes the frame
/// (`PUT /v1/frames/{id}`), the beauty of a Blender/Cycles multilayer pass is found by itself
/// (`ViewLayer.Combined`, not the AOVs beside it) or taken from the layer named with `--layer`,
/// and a pass without a beauty is refused naming the layers it has, changing nothing.
#[test]
fn multilayer_passes_from_a_worker_with_a_write_token() {
    let dir = tempfile::tempdir().unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/write_layouts.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(dir.path())
        .args([
            "--width",
            &W.to_string(),
            "--height",
            &H.to_string(),
            "--seed",
            "3",
        ])
        .output()
        .expect("running python3 (tests/run.sh installs numpy and OpenEXR)");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let file = |name: &str| dir.path().join(format!("{name}.exr"));
    let server = Server::start_with_env(
        &[],
        &[("SPLATD_TOKENS", &format!("write {WRITE};read {READ}"))],
    );
    let post = |frame: &str, layer: Option<&str>, files: &[PathBuf]| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_splatd"));
        cmd.args(["post", "--url", &server.url, "--frame", frame, "--create"])
            .env("SPLATD_TOKEN", WRITE);
        if let Some(layer) = layer {
            cmd.args(["--layer", layer]);
        }
        cmd.args(files).output().unwrap()
    };

    let done = post("cycles", None, &[file("cycles")]);
    assert!(
        done.status.success(),
        "{}",
        String::from_utf8_lossy(&done.stderr)
    );
    let done = post(
        "background",
        Some("Background.Combined"),
        &[file("cycles-two-views")],
    );
    assert!(
        done.status.success(),
        "{}",
        String::from_utf8_lossy(&done.stderr)
    );
    // Two view layers and no --layer: refused before anything is created, naming both.
    let refused = post("guess", None, &[file("cycles-two-views")]);
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        stderr.contains("\"Background.Combined\"") && stderr.contains("\"ViewLayer.Combined\""),
        "{stderr}"
    );

    // What OpenEXR reads as each beauty, posted as records: the same frames.
    let rt = runtime();
    let write = Client::new(&server.url).unwrap().with_token(WRITE);
    let read = Client::new(&server.url).unwrap().with_token(READ);
    for (frame, raw) in [
        ("cycles", "cycles"),
        ("background", "cycles-two-views-asked"),
    ] {
        let records = raw_values(&dir.path().join(format!("{raw}.exr")))
            .into_iter()
            .enumerate()
            .map(|(i, rgb)| Record::new(i as u32 % W, i as u32 / W, rgb))
            .collect();
        let id = format!("{frame}-records");
        // A worker's create-or-get: made once, found the second time.
        for _ in 0..2 {
            let info = rt
                .block_on(write.create_or_get(&CreateFrame::new(&id, W, H)))
                .unwrap();
            assert_eq!((info.id.as_str(), info.samples), (id.as_str(), 0));
        }
        let batch = Batch::new(&id, 1, 0, records).unwrap();
        rt.block_on(write.post_batch(&batch)).unwrap();
        let image = |id: &str| rt.block_on(read.image(id, &ImageQuery::default())).unwrap();
        assert!(
            image(frame) == image(&id),
            "{frame}: the pass and its records differ"
        );
    }

    // No RGB layer at all: 422 naming the layers; the frame keeps what it had.
    let before = rt.block_on(read.frame_info("cycles")).unwrap();
    let bytes = std::fs::read(file("no-rgb")).unwrap();
    let err = rt
        .block_on(write.post_pass("cycles", 9, 0, bytes.into()))
        .unwrap_err();
    match &err {
        ClientError::Rejected { status: 422, body } => {
            assert_eq!(body.error, "invalid_pass", "{body}");
            assert!(
                body.message.contains("no layer with channels R, G and B")
                    && body.message.contains("\"depth\" (Z)")
                    && body.message.contains("\"normal\" (X, Y, Z)"),
                "{body}"
            );
        }
        other => panic!("expected a 422, got {other}"),
    }
    // A named layer that is not there: the same, naming what is.
    let bytes = std::fs::read(file("cycles")).unwrap();
    let err = rt
        .block_on(write.post_pass_layer("cycles", 9, 1, Some("Noisy Image"), bytes.into()))
        .unwrap_err();
    assert!(
        matches!(&err, ClientError::Rejected { status: 422, body }
            if body.message.contains("no layer \"Noisy Image\"")
                && body.message.contains("\"ViewLayer.Noisy Image\"")),
        "{err}"
    );
    let after = rt.block_on(read.frame_info("cycles")).unwrap();
    assert_eq!(
        (after.samples, after.batches, after.rejected_batches),
        (before.samples, before.batches, before.rejected_batches + 2)
    );
    assert_eq!(after.samples, u64::from(W * H));
}

/// `splatd post` sends two passes at a time, so when one is refused the next is already on its
/// way: the tool stops starting passes, still takes the answer of the one in flight, exits
/// non-zero naming the refused file, and says how many passes it posted, which is exactly what
/// the frame holds.
#[test]
fn a_refused_pass_stops_splatd_post_and_what_it_posted_is_counted() {
    let dir = tempfile::tempdir().unwrap();
    write_passes(dir.path());
    let bad = dir.path().join("truncated.exr");
    let good = std::fs::read(dir.path().join("pass1.half.exr")).unwrap();
    std::fs::write(&bad, &good[..good.len() / 2]).unwrap();
    let files = [
        dir.path().join("pass0.half.exr"),
        dir.path().join("pass0.uint.exr"),
        bad.clone(),
        dir.path().join("pass1.uint.exr"),
        dir.path().join("pass2.half.exr"),
    ];
    let server = Server::start(&[]);
    let out = Command::new(env!("CARGO_BIN_EXE_splatd"))
        .args(["post", "--url", &server.url, "--frame", "stops", "--create"])
        .args(&files)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{said}");
    assert!(
        said.contains(&format!("posting {}", bad.display())),
        "{said}"
    );
    // The two before it, and the one sent beside it; not the one after.
    assert!(said.contains("3 of 5 passes were posted"), "{said}");
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    let info = rt.block_on(client.frame_info("stops")).unwrap();
    assert_eq!(info.samples, 3 * u64::from(W * H), "{said}");
    assert_eq!(info.batches, 3, "{said}");
}
