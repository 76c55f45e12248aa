//! Algebraic and statistical properties of the estimator core (docs/ALGORITHM.md, "Where it is
//! tested"): exact, order-independent merging; weights that only ever remove energy; nothing
//! removed where samples are plentiful; convergence to the true mean.

use proptest::prelude::*;
use splatd_estimator::{
    CascadeLayout, FrameState, ResolveParams, Resolved, SpreadParams, Variant, REC709_LUMINANCE,
    SPREAD_RADII,
};
use splatd_scenes::synth::FireflyScene;

const W: u32 = 5;
const H: u32 = 4;

fn layout() -> CascadeLayout {
    CascadeLayout::new(8.0, 6, 0.125, REC709_LUMINANCE).unwrap()
}

fn record() -> impl Strategy<Value = (u32, u32, [f32; 3])> {
    let value = prop_oneof![
        6 => 0.0f32..2.0,
        2 => 0.0f32..200.0,
        1 => 0.0f32..1e6,
    ];
    (0..W, 0..H, prop::array::uniform3(value))
}

fn records(max: usize) -> impl Strategy<Value = Vec<(u32, u32, [f32; 3])>> {
    prop::collection::vec(record(), 0..max)
}

fn state_of(records: &[(u32, u32, [f32; 3])]) -> FrameState {
    let mut state = FrameState::new(W, H, layout());
    let report = state.splat_all(records.iter().copied());
    assert_eq!(report.rejected(), 0);
    state
}

fn merged(mut a: FrameState, b: &FrameState) -> FrameState {
    a.merge(b).expect("same frame");
    a
}

/// Every float of a resolve as raw bits, so equality means bit-identical.
fn bits(r: &Resolved) -> Vec<u32> {
    [&r.reweighted, &r.mean, &r.removed]
        .iter()
        .flat_map(|layer| layer.iter().flatten().map(|v| v.to_bits()))
        .chain(r.spp.iter().map(|&n| n as u32))
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    #[test]
    fn merge_is_commutative(a in records(100), b in records(100)) {
        let (a, b) = (state_of(&a), state_of(&b));
        prop_assert_eq!(merged(a.clone(), &b), merged(b, &a));
    }

    #[test]
    fn merge_is_associative(a in records(60), b in records(60), c in records(60)) {
        let (a, b, c) = (state_of(&a), state_of(&b), state_of(&c));
        prop_assert_eq!(
            merged(merged(a.clone(), &b), &c),
            merged(a, &merged(b, &c))
        );
    }

    #[test]
    fn any_split_into_partial_states_merges_to_the_single_state(
        all in records(300),
        parts in prop::collection::vec(0usize..4, 300),
    ) {
        let single = state_of(&all);
        let mut partial: Vec<FrameState> = (0..4).map(|_| FrameState::new(W, H, layout())).collect();
        for (record, &part) in all.iter().zip(&parts) {
            partial[part].splat(record.0, record.1, record.2).unwrap();
        }
        let combined = partial.iter().fold(FrameState::new(W, H, layout()), merged);
        prop_assert_eq!(&combined, &single);
        let p = ResolveParams::with_defaults();
        prop_assert_eq!(bits(&combined.resolve(&p)), bits(&single.resolve(&p)));
    }

    #[test]
    fn resolve_is_independent_of_sample_order_bit_for_bit(
        (all, order) in records(300).prop_flat_map(|r| {
            let n = r.len();
            (Just(r), Just((0..n).collect::<Vec<_>>()).prop_shuffle())
        }),
        variant in prop_oneof![Just(Variant::Paper), Just(Variant::Shader), Just(Variant::Spread)],
    ) {
        let shuffled: Vec<_> = order.iter().map(|&i| all[i]).collect();
        let p = ResolveParams::new(variant, 3.0, 1.0, 0.0).unwrap();
        prop_assert_eq!(
            bits(&state_of(&all).resolve(&p)),
            bits(&state_of(&shuffled).resolve(&p))
        );
    }

    #[test]
    fn weights_only_remove_energy(
        all in records(300),
        variant in prop_oneof![Just(Variant::Paper), Just(Variant::Shader)],
        kappa in 0.5f64..50.0,
    ) {
        let r = state_of(&all).resolve(&ResolveParams::new(variant, kappa, 1.0, 0.0).unwrap());
        for p in 0..r.mean.len() {
            for c in 0..3 {
                prop_assert!(r.removed[p][c] >= 0.0, "negative removed energy at {p}");
                prop_assert!(r.reweighted[p][c] <= r.mean[p][c] * (1.0 + 1e-6) + 1e-30);
                let sum = r.reweighted[p][c] as f64 + r.removed[p][c] as f64;
                prop_assert!((sum - r.mean[p][c] as f64).abs() <= 1e-6 * r.mean[p][c] as f64 + 1e-30,
                    "reweighted + removed != mean at {p}");
            }
        }
    }

    /// The `spread` stage moves removed energy, it never makes any: every pixel keeps
    /// `reweighted + removed = mean`, the frame's removed energy is at least 0 and at most what
    /// the paper's resolve with the same weights removes, and more given back in one pixel is
    /// never taken from another (`reweighted >= paper's`), at any sample count (`spread`'s first
    /// stage is the paper's resolve, sparse pixels counted the same way).
    #[test]
    fn spread_moves_removed_energy_and_never_makes_any(
        all in records(300),
        kappa in 0.5f64..20.0,
        exponent in 0.0f64..0.6,
        support in 1.0f64..80.0,
        solid in 0.0f64..1.0,
        radius in prop::sample::select(SPREAD_RADII.to_vec()),
        edge in prop::option::of(0.0f64..1.0),
    ) {
        let state = state_of(&all);
        let paper = ResolveParams::new(Variant::Paper, kappa, 1.0, exponent).unwrap();
        let spread = paper
            .with_variant(Variant::Spread)
            .with_spread(SpreadParams::new(support, solid, radius).unwrap().with_edge_share(edge).unwrap());
        let (p, s) = (state.resolve(&paper), state.resolve(&spread));
        prop_assert_eq!(&p.mean, &s.mean);
        let (mut removed, mut paper_removed) = (0.0f64, 0.0f64);
        for i in 0..s.mean.len() {
            for c in 0..3 {
                let (f, r) = (s.reweighted[i][c] as f64, s.removed[i][c] as f64);
                let mean = s.mean[i][c] as f64;
                // Each layer is an f32: the identity holds to their rounding.
                prop_assert!((f + r - mean).abs() <= 1e-6 * (f.abs() + r.abs() + mean) + 1e-20,
                    "reweighted + removed != mean at {i}");
                prop_assert!(s.reweighted[i][c] >= p.reweighted[i][c],
                    "energy taken at {i}");
                removed += s.removed[i][c] as f64;
                paper_removed += p.removed[i][c] as f64;
            }
        }
        let scale = 1e-5 * s.mean.iter().flatten().map(|&v| v as f64).sum::<f64>() + 1e-20;
        prop_assert!(removed >= -scale, "the frame gained energy: {removed}");
        prop_assert!(removed <= paper_removed + scale, "{removed} > paper's {paper_removed}");
    }

    #[test]
    fn all_weights_one_is_the_plain_mean(all in records(300)) {
        let r = state_of(&all).resolve(&ResolveParams::off());
        prop_assert_eq!(&r.reweighted, &r.mean);
        prop_assert!(r.removed.iter().flatten().all(|&v| v == 0.0));
    }
}

