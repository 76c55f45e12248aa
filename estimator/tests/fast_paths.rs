//! The fast splat paths against the simple one: a batch splatted with `splat_records` (scan-order
//! runs found and splatted a block at a time, vectorized) and rows splatted with `splat_row`, on
//! every kernel this CPU runs, must leave the very same cells and report as `splat`, one sample
//! at a time, in the same order. Bit for bit: the state is compared word by word.

use proptest::prelude::*;
use splatd_estimator::{
    CascadeLayout, FrameState, Kernel, SampleError, SplatReport, MAX_PIXEL_SAMPLES,
    REC709_LUMINANCE,
};

#[path = "common/kernels.rs"]
mod kernels;
use kernels::kernels;

const W: u32 = 40;
const H: u32 = 5;

type Rec = (u32, u32, [f32; 3]);

/// The simple path: `splat` per sample, with the report built from its results.
fn one_by_one(state: &mut FrameState, records: &[Rec]) -> SplatReport {
    let mut r = SplatReport::default();
    for &(x, y, rgb) in records {
        match state.splat(x, y, rgb) {
            Ok(()) => r.accepted += 1,
            Err(SampleError::NonFinite) => r.non_finite += 1,
            Err(SampleError::Negative) => r.negative += 1,
            Err(SampleError::OutOfFrame { .. }) => r.out_of_frame += 1,
            Err(SampleError::TooBright { .. }) => r.too_bright += 1,
            Err(SampleError::PixelFull { .. }) => r.pixel_full += 1,
        }
    }
    r
}

/// Values at and around every boundary the split and the fixed-point conversion have: each
/// cascade scale (and its neighbours in `f32`), zero, `-0.0`, the largest component and the one
/// above it, tiny and subnormal values, and what must be refused.
fn edge_values(layout: &CascadeLayout) -> Vec<f32> {
    let mut v = vec![
        0.0,
        -0.0,
        f32::MIN_POSITIVE,
        1e-40,
        1e-6,
        0.5,
        1.0,
        f32::NAN,
        f32::INFINITY,
        -1.0,
        -1e-30,
    ];
    let max = layout.max_component() as f32;
    v.extend([
        max,
        f32::from_bits(max.to_bits() - 1),
        f32::from_bits(max.to_bits() + 1),
        3e38,
    ]);
    for &c in layout.scales() {
        let c = c as f32;
        for w in REC709_LUMINANCE {
            // Grey samples land exactly on c when the weights sum to 1; single channels at c / w.
            let on = (c as f64 / w) as f32;
            v.extend([
                c,
                on,
                f32::from_bits(on.to_bits() + 1),
                f32::from_bits(on.to_bits() - 1),
            ]);
        }
        v.extend([
            f32::from_bits(c.to_bits() + 1),
            f32::from_bits(c.to_bits() - 1),
        ]);
    }
    v
}

fn layouts() -> Vec<CascadeLayout> {
    vec![
        CascadeLayout::with_defaults(),
        CascadeLayout::new(8.0, 8, 0.125, REC709_LUMINANCE).unwrap(),
        // A base that is not a power of two, 16 cascades, unusual weights.
        CascadeLayout::new(3.7, 16, 0.01, [0.5, 1.0, 1.0 / 32.0]).unwrap(),
        CascadeLayout::new(1000.0, 2, 1e-3, [0.3, 0.6, 0.1]).unwrap(),
    ]
}

fn sample(edges: Vec<f32>) -> impl Strategy<Value = [f32; 3]> {
    let value = prop_oneof![
        4 => 0.0f32..2.0,
        2 => (0.0f64..1.0).prop_map(|u| (0.05 * u.powf(-1.0 / 1.2)) as f32),
        2 => prop::sample::select(edges),
        1 => 0.0f32..3e11,
    ];
    prop::array::uniform3(value)
}

