//! AOVs ride along: passes written by OpenEXR's own Python package (`tests/py/write_aov_passes.py`)
//! with a beauty, albedo, normal and depth, in Cycles' single-part layout and as one part per
//! layer, posted to real `splatd serve` processes. The served AOV layers equal numpy's mean of
//! the passes within the fixed-point step; two nodes' states merged (`splatd merge`) are the
//! bytes of the state of one node that received every pass; a restart from the snapshot serves
//! the same image; and a state in the previous format version (2, no AOV section) still imports.
//!
//! Needs `python3` with numpy and OpenEXR (`tests/run.sh` installs `tests/requirements.txt`).

use std::path::Path;
use std::process::Command;

use crate::common::{read_exr_with_python, runtime, Server, PATIENCE};
use bytes::Bytes;
use splatd_proto::api::{AovSpec, CreateFrame, ImageQuery};
use splatd_proto::{Client, ClientError};

const W: u32 = 29;
const H: u32 = 17;
const PASSES: u64 = 8;
const FRAME: &str = "aov.f";
/// The AOV channels in declaration order, as served.
const CHANNELS: [&str; 7] = [
    "ViewLayer.DiffCol.R",
    "ViewLayer.DiffCol.G",
    "ViewLayer.DiffCol.B",
    "ViewLayer.Normal.X",
    "ViewLayer.Normal.Y",
    "ViewLayer.Normal.Z",
    "ViewLayer.Depth.Z",
];

fn create() -> CreateFrame {
    CreateFrame {
        aovs: vec![
            AovSpec::new("ViewLayer.DiffCol", &["R", "G", "B"]),
            AovSpec::new("ViewLayer.Normal", &["X", "Y", "Z"]),
            AovSpec::new("ViewLayer.Depth", &["Z"]),
        ],
        ..CreateFrame::new(FRAME, W, H)
    }
}

fn write_passes(dir: &Path) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/write_aov_passes.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(dir)
        .args(["--width", &W.to_string(), "--height", &H.to_string()])
        .args(["--passes", &PASSES.to_string()])
        .output()
        .expect("running python3 (tests/run.sh installs its packages)");
    assert!(
        out.status.success(),
        "write_aov_passes.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn read(dir: &Path, name: &str) -> Bytes {
    Bytes::from(std::fs::read(dir.join(name)).unwrap())
}

fn pass(dir: &Path, k: u64) -> Bytes {
    read(dir, &format!("pass_{k}.exr"))
}

fn rejected(e: ClientError) -> (u16, String, String) {
    match e {
        ClientError::Rejected { status, body } => (status, body.error, body.message),
        other => panic!("expected a refusal, got {other}"),
    }
}

/// Posts passes `ks` (worker 1, seq = pass number) and, if `plain`, the beauty-only pass
/// (worker 2, seq 0).
async fn post(client: &Client, dir: &Path, ks: impl Iterator<Item = u64>, plain: bool) {
    client.create_or_get(&create()).await.unwrap();
    for k in ks {
        let ack = client.post_pass(FRAME, 1, k, pass(dir, k)).await.unwrap();
        assert_eq!(ack.accepted, (W * H) as u64);
    }
    if plain {
        let ack = client
            .post_pass(FRAME, 2, 0, read(dir, "plain.exr"))
            .await
            .unwrap();
        assert_eq!(ack.accepted, (W * H) as u64);
    }
}

