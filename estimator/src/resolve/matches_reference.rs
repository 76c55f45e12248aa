//! The vectorized row pass against the reference (the one-pixel-at-a-time resolve it replaced):
//! the same bits for every variant, kernel, thread count and tiling, on random valid states
//! that reach every bound the state allows (counts and sums past `2^52`, the top cascade's
//! 85-bit sums, `2^32` samples in a pixel, empty cascades and pixels, widths that are not a
//! multiple of the group or strip, neighbours across strips) and on states splatted from
//! heavy-tailed samples.

use proptest::prelude::*;
use splatd_scenes::synth::SplitMix64;

use super::{reference, resolve_bands, resolve_bands_with, ResolveParams, Resolved, Variant};
use crate::layout::{CascadeLayout, COUNT_ONE, MAX_PIXEL_SAMPLES, REC709_LUMINANCE};
use crate::state::{cell_len, FrameState, Kernel, HI_BITS, LOW_SHARE_MAX, TOP_SHARE_MAX};

/// Every number of a resolve as raw bits, so equality means bit-identical.
fn bits(r: &Resolved) -> (Vec<u32>, Vec<u64>) {
    let floats = [&r.reweighted, &r.mean, &r.removed]
        .iter()
        .flat_map(|layer| layer.iter().flatten().map(|v| v.to_bits()))
        .collect();
    (floats, r.spp.clone())
}

#[path = "../../tests/common/kernels.rs"]
mod kernels;
use kernels::kernels;

/// A random integer in `0..=max`, often one of its edges (0, 1, `max`, around `2^52`).
fn edgy(rng: &mut SplitMix64, max: u128) -> u128 {
    let pick = match rng.next_u64() % 8 {
        0 => 0,
        1 => 1,
        2 => max,
        3 => (1 << 52) - 1,
        4 => 1 << 52,
        5 => (1 << 53) + 1,
        _ => {
            // Uniform in bits, then in value: every magnitude is as likely.
            let bits = rng.next_u64() % 86;
            let r = (rng.next_u64() as u128) << 64 | rng.next_u64() as u128;
            r & ((1u128 << bits) - 1)
        }
    };
    pick.min(max)
}

/// Sample counts of a pixel: empty, few, around the fast conversion's limit `2^20` and where
/// sums can first pass `2^52` (`2^52 / LOW_SHARE_MAX`, about `2.8e6`), the most.
fn samples(rng: &mut SplitMix64) -> u64 {
    match rng.next_u64() % 10 {
        0 => 0,
        1 => 1 + rng.next_u64() % 3,
        2 => 1 << 20,
        3 => (1 << 20) + 1,
        4 => (1 << 20) + rng.next_u64() % (1 << 23),
        5 => 3 << 20,
        6 => MAX_PIXEL_SAMPLES,
        7 => 1 + rng.next_u64() % MAX_PIXEL_SAMPLES,
        _ => 1 + rng.next_u64() % 64,
    }
}

/// A valid cell (the state's bounds hold) of `k` cascades: `n` samples' counts spread over the
/// cascades, each sum of a cascade with count anywhere up to what `n` samples can add, cascades
/// often empty.
fn random_cell(rng: &mut SplitMix64, k: usize, cell: &mut [u64]) {
    let n = samples(rng);
    let mut left = n * COUNT_ONE;
    for j in 0..k {
        let count = if j + 1 == k {
            left
        } else {
            (edgy(rng, left as u128) as u64).min(left)
        };
        left -= count;
        cell[4 * j + 3] = count;
        // A cascade without count holds no energy (`FrameState::from_cells` checks it).
        let empty = rng.next_u64().is_multiple_of(3) || count == 0;
        for c in 0..3 {
            if empty {
                continue;
            }
            if j + 1 == k {
                let sum = edgy(rng, n as u128 * TOP_SHARE_MAX as u128);
                cell[4 * j + c] = sum as u64;
                cell[4 * k] |= ((sum >> 64) as u64) << (HI_BITS * c as u32);
            } else {
                cell[4 * j + c] = edgy(rng, n as u128 * LOW_SHARE_MAX as u128) as u64;
            }
        }
    }
}

fn random_state(seed: u64, width: u32, height: u32, layout: &CascadeLayout) -> FrameState {
    let mut rng = SplitMix64::new(seed);
    let len = cell_len(layout.cascades());
    let mut cells = vec![0u64; width as usize * height as usize * len];
    for cell in cells.chunks_exact_mut(len) {
        random_cell(&mut rng, layout.cascades(), cell);
    }
    FrameState::from_cells(width, height, 0..height, layout.clone(), cells).expect("valid cells")
}