/// A batch of scan-order runs (some leaving the frame, some shorter than a block) mixed with
/// loose records, as workers send them.
fn batch(edges: Vec<f32>) -> impl Strategy<Value = Vec<Rec>> {
    let run = (
        0..W + 3,
        0..H + 1,
        prop::collection::vec(sample(edges.clone()), 0..45),
    )
        .prop_map(|(x0, y, rgb)| {
            rgb.into_iter()
                .enumerate()
                .map(|(i, c)| (x0 + i as u32, y, c))
                .collect::<Vec<Rec>>()
        });
    let loose = (0..W + 1, 0..H, sample(edges)).prop_map(|r| vec![r]);
    prop::collection::vec(prop_oneof![2 => run, 1 => loose], 0..12).prop_map(|parts| parts.concat())
}

fn layout_and_batch() -> impl Strategy<Value = (CascadeLayout, Vec<Rec>)> {
    prop::sample::select(layouts()).prop_flat_map(|layout| {
        let edges = edge_values(&layout);
        (Just(layout), batch(edges))
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    #[test]
    fn splat_records_gives_the_bits_of_one_by_one((layout, records) in layout_and_batch()) {
        let mut simple = FrameState::new(W, H, layout.clone());
        let expected = one_by_one(&mut simple, &records);
        for kernel in kernels() {
            let mut fast = FrameState::new(W, H, layout.clone());
            let report = fast.splat_records_with(kernel, &records);
            prop_assert_eq!(report, expected, "{:?}", kernel);
            prop_assert!(fast == simple, "{:?}: cells differ", kernel);
            prop_assert_eq!(fast.total_samples(), simple.total_samples());
        }
        let mut from = FrameState::new(W, H, layout.clone());
        prop_assert_eq!(from.splat_records_from(in_two_runs(&records)), expected);
        prop_assert!(from == simple, "splat_records_from: cells differ");
        let mut all = FrameState::new(W, H, layout.clone());
        prop_assert_eq!(all.splat_all(records.iter().copied()), expected);
        prop_assert!(all == simple);
        // The valid samples alone (records outside the frame kept), as a caller that checked
        // them gives them.
        let valid = valid_only(&layout, &records);
        let mut simple = FrameState::new(W, H, layout.clone());
        let expected = one_by_one(&mut simple, &valid);
        let mut trusted = FrameState::new(W, H, layout);
        prop_assert_eq!(trusted.splat_valid_records_from(in_two_runs(&valid)), expected);
        prop_assert!(trusted == simple, "splat_valid_records_from: cells differ");
    }
}

/// Records in random order over a band of the frame, many blocks of them, some above, below or
/// beside the band, some invalid: the blocks that take the fast path and those that do not.
fn scattered(edges: Vec<f32>) -> impl Strategy<Value = Vec<Rec>> {
    let record = (0..W + 2, 0..H + 2, sample(edges));
    prop::collection::vec(record, 0..300)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn scattered_records_in_a_band_give_the_bits_of_one_by_one(
        (layout, records) in prop::sample::select(layouts()).prop_flat_map(|layout| {
            let edges = edge_values(&layout);
            (Just(layout), scattered(edges))
        })
    ) {
        let band = 1..H - 1;
        let mut simple = FrameState::band(W, H, band.clone(), layout.clone());
        let expected = one_by_one(&mut simple, &records);
        for kernel in kernels() {
            let mut fast = FrameState::band(W, H, band.clone(), layout.clone());
            let report = fast.splat_records_with(kernel, &records);
            prop_assert_eq!(report, expected, "{:?}", kernel);
            prop_assert!(fast == simple, "{:?}: cells differ", kernel);
        }
        let mut from = FrameState::band(W, H, band.clone(), layout.clone());
        prop_assert_eq!(from.splat_records_from(in_two_runs(&records)), expected);
        prop_assert!(from == simple, "splat_records_from: cells differ");
        let valid = valid_only(&layout, &records);
        let mut simple = FrameState::band(W, H, band.clone(), layout.clone());
        let expected = one_by_one(&mut simple, &valid);
        let mut trusted = FrameState::band(W, H, band, layout);
        prop_assert_eq!(trusted.splat_valid_records_from(in_two_runs(&valid)), expected);
        prop_assert!(trusted == simple, "splat_valid_records_from: cells differ");
    }
}

/// `records` as an iterator over two runs of them (split a third of the way in), as a band's
/// runs of a batch come: not one slice.
fn in_two_runs(records: &[Rec]) -> impl Iterator<Item = Rec> + '_ {
    let (a, b) = records.split_at(records.len() / 3);
    a.iter().chain(b).copied()
}

/// The records whose samples `layout` accepts, in order.
fn valid_only(layout: &CascadeLayout, records: &[Rec]) -> Vec<Rec> {
    records
        .iter()
        .filter(|r| layout.check_sample(r.2).is_ok())
        .copied()
        .collect()
}

/// Every edge value in every channel position, as whole rows, on every kernel.
#[test]
fn rows_of_edge_values_give_the_bits_of_one_by_one() {
    for layout in layouts() {
        let edges = edge_values(&layout);
        let mut rgb = Vec::new();
        for (i, &a) in edges.iter().enumerate() {
            for &b in &edges[i % 7..i % 7 + 3] {
                rgb.push([a, b, 0.25]);
                rgb.push([b, 0.0, a]);
                rgb.push([a, a, a]);
            }
        }
        let width = rgb.len() as u32;
        let mut simple = FrameState::new(width, 2, layout.clone());
        let records: Vec<Rec> = rgb
            .iter()
            .enumerate()
            .map(|(x, &c)| (x as u32, 1, c))
            .collect();
        let expected = one_by_one(&mut simple, &records);
        assert!(expected.accepted > 0 && expected.rejected() > 0);
        for kernel in kernels() {
            let mut fast = FrameState::new(width, 2, layout.clone());
            assert_eq!(fast.splat_row_with(kernel, 0, 1, &rgb), expected);
            assert!(fast == simple, "{kernel:?} with {layout:?}");
            // Only valid samples, so that every block takes the fast path.
            let valid: Vec<[f32; 3]> = rgb
                .iter()
                .copied()
                .filter(|&c| layout.check_sample(c).is_ok())
                .collect();
            let mut simple = FrameState::new(valid.len() as u32, 1, layout.clone());
            for (x, &c) in valid.iter().enumerate() {
                simple.splat(x as u32, 0, c).unwrap();
            }
            let mut fast = FrameState::new(valid.len() as u32, 1, layout.clone());
            let report = fast.splat_row_with(kernel, 0, 0, &valid);
            assert_eq!(report.accepted, valid.len() as u64);
            assert!(fast == simple, "{kernel:?} with {layout:?}, valid samples");
        }
        // The same valid samples as a caller that checked them gives them (the detected
        // kernel), also past the row's end, where they are refused one by one as outside.
        let valid: Vec<[f32; 3]> = rgb
            .iter()
            .copied()
            .filter(|&c| layout.check_sample(c).is_ok())
            .collect();
        let n = valid.len() as u32;
        let mut simple = FrameState::new(n, 1, layout.clone());
        let records: Vec<Rec> = (0..n).map(|x| (x + 5, 0, valid[x as usize])).collect();
        let expected = one_by_one(&mut simple, &records);
        assert_eq!(expected.out_of_frame, 5);
        let mut trusted = FrameState::new(n, 1, layout.clone());
        assert_eq!(trusted.splat_valid_row(5, 0, &valid), expected);
        assert!(trusted == simple, "splat_valid_row with {layout:?}");
        let mut trusted = FrameState::new(n, 1, layout.clone());
        let report = trusted.splat_valid_row(0, 0, &valid);
        assert_eq!(report.accepted, n as u64);
        let mut fast = FrameState::new(n, 1, layout.clone());
        fast.splat_row(0, 0, &valid);
        assert!(trusted == fast, "splat_valid_row with {layout:?}, inside");
    }
}

/// The largest component many times over: the top cascade's words carry into the high word on
/// the fast path exactly as on the simple one.
#[test]
fn carries_into_the_high_word_match() {
    let layout = CascadeLayout::with_defaults();
    let m = layout.max_component() as f32;
    let row = [[m, m * 0.75, 0.0]; 20];
    let mut simple = FrameState::new(20, 1, layout.clone());
    let mut snapshots = Vec::new();
    for pass in 0..5000 {
        for (x, &c) in row.iter().enumerate() {
            simple.splat(x as u32, 0, c).unwrap();
        }
        if pass % 1000 == 999 {
            snapshots.push(simple.clone());
        }
    }
    for kernel in kernels() {
        let mut fast = FrameState::new(20, 1, layout.clone());
        for pass in 0..5000 {
            fast.splat_row_with(kernel, 0, 0, &row);
            if pass % 1000 == 999 {
                assert!(
                    fast == snapshots[pass / 1000],
                    "{kernel:?} after {} passes",
                    pass + 1
                );
            }
        }
        assert_eq!(fast.total_samples(), 100_000);
    }
    // The words did carry: 5000 samples of 2^52 units are past 2^64.
    assert!(splatd_estimator::top_sum(&simple.cells()[..25], 0) > 1 << 64);
}

/// A row across pixels that are full or one sample from full: refused exactly where the simple
/// path refuses, the rest accepted.
#[test]
fn full_pixels_are_refused_as_one_by_one() {
    let layout = CascadeLayout::with_defaults();
    let mut state = FrameState::new(W, 1, layout.clone());
    // Pixel 3 at 2^32 - 1 samples, pixel 20 at 2^32, the rest at 2^31 or 0.
    let mut one = FrameState::new(W, 1, layout.clone());
    one.splat_row(0, 0, &[[1.0, 2.0, 3.0]; W as usize]);
    let mut doubled = one.clone();
    for _ in 0..31 {
        let copy = doubled.clone();
        doubled.merge(&copy).unwrap();
    }
    state.merge(&doubled).unwrap();
    assert_eq!(state.spp(3, 0), 1 << 31);
    let mut top_up = FrameState::new(W, 1, layout.clone());
    let mut part = FrameState::new(W, 1, layout.clone());
    part.splat(3, 0, [0.5; 3]).unwrap();
    part.splat(20, 0, [0.5; 3]).unwrap();
    for _ in 0..31 {
        let copy = part.clone();
        part.merge(&copy).unwrap();
    }
    top_up.merge(&part).unwrap();
    state.merge(&top_up).unwrap();
    let mut minus_one = FrameState::new(W, 1, layout.clone());
    minus_one.splat(3, 0, [0.5; 3]).unwrap();
    let less = state.delta_since(&minus_one);
    // delta_since subtracts from the later state: less = state - one sample at pixel 3.
    let state = less.unwrap();
    assert_eq!(state.spp(3, 0), MAX_PIXEL_SAMPLES - 1);
    assert_eq!(state.spp(20, 0), MAX_PIXEL_SAMPLES);
    let rgb: Vec<[f32; 3]> = (0..W).map(|x| [x as f32, 1.0, 2.0]).collect();
    let records: Vec<Rec> = rgb
        .iter()
        .enumerate()
        .map(|(x, &c)| (x as u32, 0, c))
        .chain(rgb.iter().enumerate().map(|(x, &c)| (x as u32, 0, c)))
        .collect();
    let mut simple = state.clone();
    let expected = one_by_one(&mut simple, &records);
    assert_eq!(expected.pixel_full, 3, "20 twice, then 3 once it is full");
    for kernel in kernels() {
        let mut fast = state.clone();
        assert_eq!(fast.splat_records_with(kernel, &records), expected);
        assert!(fast == simple, "{kernel:?}");
    }
    let mut from = state.clone();
    assert_eq!(from.splat_records_from(in_two_runs(&records)), expected);
    assert!(from == simple, "splat_records_from");
    let mut trusted = state.clone();
    assert_eq!(
        trusted.splat_valid_records_from(in_two_runs(&records)),
        expected
    );
    assert!(trusted == simple, "splat_valid_records_from");
}
