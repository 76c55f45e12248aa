//! The optimized estimator against a deliberately simple reference written from docs/ALGORITHM.md:
//! it keeps every sample, works in `f64` throughout, finds cascades with logarithms, and resolves
//! with plain 3x3 loops. Disagreement beyond fixed-point rounding is a bug in one of them.

// The reference reads like the formulas it checks: indices, not iterator chains.
#![allow(clippy::needless_range_loop)]

use proptest::prelude::*;
use splatd_estimator::{
    CascadeLayout, FrameState, ResolveParams, Variant, FRAC_BITS, REC709_LUMINANCE,
};

/// One pixel's cascades, with bounds on the estimator's rounding of them.
struct Cascades {
    sums: Vec<[f64; 3]>,
    counts: Vec<f64>,
    /// Most a channel's sum of each cascade may be off by (the same for every channel).
    sum_err: Vec<f64>,
    /// Most each cascade's count may be off by.
    count_err: Vec<f64>,
}

/// The reference: samples per pixel, nothing else.
struct Reference {
    width: usize,
    height: usize,
    base: f64,
    c0: f64,
    k: usize,
    samples: Vec<Vec<[f64; 3]>>,
}

fn lum(s: [f64; 3]) -> f64 {
    REC709_LUMINANCE[0] * s[0] + REC709_LUMINANCE[1] * s[1] + REC709_LUMINANCE[2] * s[2]
}

impl Reference {
    fn scale(&self, j: usize) -> f64 {
        self.c0 * self.base.powi(j as i32)
    }

    /// Cascade sums and explicit counts of one pixel, straight from the definitions, and the
    /// most the estimator's fixed point may differ from each: every share it stores is rounded
    /// to `2^-FRAC_BITS` of its cascade's scale (values) or of one sample (counts).
    fn cascades(&self, p: usize) -> Cascades {
        let mut sums = vec![[0.0; 3]; self.k];
        let mut counts = vec![0.0; self.k];
        let mut shares = vec![0.0; self.k];
        for &s in &self.samples[p] {
            let l = lum(s);
            let top = self.k - 1;
            let mut add = |j: usize, w: f64, count: f64| {
                for c in 0..3 {
                    sums[j][c] += w * s[c];
                }
                counts[j] += count;
                shares[j] += 1.0;
            };
            if l <= self.c0 {
                add(0, 1.0, 1.0);
            } else if l >= self.scale(top) {
                add(top, 1.0, 1.0);
            } else {
                // Notes: j = floor(log_b(L / c0)); weight (b^j/L - 1/b)/(1 - 1/b) in c0 units.
                let mut j = ((l / self.c0).ln() / self.base.ln()).floor() as usize;
                // Guard against log rounding right at a boundary.
                while j > 0 && self.scale(j) > l {
                    j -= 1;
                }
                while j + 1 < top && self.scale(j + 1) <= l {
                    j += 1;
                }
                let r = self.scale(j) / l;
                let w = (r - 1.0 / self.base) / (1.0 - 1.0 / self.base);
                add(j, w, w * l / self.scale(j));
                add(j + 1, 1.0 - w, (1.0 - w) * l / self.scale(j + 1));
            }
        }
        let ulp = 0.5f64.powi(FRAC_BITS as i32);
        Cascades {
            sum_err: (0..self.k)
                .map(|j| shares[j] * ulp * self.scale(j))
                .collect(),
            count_err: shares.iter().map(|n| n * ulp).collect(),
            sums,
            counts,
        }
    }

    fn support(&self, counts: &[f64], j: usize) -> f64 {
        let mut n = counts[j];
        if j > 0 {
            n += counts[j - 1];
        }
        if j + 1 < self.k {
            n += counts[j + 1];
        }
        n
    }