/// Heavy-tailed samples (most dim, a few fireflies), some pixels left empty.
fn splatted_state(seed: u64, width: u32, height: u32, layout: &CascadeLayout) -> FrameState {
    let mut rng = SplitMix64::new(seed);
    let mut state = FrameState::new(width, height, layout.clone());
    for _ in 0..width * height * 3 {
        let (x, y) = (
            (rng.next_u64() % width as u64) as u32,
            (rng.next_u64() % height as u64) as u32,
        );
        let z = 0.05 * rng.next_f64().powf(-1.0 / 1.1);
        let rgb = [z as f32, (z * rng.next_f64()) as f32, (z * 0.3) as f32];
        if layout.check_sample(rgb).is_ok() {
            state.splat(x, y, rgb).expect("checked");
        }
    }
    state
}

/// The state cut into bands at `cut` (when it is inside the frame).
fn cut(state: &FrameState, cut: u32) -> Vec<FrameState> {
    let (w, h) = (state.width(), state.height());
    let len = cell_len(state.layout().cascades()) * w as usize;
    let cut = cut.clamp(1, h);
    [0..cut, cut..h]
        .into_iter()
        .filter(|r| !r.is_empty())
        .map(|rows| {
            let cells = state.cells()[rows.start as usize * len..rows.end as usize * len].to_vec();
            FrameState::from_cells(w, h, rows, state.layout().clone(), cells).expect("a band")
        })
        .collect()
}

fn params() -> Vec<ResolveParams> {
    let mut all = Vec::new();
    for variant in [
        Variant::Paper,
        Variant::Shader,
        Variant::Off,
        Variant::Spread,
    ] {
        for (kappa, kappa_min, exponent) in [(4.0, 1.0, 0.0), (0.7, 0.0, 0.35), (1e6, 1e6, 0.9)] {
            all.push(ResolveParams::new(variant, kappa, kappa_min, exponent).expect("valid"));
        }
    }
    all
}

fn layouts() -> Vec<CascadeLayout> {
    vec![
        CascadeLayout::new(8.0, 8, 0.125, REC709_LUMINANCE).unwrap(),
        CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap(),
        CascadeLayout::new(2.0, 2, 1e-3, [1.0 / 32.0, 1.0, 0.5]).unwrap(),
        CascadeLayout::new(3.5, 16, 1e-6, [0.3, 0.6, 0.1]).unwrap(),
    ]
}

