//! `splatd_formats::passes` against EXR files written by an independent writer: OpenEXR's own Python
//! package (the reference C++ library), through `tests/py/write_passes.py`.
//!
//! Needs `python3` with numpy and OpenEXR (`tests/run.sh` installs `tests/requirements.txt`).

use std::path::{Path, PathBuf};
use std::process::Command;

use exr::prelude::f16;
use splatd_formats::passes::{decode_pass, Pass, PassError};

const WIDTH: u32 = 37;
const HEIGHT: u32 = 23;
const PASSES: usize = 3;

/// Runs the Python writer into a fresh temporary directory and returns its manifest.
fn write_passes(dir: &Path) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/write_passes.py");
    let output = Command::new("python3")
        .arg(&script)
        .arg(dir)
        .args(["--width", &WIDTH.to_string()])
        .args(["--height", &HEIGHT.to_string()])
        .args(["--passes", &PASSES.to_string()])
        .args(["--seed", "20180611"])
        .output()
        .expect("running python3 (tests/run.sh installs what tests/py/write_passes.py needs)");
    assert!(
        output.status.success(),
        "{} failed (pip install -r tests/requirements.txt?):\n{}",
        script.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    let manifest = std::fs::read(dir.join("manifest.json")).expect("the writer's manifest");
    serde_json::from_slice(&manifest).expect("the manifest is JSON")
}

fn path(value: &serde_json::Value) -> PathBuf {
    PathBuf::from(value.as_str().expect("a path in the manifest"))
}

fn read_raw(path: &Path) -> Vec<[f32; 3]> {
    let bytes = std::fs::read(path).expect("a raw .f32 file");
    assert_eq!(
        bytes.len() % 12,
        0,
        "{}: not whole RGB triples",
        path.display()
    );
    bytes
        .chunks_exact(12)
        .map(|px| {
            let f = |i: usize| f32::from_le_bytes([px[i], px[i + 1], px[i + 2], px[i + 3]]);
            [f(0), f(4), f(8)]
        })
        .collect()
}

fn decode_file(path: &Path) -> Result<Pass, PassError> {
    decode_pass(&std::fs::read(path).expect("an EXR the writer wrote"))
}

/// Same value, NaN equal to NaN and the sign of zero respected.
fn same(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

fn assert_pixels_equal(what: &str, got: &[[f32; 3]], want: &[[f32; 3]]) {
    assert_eq!(got.len(), want.len(), "{what}: pixel count");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        let (x, y) = (i % WIDTH as usize, i / WIDTH as usize);
        for c in 0..3 {
            assert!(
                same(g[c], w[c]),
                "{what}: pixel ({x}, {y}) channel {c}: decoded {} but the writer stored {}",
                g[c],
                w[c]
            );
        }
    }
}

#[test]
fn passes_written_by_openexr_decode_value_for_value() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let manifest = write_passes(dir.path());
    let files = manifest["passes"].as_array().expect("a list of passes");
    assert_eq!(files.len(), 3 * PASSES, "float, half and uint per pass");
    let mut variants = std::collections::BTreeSet::new();
    for file in files {
        let variant = file["variant"].as_str().expect("a variant");
        variants.insert(variant.to_string());
        let exr = path(&file["exr"]);
        let pass = decode_file(&exr).unwrap_or_else(|e| panic!("{}: {e}", exr.display()));
        assert_eq!(
            (pass.width, pass.height),
            (WIDTH, HEIGHT),
            "{}",
            exr.display()
        );
        let mut want = read_raw(&path(&file["raw"]));
        if variant == "half" {
            // The file holds the values rounded to half (numpy rounds to nearest even, as does
            // `half`); the raw file holds them before rounding.
            for px in &mut want {
                *px = px.map(|v| f16::from_f32(v).to_f32());
            }
        }
        assert_pixels_equal(&exr.display().to_string(), &pass.rgb, &want);
    }
    assert_eq!(
        variants.into_iter().collect::<Vec<_>>(),
        ["float", "half", "uint"]
    );
}

#[test]
fn records_are_one_sample_per_pixel_row_major_and_unfiltered() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let manifest = write_passes(dir.path());
    let file = &manifest["passes"][0];
    assert_eq!(file["variant"], "float");
    let pass = decode_file(&path(&file["exr"])).expect("the first float pass");
    let records: Vec<_> = pass.records().collect();
    assert_eq!(records.len(), (WIDTH * HEIGHT) as usize);
    for (i, r) in records.iter().enumerate() {
        let i = i as u32;
        assert_eq!((r.x, r.y), (i % WIDTH, i / WIDTH), "record {i}");
        assert_eq!(
            r.rgb.map(f32::to_bits),
            pass.rgb[i as usize].map(f32::to_bits)
        );
    }
    // The writer put invalid samples in the corners; they are the server's to reject.
    let first = records[0].rgb;
    assert!(first[0] == -1.0 && first[1].is_nan() && first[2] == f32::INFINITY);
    let last = records[records.len() - 1].rgb;
    assert_eq!(last, [f32::NEG_INFINITY, -0.5, 3.0e38]);
    assert!(pass.check(WIDTH, HEIGHT).is_ok());
    assert_eq!(
        pass.check(WIDTH * 2, HEIGHT).unwrap_err().to_string(),
        format!(
            "pass is {WIDTH}x{HEIGHT} but the frame is {}x{HEIGHT}",
            WIDTH * 2
        )
    );
}

#[test]
fn the_part_named_beauty_of_a_multipart_file_is_read() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let manifest = write_passes(dir.path());
    let multi = &manifest["multipart"];
    let pass = decode_file(&path(&multi["exr"])).expect("the multi-part file");
    assert_pixels_equal("multipart.exr", &pass.rgb, &read_raw(&path(&multi["raw"])));
}

#[test]
fn files_that_are_not_passes_are_refused_with_what_was_found() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let manifest = write_passes(dir.path());

    let err = decode_file(&path(&manifest["luminance"])).unwrap_err();
    assert!(matches!(err, PassError::NoRgbLayer { .. }), "{err:?}");
    assert_eq!(
        err.to_string(),
        "the EXR has no layer with channels R, G and B; layers found: unnamed (Y)"
    );

    let err = decode_file(&path(&manifest["cropped"])).unwrap_err();
    assert!(matches!(err, PassError::Window { .. }), "{err:?}");
    assert_eq!(
        err.to_string(),
        format!(
            "the pass's data window (2, 3) size {}x{} is not its display window (0, 0) size \
             {WIDTH}x{HEIGHT}: cropped and overscanned passes are not supported (render the \
             full frame)",
            WIDTH - 3,
            HEIGHT - 4
        )
    );

    let raw = std::fs::read(path(&manifest["passes"][0]["raw"])).expect("a raw file");
    let err = decode_pass(&raw).unwrap_err();
    assert!(matches!(err, PassError::NotExr { .. }), "{err:?}");
}
