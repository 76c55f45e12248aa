//! The Blender worker end to end: Debian's Blender renders Cycles passes of a tiny built-in scene
//! with a small bright lamp and posts them with the installed Python client holding only a
//! `write` token. The served `mean` is the mean of the passes as Blender wrote them, `spp` is the
//! pass count, and the mean of the passes agrees with a high-spp box-filtered render within
//! noise, over the whole image, at the lamp and along edges (where a fixed sub-pixel position is
//! biased). The passes carry Cycles' albedo, normal and depth passes as AOVs (multilayer EXRs),
//! and the served AOV layers are their exact means.
//!
//! Blender is installed by `tests/setup/blender.sh`; when that cannot be done the test says why
//! and passes without running (the rest of the suite does not need Blender).

mod common;

use std::path::Path;
use std::process::Command;

use common::{python_package_venv, run_setup, runtime, venv_site_packages, Server};
use splatd_proto::api::ImageQuery;
use splatd_proto::Client;

const WRITE: &str = "w-blender-0123456789abcdef";
const READ: &str = "r-blender-0123456789abcdef";
const PASSES: usize = 256;
const REFERENCE_SPP: usize = 4096;

#[test]
fn blender_passes_converge_to_the_antialiased_image() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let blender = match run_setup("blender.sh") {
        Ok(path) => path,
        Err(e) => {
            eprintln!("skipping the Blender worker test: Blender could not be installed: {e}");
            return;
        }
    };

    let dir = tempfile::tempdir().unwrap();
    let python = python_package_venv(dir.path());
    let site = venv_site_packages(&python);
    let server = Server::start_with_env(
        &[],
        &[("SPLATD_TOKENS", &format!("write {WRITE};read {READ}"))],
    );
    let worker = root.join("proto/python/blender_worker.py");
    let blender_run = |args: &[&str], what: &str| {
        let out = Command::new(&blender)
            .args([
                "-b",
                "--factory-startup",
                "--python-use-system-env",
                "--python",
            ])
            .arg(&worker)
            .arg("--")
            .args(args)
            .env("PYTHONPATH", &site)
            .env("SPLATD_TOKEN", WRITE)
            .output()
            .unwrap_or_else(|e| panic!("{what}: {e}"));
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success() && !stdout.contains("Traceback"),
            "{what} failed:\n{stdout}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        stdout
    };
    let passes_dir = dir.path().join("passes");
    let passes = PASSES.to_string();
    blender_run(
        &[
            "--url",
            &server.url,
            "--frame",
            "cycles",
            "--passes",
            &passes,
            "--seed",
            "15",
            "--demo-scene",
            "--aovs",
            "albedo,normal,depth",
            "--keep-dir",
            passes_dir.to_str().unwrap(),
        ],
        "the Blender worker",
    );
    let reference = dir.path().join("reference.exr");
    blender_run(
        &[
            "--demo-scene",
            "--reference",
            &REFERENCE_SPP.to_string(),
            "--output",
            reference.to_str().unwrap(),
        ],
        "the reference render",
    );

    let rt = runtime();
    let read = Client::new(&server.url).unwrap().with_token(READ);
    let served = rt
        .block_on(read.image("cycles", &ImageQuery::default()))
        .unwrap();
    std::fs::write(dir.path().join("served.exr"), &served).unwrap();
    let info = rt.block_on(read.frame_info("cycles")).unwrap();
    assert_eq!((info.spp_min, info.spp_max), (PASSES as u64, PASSES as u64));
    let declared: Vec<(&str, Vec<&str>)> = info
        .aovs
        .iter()
        .map(|a| {
            (
                a.name.as_str(),
                a.channels.iter().map(|c| c.as_str()).collect(),
            )
        })
        .collect();
    assert_eq!(
        declared,
        [
            ("ViewLayer.DiffCol", vec!["R", "G", "B"]),
            ("ViewLayer.Normal", vec!["X", "Y", "Z"]),
            ("ViewLayer.Depth", vec!["Z"]),
        ]
    );

    let out = Command::new("python3")
        .arg(root.join("tests/py/blender_stats.py"))
        .arg(dir.path())
        .arg(&passes)
        .arg(REFERENCE_SPP.to_string())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "blender_stats.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stats: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("Blender passes against the reference: {stats}");
    let f = |v: &serde_json::Value| v.as_f64().unwrap();

    // The served mean is the passes' mean, to the fixed point's rounding.
    assert!(
        f(&stats["served_vs_passes"]["max_rel"]) < 1e-5
            || f(&stats["served_vs_passes"]["max_abs"]) < 1e-6,
        "{stats}"
    );
    // Every AOV channel of the passes is served, as their mean to the fixed point's step.
    let aovs: Vec<&str> = stats["aovs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert_eq!(aovs.len(), 7, "{stats}");
    assert!(f(&stats["aovs_worst"]) <= 1.0, "{stats}");
    assert_eq!(f(&stats["spp_min"]), PASSES as f64, "{stats}");
    assert_eq!(f(&stats["spp_max"]), PASSES as f64, "{stats}");
    // No systematic offset: over the image, at the lamp and along edges, within 5 standard
    // deviations. (Passes that all sample the pixel centres, as Cycles' own seeds do, are 24 %
    // too bright at this lamp: hundreds of standard deviations.)
    for region in ["global", "lamp", "edges"] {
        let r = &stats[region];
        assert!(
            f(&r["sum"]).abs() <= 5.0 * f(&r["sigma"]),
            "{region}: the passes' mean is off the reference by {} (sigma {}, reference {})",
            f(&r["sum"]),
            f(&r["sigma"]),
            f(&r["reference"])
        );
    }
}
