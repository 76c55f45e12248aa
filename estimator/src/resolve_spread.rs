//! The `spread` resolve, splatd's default: the paper's reweighting, then each band's removed
//! energy given back blurred wherever that band is supported at a wider scale
//! (docs/ALGORITHM.md, "Beyond the paper").
//!
//! A firefly is unsupported at every scale: no other sample of its brightness band lands near
//! it. A caustic or a small highlight that is sparsely sampled *per pixel* is supported over a
//! wider window: its band has many samples a few pixels around. The paper's resolve judges
//! support over 3x3 pixels only and removes both. Here, for every pixel `q` and band `j`, the
//! energy the paper removed, `r_j(q) = (1 - w_j) B_j(q) / N_q` (in pixel-value units), is
//! *scattered* uniformly over the smallest square window around `q` (radius `1, 2, 3, 4, 6, 8`
//! up to [`SpreadParams::max_radius`], clamped to the frame) holding at least `support` samples
//! of band `j` (with its neighbouring bands, the same support count the paper uses); if even the
//! widest window holds fewer, the energy stays removed. It also stays removed once a window
//! reaches a pixel where the band is *solid*, supported on its own by `kappa(N) + kappa_min`
//! samples (the paper trusts it there without help): such energy was cut at the edge of a light
//! or a highlight, and blurring it would smear the edge over dark pixels (measured: a visible
//! light in the "caustic" scene and the sun in a mirror ball in "pool" lost 3-1000x in relMSE
//! without this rule). Right next to a solid pixel, where the band holds at least `edge_share`
//! of the pixel's own samples (the pixel partly covers the light; the solid pixel itself is one),
//! it is given back in place instead.
//!
//! This is an adaptive ("sample-point") box-kernel density estimate of the removed energy whose
//! bandwidth shrinks where the band is dense, so:
//! * every pixel's given-back energy is a sum of non-negative shares of removed energy, and each
//!   source gives back exactly what it removed or nothing: the frame's removed energy stays
//!   `>= 0`, in every realization, not only in expectation;
//! * it is consistent: as `N` grows every band of positive probability is fully trusted by the
//!   paper's weights, `r_j -> 0`, and the estimate converges to the mean like the paper's;
//! * it reads only the state: bit-identical for any arrival order or merge, and the scatter runs
//!   in a fixed order on one thread whatever the resolve's thread count.

use super::layout::{CascadeLayout, ParamError};
use super::resolve::{ResolveParams, Resolved};

/// Window radii tried, smallest first: 3x3 up to 33x33 (those up to
/// [`SpreadParams::max_radius`]).
pub const SPREAD_RADII: [usize; 8] = [1, 2, 3, 4, 6, 8, 12, 16];
/// splatd's default support a band needs in a window before its removed energy is given back
/// over that window, chosen by the quality benchmark.
pub const DEFAULT_SPREAD_SUPPORT: f64 = 64.0;
/// splatd's default share of a pixel's samples a band needs there (besides full trust) to count
/// as solid, chosen by the quality benchmark.
pub const DEFAULT_SPREAD_SOLID_SHARE: f64 = 0.0;
/// splatd's default for [`SpreadParams::with_edge_share`], chosen by the quality benchmark.
pub const DEFAULT_SPREAD_EDGE_SHARE: Option<f64> = Some(0.1);
/// splatd's default widest window radius, chosen by the quality benchmark.
pub const DEFAULT_SPREAD_MAX_RADIUS: usize = 8;

/// Settings of the spread stage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpreadParams {
    support: f64,
    solid_share: f64,
    max_radius: usize,
    edge_share: Option<f64>,
}

