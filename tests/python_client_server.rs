//! The Python client package, installed by pip into a fresh virtual environment, against a real
//! server: what it (and the Mitsuba worker's posting helper, importing the installed package)
//! posts resolves to exactly the core's image of the same samples; its own tests pass there too.

use std::path::Path;
use std::process::Command;

use crate::common::{python_package_venv, Server};
use splatd_estimator::{CascadeLayout, FrameState, ResolveParams};
use splatd_formats::exr::{encode_exr, Provenance};

#[test]
fn the_installed_python_client_posts_what_the_core_resolves() {
    let server = Server::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let python = python_package_venv(dir.path());
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let run = |args: &[&std::ffi::OsStr], what: &str| {
        let out = Command::new(&python)
            .args(args)
            .env("SPLATD_CLIENT_INSTALLED", "1")
            .current_dir(dir.path())
            .output()
            .unwrap_or_else(|e| panic!("{what}: {e}"));
        assert!(
            out.status.success(),
            "{what} failed:\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };

    // The package pip installed, not the checkout, with the version pip recorded.
    let found = run(
        &[
            "-c".as_ref(),
            "import importlib.metadata as m, splatd_client as s; \
             print(s.__file__, s.__version__, m.version('splatd-client'), s.VERSION)"
                .as_ref(),
        ],
        "importing the installed package",
    );
    let fields: Vec<&str> = found.split_whitespace().collect();
    assert!(
        fields[0].starts_with(dir.path().join("venv").to_str().unwrap()),
        "{found}"
    );
    assert_eq!(fields[1], fields[2], "{found}");
    assert_eq!(fields[1].split('.').next(), Some(fields[3]), "{found}");

    run(
        &[root.join("proto/python/test_splatd_client.py").as_os_str()],
        "the package's tests in the venv",
    );
    run(
        &[
            root.join("tests/py/drive_python_client.py").as_os_str(),
            server.url.as_ref(),
            dir.path().as_os_str(),
        ],
        "the Python driver",
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
    let params = ResolveParams::with_defaults();
    let provenance = Provenance {
        layout: reference.layout(),
        params: &params,
    };
    let expected = encode_exr(&reference.resolve(&params), &[], &[], &provenance).unwrap();
    let served = std::fs::read(dir.path().join("served.exr")).unwrap();
    assert!(
        served == expected,
        "the served EXR differs from the core's resolve"
    );
}