/// The fast resolve of `state` on every kernel, thread count and cut equals the reference's.
fn check(state: &FrameState, cut_at: u32) -> Result<(), TestCaseError> {
    let bands = cut(state, cut_at);
    let band_refs: Vec<&FrameState> = bands.iter().collect();
    let pixels = (state.width() * state.height()) as usize;
    // A buffer of the right size holding numbers no resolve gives: every one must be rewritten.
    let garbage = Resolved {
        width: state.width(),
        height: state.height(),
        reweighted: vec![[f32::NAN; 3]; pixels],
        mean: vec![[-1.0; 3]; pixels],
        removed: vec![[f32::INFINITY; 3]; pixels],
        spp: vec![u64::MAX; pixels],
        scratch: Default::default(),
    };
    for p in params() {
        let expected = bits(&reference::resolve_bands(&[state], &p, 1).expect("whole frame"));
        for kernel in kernels() {
            for threads in [1, 2, 3] {
                let mut fresh = Resolved::default();
                resolve_bands_with(kernel, &[state], &p, threads, &mut fresh).expect("frame");
                prop_assert!(
                    bits(&fresh) == expected,
                    "{kernel:?}, {threads} threads, {p:?}"
                );
            }
            let mut reused = garbage.clone();
            resolve_bands_with(kernel, &band_refs, &p, 2, &mut reused).expect("bands tile");
            prop_assert!(
                bits(&reused) == expected,
                "{kernel:?}, bands, reused, {p:?}"
            );
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn random_states_at_every_bound_resolve_to_the_reference_bits(
        seed in any::<u64>(),
        // Narrow frames, and frames of two and three strips (64 pixels) with a ragged end.
        width in prop_oneof![1u32..20, 60u32..140],
        height in 1u32..6,
        layout in 0usize..4,
        cut_at in 0u32..6,
    ) {
        let state = random_state(seed, width, height, &layouts()[layout]);
        check(&state, cut_at)?;
    }

    #[test]
    fn splatted_states_resolve_to_the_reference_bits(
        seed in any::<u64>(),
        width in prop_oneof![1u32..27, 60u32..140],
        height in 1u32..6,
        layout in 0usize..4,
        cut_at in 0u32..6,
    ) {
        let state = splatted_state(seed, width, height, &layouts()[layout]);
        check(&state, cut_at)?;
    }
}

/// Pixels that each sit on one bound, side by side, so that every group mixes them.
#[test]
fn a_frame_of_extreme_pixels_resolves_to_the_reference_bits() {
    let layout = CascadeLayout::new(8.0, 8, 0.125, REC709_LUMINANCE).unwrap();
    let k = layout.cascades();
    let len = cell_len(k);
    let (w, h) = (11u32, 3u32);
    let mut cells = vec![0u64; (w * h) as usize * len];
    for (i, cell) in cells.chunks_exact_mut(len).enumerate() {
        let n = [0, 1, 1 << 20, (1 << 20) + 1, 3 << 20, MAX_PIXEL_SAMPLES][i % 6];
        if n == 0 {
            continue;
        }
        // Every cascade has some count (a cascade without holds no energy), most in cascade 0.
        cell[3] = n * COUNT_ONE - (k as u64 - 1);
        for j in 1..k {
            cell[4 * j + 3] = 1;
        }
        match i % 3 {
            // Every sum at its bound.
            0 => {
                for j in 0..k - 1 {
                    cell[4 * j..4 * j + 3].fill(n * LOW_SHARE_MAX);
                }
                let top = n as u128 * TOP_SHARE_MAX as u128;
                for c in 0..3 {
                    cell[4 * (k - 1) + c] = top as u64;
                    cell[4 * k] |= ((top >> 64) as u64) << (HI_BITS * c as u32);
                }
            }
            // Only the top cascade, with a high word where `n` allows one.
            1 => {
                let top = ((1u128 << 65) - 1).min(n as u128 * TOP_SHARE_MAX as u128);
                cell[4 * (k - 1)] = top as u64;
                cell[4 * k] = (top >> 64) as u64;
            }
            // Sums just below and at 2^52 in the low cascades.
            _ => {
                let max = n * LOW_SHARE_MAX;
                cell[0] = ((1 << 52) - 1).min(max);
                cell[5] = (1 << 52).min(max);
                cell[10] = ((1 << 52) + 1).min(max);
            }
        }
    }
    let state = FrameState::from_cells(w, h, 0..h, layout, cells).expect("valid cells");
    check(&state, 1).expect("same bits");
}

/// A frame wider than a column of strips (`COLUMN_STRIPS * STRIP` = 512 pixels), with a ragged
/// last strip: the columns' edges and rings.
#[test]
fn a_frame_wider_than_a_column_resolves_to_the_reference_bits() {
    let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
    check(&splatted_state(7, 1061, 3, &layout), 2).expect("same bits");
    check(&random_state(8, 1030, 2, &layout), 1).expect("same bits");
}

/// A cascade empty in every pixel of a strip but one, where only one channel holds a value, is
/// weighed: only cascades empty in the whole strip are skipped.
#[test]
fn a_cascade_with_one_value_in_a_strip_resolves_to_the_reference_bits() {
    let layout = CascadeLayout::new(8.0, 8, 0.125, REC709_LUMINANCE).unwrap();
    let k = layout.cascades();
    let len = cell_len(k);
    let (w, h) = (70u32, 3u32);
    for (j, channel) in [(5, 2), (3, 1), (k - 1, 0), (k - 1, 2)] {
        let mut cells = vec![0u64; (w * h) as usize * len];
        for (i, cell) in cells.chunks_exact_mut(len).enumerate() {
            // Two samples in cascade 0 everywhere, dim and even.
            cell[0..4].copy_from_slice(&[3 << 20, 3 << 20, 3 << 20, 2 * COUNT_ONE]);
            if i == w as usize + 37 {
                // A third sample, in cascade `j` alone and one channel of it: a firefly.
                cell[4 * j + channel] = 1 << 30;
                cell[4 * j + 3] = COUNT_ONE;
            }
        }
        let state = FrameState::from_cells(w, h, 0..h, layout.clone(), cells).expect("valid");
        check(&state, 1).expect("same bits");
        let out = resolve_bands(&[&state], &ResolveParams::with_defaults(), 1).expect("frame");
        let firefly = (w + 37) as usize;
        assert!(
            out.mean[firefly][channel] > 2.0 * out.mean[0][channel],
            "the firefly is in the mean: {:?}",
            out.mean[firefly]
        );
    }
}

/// The spread stage merges each band's sources from every part's columns into row-major
/// order: a frame of two columns of strips, cut into several parts, with settings that give
/// back a lot.
#[test]
fn sources_of_several_parts_and_columns_give_back_the_reference_bits() {
    let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
    for state in [
        splatted_state(11, 1061, 13, &layout),
        random_state(12, 1030, 9, &layout),
    ] {
        for p in spread_params() {
            let expected = bits(&reference::resolve_bands(&[&state], &p, 1).expect("frame"));
            for threads in 1..=3 {
                let mut out = Resolved::default();
                resolve_bands_with(Kernel::detect(), &[&state], &p, threads, &mut out)
                    .expect("frame");
                assert!(bits(&out) == expected, "{threads} threads, {p:?}");
            }
        }
    }
}

/// The spread stage resolves a block of rows at a time, every column of strips in turn, and a
/// column's next block starts from the support rows its last block left in the ring: a frame
/// of three columns and three blocks.
#[test]
fn blocks_of_rows_over_several_columns_give_back_the_reference_bits() {
    let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
    let rows = 2 * crate::resolve_spread::BLOCK_ROWS as u32 + 5;
    let state = splatted_state(13, 1061, rows, &layout);
    for p in spread_params() {
        let expected = bits(&reference::resolve_bands(&[&state], &p, 1).expect("frame"));
        let mut out = Resolved::default();
        resolve_bands_with(Kernel::detect(), &[&state], &p, 1, &mut out).expect("frame");
        assert!(bits(&out) == expected, "{p:?}");
    }
}

/// Spread settings that give back a lot: low support, every widest window.
fn spread_params() -> Vec<ResolveParams> {
    let mut all = Vec::new();
    for max_radius in [1, 8, 16] {
        for (support, edge_share) in [(2.0, Some(0.1)), (20.0, None), (64.0, Some(0.0))] {
            let spread = crate::SpreadParams::new(support, 0.0, max_radius)
                .and_then(|s| s.with_edge_share(edge_share))
                .expect("valid");
            for (kappa, exponent) in [(4.0, 0.0), (3.0, 0.3)] {
                all.push(
                    ResolveParams::new(Variant::Spread, kappa, 1.0, exponent)
                        .expect("valid")
                        .with_spread(spread),
                );
            }
        }
    }
    all
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Frames taller than the widest window (the summed-area table's ring of rows wraps), with
    /// the sparse, threaded spread stage against the dense one, at every thread count.
    #[test]
    fn the_spread_stage_gives_back_the_reference_bits(
        seed in any::<u64>(),
        width in 1u32..90,
        height in 1u32..50,
        layout in 0usize..2,
        random in any::<bool>(),
    ) {
        let layout = &layouts()[layout];
        let state = if random {
            random_state(seed, width, height, layout)
        } else {
            splatted_state(seed, width, height, layout)
        };
        // Also into one buffer reused by every resolve (holding the last one's layers).
        let mut reused = Resolved::default();
        for p in spread_params() {
            let expected = bits(&reference::resolve_bands(&[&state], &p, 1).expect("frame"));
            for threads in 1..=4 {
                let mut out = Resolved::default();
                resolve_bands_with(Kernel::detect(), &[&state], &p, threads, &mut out)
                    .expect("frame");
                prop_assert!(bits(&out) == expected, "{threads} threads, {p:?}");
                resolve_bands_with(Kernel::detect(), &[&state], &p, 5 - threads, &mut reused)
                    .expect("frame");
                prop_assert!(bits(&reused) == expected, "reused, {p:?}");
            }
        }
    }
}

/// Support sums past `u64`: a source at the centre of a 17x17 frame whose support reaches
/// `support` only in the widest window, which holds a ring of 64 pixels of `2^32` samples each
/// (`2^64` units of support; not solid with this `kappa`). Summed in `u64` the window's support
/// wraps below `support` and the energy would stay removed; the stage sums such a frame in
/// `u128`, as the reference always does.
#[test]
fn support_sums_past_u64_give_back_the_reference_bits() {
    let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
    let (w, h, centre) = (17u32, 17u32, 8u32);
    let mut state = FrameState::new(w, h, layout.clone());
    for y in 0..h {
        for x in 0..w {
            if x.abs_diff(centre).max(y.abs_diff(centre)) < 8 {
                state.splat(x, y, [0.01; 3]).unwrap();
            }
        }
    }
    let len = cell_len(layout.cascades());
    let mut cells = state.cells().to_vec();
    for (i, cell) in cells.chunks_exact_mut(len).enumerate() {
        let (x, y) = (i as u32 % w, i as u32 / w);
        if x.abs_diff(centre).max(y.abs_diff(centre)) == 8 {
            // Samples of value 0 in cascade 0: support, no energy.
            cell[3] = MAX_PIXEL_SAMPLES * COUNT_ONE;
        }
    }
    let state = FrameState::from_cells(w, h, 0..h, layout, cells).expect("valid cells");
    let spread = crate::SpreadParams::new(1e6, 0.0, 8).expect("valid");
    let p = ResolveParams::new(Variant::Spread, 1e6, 1.0, 0.9)
        .expect("valid")
        .with_spread(spread);
    centre_given_back_with_the_reference_bits(&state, &p, centre, "the widest window");
}

/// The reference resolve of `state` with `p` gives the centre pixel (`centre`, `centre`) back
/// energy the paper removed (`what` gives it back), and the spread stage gives the reference's
/// bits on 1 and 2 threads.
fn centre_given_back_with_the_reference_bits(
    state: &FrameState,
    p: &ResolveParams,
    centre: u32,
    what: &str,
) {
    let expected = reference::resolve_bands(&[state], p, 1).expect("frame");
    let paper = reference::resolve_bands(&[state], &p.with_variant(Variant::Paper), 1).unwrap();
    let at = (centre * state.width() + centre) as usize;
    assert!(
        expected.reweighted[at][0] > paper.reweighted[at][0],
        "{what}: a window gives the centre's energy back"
    );
    for threads in [1, 2] {
        let mut out = Resolved::default();
        resolve_bands_with(Kernel::detect(), &[state], p, threads, &mut out).expect("frame");
        assert!(bits(&out) == bits(&expected), "{what}, {threads} threads");
    }
}

/// Support sums near the top of what the spread stage's `u64` table entries hold (53 bits of
/// support units beside 11 of solid pixels): 33x33 frames whose pixels hold 120 000 samples
/// of a band with no energy (a full 33x33 box of them is `2^52.7` units), all of them or a ring
/// at the widest window's edge, and past it (`2^17` samples: summed in `u128`), around a
/// firefly at the centre that no `kappa` trusts. The same bits as the reference, which sums
/// in `u128` always.
#[test]
fn support_sums_near_the_top_of_u64_entries_give_back_the_reference_bits() {
    let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
    let (w, h, centre) = (33u32, 33u32, 16u32);
    let len = cell_len(layout.cascades());
    let spread = crate::SpreadParams::new(1e6, 0.0, 16).expect("valid");
    let p = ResolveParams::new(Variant::Spread, 1e6, 1.0, 0.9)
        .expect("valid")
        .with_spread(spread);
    let ring = |x: u32, y: u32| x.abs_diff(centre).max(y.abs_diff(centre)) == 16;
    // Per frame: its name, then the samples of a pixel on the ring and off it.
    let frames = [
        ("every pixel 120 000", 120_000, 120_000),
        ("a ring of 120 000", 120_000, 1),
        ("every pixel 2^17", 1 << 17, 1 << 17),
    ];
    for (name, on_ring, off_ring) in frames {
        // The firefly: one sample of cascade 2 at the centre; every pixel's samples of value 0
        // in cascade 3 (band 2's neighbour: its support).
        let mut state = FrameState::new(w, h, layout.clone());
        state.splat(centre, centre, [20.0; 3]).unwrap();
        let mut cells = state.cells().to_vec();
        for (i, cell) in cells.chunks_exact_mut(len).enumerate() {
            let (x, y) = (i as u32 % w, i as u32 / w);
            let samples: u64 = if ring(x, y) { on_ring } else { off_ring };
            cell[4 * 3 + 3] += samples * COUNT_ONE;
        }
        let state = FrameState::from_cells(w, h, 0..h, layout.clone(), cells).expect("valid");
        centre_given_back_with_the_reference_bits(&state, &p, centre, name);
    }
}