impl SpreadParams {
    /// Validates and builds spread settings.
    ///
    /// * `support in [1, 1e6]`: samples of a band (with its neighbouring bands) a window needs
    ///   before the band's removed energy is given back over it;
    /// * `solid_share in [0, 1]`: a band is *solid* in a pixel, and energy removed next to it
    ///   stays removed, where the paper trusts it fully on its own and it holds at least this
    ///   share of the pixel's samples (the edge of a light, not a dense caustic);
    /// * `max_radius`: the widest window, one of [`SPREAD_RADII`].
    pub fn new(support: f64, solid_share: f64, max_radius: usize) -> Result<Self, ParamError> {
        if !(support.is_finite() && (1.0..=1e6).contains(&support)) {
            return Err(ParamError::new(
                "spread_support",
                format!("must be a number in [1, 1e6], got {support}"),
            ));
        }
        if !(solid_share.is_finite() && (0.0..=1.0).contains(&solid_share)) {
            return Err(ParamError::new(
                "spread_solid_share",
                format!("must be a number in [0, 1], got {solid_share}"),
            ));
        }
        if !SPREAD_RADII.contains(&max_radius) {
            return Err(ParamError::new(
                "spread_max_radius",
                format!("must be one of {SPREAD_RADII:?}, got {max_radius}"),
            ));
        }
        Ok(Self {
            support,
            solid_share,
            max_radius,
            edge_share: DEFAULT_SPREAD_EDGE_SHARE,
        })
    }

    /// The same settings, with energy removed right next to a solid pixel (in the 3x3 around
    /// it) given back where it was removed if the band holds at least this share of the
    /// pixel's own samples there (`Some`, in `[0, 1]`: the pixel partly covers a light), or
    /// left removed (`None`).
    pub fn with_edge_share(self, edge_share: Option<f64>) -> Result<Self, ParamError> {
        if let Some(share) = edge_share {
            if !(share.is_finite() && (0.0..=1.0).contains(&share)) {
                return Err(ParamError::new(
                    "spread_edge_share",
                    format!("must be a number in [0, 1], got {share}"),
                ));
            }
        }
        Ok(Self { edge_share, ..self })
    }

    /// The share of its samples a pixel next to a solid one needs in the band to get its
    /// removed energy back in place (`None`: never).
    pub fn edge_share(&self) -> Option<f64> {
        self.edge_share
    }

    /// splatd's defaults.
    pub fn with_defaults() -> Self {
        Self::new(
            DEFAULT_SPREAD_SUPPORT,
            DEFAULT_SPREAD_SOLID_SHARE,
            DEFAULT_SPREAD_MAX_RADIUS,
        )
        .expect("defaults are valid")
    }

    /// The support a window needs.
    pub fn support(&self) -> f64 {
        self.support
    }

    /// The share of a pixel's samples that makes a trusted band solid there.
    pub fn solid_share(&self) -> f64 {
        self.solid_share
    }

    /// The widest window's radius.
    pub fn max_radius(&self) -> usize {
        self.max_radius
    }
}

/// Per pixel and band, what the first (paper) stage leaves for the spread stage: the removed
/// energy in pixel-value units (RGB) and the band's support count.
pub(crate) const BAND_FLOATS: usize = 4;