#[test]
fn a_constant_image_with_enough_samples_loses_nothing() {
    // Dim (below c0), inside the range, exactly on a boundary, and beyond the top cascade.
    let values = [0.0f32, 0.01, 0.125, 0.3, 1.0, 7.7, 64.0, 1000.0, 1e7];
    for variant in [Variant::Paper, Variant::Shader] {
        for kappa in [1.0f64, 4.0, 20.0] {
            let kappa_min: f64 = 1.0;
            // The paper's weight reaches 1 once the count term does: n >= kappa + kappa_min.
            // The shader averages the count and value terms, so it needs the count term at 2.
            let n = match variant {
                Variant::Shader => 2.0 * kappa + kappa_min,
                _ => kappa + kappa_min,
            }
            .ceil() as u32;
            let params = ResolveParams::new(variant, kappa, kappa_min, 0.0).unwrap();
            for &v in &values {
                let mut state = FrameState::new(4, 3, layout());
                for _ in 0..n {
                    for y in 0..3 {
                        for x in 0..4 {
                            state.splat(x, y, [v, v * 0.5, v * 2.0]).unwrap();
                        }
                    }
                }
                let r = state.resolve(&params);
                assert_eq!(
                    r.reweighted, r.mean,
                    "{variant:?} kappa={kappa} value={v}: constant image with {n} spp lost energy"
                );
                let expected = [v, v * 0.5, v * 2.0];
                for (c, e) in expected.iter().enumerate() {
                    let got = r.mean[0][c];
                    assert!(
                        (got - e).abs() <= 1e-6 * e.abs(),
                        "mean {got} != sample {e} for value {v}"
                    );
                }
            }
        }
    }
}

#[test]
fn resolve_converges_to_the_true_mean_as_samples_pile_up() {
    // The lower part of the heavy-tailed half of the synthetic scene: Pareto tails with alpha in
    // 1.5 .. 2 (finite mean, infinite variance). As N grows, support counts grow, weights go to 1
    // and the removed energy goes to 0, like the energy of the tail beyond the band that still
    // has fewer than kappa samples, ~ N^-(alpha-1)/alpha. (Rows with alpha near 1.1 converge too,
    // but as N^-0.09: far too slowly to test.)
    let scene = FireflyScene::new(32, 16, 99);
    let heavy: Vec<(u32, u32)> = (7..16).flat_map(|y| (0..12).map(move |x| (x, y))).collect();
    let exact: f64 = heavy
        .iter()
        .map(|&(x, y)| scene.mean(x, y).iter().sum::<f64>())
        .sum();
    let mut state = FrameState::new(32, 16, CascadeLayout::with_defaults());
    let params = ResolveParams::with_defaults();
    let mut removed_fraction = Vec::new();
    let mut done = 0;
    for n in [16u64, 256, 4096, 32768] {
        for pass in done..n {
            for &(x, y) in &heavy {
                state.splat(x, y, scene.sample(pass, x, y)).unwrap();
            }
        }
        done = n;
        let r = state.resolve(&params);
        let sum = |layer: &[[f32; 3]]| -> f64 {
            heavy
                .iter()
                .map(|&(x, y)| {
                    layer[(y * 32 + x) as usize]
                        .iter()
                        .map(|&v| v as f64)
                        .sum::<f64>()
                })
                .sum()
        };
        let (reweighted, mean) = (sum(&r.reweighted), sum(&r.mean));
        removed_fraction.push((n, 1.0 - reweighted / mean, reweighted / exact - 1.0));
    }
    for pair in removed_fraction.windows(2) {
        assert!(
            pair[1].1 < pair[0].1,
            "removed energy must shrink as N grows: {removed_fraction:?}"
        );
    }
    let (_, removed, bias) = removed_fraction[removed_fraction.len() - 1];
    assert!(
        removed < 0.005,
        "weights should be ~1 at 32768 spp: {removed_fraction:?}"
    );
    assert!(
        bias.abs() < 0.01,
        "reweighted should approach the true mean: {removed_fraction:?}"
    );
}
