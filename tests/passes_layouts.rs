//! The beauty of a pass found in every layout renderers write (single-part prefixed layers,
//! Blender/Cycles multilayer, multi-part, tiled, every compression), in files written by
//! OpenEXR's own Python package (`tests/py/write_layouts.py`), and compared value for value with
//! what OpenEXR itself reads back from the same file. Passes whose beauty cannot be found are
//! refused naming the layers they have.
//!
//! Needs `python3` with numpy and OpenEXR (`tests/run.sh` installs `tests/requirements.txt`).

use std::path::{Path, PathBuf};
use std::process::Command;

use splatd_formats::passes::{decode_pass_with, PassError, MAX_PASS_PIXELS};

fn write_layouts(dir: &Path) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/write_layouts.py");
    let output = Command::new("python3")
        .arg(&script)
        .arg(dir)
        .args(["--width", "37", "--height", "23", "--seed", "15"])
        .output()
        .expect("running python3 (tests/run.sh installs what tests/py/write_layouts.py needs)");
    assert!(
        output.status.success(),
        "{} failed:\n{}",
        script.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    let manifest = std::fs::read(dir.join("manifest.json")).expect("the writer's manifest");
    serde_json::from_slice(&manifest).expect("the manifest is JSON")
}

fn read_raw(path: &Path) -> Vec<[f32; 3]> {
    std::fs::read(path)
        .expect("a raw .f32 file")
        .chunks_exact(12)
        .map(|px| {
            let f = |i: usize| f32::from_le_bytes(px[i..i + 4].try_into().unwrap());
            [f(0), f(4), f(8)]
        })
        .collect()
}

#[test]
fn the_beauty_is_found_and_read_exactly_in_every_layout() {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let manifest = write_layouts(dir.path());
    let (width, height) = (
        manifest["width"].as_u64().unwrap() as u32,
        manifest["height"].as_u64().unwrap() as u32,
    );
    let files = manifest["files"].as_array().expect("a list of files");
    let (mut read, mut refused) = (0, 0);
    for file in files {
        let name = file["name"].as_str().unwrap();
        let exr = PathBuf::from(file["exr"].as_str().unwrap());
        let bytes = std::fs::read(&exr).unwrap();
        let ask = file["ask"].as_str();
        let result = decode_pass_with(&bytes, ask, MAX_PASS_PIXELS);
        if file["error"] == true {
            let err = result.expect_err(name);
            assert!(
                matches!(
                    err,
                    PassError::NoRgbLayer { .. }
                        | PassError::Ambiguous { .. }
                        | PassError::UnknownLayer { .. }
                        | PassError::NotRgb { .. }
                        | PassError::Exr(_)
                ),
                "{name}: {err:?}"
            );
            let message = err.to_string();
            for mention in file["mentions"].as_array().unwrap() {
                let mention = mention.as_str().unwrap();
                assert!(
                    message.contains(mention),
                    "{name}: {message:?} does not mention {mention:?}"
                );
            }
            refused += 1;
            continue;
        }
        let pass = result.unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(pass.layer, file["layer"].as_str().unwrap(), "{name}");
        assert_eq!((pass.width, pass.height), (width, height), "{name}");
        let want = read_raw(Path::new(file["raw"].as_str().unwrap()));
        assert_eq!(pass.rgb.len(), want.len(), "{name}");
        for (i, (got, want)) in pass.rgb.iter().zip(&want).enumerate() {
            assert_eq!(
                got.map(f32::to_bits),
                want.map(f32::to_bits),
                "{name}: pixel ({}, {}): decoded {got:?}, OpenEXR reads {want:?}",
                i % width as usize,
                i / width as usize
            );
        }
        read += 1;
    }
    // The writer's list, so that a file silently left out of it is noticed.
    assert_eq!((read, refused), (22, 6));
}