/// Gives removed energy back. `bands` holds, per band and pixel (row-major), `[r, g, b, n_j]`;
/// `out` holds the paper's images, updated in place.
pub(crate) fn spread(
    layout: &CascadeLayout,
    bands: &[Vec<f32>],
    params: &ResolveParams,
    out: &mut Resolved,
) {
    let SpreadParams {
        support,
        solid_share,
        max_radius,
        edge_share,
    } = params.spread();
    let radii = SPREAD_RADII.iter().copied().filter(|&r| r <= max_radius);
    let (w, h) = (out.width as usize, out.height as usize);
    let pixels = w * h;
    debug_assert!(
        bands.len() == layout.cascades() && bands.iter().all(|b| b.len() == pixels * BAND_FLOATS)
    );
    let stride = w + 1;
    // Per pixel, the support from which a band is solid there (computed once for every band).
    let solid_from: Vec<f32> = out
        .spp
        .iter()
        .map(|&n| {
            let n = n as f64;
            if n == 0.0 {
                f32::INFINITY
            } else {
                (params.kappa_at(n) + params.kappa_min()).max(solid_share * n) as f32
            }
        })
        .collect();
    // Summed-area table of one band's `[support, solid pixels]`, and one 2D difference array of
    // the give-back of every band (box sums are linear, so one set of prefix sums at the end
    // serves all bands).
    let mut sat = vec![[0.0f64; 2]; stride * (h + 1)];
    let mut diff = vec![[0.0f64; 3]; stride * (h + 1)];
    for plane in bands {
        if plane.chunks_exact(BAND_FLOATS).all(|b| b[..3] == [0.0; 3]) {
            continue;
        }
        for y in 0..h {
            let mut row = [0.0, 0.0];
            let (above, here) = sat[y * stride..(y + 2) * stride].split_at_mut(stride);
            let cells = &plane[y * w * BAND_FLOATS..(y + 1) * w * BAND_FLOATS];
            let solid = &solid_from[y * w..(y + 1) * w];
            for x in 0..w {
                let n = cells[x * BAND_FLOATS + 3];
                row[0] += n as f64;
                row[1] += if n >= solid[x] { 1.0 } else { 0.0 };
                here[x + 1] = [above[x + 1][0] + row[0], above[x + 1][1] + row[1]];
            }
        }
        let boxed = |x0: usize, x1: usize, y0: usize, y1: usize| {
            let [a, b, c, d] = [
                sat[y1 * stride + x1],
                sat[y0 * stride + x1],
                sat[y1 * stride + x0],
                sat[y0 * stride + x0],
            ];
            [a[0] - b[0] - c[0] + d[0], a[1] - b[1] - c[1] + d[1]]
        };
        for (p, band) in plane.chunks_exact(BAND_FLOATS).enumerate() {
            if band[..3] == [0.0; 3] {
                continue;
            }
            let (x, y) = (p % w, p / w);
            let mut window = None;
            for (i, r) in radii.clone().enumerate() {
                let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
                let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
                let [n, solid] = boxed(x0, x1, y0, y1);
                if solid > 0.5 {
                    // The band is solid (fully trusted on its own, and a large share of the
                    // samples) in a pixel of the window: this energy was cut at the edge of a
                    // light or highlight, and blurring it would smear that edge. Right next to
                    // the solid pixel it is the pixel's partial cover of the light: given back
                    // in place (if the band holds `edge_share` of the pixel's samples); farther
                    // away it stays removed.
                    let own = band[3] as f64;
                    let spp = out.spp[p] as f64;
                    if i == 0 && edge_share.is_some_and(|share| own >= share * spp) {
                        window = Some((x, x + 1, y, y + 1));
                    }
                    break;
                }
                if n >= support {
                    window = Some((x0, x1, y0, y1));
                    break;
                }
            }
            let Some((x0, x1, y0, y1)) = window else {
                continue;
            };
            // Every pixel of the window (clamped to the frame) gets an equal share.
            let share = 1.0 / ((x1 - x0) * (y1 - y0)) as f64;
            for c in 0..3 {
                let v = band[c] as f64 * share;
                diff[y0 * stride + x0][c] += v;
                diff[y0 * stride + x1][c] -= v;
                diff[y1 * stride + x0][c] -= v;
                diff[y1 * stride + x1][c] += v;
            }
        }
    }
    // Prefix sums turn the corners into boxes: along each row, then down each column (kept as
    // one running sum per column, so the frame is read in memory order).
    let mut col = vec![[0.0f64; 3]; w];
    for y in 0..h {
        let mut run = [0.0; 3];
        let row = y * w..(y + 1) * w;
        let pixels = out.reweighted[row.clone()]
            .iter_mut()
            .zip(&mut out.removed[row]);
        for ((x, (f, r)), col) in pixels.enumerate().zip(&mut col) {
            let d = &diff[y * stride + x];
            for c in 0..3 {
                run[c] += d[c];
                col[c] += run[c];
                // Rounding of the running sums may leave a hair below 0 where nothing was
                // given; nothing is ever taken.
                let given = col[c].max(0.0);
                f[c] = (f[c] as f64 + given) as f32;
                r[c] = (r[c] as f64 - given) as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::{
        resolve_bands, CascadeLayout, FrameState, ResolveParams, Resolved, SpreadParams, Variant,
    };
    use splatd_scenes::synth::SplitMix64;

    fn spread_params() -> ResolveParams {
        ResolveParams::new(Variant::Spread, 4.0, 1.0, 0.0)
            .unwrap()
            .with_spread(SpreadParams::new(8.0, 0.0, 8).unwrap())
    }

    fn paper_params() -> ResolveParams {
        ResolveParams::new(Variant::Paper, 4.0, 1.0, 0.0).unwrap()
    }

    /// A `size` x `size` frame of grey samples: 0.5 everywhere, and in a disc a rare caustic,
    /// `1/p` with probability `p = 1/48`, else 0 (mean 1).
    fn caustic_state(size: u32, spp: u64, seed: u64) -> FrameState {
        let mut state = FrameState::new(size, size, CascadeLayout::with_defaults());
        let mut rng = SplitMix64::new(seed);
        let c = size as f64 / 2.0;
        for _ in 0..spp {
            for y in 0..size {
                for x in 0..size {
                    let (dx, dy) = (x as f64 + 0.5 - c, y as f64 + 0.5 - c);
                    let v = if dx * dx + dy * dy < (c * 0.6) * (c * 0.6) {
                        if rng.next_f64() <= 1.0 / 48.0 {
                            48.0
                        } else {
                            0.0
                        }
                    } else {
                        0.5
                    };
                    state.splat(x, y, [v as f32; 3]).unwrap();
                }
            }
        }
        state
    }

    fn sum(image: &[[f32; 3]]) -> f64 {
        image.iter().map(|p| p[0] as f64).sum()
    }

    #[test]
    fn a_band_supported_in_a_wider_window_gets_its_energy_back_and_a_lone_firefly_does_not() {
        // Background 0.5 (cascades 0 and 1, 16 spp: fully trusted), a lone firefly of 3000
        // (cascades 4 and 5) at (1, 1).
        let mut lone = FrameState::new(15, 15, CascadeLayout::with_defaults());
        for y in 0..15 {
            for x in 0..15 {
                for _ in 0..16 {
                    lone.splat(x, y, [0.5; 3]).unwrap();
                }
            }
        }
        lone.splat(1, 1, [3000.0; 3]).unwrap();
        let paper = lone.resolve(&paper_params());
        assert!(sum(&paper.removed) > 100.0, "the paper removes the firefly");
        assert_eq!(
            lone.resolve(&spread_params()),
            paper,
            "nothing supports it anywhere"
        );
        // Nine samples of 30 (cascades 2 and 3) three pixels apart: every one is alone in its
        // 3x3 neighbourhood, so the paper removes most of their cascade-3 part, but a 7x7 or
        // 13x13 window holds all nine (support >= 8). (Within 8 pixels of the firefly they add
        // only 4 * 0.39 to its support.)
        let mut both = lone.clone();
        for y in [6, 9, 12] {
            for x in [6, 9, 12] {
                both.splat(x, y, [30.0; 3]).unwrap();
            }
        }
        let paper_both = both.resolve(&paper_params());
        let spread = both.resolve(&spread_params());
        let cluster_removed = sum(&paper_both.removed) - sum(&paper.removed);
        assert!(
            cluster_removed > 1.0,
            "the paper removes the cluster: {cluster_removed}"
        );
        assert!(
            (sum(&spread.removed) - sum(&paper.removed)).abs() < 1e-3,
            "only the firefly stays removed: {} vs {}",
            sum(&spread.removed),
            sum(&paper.removed)
        );
        assert!(
            (sum(&spread.reweighted) + sum(&spread.removed) - sum(&spread.mean)).abs() < 1e-3,
            "energy is moved, not made"
        );
        // Windows reach at most 8 pixels from a cluster sample: row 0 and column 0 lie 6 away
        // from (6, 6) and get some; the firefly's own pixel gets a share like its neighbours.
        for i in 0..15 * 15 {
            assert!(spread.reweighted[i][0] >= paper_both.reweighted[i][0]);
        }
    }

    #[test]
    fn the_edge_of_a_solid_light_is_not_smeared() {
        // A light fully covering (4, 4) (its band solid there: 16 samples) and 2 of 16 samples
        // of (5, 4): the paper cuts most of the edge pixel's light (its pooled support is low),
        // and the window around it holds enough support (18 >= 8) but also the solid pixel, so
        // the cut is not blurred over the dark pixels around. It stays removed, or, where the
        // band holds at least `edge_share` of the edge pixel's samples (here 2/16), it is
        // given back in place: that pixel partly covers the light.
        let mut state = FrameState::new(9, 9, CascadeLayout::with_defaults());
        for y in 0..9 {
            for x in 0..9 {
                for i in 0..16 {
                    let v = match (x, y, i) {
                        (4, 4, _) => 300.0,
                        (5, 4, 0 | 1) => 300.0,
                        _ => 0.5,
                    };
                    state.splat(x, y, [v; 3]).unwrap();
                }
            }
        }
        let paper = state.resolve(&paper_params());
        let edge = 4 * 9 + 5;
        assert!(paper.removed[edge][0] > 10.0, "{:?}", paper.removed[edge]);
        let with = |edge_share| {
            spread_params().with_spread(
                SpreadParams::new(8.0, 0.0, 8)
                    .unwrap()
                    .with_edge_share(edge_share)
                    .unwrap(),
            )
        };
        assert_eq!(state.resolve(&with(None)), paper, "left removed");
        // The paper also cuts 3/4 of the light's own pixel (its 3x3 pooled support is 2): a
        // pixel where the band is solid is next to itself, and all its samples are in the band.
        let light = 4 * 9 + 4;
        assert!(
            paper.removed[light][0] > 200.0,
            "{:?}",
            paper.removed[light]
        );
        let restored = |r: &Resolved, i: usize| {
            (r.reweighted[i][0] - r.mean[i][0]).abs() < 1e-3 && r.removed[i][0].abs() < 1e-3
        };
        for (share, back) in [(0.2, vec![light]), (0.1, vec![light, edge])] {
            let r = state.resolve(&with(Some(share)));
            for i in 0..81 {
                if back.contains(&i) {
                    assert!(
                        restored(&r, i),
                        "share {share}: pixel {i} given back in place"
                    );
                } else {
                    assert_eq!(
                        r.reweighted[i], paper.reweighted[i],
                        "share {share}: pixel {i}"
                    );
                }
            }
        }
    }

    #[test]
    fn removed_energy_of_the_frame_is_never_negative() {
        for seed in 0..6 {
            for spp in [4, 16, 64] {
                let state = caustic_state(24, spp, seed);
                let r = state.resolve(&spread_params());
                let removed = sum(&r.removed);
                let paper = sum(&state.resolve(&paper_params()).removed);
                assert!(
                    removed >= -1e-6 * sum(&r.mean),
                    "seed {seed} spp {spp}: {removed}"
                );
                assert!(
                    removed <= paper + 1e-6,
                    "gives back at most what the paper removed"
                );
            }
        }
    }

    #[test]
    fn consistent_the_estimate_converges_to_the_mean() {
        // At every N spread keeps at most what the paper removes; the paper's removal goes to 0
        // as N grows, and at 2048 spp every band of the caustic is trusted: the estimate is the
        // mean, whose error goes as 1/sqrt(N). (Spread's own removal need not fall
        // monotonically: once the caustic's band turns solid in some pixels, the energy cut
        // next to them stays removed.)
        for spp in [16, 256, 2048] {
            let state = caustic_state(16, spp, 3);
            let r = state.resolve(&spread_params());
            let paper = state.resolve(&paper_params());
            assert!(sum(&r.removed) <= sum(&paper.removed) + 1e-6, "{spp}");
            assert!(sum(&r.removed) >= -1e-6, "{spp}");
        }
        let state = caustic_state(16, 2048, 3);
        let r = state.resolve(&spread_params());
        assert_eq!(r.reweighted, r.mean, "at 2048 spp every band is supported");
        let early = caustic_state(16, 16, 3).resolve(&paper_params());
        assert!(
            sum(&early.removed) > 1.0,
            "at 16 spp the test has something to remove"
        );
    }

    #[test]
    fn bit_identical_for_any_merge_split_and_thread_count() {
        // The same samples split over three partial states, merged in another order.
        let parts: Vec<FrameState> = (0..3).map(|s| caustic_state(20, 8, 100 + s)).collect();
        let mut a = parts[0].clone();
        a.merge(&parts[1]).unwrap();
        a.merge(&parts[2]).unwrap();
        let mut b = parts[2].clone();
        b.merge(&parts[0]).unwrap();
        b.merge(&parts[1]).unwrap();
        let p = spread_params();
        let ra = a.resolve(&p);
        assert_eq!(ra, b.resolve(&p));
        for threads in [2, 3, 7] {
            assert_eq!(resolve_bands(&[&a], &p, threads).unwrap(), ra);
        }
        // The frame held as bands (as a sharded server holds it) resolves the same.
        let mut bands = FrameState::bands(20, 20, 3, a.layout());
        for band in &mut bands {
            band.merge_overlap(&a).unwrap();
        }
        let refs: Vec<&FrameState> = bands.iter().collect();
        assert_eq!(resolve_bands(&refs, &p, 2).unwrap(), ra);
        assert_ne!(
            ra.reweighted,
            a.resolve(&paper_params()).reweighted,
            "spread did act"
        );
    }
}
