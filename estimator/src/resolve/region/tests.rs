//! Region resolves against whole-frame resolves of the same state, bit for bit.

use splatd_scenes::synth::SplitMix64;

use super::{affected, dependency_radius, reach, region, resolve_region_into, Rect};
use crate::layout::CascadeLayout;
use crate::resolve::{resolve_bands, resolve_bands_into, ResolveParams, Resolved, Variant};
use crate::resolve_spread::{SpreadParams, GIVE_BACK_TILE};
use crate::state::{cell_len, FrameState, Kernel};

/// Every number of a resolve as raw bits, so equality means bit-identical.
fn bits(r: &Resolved) -> (u32, u32, Vec<u32>, Vec<u64>) {
    let floats = [&r.reweighted, &r.mean, &r.removed]
        .iter()
        .flat_map(|layer| layer.iter().flatten().map(|v| v.to_bits()))
        .collect();
    (r.width, r.height, floats, r.spp.clone())
}

/// A scene a sample at a time: dim noise, rare fireflies, a caustic (a disc where a sample is
/// bright with probability 1/12, so that its band is supported only over wider windows), and
/// a small light whose band is solid (with partly covered pixels around it, for the edge rule).
struct Scene {
    w: u32,
    h: u32,
    caustic: (f64, f64, f64),
    light: Rect,
}

impl Scene {
    fn new(rng: &mut SplitMix64, w: u32, h: u32) -> Self {
        let at = |rng: &mut SplitMix64, n: u32| (rng.next_u64() % n as u64) as u32;
        let (lx, ly) = (at(rng, w), at(rng, h));
        Self {
            w,
            h,
            caustic: (
                at(rng, w) as f64,
                at(rng, h) as f64,
                2.0 + rng.next_f64() * (w.min(h) as f64 / 3.0),
            ),
            light: Rect::new(lx, ly, lx + 1 + at(rng, 3), ly + 1 + at(rng, 3)),
        }
    }

    fn sample(&self, rng: &mut SplitMix64, x: u32, y: u32) -> [f32; 3] {
        let (cx, cy, r) = self.caustic;
        let (dx, dy) = (x as f64 - cx, y as f64 - cy);
        let inside = |l: &Rect| x >= l.x0 && x < l.x1 && y >= l.y0 && y < l.y1;
        let around = Rect::new(
            self.light.x0.saturating_sub(1),
            self.light.y0.saturating_sub(1),
            self.light.x1 + 1,
            self.light.y1 + 1,
        );
        // The light, and pixels around it partly covering it.
        let v = if inside(&self.light) || (inside(&around) && rng.next_f64() < 0.2) {
            300.0
        } else if dx * dx + dy * dy < r * r && rng.next_f64() < 1.0 / 12.0 {
            40.0
        } else if rng.next_f64() < 1.0 / 400.0 {
            2000.0 + 20000.0 * rng.next_f64()
        } else {
            0.5 * rng.next_f64()
        };
        let v = v as f32;
        [v, v * 0.7, v * 0.4]
    }

    /// Up to `most` samples in every pixel of `rect` (clamped to the frame); some pixels none.
    fn splat(&self, rng: &mut SplitMix64, state: &mut FrameState, rect: &Rect, most: u64) {
        for y in rect.y0..rect.y1.min(self.h) {
            for x in rect.x0..rect.x1.min(self.w) {
                for _ in 0..rng.next_u64() % (most + 1) {
                    let rgb = self.sample(rng, x, y);
                    state.splat(x, y, rgb).expect("a valid sample");
                }
            }
        }
    }
}

/// The state cut into bands at row `cut` (when inside the frame).
fn cut(state: &FrameState, cut: u32) -> Vec<FrameState> {
    let (w, h) = (state.width(), state.height());
    let len = cell_len(state.layout().cascades()) * w as usize;
    [0..cut.min(h), cut.min(h)..h]
        .into_iter()
        .filter(|r| !r.is_empty())
        .map(|rows| {
            let cells = state.cells()[rows.start as usize * len..rows.end as usize * len].to_vec();
            FrameState::from_cells(w, h, rows, state.layout().clone(), cells).expect("a band")
        })
        .collect()
}

/// Random rectangles: anywhere, at the edges and corners, past them, overlapping, empty.
fn rects(rng: &mut SplitMix64, w: u32, h: u32) -> Vec<Rect> {
    let n = rng.next_u64() % 4;
    let mut out = Vec::new();
    for _ in 0..n {
        let mut at = |n: u32| (rng.next_u64() % (n as u64 + 3)) as u32;
        let (x0, y0) = (at(w), at(h));
        let r = match at(6) {
            0 => Rect::new(0, 0, 1 + at(3), 1 + at(3)),
            1 => Rect::new(
                w.saturating_sub(1 + at(3)),
                h.saturating_sub(1),
                w + at(2),
                h,
            ),
            2 => Rect::new(x0, y0, x0, y0 + 3),
            3 => Rect::new(x0, 0, x0 + 1 + at(4), h + 2),
            _ => Rect::new(x0, y0, x0 + 1 + at(6), y0 + 1 + at(6)),
        };
        out.push(r);
    }
    if let Some(&first) = out.first() {
        if rng.next_u64().is_multiple_of(2) {
            // One overlapping another.
            out.push(Rect::new(
                first.x0 + 1,
                first.y0,
                first.x1 + 2,
                first.y1 + 1,
            ));
        }
    }
    out
}

