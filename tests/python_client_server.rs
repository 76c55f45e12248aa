//! The Python client (and the Mitsuba worker's posting helper) against a real server: what it
//! posts resolves to exactly the core's image of the same samples.

mod common;

use std::path::Path;
use std::process::Command;

use common::Server;
use splatd_estimator::{CascadeLayout, FrameState, ResolveParams};
use splatd_server::image::encode_exr;

#[test]
fn python_client_posts_what_the_core_resolves() {
    let server = Server::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/drive_python_client.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(&server.url)
        .arg(dir.path())
        .output()
        .expect("running python3 (tests/run.sh installs numpy)");
    assert!(
        out.status.success(),
        "the Python driver failed:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let (w, h, passes) = (23u32, 17u32, 6usize);
    let raw = std::fs::read(dir.path().join("samples.f32")).unwrap();
    assert_eq!(raw.len(), passes * (w * h) as usize * 12);
    let mut reference = FrameState::new(w, h, CascadeLayout::with_defaults());
    for (i, c) in raw.chunks_exact(12).enumerate() {
        let f = |k: usize| f32::from_le_bytes(c[k..k + 4].try_into().unwrap());
        let p = (i % (w * h) as usize) as u32;
        reference.splat(p % w, p / w, [f(0), f(4), f(8)]).unwrap();
    }
    let expected = encode_exr(&reference.resolve(&ResolveParams::with_defaults()), &[]).unwrap();
    let served = std::fs::read(dir.path().join("served.exr")).unwrap();
    assert!(
        served == expected,
        "the served EXR differs from the core's resolve"
    );
}