#[test]
fn aovs_are_exact_means_through_merge_restart_and_old_states() {
    let dir = tempfile::tempdir().unwrap();
    let passes = dir.path().join("passes");
    write_passes(&passes);
    let expected: Vec<f64> = std::fs::read(passes.join("expected.f64"))
        .unwrap()
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
        .collect();
    let pixels = (W * H) as usize;
    assert_eq!(expected.len(), CHANNELS.len() * pixels);

    let rt = runtime();
    let data = dir.path().join("data");
    let data_arg = data.to_str().unwrap();
    let a = Server::start(&["--data-dir", data_arg]);
    let ca = Client::new(&a.url).unwrap();
    let (image_a, state_a) = rt.block_on(async {
        post(&ca, &passes, 0..PASSES, true).await;
        // Refused whole, naming what is wrong: a pass with some AOVs but not all, and a pass
        // with a value outside the AOV bounds.
        let (status, code, message) = rejected(
            ca.post_pass(FRAME, 3, 0, read(&passes, "partial.exr"))
                .await
                .unwrap_err(),
        );
        assert_eq!((status, code.as_str()), (422, "invalid_pass"), "{message}");
        assert!(
            message.contains("\"ViewLayer.Normal.X\"") && message.contains("\"ViewLayer.Depth.Z\""),
            "{message}"
        );
        let (status, code, message) = rejected(
            ca.post_pass(FRAME, 3, 1, read(&passes, "bad_depth.exr"))
                .await
                .unwrap_err(),
        );
        assert_eq!((status, code.as_str()), (422, "invalid_aov"), "{message}");
        assert!(
            message.contains("\"ViewLayer.Depth.Z\"") && message.contains("pixel (3, 2)"),
            "{message}"
        );
        let info = ca.frame_info(FRAME).await.unwrap();
        assert_eq!(info.samples, (PASSES + 1) * (W * H) as u64);
        assert_eq!(info.rejected_batches, 2);
        // The AOVs count against the frame's memory: 7 channels, 15 words per pixel.
        assert_eq!(info.memory_bytes, (W * H) as u64 * (25 + 15) * 8);
        let listed: Vec<(&str, usize)> = info
            .aovs
            .iter()
            .map(|a| (a.name.as_str(), a.channels.len()))
            .collect();
        assert_eq!(listed.len(), 3, "{listed:?}");
        assert_eq!(listed.iter().map(|l| l.1).sum::<usize>(), 7, "{listed:?}");
        let image = ca.image(FRAME, &ImageQuery::default()).await.unwrap();
        let state = ca.export_state(FRAME).await.unwrap();
        ca.sync(FRAME).await.unwrap();
        (image, state)
    });

    // The served AOV layers, read by OpenEXR, are numpy's means of the AOV passes (the plain
    // pass carries none, so it changes spp but not the AOV means).
    let path = dir.path().join("a.exr");
    std::fs::write(&path, &image_a).unwrap();
    let (w, h, channels) = read_exr_with_python(&path);
    assert_eq!((w, h), (W, H));
    let channel = |name: &str| {
        &channels
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("no channel {name} in image.exr"))
            .1
    };
    let step = 1.0 / (1u64 << splatd_estimator::AOV_FRAC_BITS) as f64;
    for (c, name) in CHANNELS.iter().enumerate() {
        for (i, &served) in channel(name).iter().enumerate() {
            let mean = expected[c * pixels + i];
            // One fixed-point step, and the f32 the mean is served as.
            let tolerance = step + mean.abs() * f32::EPSILON as f64;
            assert!(
                (served - mean).abs() <= tolerance,
                "{name} at pixel {i}: served {served}, numpy {mean}"
            );
        }
    }
    assert!(channel("spp.Y").iter().all(|&n| n == (PASSES + 1) as f64));

    // Two nodes, each with some of the passes: their states merged offline are the very bytes of
    // the state of the node that received every pass, AOVs included.
    let b = Server::start(&[]);
    let c = Server::start(&[]);
    let (cb, cc) = (Client::new(&b.url).unwrap(), Client::new(&c.url).unwrap());
    let (state_b, state_c) = rt.block_on(async {
        post(&cb, &passes, (0..PASSES).filter(|k| k % 2 == 0), true).await;
        post(&cc, &passes, (0..PASSES).filter(|k| k % 2 == 1), false).await;
        (
            cb.export_state(FRAME).await.unwrap(),
            cc.export_state(FRAME).await.unwrap(),
        )
    });
    let (sb, sc, merged) = (
        dir.path().join("b.state"),
        dir.path().join("c.state"),
        dir.path().join("merged.state"),
    );
    std::fs::write(&sb, &state_b).unwrap();
    std::fs::write(&sc, &state_c).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_splatd"))
        .arg("merge")
        .args([&sb, &sc])
        .arg("-o")
        .arg(&merged)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(std::fs::read(&merged).unwrap() == state_a.as_ref());
    // ... and imported over HTTP into a third node, the served image is node a's, bit for bit.
    rt.block_on(async {
        let d = Server::start(&[]);
        let cd = Client::new(&d.url).unwrap();
        cd.create_or_get(&create()).await.unwrap();
        cd.import_state(FRAME, state_b.clone()).await.unwrap();
        cd.import_state(FRAME, state_c.clone()).await.unwrap();
        let image = cd.image(FRAME, &ImageQuery::default()).await.unwrap();
        assert!(image == image_a, "the merged frame's image differs");
        // A state of a frame with other AOVs (as many channels, one named differently) is
        // refused, naming both.
        let e = Server::start(&[]);
        let ce = Client::new(&e.url).unwrap();
        let mut other = create();
        other.aovs[2].name = "ViewLayer.Mist".into();
        ce.create_or_get(&other).await.unwrap();
        let (status, code, message) =
            rejected(ce.import_state(FRAME, state_a.clone()).await.unwrap_err());
        assert_eq!((status, code.as_str()), (409, "aov_mismatch"), "{message}");
        assert!(message.contains("\"ViewLayer.Depth\" (Z)"), "{message}");
    });

    // A restart from the snapshot serves the same image.
    assert_eq!(a.terminate(), Some(0));
    let a2 = Server::start(&["--data-dir", data_arg]);
    let ca2 = Client::new(&a2.url).unwrap();
    rt.block_on(async {
        let image = ca2.image(FRAME, &ImageQuery::default()).await.unwrap();
        assert!(image == image_a, "the restored frame's image differs");
        assert!(ca2.export_state(FRAME).await.unwrap() == state_a);
    });

    // A state in format version 2 (no AOV section: version 3 without its last 8 bytes, an
    // empty AOV list) still imports, as a state without AOV samples: spp grows, AOV means stay.
    rt.block_on(async {
        let plain = Server::start(&[]);
        let cp = Client::new(&plain.url).unwrap();
        cp.create_frame(&CreateFrame::new(FRAME, W, H))
            .await
            .unwrap();
        cp.post_pass(FRAME, 9, 0, read(&passes, "plain.exr"))
            .await
            .unwrap();
        let v3 = cp.export_state(FRAME).await.unwrap();
        assert_eq!(&v3[4..6], &3u16.to_le_bytes());
        assert_eq!(&v3[v3.len() - 8..], &0u64.to_le_bytes());
        let mut v2 = v3[..v3.len() - 8].to_vec();
        v2[4..6].copy_from_slice(&2u16.to_le_bytes());
        let ack = ca2.import_state(FRAME, Bytes::from(v2)).await.unwrap();
        assert_eq!(ack.samples, (W * H) as u64);
        let image = ca2.image(FRAME, &ImageQuery::default()).await.unwrap();
        let path = dir.path().join("v2.exr");
        std::fs::write(&path, &image).unwrap();
        let (_, _, after) = read_exr_with_python(&path);
        for (name, values) in &after {
            if CHANNELS.contains(&name.as_str()) {
                assert!(values == channel(name), "{name} changed");
            }
            if name == "spp.Y" {
                assert!(values.iter().all(|&n| n == (PASSES + 2) as f64));
            }
        }
    });
}