fn spread(support: f64, max_radius: usize, edge_share: Option<f64>) -> ResolveParams {
    ResolveParams::new(Variant::Spread, 4.0, 1.0, 0.0)
        .unwrap()
        .with_spread(
            SpreadParams::new(support, 0.0, max_radius)
                .unwrap()
                .with_edge_share(edge_share)
                .unwrap(),
        )
}

fn params() -> Vec<ResolveParams> {
    vec![
        ResolveParams::new(Variant::Paper, 4.0, 1.0, 0.0).unwrap(),
        ResolveParams::new(Variant::Paper, 3.0, 1.0, 0.3).unwrap(),
        ResolveParams::new(Variant::Shader, 4.0, 1.0, 0.0).unwrap(),
        ResolveParams::off(),
        ResolveParams::with_defaults(),
        spread(4.0, 1, Some(0.1)),
        spread(8.0, 2, None),
        spread(8.0, 8, Some(0.1)),
        spread(6.0, 16, Some(0.0)),
    ]
}

/// Rounds of random changes, each patched into the last result and checked against a whole
/// resolve, with the frame cut into bands at other rows each round.
fn check(w: u32, h: u32, seed: u64, full_above: f64) {
    let layout = CascadeLayout::with_defaults();
    for (i, p) in params().iter().enumerate() {
        for threads in [1, 3] {
            let mut rng = SplitMix64::new(seed * 1000 + i as u64 * 10 + threads as u64);
            let scene = Scene::new(&mut rng, w, h);
            let mut state = FrameState::new(w, h, layout.clone());
            scene.splat(&mut rng, &mut state, &Rect::new(0, 0, w, h), 6);
            let mut out = Resolved::default();
            let bands = cut(&state, h / 2);
            let refs: Vec<&FrameState> = bands.iter().collect();
            resolve_bands_into(&refs, p, threads, &mut out).unwrap();
            for round in 0..3 {
                let changed = rects(&mut rng, w, h);
                for r in &changed {
                    scene.splat(&mut rng, &mut state, r, 4);
                }
                let bands = cut(&state, (rng.next_u64() % (h as u64 + 1)) as u32);
                let refs: Vec<&FrameState> = bands.iter().collect();
                region(
                    Kernel::detect(),
                    &refs,
                    p,
                    threads,
                    &changed,
                    &mut out,
                    full_above,
                )
                .unwrap();
                let expected = resolve_bands(&refs, p, 1).unwrap();
                assert!(
                    bits(&out) == bits(&expected),
                    "{w}x{h} seed {seed} round {round} threads {threads} {changed:?} {p:?}"
                );
            }
        }
    }
}

#[test]
fn region_resolves_equal_whole_resolves_on_small_and_thin_frames() {
    // Smaller than every radius, one row, one column.
    for (w, h) in [(1, 1), (1, 23), (29, 1), (3, 2), (7, 5), (2, 40)] {
        for seed in 0..3 {
            check(w, h, seed, f64::INFINITY);
        }
    }
}

#[test]
fn region_resolves_equal_whole_resolves_on_frames_of_several_tiles() {
    for (seed, (w, h)) in [(70, 45), (100, 64), (131, 97), (65, 130)]
        .into_iter()
        .enumerate()
    {
        check(w, h, seed as u64, f64::INFINITY);
        // As the public function chooses between crops and the whole frame.
        check(w, h, seed as u64 + 10, super::FULL_ABOVE);
    }
}