    /// Reweighted, mean and removed of every pixel, and for each of them the most the
    /// estimator's value may differ by: the fixed point's rounding of the cascades (see
    /// [`Reference::cascades`]) carried through the weights, whose value term grows with the
    /// luminance of the bands below and whose count term with the supports.
    fn resolve(&self, params: &ResolveParams) -> Vec<[[f64; 3]; 6]> {
        let (w, h) = (self.width as i64, self.height as i64);
        let all: Vec<_> = (0..self.samples.len()).map(|p| self.cascades(p)).collect();
        let mut out = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let p = (y * w + x) as usize;
                let n = self.samples[p].len() as f64;
                if n == 0.0 {
                    out.push([[0.0; 3]; 6]);
                    continue;
                }
                let Cascades {
                    sums,
                    counts,
                    sum_err,
                    count_err,
                } = &all[p];
                let mut f = [0.0; 3];
                let mut mean = [0.0; 3];
                let mut removed = [0.0; 3];
                // Error bounds of f (reweighted), mean and removed.
                let (mut f_err, mut mean_err, mut removed_err) = (0.0, 0.0, 0.0);
                let kappa = params.kappa() * n.powf(params.kappa_exponent());
                let kmin = params.kappa_min();
                for j in 0..self.k {
                    // Pooled support of the clamped 3x3 neighbourhood, relative to own N.
                    let (mut pool_n, mut pool_err, mut pool_total) = (0.0, 0.0, 0.0);
                    for dy in -1..=1 {
                        for dx in -1..=1 {
                            let q =
                                ((y + dy).clamp(0, h - 1) * w + (x + dx).clamp(0, w - 1)) as usize;
                            pool_n += self.support(&all[q].counts, j);
                            pool_err += self.support(&all[q].count_err, j);
                            pool_total += self.samples[q].len() as f64;
                        }
                    }
                    // The paper's count term takes a pixel as having so many samples that half
                    // its neighbourhood's samples give full weight (twice kappa + kappa_min),
                    // but at most kappa_min times those samples (so that a band seen by one
                    // sample of the neighbourhood stays at or below kappa_min), and at least
                    // its own.
                    let counted = match params.variant() {
                        Variant::Paper => n.max((2.0 * (kappa + kmin)).min(kmin * pool_total)),
                        _ => n,
                    };
                    let pooled = counted * pool_n / pool_total;
                    let own = self.support(counts, j);
                    // How far the count and value terms may be off: the supports' rounding, and
                    // the rounding of the bands below carried in `f` (luminance weights add to
                    // 1, so a channel bound is a luminance bound).
                    let wc_err =
                        (counted * pool_err / pool_total).max(self.support(count_err, j)) / kappa;
                    let wv_err = f_err / (kappa * self.scale(j));
                    let lf = lum(f);
                    let c = self.scale(j);
                    let (wj, w_err) = match params.variant() {
                        Variant::Off => (1.0, 0.0),
                        Variant::Paper => {
                            let wc = (pooled - kmin) / kappa;
                            let wv = n * (lf / n) / (kappa * c);
                            let wj = f64::min(1.0, f64::max(wc, wv)).max(0.0);
                            (wj, wc_err + wv_err)
                        }
                        Variant::Shader => {
                            let global = (pooled - kmin) / kappa;
                            let wc = if global >= 0.0 {
                                (own - kmin) / kappa
                            } else {
                                global
                            };
                            let t = f64::min(1.0, 1.0 / kappa);
                            let factor = (1.0 - t) * (0.4 + 0.6 * self.base) + t;
                            let wv = f64::max(lf / n, 0.05) * n / (kappa * c) * factor;
                            let wj = ((wc + wv) / 2.0).clamp(0.0, 1.0);
                            (wj, (wc_err + wv_err * factor) / 2.0)
                        }
                        // Its second stage moves energy between pixels; resolve_spread's own
                        // tests check it (this reference is per pixel).
                        Variant::Spread => unreachable!("the per-pixel reference has no spread"),
                    };
                    for ch in 0..3 {
                        f[ch] += wj * sums[j][ch];
                        mean[ch] += sums[j][ch];
                        removed[ch] += (1.0 - wj) * sums[j][ch];
                    }
                    let big = sums[j].iter().fold(0.0f64, |m, v| m.max(v.abs()));
                    let moved = w_err.min(1.0) * (big + sum_err[j]);
                    f_err += wj * sum_err[j] + moved;
                    mean_err += sum_err[j];
                    removed_err += (1.0 - wj) * sum_err[j] + moved;
                }
                out.push([
                    f.map(|v| v / n),
                    mean.map(|v| v / n),
                    removed.map(|v| v / n),
                    [f_err / n; 3],
                    [mean_err / n; 3],
                    [removed_err / n; 3],
                ]);
            }
        }
        out
    }
}

