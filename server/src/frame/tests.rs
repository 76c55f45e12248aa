//! The frame's unit tests: ingest, imports, cuts and refusals against the core.

use std::sync::Arc;

use splatd_estimator::{
    self as estimator, CascadeLayout, CellsError, FrameState, MergeError, SampleError,
    MAX_PIXEL_SAMPLES,
};
use splatd_formats::state::ImportError;
use splatd_proto::api::{AovSpec, CreateFrame};
use splatd_proto::{Batch, Origin, StateError};

use super::*;
use splatd_proto::Record;
use splatd_scenes::synth::{FireflyScene, SplitMix64};

fn spec(w: u32, h: u32) -> FrameSpec {
    FrameSpec::new(CreateFrame::new("f", w, h)).expect("valid")
}

fn batch(worker: u64, seq: u64, records: Vec<Record>) -> Batch {
    Batch::new("f", worker, seq, records).expect("valid frame id")
}

fn records(scene: &FireflyScene, pass: u64) -> Vec<Record> {
    scene
        .pass(pass)
        .map(|(x, y, rgb)| Record { x, y, rgb })
        .collect()
}

/// Names are printable ASCII and `<name>.<channel>` at most 255 bytes; each refusal names
/// its rule, and quotes a long name cut short.
#[test]
fn aov_names_are_what_openexr_holds() {
    let spec = |name: &str, channel: &str| {
        FrameSpec::new(CreateFrame {
            aovs: vec![AovSpec::new(name, &[channel])],
            ..CreateFrame::new("f", 2, 2)
        })
    };
    let refused = |name: &str, channel: &str| spec(name, channel).unwrap_err().to_string();
    let long = |n: usize| "a".repeat(n);
    assert!(spec(&long(253), "R").is_ok());
    assert!(spec("x", &long(253)).is_ok());
    assert!(spec(r#"View Layer #1 ~!@$%^&*()[]{}<>|\/?;:'",+=-_`"#, "r g").is_ok());
    for (name, channel, rule) in [
        ("a\0b", "R", "characters rule"),
        ("ab", "\u{1b}", "characters rule"),
        ("été", "R", "encoding rule"),
        ("ab", "深", "encoding rule"),
        (long(254).as_str(), "R", "length rule"),
        ("x", long(254).as_str(), "length rule"),
        (long(30_000).as_str(), "R", "length rule"),
    ] {
        let e = refused(name, channel);
        assert!(e.contains(rule), "{e}");
        assert!(e.len() < 400, "{e}");
    }
    assert!(refused("a\0b", "R").contains("byte 1 is the control character 0x00"));
}

#[test]
fn banded_frame_resolves_like_one_state() {
    let scene = FireflyScene::new(13, 70, 5);
    let frame = ShardedFrame::new(spec(13, 70));
    assert!(frame.bands.len() > 1, "the test needs several bands");
    let mut reference = FrameState::new(13, 70, CascadeLayout::with_defaults());
    for pass in 0..24 {
        reference.splat_all(scene.pass(pass));
        let got = frame
            .ingest(&batch(1, pass, records(&scene, pass)))
            .unwrap();
        assert_eq!(got.accepted, 13 * 70);
    }
    let params = estimator::ResolveParams::with_defaults();
    assert_eq!(frame.cut().resolve(&params, 2), reference.resolve(&params));
    assert_eq!(frame.cut().whole(), reference);
    let info = frame.info();
    assert_eq!(
        (info.spp_min, info.spp_max, info.samples),
        (24, 24, 24 * 910)
    );
}

/// A batch whose records hop between bands (shuffled, and one band's records apart from the
/// rest) is splatted as the same samples into each band: each band takes its runs of the
/// batch in order, however short.
#[test]
fn a_batch_hopping_between_bands_gives_the_one_state() {
    let scene = FireflyScene::new(13, 70, 7);
    let frame = ShardedFrame::new(spec(13, 70));
    assert!(frame.bands.len() > 2, "the test needs several bands");
    let mut reference = FrameState::new(13, 70, CascadeLayout::with_defaults());
    let mut rng = SplitMix64::new(3);
    for pass in 0..4 {
        let mut recs = records(&scene, pass);
        if pass % 2 == 0 {
            for i in (1..recs.len()).rev() {
                recs.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
            }
        } else {
            // Scan order with the first band's rows last: two runs of one band, far apart.
            recs.rotate_left(13 * 4);
        }
        reference.splat_all(recs.iter().map(|r| (r.x, r.y, r.rgb)));
        let got = frame.ingest(&batch(1, pass, recs)).unwrap();
        assert_eq!(got.accepted, 13 * 70);
    }
    assert!(frame.cut().whole() == reference, "the frame differs");
}

#[test]
fn a_bad_record_anywhere_leaves_the_frame_untouched() {
    let frame = ShardedFrame::new(spec(4, 40));
    let mut recs: Vec<Record> = (0..40)
        .map(|y| Record {
            x: 1,
            y,
            rgb: [1.0; 3],
        })
        .collect();
    recs[39].rgb[1] = f32::NAN;
    let err = frame.ingest(&batch(1, 0, recs.clone())).unwrap_err();
    assert!(
        matches!(err, IngestError::Sample { index: 39, .. }),
        "{err}"
    );
    recs[39].rgb[1] = 1.0;
    recs[20].x = 4;
    let err = frame.ingest(&batch(1, 0, recs.clone())).unwrap_err();
    assert!(
        err.to_string().starts_with("record 20 (pixel (4, 20)")
            && err.to_string().contains("outside the 4x40 frame"),
        "{err}"
    );
    // Below the frame; a negative sample; both, the first one named.
    recs[20].x = 1;
    recs[25].y = 40;
    let below = |err: &IngestError| {
        err.to_string().starts_with("record 25 (pixel (1, 40)")
            && err.to_string().contains("outside the 4x40 frame")
    };
    let err = frame.ingest(&batch(1, 0, recs.clone())).unwrap_err();
    assert!(below(&err), "{err}");
    recs[25].y = 25;
    recs[31].rgb[0] = -1.0;
    let err = frame.ingest(&batch(1, 0, recs.clone())).unwrap_err();
    assert!(
        matches!(
            err,
            IngestError::Sample {
                index: 31,
                error: SampleError::Negative,
                ..
            }
        ),
        "{err}"
    );
    recs[25].y = 40;
    let err = frame.ingest(&batch(1, 0, recs)).unwrap_err();
    assert!(below(&err), "{err}");
    assert_eq!(frame.cut().whole().total_samples(), 0);
    let info = frame.info();
    assert_eq!((info.rejected_batches, info.rejected_samples), (5, 200));
    assert_eq!(frame.version(), 0);
}

#[test]
fn a_retried_batch_counts_once() {
    let frame = ShardedFrame::new(spec(4, 4));
    let recs = vec![Record {
        x: 0,
        y: 0,
        rgb: [2.0; 3],
    }];
    let first = frame.ingest(&batch(9, 0, recs.clone())).unwrap();
    let again = frame.ingest(&batch(9, 0, recs.clone())).unwrap();
    assert_eq!(
        first,
        Ingested {
            accepted: 1,
            duplicate: false
        }
    );
    assert_eq!(
        again,
        Ingested {
            accepted: 0,
            duplicate: true
        }
    );
    assert!(!frame.ingest(&batch(8, 0, recs)).unwrap().duplicate);
    assert_eq!(frame.info().samples, 2);
}

#[test]
fn imports_add_exactly_and_deltas_count_once() {
    let scene = FireflyScene::new(9, 30, 2);
    let frame = ShardedFrame::new(spec(9, 30));
    let mut other = FrameState::new(9, 30, CascadeLayout::with_defaults());
    for pass in 0..5 {
        other.splat_all(scene.pass(pass));
        frame
            .ingest(&batch(1, pass, records(&scene, pass)))
            .unwrap();
    }
    let origin = Origin {
        node: "n1".into(),
        seq: 0,
    };
    assert_eq!(
        frame.import("f", &other, None, Some(&origin), &[]),
        Ok(Some(other.total_samples()))
    );
    assert_eq!(
        frame.import("f", &other, None, Some(&origin), &[]),
        Ok(None)
    );
    let mut expected = other.clone();
    expected.merge(&other).unwrap();
    assert_eq!(frame.cut().whole(), expected);

    let wrong = FrameState::new(9, 31, CascadeLayout::with_defaults());
    let err = frame.import("f", &wrong, None, None, &[]).unwrap_err();
    assert!(err.to_string().contains("9x30"), "{err}");
    assert_eq!(frame.cut().whole(), expected);
}

/// A cut holds every band as it was at the cut, whatever is applied while it is held
/// (a batch over every band, an import), and the frame itself loses nothing; only bands
/// changed while a cut holds them are copied.
#[test]
fn a_cut_is_the_frame_at_the_cut() {
    let scene = FireflyScene::new(9, 70, 3);
    let frame = ShardedFrame::new(spec(9, 70));
    assert!(frame.bands.len() >= 4, "the test needs several bands");
    for pass in 0..3 {
        frame
            .ingest(&batch(1, pass, records(&scene, pass)))
            .unwrap();
    }
    let cut = frame.cut();
    let at_cut: Vec<FrameState> = cut.bands.iter().map(|b| (**b).clone()).collect();
    let at_cut_seen = cut.seen.clone();
    let mut other = FrameState::new(9, 70, CascadeLayout::with_defaults());
    other.splat_all(scene.pass(7));

    // The cut shares the bands: taking it copied nothing.
    for (band, held) in frame.bands.iter().zip(&cut.bands) {
        assert!(Arc::ptr_eq(&lock(band), held));
    }
    frame.ingest(&batch(1, 3, records(&scene, 3))).unwrap();
    frame.import("f", &other, None, None, &[]).unwrap();
    let held: Vec<FrameState> = cut.bands.iter().map(|b| (**b).clone()).collect();
    assert_eq!(held, at_cut, "the cut is the frame as it was");
    assert_eq!(cut.seen, at_cut_seen);
    for (band, held) in frame.bands.iter().zip(&cut.bands) {
        assert!(!Arc::ptr_eq(&lock(band), held), "changed bands were copied");
    }

    let mut expected = cut.whole();
    expected.splat_all(scene.pass(3));
    expected.merge(&other).unwrap();
    drop(cut);
    assert_eq!(frame.cut().whole(), expected);

    // With no cut held, a writer changes its band in place.
    let before: Vec<*const FrameState> =
        frame.bands.iter().map(|b| Arc::as_ptr(&lock(b))).collect();
    frame.ingest(&batch(1, 4, records(&scene, 4))).unwrap();
    let after: Vec<*const FrameState> = frame.bands.iter().map(|b| Arc::as_ptr(&lock(b))).collect();
    assert_eq!(before, after, "no copy without a cut");
}

#[test]
fn nonsense_parameters_are_refused_by_name() {
    let mut req = CreateFrame::new("f", 4, 4);
    req.cascades.base = 1.0;
    let err = FrameSpec::new(req).unwrap_err();
    assert!(err.to_string().contains("base"), "{err}");
    let err = FrameSpec::new(CreateFrame::new("f", 0, 4)).unwrap_err();
    assert!(err.to_string().contains("0x4"), "{err}");
    let mut req = CreateFrame::new("f", 4, 4);
    req.resolve.kappa = -1.0;
    assert!(FrameSpec::new(req)
        .unwrap_err()
        .to_string()
        .contains("kappa"));
}

/// A batch id reused for other records is refused by name, applies nothing and is counted;
/// the original batch's retry is still a plain duplicate.
#[test]
fn an_id_reused_for_other_records_is_refused() {
    let frame = ShardedFrame::new(spec(4, 4));
    let first = vec![Record::new(0, 0, [2.0; 3])];
    let other = vec![Record::new(1, 1, [3.0; 3])];
    frame.ingest(&batch(9, 0, first.clone())).unwrap();
    let before = frame.cut().whole();
    let err = frame.ingest(&batch(9, 0, other)).unwrap_err();
    assert!(
        matches!(
            err,
            IngestError::IdReused {
                worker: 9,
                seq: 0,
                ..
            }
        ),
        "{err}"
    );
    assert!(
        err.to_string()
            .contains("already applied with other records"),
        "{err}"
    );
    assert_eq!(
        frame.cut().whole(),
        before,
        "nothing of the refused batch applied"
    );
    let info = frame.info();
    assert_eq!(
        (info.samples, info.rejected_batches, info.rejected_samples),
        (1, 1, 1)
    );
    assert!(frame.ingest(&batch(9, 0, first)).unwrap().duplicate);
}

/// A state holding only some rows of the frame (legal in the state format) is added whole,
/// into whichever bands its rows fall in; a state that does not fit changes nothing: not the
/// cells, not the origins seen, not the version.
#[test]
fn imports_are_all_or_nothing() {
    let scene = FireflyScene::new(16, 64, 8);
    let frame = ShardedFrame::new(spec(16, 64));
    assert!(frame.bands.len() >= 8, "the test needs several bands");
    let layout = CascadeLayout::with_defaults();
    // Rows 4..20 straddle band boundaries.
    let mut part = FrameState::band(16, 64, 4..20, layout.clone());
    let mut whole = FrameState::new(16, 64, layout.clone());
    for pass in 0..6 {
        let rows = part.rows();
        part.splat_all(scene.pass(pass).filter(|s| rows.contains(&s.1)));
    }
    whole.merge(&part).unwrap();
    let origin = Origin {
        node: "n".into(),
        seq: 0,
    };
    assert_eq!(
        frame.import("f", &part, None, Some(&origin), &[]),
        Ok(Some(part.total_samples()))
    );
    assert_eq!(frame.cut().whole(), whole);
    assert_eq!(frame.version(), 1);

    let other_layout = CascadeLayout::new(
        layout.base(),
        5,
        layout.lowest_scale(),
        layout.luminance_weights(),
    )
    .unwrap();
    let misfit = FrameState::band(16, 64, 0..8, other_layout);
    let retry = Origin {
        node: "m".into(),
        seq: 0,
    };
    let err = frame
        .import("f", &misfit, None, Some(&retry), &[])
        .unwrap_err();
    assert!(matches!(err, ImportRefused::Mismatch { .. }), "{err}");
    assert_eq!(frame.cut().whole(), whole);
    assert_eq!(frame.version(), 1);
    assert!(
        !frame.cut().seen.nodes.contains_key("m"),
        "a refused import's origin is not recorded"
    );
}

/// A batch with a sample brighter than the layout represents, or one that would put more
/// than 2^32 samples in a pixel, is refused whole and counted; so is an import that would.
#[test]
fn too_bright_samples_and_full_pixels_are_refused_whole() {
    let frame = ShardedFrame::new(spec(4, 40));
    let max = frame.spec().layout.max_component() as f32;
    let mut recs: Vec<Record> = (0..40).map(|y| Record::new(1, y, [max; 3])).collect();
    recs[30].rgb[2] = 1e14;
    let err = frame.ingest(&batch(1, 0, recs.clone())).unwrap_err();
    assert!(
        matches!(
            err,
            IngestError::Sample {
                index: 30,
                error: SampleError::TooBright { .. },
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("largest representable"), "{err}");
    assert_eq!(frame.version(), 0);
    recs[30].rgb[2] = max;
    assert_eq!(frame.ingest(&batch(1, 0, recs)).unwrap().accepted, 40);

    // Fill pixel (2, 3) to 2^32 samples, by an import.
    let mut full = FrameState::new(4, 40, frame.spec().layout.clone());
    full.splat(2, 3, [1.0; 3]).unwrap();
    for _ in 0..32 {
        let copy = full.clone();
        full.merge(&copy).unwrap();
    }
    assert_eq!(
        frame.import("f", &full, None, None, &[]),
        Ok(Some(full.total_samples()))
    );
    let before = frame.cut().whole();
    let recs = vec![
        Record::new(0, 0, [1.0; 3]),
        Record::new(2, 3, [1.0; 3]),
        Record::new(3, 3, [1.0; 3]),
    ];
    let err = frame.ingest(&batch(1, 1, recs)).unwrap_err();
    assert!(
        matches!(
            err,
            IngestError::Sample {
                index: 1,
                error: SampleError::PixelFull { x: 2, y: 3 },
                ..
            }
        ),
        "{err}"
    );
    let mut one = FrameState::new(4, 40, frame.spec().layout.clone());
    one.splat(2, 3, [1.0; 3]).unwrap();
    one.splat(0, 39, [1.0; 3]).unwrap();
    let err = frame.import("f", &one, None, None, &[]).unwrap_err();
    assert_eq!(
        err,
        ImportRefused::Mismatch {
            frame: "f".into(),
            error: MergeError::TooManySamples { x: 2, y: 3 }
        }
    );
    assert_eq!(frame.cut().whole(), before, "nothing of either applied");
    let info = frame.info();
    assert_eq!(info.samples, 40 + (1 << 32));
    assert_eq!(info.spp_max, 1 << 32);
    assert_eq!((info.rejected_batches, info.rejected_samples), (2, 43));
    // Other pixels still take samples.
    let ok = vec![Record::new(0, 0, [1.0; 3]), Record::new(3, 39, [2.0; 3])];
    assert_eq!(frame.ingest(&batch(1, 2, ok)).unwrap().accepted, 2);
}

/// A pass large enough to be splatted on several threads ([`super::ingest`]'s
/// `PARALLEL_SAMPLES`) gives the frame one state would hold, bit for bit.
#[test]
fn a_large_pass_splatted_on_several_threads_is_the_one_state() {
    let (w, h) = (1024, 512);
    let scene = FireflyScene::new(w, h, 5);
    let frame = ShardedFrame::new(spec(w, h));
    assert!(frame.bands.len() > 1, "the test needs several bands");
    let mut reference = FrameState::new(w, h, CascadeLayout::with_defaults());
    for pass in 0..2 {
        let rgb: Vec<[f32; 3]> = scene.pass(pass).map(|(_, _, rgb)| rgb).collect();
        reference.splat_all(scene.pass(pass));
        let got = frame.ingest_pass(1, pass, &rgb, None).unwrap();
        assert_eq!(got.accepted, u64::from(w * h));
    }
    assert!(frame.cut().whole() == reference, "the frame differs");
}

/// A pass ingested whole (rows straight into the bands) against the batch of its records:
/// the same cells over several bands, the same digest (a pass retried as records is a
/// duplicate, other records under its id a conflict), the same refusals with the same
/// index and record for a bad sample and for a full pixel, and nothing applied by them.
#[test]
fn a_pass_is_ingested_as_the_batch_of_its_records() {
    let (w, h) = (13, 70);
    let scene = FireflyScene::new(w, h, 5);
    let by_pass = ShardedFrame::new(spec(w, h));
    let by_records = ShardedFrame::new(spec(w, h));
    assert!(by_pass.bands.len() > 1, "the test needs several bands");
    for pass in 0..6 {
        let recs = records(&scene, pass);
        let rgb: Vec<[f32; 3]> = recs.iter().map(|r| r.rgb).collect();
        let got = by_pass.ingest_pass(1, pass, &rgb, None).unwrap();
        assert_eq!(got.accepted, (w * h) as u64);
        by_records.ingest(&batch(1, pass, recs)).unwrap();
    }
    assert_eq!(by_pass.cut().whole(), by_records.cut().whole());
    let again = by_pass.ingest(&batch(1, 5, records(&scene, 5))).unwrap();
    assert!(again.duplicate, "the records of pass 5 are its retry");
    let err = by_pass
        .ingest(&batch(1, 5, records(&scene, 6)))
        .unwrap_err();
    assert!(matches!(err, IngestError::IdReused { .. }), "{err}");

    // A bad sample: refused naming the same record as the batch refusal does.
    let mut recs = records(&scene, 6);
    recs[200].rgb[1] = -1.0;
    let rgb: Vec<[f32; 3]> = recs.iter().map(|r| r.rgb).collect();
    let version = by_pass.version();
    let err = by_pass.ingest_pass(1, 6, &rgb, None).unwrap_err();
    assert_eq!(err, by_records.ingest(&batch(1, 6, recs)).unwrap_err());
    assert!(
        matches!(err, IngestError::Sample { index: 200, .. }),
        "{err}"
    );
    assert_eq!(by_pass.version(), version);

    // A full pixel: pixel (2, 3), holding 6 samples, to 2^32 by an import into both frames
    // of 2^32 samples less 6.
    let layout = by_pass.spec().layout.clone();
    let mut full = FrameState::new(w, h, layout.clone());
    full.splat(2, 3, [1.0; 3]).unwrap();
    for _ in 0..32 {
        let copy = full.clone();
        full.merge(&copy).unwrap();
    }
    let mut six = FrameState::new(w, h, layout);
    for _ in 0..6 {
        six.splat(2, 3, [1.0; 3]).unwrap();
    }
    let top = full.delta_since(&six).unwrap();
    for frame in [&by_pass, &by_records] {
        assert_eq!(
            frame.import("f", &top, None, None, &[]),
            Ok(Some(top.total_samples()))
        );
        assert_eq!(frame.cut().whole().spp(2, 3), MAX_PIXEL_SAMPLES);
    }
    let before = by_pass.cut().whole();
    let recs = records(&scene, 7);
    let rgb: Vec<[f32; 3]> = recs.iter().map(|r| r.rgb).collect();
    let err = by_pass.ingest_pass(1, 7, &rgb, None).unwrap_err();
    assert_eq!(err, by_records.ingest(&batch(1, 7, recs)).unwrap_err());
    assert!(
        matches!(
            err,
            IngestError::Sample {
                index: 41,
                error: SampleError::PixelFull { x: 2, y: 3 },
                ..
            }
        ),
        "{err}"
    );
    assert_eq!(by_pass.cut().whole(), before, "nothing of it applied");
    let info = by_pass.info();
    // The conflicting id, the bad sample and the full pixel.
    assert_eq!((info.rejected_batches, info.rejected_samples), (3, 3 * 910));
}

/// A state body imported from its runs (checked and added piece by piece, straight from the
/// bytes) gives the frame the same cells as the decoded state, with the same refusals.
#[test]
fn imports_from_runs_match_imports_of_states() {
    let import_runs = |frame: &ShardedFrame, state: &FrameState| {
        let bytes = splatd_formats::state::dump(state, None, "f", None, vec![]).encode();
        let (dump, runs, aov_runs) =
            splatd_proto::StateDump::decode_runs(&bytes, u64::MAX).unwrap();
        let decoded = splatd_formats::state::load_runs(dump, runs, aov_runs).unwrap();
        frame.import("f", &decoded, decoded.aovs(), None, &[])
    };
    let scene = FireflyScene::new(16, 64, 9);
    let layout = CascadeLayout::with_defaults();
    // Rows 4..20 straddle band boundaries; every other pixel of a row is empty, so the
    // state is many short runs.
    let mut part = FrameState::band(16, 64, 4..20, layout.clone());
    for pass in 0..5 {
        let rows = part.rows();
        part.splat_all(
            scene
                .pass(pass)
                .filter(|s| rows.contains(&s.1) && (s.0 + s.1) % 2 == 0),
        );
    }
    let (states, runs) = (
        ShardedFrame::new(spec(16, 64)),
        ShardedFrame::new(spec(16, 64)),
    );
    assert!(runs.bands.len() >= 8, "the test needs several bands");
    for _ in 0..2 {
        let added = Ok(Some(part.total_samples()));
        assert_eq!(states.import("f", &part, None, None, &[]), added);
        assert_eq!(import_runs(&runs, &part), added);
    }
    assert_eq!(runs.cut().whole(), states.cut().whole());
    assert_eq!(runs.info().samples, 2 * part.total_samples());

    // A pixel at 2^32 samples refuses a state adding one more, whole.
    let small = ShardedFrame::new(spec(4, 40));
    let mut full = FrameState::new(4, 40, small.spec().layout.clone());
    full.splat(2, 3, [1.0; 3]).unwrap();
    for _ in 0..32 {
        let copy = full.clone();
        full.merge(&copy).unwrap();
    }
    assert_eq!(import_runs(&small, &full), Ok(Some(full.total_samples())));
    let before = small.cut().whole();
    let mut one = FrameState::new(4, 40, small.spec().layout.clone());
    one.splat(0, 0, [1.0; 3]).unwrap();
    one.splat(2, 3, [1.0; 3]).unwrap();
    assert_eq!(
        import_runs(&small, &one).unwrap_err(),
        ImportRefused::Mismatch {
            frame: "f".into(),
            error: MergeError::TooManySamples { x: 2, y: 3 }
        }
    );
    assert_eq!(small.cut().whole(), before, "nothing of it applied");
}

/// `bytes` (a state body) imported as the server imports a body: decoded in place, its cells
/// checked as they are added.
fn import_body(
    frame: &ShardedFrame,
    bytes: &[u8],
    origin: Option<&Origin>,
) -> Result<Option<u64>, ImportRefused> {
    let (dump, runs, aov_runs) = splatd_proto::StateDump::decode_runs(bytes, u64::MAX).unwrap();
    let decoded = splatd_formats::state::load_runs(dump, runs, aov_runs).unwrap();
    frame.import("f", &decoded, decoded.aovs(), origin, &[])
}

/// A state's cells are checked as they are added, so a bad pixel may be found after much of
/// the state was added (by every thread adding a share): the import is refused, naming the
/// first bad pixel in pixel order, and the frame is left bit for bit as it was (what was added
/// is taken back), its samples, version and applied origins too. A good state adds after that.
#[test]
fn a_refusal_found_while_adding_leaves_the_frame_as_it_was() {
    let (w, h) = (256, 160);
    let frame = ShardedFrame::new(spec(w, h));
    let layout = CascadeLayout::with_defaults();
    let stride = estimator::cell_len(layout.cascades());
    let scene = FireflyScene::new(w, h, 21);
    let mut state = FrameState::new(w, h, layout.clone());
    state.splat_all(scene.pass(0));
    assert_eq!(
        frame.import("f", &state, None, None, &[]),
        Ok(Some(state.total_samples()))
    );
    state.splat_all(scene.pass(1));
    let good = splatd_formats::state::dump(&state, None, "f", None, vec![]);
    assert_eq!(
        good.cells.len(),
        (w * h) as usize * stride,
        "every pixel is held"
    );
    let before = frame.cut().whole();
    let (version, samples) = (frame.version(), frame.info().samples);
    let origin = Origin {
        node: "n".into(),
        seq: 7,
    };
    let unchanged = |what: &str| {
        assert!(frame.cut().whole() == before, "{what}: the frame changed");
        assert_eq!(frame.version(), version, "{what}");
        assert_eq!(frame.info().samples, samples, "{what}");
        assert!(!frame.cut().seen.nodes.contains_key("n"), "{what}");
    };
    let pixel = |x: u32, y: u32| (y * w + x) as usize;

    // Counts that are not whole samples: in the last rows, in the middle, and in both (the
    // first is named, whichever share of the pixels it lies in).
    for bad in [
        vec![(7, h - 2)],
        vec![(3, h / 2 - 1)],
        vec![(200, h - 1), (5, 40)],
    ] {
        let mut dump = good.clone();
        for &(x, y) in &bad {
            dump.cells[pixel(x, y) * stride + 3] += 1;
        }
        let first = *bad.iter().min_by_key(|&&(x, y)| pixel(x, y)).unwrap();
        let err = import_body(&frame, &dump.encode(), Some(&origin)).unwrap_err();
        assert!(
            matches!(
                &err,
                ImportRefused::Invalid(ImportError::Cells(CellsError::Invalid { x, y, .. }))
                    if (*x, *y) == first
            ),
            "{bad:?}: {err}"
        );
        unchanged(&format!("{bad:?}"));
    }

    // A pixel of a run that holds nothing, near the end: the state is one run of every pixel,
    // so its cells lie after the run header at a known place.
    let mut bytes = good.encode();
    let cells_at = bytes.len() - 8 * good.cells.len() - 8 - 8 - 8;
    assert_eq!(bytes[cells_at - 8..cells_at - 4], 0u32.to_le_bytes());
    assert_eq!(bytes[cells_at - 4..cells_at], (w * h).to_le_bytes());
    let p = pixel(9, h - 3);
    bytes[cells_at + 8 * p * stride..cells_at + 8 * (p + 1) * stride].fill(0);
    let err = import_body(&frame, &bytes, Some(&origin)).unwrap_err();
    assert!(
        matches!(&err, ImportRefused::Invalid(ImportError::State(StateError::Malformed(m))) if m.contains(&format!("pixel {p} "))),
        "{err}"
    );
    unchanged("a pixel holding nothing");

    // A pixel with no room left, near the end: filled to 2^32 samples in a frame of its own.
    let full_frame = ShardedFrame::new(spec(w, h));
    let mut full = FrameState::new(w, h, layout.clone());
    full.splat(250, h - 4, [1.0; 3]).unwrap();
    for _ in 0..32 {
        let copy = full.clone();
        full.merge(&copy).unwrap();
    }
    full_frame.import("f", &full, None, None, &[]).unwrap();
    let full_before = full_frame.cut().whole();
    let err = import_body(&full_frame, &good.encode(), Some(&origin)).unwrap_err();
    assert_eq!(
        err,
        ImportRefused::Mismatch {
            frame: "f".into(),
            error: MergeError::TooManySamples { x: 250, y: h - 4 }
        }
    );
    assert!(
        full_frame.cut().whole() == full_before,
        "the full frame changed"
    );
    assert!(!full_frame.cut().seen.nodes.contains_key("n"));

    // The good state adds whole.
    assert_eq!(
        import_body(&frame, &good.encode(), Some(&origin)),
        Ok(Some(state.total_samples()))
    );
    let mut expected = before.clone();
    expected.merge(&state).unwrap();
    assert!(frame.cut().whole() == expected);
    assert_eq!(frame.info().samples, samples + state.total_samples());
    assert!(frame.cut().seen.nodes.contains_key("n"));
}

/// A state's header is checked before its AOV words are expanded, with the refusals that
/// `import` gives: another frame's id, another size, AOVs other than the frame's (a state
/// without AOVs is fine). Nothing is applied by a check.
#[test]
fn state_headers_are_checked_before_aov_words_are_expanded() {
    let albedo = vec![AovSpec::new("albedo", &["R", "G", "B"])];
    let mut request = CreateFrame::new("f", 8, 4);
    request.aovs = albedo.clone();
    let frame = ShardedFrame::new(FrameSpec::new(request).unwrap());
    assert_eq!(frame.check_state_header("f", 8, 4, &albedo), Ok(()));
    assert_eq!(frame.check_state_header("f", 8, 4, &[]), Ok(()));
    assert!(matches!(
        frame.check_state_header("g", 9, 4, &albedo),
        Err(ImportRefused::WrongFrame { state, .. }) if state == "g"
    ));
    assert_eq!(
        frame.check_state_header("f", 9, 4, &albedo),
        Err(ImportRefused::Mismatch {
            frame: "f".into(),
            error: MergeError::Size {
                ours_w: 8,
                ours_h: 4,
                theirs_w: 9,
                theirs_h: 4
            }
        })
    );
    let depth = [AovSpec::new("depth", &["Z"])];
    match frame.check_state_header("f", 8, 4, &depth) {
        Err(ImportRefused::Aovs { reason, .. }) => {
            assert!(reason.contains("\"depth\" (Z)"), "{reason}");
            assert!(reason.contains("\"albedo\" (R, G, B)"), "{reason}");
        }
        other => panic!("{other:?}"),
    }
    // A frame without AOVs takes no state with AOVs.
    let plain = ShardedFrame::new(spec(8, 4));
    assert!(matches!(
        plain.check_state_header("f", 8, 4, &albedo),
        Err(ImportRefused::Aovs { .. })
    ));
    assert_eq!(frame.info().samples, 0);
}

/// After `retire` returns, nothing is applied: batches and imports are refused by name.
#[test]
fn a_retired_frame_takes_nothing() {
    let frame = ShardedFrame::new(spec(4, 4));
    frame
        .ingest(&batch(1, 0, vec![Record::new(0, 0, [1.0; 3])]))
        .unwrap();
    frame.retire();
    let err = frame
        .ingest(&batch(1, 1, vec![Record::new(0, 0, [1.0; 3])]))
        .unwrap_err();
    assert!(matches!(err, IngestError::Deleted { .. }), "{err}");
    let state = frame.cut().whole();
    assert!(matches!(
        frame.import("f", &state, None, None, &[]),
        Err(ImportRefused::Deleted { .. })
    ));
    assert_eq!(frame.info().samples, 1);
    frame.unretire();
    assert!(frame
        .ingest(&batch(1, 1, vec![Record::new(0, 0, [1.0; 3])]))
        .is_ok());
}

/// A deletion waits for the answers of requests that hold a lease, and no lease is given
/// after it began.
#[tokio::test]
async fn a_deletion_drains_leased_requests_first() {
    let frame = Arc::new(ShardedFrame::new(spec(4, 4)));
    let lease = frame.lease().await.expect("a live frame leases");
    let deleting = tokio::spawn({
        let frame = frame.clone();
        async move { frame.retire_and_drain().await }
    });
    // Retiring runs on a blocking thread that a loaded machine may start late: wait for it
    // as an event, bounded only against a hang.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    while !frame.is_retired() && std::time::Instant::now() < deadline {
        tokio::time::sleep(std::time::Duration::from_millis(1)).await;
    }
    assert!(frame.is_retired());
    assert!(frame.lease().await.is_none(), "no lease after retiring");
    tokio::task::yield_now().await;
    assert!(
        !deleting.is_finished(),
        "the deletion waits for the leased request"
    );
    drop(lease);
    deleting.await.unwrap();
}