/// Push: a node started with `--upstream` pushes its frame's AOVs with the cascades, the first
/// push whole and later ones as deltas; once it has exited the upstream holds its very state.
#[test]
fn pushed_deltas_carry_the_aovs() {
    let dir = tempfile::tempdir().unwrap();
    write_passes(dir.path());
    let rt = runtime();
    let upstream = Server::start(&[]);
    let node = Server::start(&["--upstream", &upstream.url, "--push-interval-ms", "50"]);
    let head = Client::new(&upstream.url).unwrap();
    let local = Client::new(&node.url).unwrap();
    let state = rt.block_on(async {
        post(&local, dir.path(), 0..PASSES / 2, false).await;
        // The first push has arrived when the upstream holds these samples.
        let first = PASSES / 2 * (W * H) as u64;
        let deadline = std::time::Instant::now() + PATIENCE;
        loop {
            match head.frame_info(FRAME).await {
                Ok(info) if info.samples == first => break,
                _ => assert!(
                    std::time::Instant::now() < deadline,
                    "the first push did not arrive"
                ),
            }
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
        post(&local, dir.path(), PASSES / 2..PASSES, false).await;
        local.export_state(FRAME).await.unwrap()
    });
    assert_eq!(node.terminate(), Some(0));
    let pushed = rt.block_on(head.export_state(FRAME)).unwrap();
    assert!(
        pushed == state,
        "the upstream's state after the pushes differs from the node's"
    );
}