#[test]
fn a_change_at_distance_two_max_radius_reaches_a_window() {
    // Max radius 2 (windows 3x3, 5x5), support 4. Background 0.5 (cascades 0, 1; trusted). A
    // sample of 300 (cascades 3, 4) at q = (30, 4) is unsupported in its 3x3: the paper
    // removes most of it, and neither window holds 4 samples of its bands. Three samples of
    // 300 at c = (28, 4), two left of q, make the 5x5 around q hold 4: q's energy is given
    // back over it, reaching p = (32, 4), 4 = 2 max_radius from c, and the first pixel of the
    // give-back's second column of tiles (so a reach of 3 would not resolve p's tile again).
    let m = 2;
    let p = spread(4.0, m, None);
    let (w, h) = (70, 9);
    let mut state = FrameState::new(w, h, CascadeLayout::with_defaults());
    for y in 0..h {
        for x in 0..w {
            for _ in 0..16 {
                state.splat(x, y, [0.5; 3]).unwrap();
            }
        }
    }
    state.splat(30, 4, [300.0; 3]).unwrap();
    let mut out = Resolved::default();
    resolve_bands_into(&[&state], &p, 1, &mut out).unwrap();
    let before = out.clone();
    for _ in 0..3 {
        state.splat(28, 4, [300.0; 3]).unwrap();
    }
    let after = state.resolve(&p);
    let at = |x: usize| 4 * w as usize + x;
    assert_eq!(GIVE_BACK_TILE, 32, "p starts a tile column");
    assert!(
        after.reweighted[at(32)][0] > before.reweighted[at(32)][0],
        "the change reaches 2 max_radius: {:?} {:?}",
        after.reweighted[at(32)],
        before.reweighted[at(32)]
    );
    resolve_region_into(&[&state], &p, 1, &[Rect::pixel(28, 4)], &mut out).unwrap();
    assert!(
        bits(&out) == bits(&after),
        "the region resolve reaches p's tile"
    );
    assert_eq!(reach(&p).0, 2 * m as u32, "the tiles' reach is tight");
    assert!(
        affected(&Rect::pixel(28, 4), (2 * m as u32 - 1, 32), w, h).x1 <= 32,
        "one less would miss p's tile"
    );
    assert_eq!(dependency_radius(&p), 2 * m as u32 + 31);
}

#[test]
fn a_large_change_or_an_unknown_result_resolves_the_whole_frame() {
    let (w, h) = (220, 150);
    let layout = CascadeLayout::with_defaults();
    let mut rng = SplitMix64::new(7);
    let scene = Scene::new(&mut rng, w, h);
    let mut state = FrameState::new(w, h, layout);
    scene.splat(&mut rng, &mut state, &Rect::new(0, 0, w, h), 4);
    let p = ResolveParams::with_defaults();
    let mut out = Resolved::default();
    resolve_bands_into(&[&state], &p, 2, &mut out).unwrap();
    // A small change: in crops.
    let small = [Rect::new(60, 40, 66, 44)];
    scene.splat(&mut rng, &mut state, &small[0], 3);
    resolve_region_into(&[&state], &p, 2, &small, &mut out).unwrap();
    assert!(out.scratch.crop.is_some(), "resolved in a crop");
    assert!(bits(&out) == bits(&state.resolve(&p)));
    // Most of the frame: whole.
    let mut whole = out.clone();
    whole.scratch.resolved_with = Some(p);
    let big = [Rect::new(0, 0, 180, 120)];
    scene.splat(&mut rng, &mut state, &big[0], 3);
    resolve_region_into(&[&state], &p, 2, &big, &mut whole).unwrap();
    assert!(whole.scratch.crop.is_none(), "resolved whole");
    assert!(bits(&whole) == bits(&state.resolve(&p)));
    // A clone (no record of its parameters), or other parameters: whole, even if nothing
    // changed.
    let paper = ResolveParams::new(Variant::Paper, 4.0, 1.0, 0.0).unwrap();
    let mut other = state.resolve(&p);
    resolve_region_into(&[&state], &paper, 1, &[], &mut other).unwrap();
    assert!(bits(&other) == bits(&state.resolve(&paper)));
    let mut cloned = state.resolve(&paper).clone();
    cloned.reweighted[0] = [9.0; 3];
    resolve_region_into(&[&state], &paper, 1, &[], &mut cloned).unwrap();
    assert!(bits(&cloned) == bits(&state.resolve(&paper)));
}

#[test]
fn merged_rectangles_cover_every_pixel_and_are_few() {
    let mut rng = SplitMix64::new(3);
    for case in 0..200 {
        let n = [0, 1, 3, 20, 300][case % 5];
        let rects: Vec<Rect> = (0..n)
            .map(|_| {
                let x0 = (rng.next_u64() % 200) as u32;
                let y0 = (rng.next_u64() % 200) as u32;
                Rect::new(
                    x0,
                    y0,
                    x0 + (rng.next_u64() % 12) as u32,
                    y0 + (rng.next_u64() % 12) as u32,
                )
            })
            .collect();
        for max in [1, 4, 16] {
            let merged = Rect::merge(&rects, max);
            assert!(merged.len() <= max, "{case}");
            assert!(merged.iter().all(|r| !r.is_empty()));
            for r in &rects {
                // Inside one merged rectangle (merges are unions).
                if !r.is_empty() {
                    assert!(merged.iter().any(|m| m.union(r) == *m), "{case}: {r:?}");
                }
            }
        }
    }
    // Overlapping ones merge although more are allowed.
    let two = [Rect::new(0, 0, 10, 10), Rect::new(0, 5, 10, 12)];
    assert_eq!(Rect::merge(&two, 16), vec![Rect::new(0, 0, 10, 12)]);
    let apart = [Rect::new(0, 0, 2, 2), Rect::new(50, 50, 52, 52)];
    assert_eq!(Rect::merge(&apart, 16).len(), 2);
}