/// Whether the optimized `a` is the reference's `b` to within `err`, the bound the reference
/// derives from the fixed point's rounding (twice it, for the arithmetic's own rounding), plus
/// the `f32` output's rounding and `1e-12` of the pixel's mean `m` (sums in another order).
fn close(a: f32, b: f64, err: f64, m: f64, what: &str) -> Result<(), TestCaseError> {
    let tol = 2.0 * err + b.abs() * 0.5f64.powi(22) + 1e-12 * (1.0 + m.abs());
    prop_assert!(
        (a as f64 - b).abs() <= tol,
        "{what}: optimized {a} vs reference {b} (allowed {tol:e})"
    );
    Ok(())
}

/// Sample values spanning dim, in-range and far-out-of-range brightness, with fireflies.
fn sample() -> impl Strategy<Value = [f32; 3]> {
    prop_oneof![
        4 => prop::array::uniform3(0.0f32..1.0),
        2 => prop::array::uniform3(0.0f32..50.0),
        1 => prop::array::uniform3(0.0f32..1e5),
        1 => Just([0.0f32; 3]),
    ]
}

/// Width, height and `(x, y, rgb)` records.
type Scene = (usize, usize, Vec<(usize, usize, [f32; 3])>);

fn scene() -> impl Strategy<Value = Scene> {
    (1usize..6, 1usize..6).prop_flat_map(|(w, h)| {
        let records = prop::collection::vec((0..w, 0..h, sample()), 0..300);
        (Just(w), Just(h), records)
    })
}

fn params() -> impl Strategy<Value = ResolveParams> {
    (
        prop_oneof![
            Just(Variant::Paper),
            Just(Variant::Shader),
            Just(Variant::Off)
        ],
        0.5f64..40.0,
        0.0f64..2.0,
        prop_oneof![Just(0.0), 0.0f64..0.9],
    )
        .prop_map(|(v, k, kmin, e)| ResolveParams::new(v, k, kmin, e).unwrap())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn optimized_resolve_matches_the_per_sample_reference(
        (w, h, records) in scene(),
        base in prop_oneof![Just(8.0f64), 2.0f64..16.0],
        k in 2u32..8,
        c0 in prop_oneof![Just(1.0f64), Just(0.125), 0.01f64..2.0],
        params in params(),
    ) {
        let layout = CascadeLayout::new(base, k, c0, REC709_LUMINANCE).unwrap();
        let mut state = FrameState::new(w as u32, h as u32, layout);
        let mut reference = Reference {
            width: w, height: h, base, c0, k: k as usize,
            samples: vec![Vec::new(); w * h],
        };
        for &(x, y, rgb) in &records {
            state.splat(x as u32, y as u32, rgb).unwrap();
            reference.samples[y * w + x].push(rgb.map(|v| v as f64));
        }
        let ours = state.resolve(&params);
        let theirs = reference.resolve(&params);
        for p in 0..w * h {
            prop_assert_eq!(ours.spp[p], reference.samples[p].len() as u64);
            for c in 0..3 {
                let [f, m, r, f_err, m_err, r_err] = theirs[p];
                close(ours.reweighted[p][c], f[c], f_err[c], m[c], "reweighted")?;
                close(ours.mean[p][c], m[c], m_err[c], m[c], "mean")?;
                close(ours.removed[p][c], r[c], r_err[c], m[c], "removed")?;
            }
        }
    }
}
