//! The offline tools take memory by what state files hold, not by the frame they declare. A state
//! lists only the pixels with samples, so a file of a hundred bytes may declare 8192x8192 pixels
//! with 16 cascades. The real `splatd merge` and `splatd resolve` run here under an address-space
//! limit (`prlimit --as`) on such files.
//!
//! Before: `splatd merge` expanded every input into the whole declared frame. A 104-byte file
//! declaring 2048x2048 took 805 MB; under this limit each case below aborted ("memory
//! allocation of ... bytes failed", SIGABRT), and without one 4096x4096x16 and 8192x8192 aborted
//! too. Now the merge holds only the pixels the files hold, succeeds within the limit, and
//! writes a state as small as its inputs with the pixels added exactly; `splatd resolve`, which
//! must expand the frame it renders, exits 1 naming the size instead of aborting.
//!
//! `SPLATD_BIN=/path/to/splatd` runs it against another build.

use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use splatd_estimator::{CascadeLayout, FrameState, FRAC_BITS};
use splatd_proto::api::AovSpec;
use splatd_proto::StateDump;

/// The address space the tools get: far below any of the frames declared here.
const LIMIT: u64 = 512 << 20;

fn splatd() -> PathBuf {
    std::env::var_os("SPLATD_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_splatd")))
}

/// `splatd ARGS` under the address-space limit.
fn limited(args: &[&str]) -> Output {
    Command::new("prlimit")
        .arg(format!("--as={LIMIT}"))
        .arg("--")
        .arg(splatd())
        .args(args)
        .output()
        .expect("running prlimit (util-linux)")
}

/// A state of a `width`x`height` frame with `cascades` cascades and `channels` AOV channels that
/// holds one sample of `rgb` at pixel (`x`, `y`) if given, else nothing; and that pixel's cells.
fn state_file(
    path: &Path,
    (width, height, cascades, channels): (u32, u32, u32, usize),
    sample: Option<(u32, u32, [f32; 3])>,
) -> Vec<u64> {
    let layout =
        CascadeLayout::new(8.0, cascades, 0.125, splatd_proto::api::DEFAULT_LUMINANCE).unwrap();
    let aovs = match channels {
        0 => vec![],
        n => {
            let names: Vec<String> = (0..n).map(|c| format!("c{c}")).collect();
            let names: Vec<&str> = names.iter().map(String::as_str).collect();
            vec![AovSpec::new("A", &names)]
        }
    };
    let dump = StateDump {
        frame: "huge".into(),
        width,
        height,
        rows_start: 0,
        rows_end: height,
        base: layout.base(),
        cascades,
        lowest_scale: layout.lowest_scale(),
        luminance: layout.luminance_weights(),
        frac_bits: FRAC_BITS,
        origin: None,
        cells: vec![],
        batches: vec![],
        aovs,
        aov_cells: vec![],
    };
    // The pixel's cells, from a one-pixel state of the same layout.
    let mut one = FrameState::new(1, 1, layout);
    let mut cells = Vec::new();
    let mut at = None;
    if let Some((x, y, rgb)) = sample {
        one.splat(0, 0, rgb).unwrap();
        cells = one.cells().to_vec();
        at = Some(y as u64 * width as u64 + x as u64);
    }
    // AOV words of one value 1.0 in every channel: count 1, sums 2^20 (128-bit).
    let mut words = vec![1u64];
    for _ in 0..channels {
        words.extend([1 << 20, 0]);
    }
    let aov_words: Vec<(u64, &[u64])> = at.map(|p| (p, words.as_slice())).into_iter().collect();
    let bytes = dump.encode_sparse(
        at.map(|p| (p, cells.as_slice())),
        if channels > 0 { aov_words } else { vec![] },
    );
    std::fs::write(path, &bytes).unwrap();
    cells
}

#[test]
fn merge_holds_what_the_files_hold_and_resolve_refuses_what_does_not_fit() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        ("2048x2048", (2048, 2048, 6, 0)),
        ("4096x4096, 16 cascades", (4096, 4096, 16, 0)),
        ("8192x8192", (8192, 8192, 6, 0)),
        ("2048x2048, 64 AOV channels", (2048, 2048, 6, 64)),
    ];
    for (what, geometry) in cases {
        let (width, height, cascades, channels) = geometry;
        let (a, b, empty) = (
            dir.path().join("a.state"),
            dir.path().join("b.state"),
            dir.path().join("empty.state"),
        );
        let (x, y) = (width - 1, height - 1);
        let cell = state_file(&a, geometry, Some((x, y, [0.5, 1.0, 2.0])));
        state_file(&b, geometry, Some((x, y, [0.5, 1.0, 2.0])));
        state_file(&empty, geometry, None);
        let small = std::fs::metadata(&empty).unwrap().len();
        assert!(small < 1024, "{what}: the empty state is {small} bytes");

        let out = dir.path().join("merged.state");
        let merged = limited(&[
            "merge",
            a.to_str().unwrap(),
            empty.to_str().unwrap(),
            b.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ]);
        assert!(
            merged.status.success(),
            "{what}: merge under {LIMIT} bytes of address space: {:?} (signal {:?}) {}",
            merged.status.code(),
            merged.status.signal(),
            String::from_utf8_lossy(&merged.stderr)
        );
        // The merge holds the one pixel, added exactly: two samples of it.
        let bytes = std::fs::read(&out).unwrap();
        assert!(bytes.len() < 64 << 10, "{what}: {} bytes", bytes.len());
        let (dump, runs, aov_runs) = StateDump::decode_runs(&bytes, u64::MAX).unwrap();
        assert_eq!(
            (dump.width, dump.height, dump.cascades),
            (width, height, cascades)
        );
        let mut pixels = Vec::new();
        runs.try_for_each(|first, cells| {
            pixels.push((first, cells.to_vec()));
            Ok::<(), splatd_proto::StateError>(())
        })
        .unwrap();
        let mut twice = FrameState::from_cells(
            1,
            1,
            0..1,
            CascadeLayout::new(8.0, cascades, 0.125, splatd_proto::api::DEFAULT_LUMINANCE).unwrap(),
            cell.clone(),
        )
        .unwrap();
        let copy = twice.clone();
        twice.merge(&copy).unwrap();
        let at = y as u64 * width as u64 + x as u64;
        assert_eq!(pixels, vec![(at, twice.cells().to_vec())], "{what}");
        assert_eq!(twice.total_samples(), 2);
        if channels > 0 {
            let mut words = Vec::new();
            aov_runs
                .unwrap()
                .try_for_each(|first, w| {
                    words.push((first, w.to_vec()));
                    Ok::<(), splatd_proto::StateError>(())
                })
                .unwrap();
            let mut expected = vec![2u64];
            for _ in 0..channels {
                expected.extend([2 << 20, 0]);
            }
            assert_eq!(words, vec![(at, expected)], "{what}: AOV words");
        }

        // Resolving renders the whole declared frame: refused with a message, not an abort.
        let exr = dir.path().join("huge.exr");
        let resolved = limited(&[
            "resolve",
            out.to_str().unwrap(),
            "-o",
            exr.to_str().unwrap(),
        ]);
        let stderr = String::from_utf8_lossy(&resolved.stderr);
        assert_eq!(
            (resolved.status.code(), resolved.status.signal()),
            (Some(1), None),
            "{what}: resolve: {stderr}"
        );
        assert!(
            stderr.contains(&format!("declares a {width}x{height} frame"))
                && stderr.contains("could not be allocated"),
            "{what}: {stderr}"
        );
        assert!(!exr.exists(), "{what}: no image written");
    }
}
