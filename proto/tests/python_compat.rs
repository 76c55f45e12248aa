//! The Python client (package `splatd_client` in `proto/python/`) and this crate must
//! produce and accept exactly the same bytes.
//!
//! This test needs `python3` with numpy and fails (it does not skip) when
//! they are missing, so that a CI without them cannot silently stop checking
//! the Python wire format.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use splatd_proto::{Batch, DecodeLimits, Record};

const INSTALL_HINT: &str = "install Python 3 (e.g. `apt-get install python3`) and numpy \
     (`python3 -m pip install numpy`)";

/// The directory holding the `splatd_client` package, put on `PYTHONPATH` so that
/// `python3 -m splatd_client` runs this checkout's client (not an installed one).
fn package_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("python")
}

fn python(args: &[&std::ffi::OsStr]) -> Output {
    match Command::new("python3")
        .env("PYTHONPATH", package_dir())
        .args(args)
        .output()
    {
        Ok(out) => out,
        Err(e) => panic!("cannot run python3 ({e}); {INSTALL_HINT}"),
    }
}

fn require_python_with_numpy() {
    let out = python(&["-c".as_ref(), "import numpy".as_ref()]);
    assert!(
        out.status.success(),
        "python3 cannot import numpy; {INSTALL_HINT}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The batch `python3 -m splatd_client --selftest-emit` writes (see `selftest_batch`
/// there). Decimal values go through f64 first, as numpy's do.
fn expected() -> Batch {
    Batch {
        frame: "selftest.frame-01".into(),
        worker: 0x0102_0304_0506_0708,
        seq: (1 << 63) + 5,
        records: vec![
            Record::new(0, 0, [0.0, 0.5, 1.0]),
            Record::new(1919, 1079, [0.1_f64 as f32, 1e-3_f64 as f32, 65504.0]),
            Record::new(
                u32::MAX,
                u32::MAX,
                [f32::from_bits(1), f32::MAX, 2f32.powi(-20)],
            ),
            Record::new(7, 3, [123.456_f64 as f32, 0.0, (1.0_f64 / 3.0) as f32]),
        ],
    }
}

#[test]
fn python_and_rust_encodings_are_identical() {
    require_python_with_numpy();
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"));
    let from_python = dir.join(format!("python_selftest_{}.bin", std::process::id()));
    let out = python(&[
        "-m".as_ref(),
        "splatd_client".as_ref(),
        "--selftest-emit".as_ref(),
        from_python.as_os_str(),
    ]);
    assert!(
        out.status.success(),
        "python3 -m splatd_client --selftest-emit failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let bytes = std::fs::read(&from_python)
        .unwrap_or_else(|e| panic!("reading {}: {e}", from_python.display()));
    std::fs::remove_file(&from_python).ok();

    let decoded = Batch::decode(&bytes, &DecodeLimits::default())
        .unwrap_or_else(|e| panic!("Rust cannot decode Python's batch: {e}"));
    let expected = expected();
    assert_eq!(decoded, expected);
    assert_eq!(expected.encode(), bytes, "Rust and Python encodings differ");

    // And the other way round: Python decodes Rust's bytes.
    let from_rust = dir.join(format!("rust_selftest_{}.bin", std::process::id()));
    std::fs::write(&from_rust, expected.encode())
        .unwrap_or_else(|e| panic!("writing {}: {e}", from_rust.display()));
    let out = python(&[
        "-m".as_ref(),
        "splatd_client".as_ref(),
        "--selftest-check".as_ref(),
        from_rust.as_os_str(),
    ]);
    std::fs::remove_file(&from_rust).ok();
    assert!(
        out.status.success(),
        "Python rejects Rust's encoding:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
