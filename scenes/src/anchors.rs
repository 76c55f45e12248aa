//! The robust estimators splatd's resolve is measured against (the quality benchmark's anchors),
//! as pure functions of one pixel's samples in arrival order.
//!
//! * [`clamped_mean`]: every sample's luminance clamped to a ceiling (colour scaled with it);
//! * [`median_of_means`]: the samples dealt into `M` sets (sample `i` to set `i mod M`, as a
//!   renderer that posts whole passes would), the median of the set means by luminance;
//! * [`gmon`]: G-MoN (Buisine, Delepoulle & Renaud, "Firefly Removal in Monte Carlo Rendering
//!   with Adaptive Median of meaNs", EGSR 2021): the same `M` set means sorted by luminance; their
//!   Gini coefficient `G` decides how many are dropped at each end, `c = floor(G * floor(M/2))`,
//!   and the `M - 2c` central ones are averaged. Equal means (`G = 0`) give the plain mean; one
//!   set holding everything (`G -> 1`) gives the median.

use splatd_estimator::REC709_LUMINANCE;

fn luminance(rgb: [f64; 3]) -> f64 {
    REC709_LUMINANCE[0] * rgb[0] + REC709_LUMINANCE[1] * rgb[1] + REC709_LUMINANCE[2] * rgb[2]
}

fn widen(rgb: [f32; 3]) -> [f64; 3] {
    rgb.map(f64::from)
}

/// Mean of the samples with every sample's luminance clamped to at most `ceiling`.
pub fn clamped_mean(samples: &[[f32; 3]], ceiling: f64) -> [f64; 3] {
    let mut acc = [0.0; 3];
    for &s in samples {
        let s = widen(s);
        let l = luminance(s);
        let k = if l > ceiling { ceiling / l } else { 1.0 };
        for c in 0..3 {
            acc[c] += s[c] * k;
        }
    }
    acc.map(|v| v / samples.len().max(1) as f64)
}

/// The means of `m` sets, sample `i` in set `i mod m`, sorted by luminance (ties keep set order).
///
/// # Panics
/// If `m` is 0 or there are fewer samples than sets.
pub fn sorted_set_means(samples: &[[f32; 3]], m: usize) -> Vec<[f64; 3]> {
    assert!(
        m > 0 && samples.len() >= m,
        "{m} sets need at least {m} samples"
    );
    let mut sums = vec![([0.0; 3], 0usize); m];
    for (i, &s) in samples.iter().enumerate() {
        let (sum, n) = &mut sums[i % m];
        for (acc, v) in sum.iter_mut().zip(widen(s)) {
            *acc += v;
        }
        *n += 1;
    }
    let mut means: Vec<[f64; 3]> = sums
        .into_iter()
        .map(|(sum, n)| sum.map(|v| v / n as f64))
        .collect();
    means.sort_by(|a, b| luminance(*a).total_cmp(&luminance(*b)));
    means
}

/// The Gini coefficient of non-negative values sorted ascending:
/// `G = Σ_i (2i - m + 1) x_i / (m Σ_i x_i)` with `i = 0..m`; 0 when they sum to 0.
pub fn gini(sorted: &[f64]) -> f64 {
    let m = sorted.len() as f64;
    let total: f64 = sorted.iter().sum();
    if total <= 0.0 {
        return 0.0;
    }
    let weighted: f64 = sorted
        .iter()
        .enumerate()
        .map(|(i, x)| (2.0 * i as f64 - m + 1.0) * x)
        .sum();
    weighted / (m * total)
}

fn mean_of(means: &[[f64; 3]]) -> [f64; 3] {
    let mut acc = [0.0; 3];
    for m in means {
        for c in 0..3 {
            acc[c] += m[c];
        }
    }
    acc.map(|v| v / means.len() as f64)
}

/// Median of `m` means by luminance (the mean of the two middle ones when `m` is even).
pub fn median_of_means(samples: &[[f32; 3]], m: usize) -> [f64; 3] {
    let means = sorted_set_means(samples, m);
    let lo = (m - 1) / 2;
    mean_of(&means[lo..m - lo])
}

/// G-MoN with `m` sets (see the module docs).
pub fn gmon(samples: &[[f32; 3]], m: usize) -> [f64; 3] {
    let means = sorted_set_means(samples, m);
    let lum: Vec<f64> = means.iter().map(|&x| luminance(x)).collect();
    let c = (gini(&lum) * (m / 2) as f64).floor() as usize;
    // A set mean's luminance is never negative, so G <= 1 - 1/m and c < m/2.
    let c = c.min((m - 1) / 2);
    mean_of(&means[c..m - c])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grey(v: f32) -> [f32; 3] {
        [v, v, v]
    }

    #[test]
    fn clamp_scales_colour_to_the_luminance_ceiling() {
        // Luminance of grey v is v (the weights sum to 1).
        let m = clamped_mean(&[grey(1.0), [10.0, 0.0, 0.0]], 1.0);
        // [10, 0, 0] has luminance 2.126: scaled by 1/2.126 to [4.7037.., 0, 0].
        let r = (1.0 + 10.0 / 2.126) / 2.0;
        assert!((m[0] - r).abs() < 1e-12, "{m:?}");
        assert!((m[1] - 0.5).abs() < 1e-12);
    }

    #[test]
    fn gini_matches_the_textbook_pairwise_definition() {
        // G = Σ_i Σ_j |x_i - x_j| / (2 m^2 mean): for [0, 0, 0, 4] that is 2*3*4 / (2*16*1).
        assert!((gini(&[0.0, 0.0, 0.0, 4.0]) - 0.75).abs() < 1e-12);
        assert_eq!(gini(&[2.0, 2.0, 2.0]), 0.0);
        // [1, 2, 3]: pairs |1-2|,|1-3|,|2-3| twice = 8; 8 / (2 * 9 * 2) = 2/9.
        assert!((gini(&[1.0, 2.0, 3.0]) - 2.0 / 9.0).abs() < 1e-12);
        assert_eq!(gini(&[0.0, 0.0]), 0.0);
    }

    #[test]
    fn median_of_means_by_hand() {
        // 8 samples in 4 sets: set i gets samples i and i + 4.
        let s = [1.0, 2.0, 3.0, 100.0, 1.0, 2.0, 3.0, 100.0].map(grey);
        // Set means 1, 2, 3, 100: the median of 4 is (2 + 3) / 2.
        assert_eq!(median_of_means(&s, 4), [2.5; 3]);
        // 3 sets: samples {1, 100, 3}, {2, 1, 100}, {3, 2}: means 104/3, 103/3, 2.5 -> 103/3.
        let m = median_of_means(&s, 3);
        assert!((m[0] - 103.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn gmon_by_hand() {
        // Means 0, 0, 0, 0, 0, 0, 0, 8 (one firefly): G = 7*8 / (8*8) = 0.875,
        // c = floor(0.875 * 4) = 3, so the central 2 (both 0) are kept.
        let mut s = [grey(0.0); 8];
        s[7] = grey(8.0);
        assert_eq!(gmon(&s, 8), [0.0; 3]);
        // Equal means: G = 0, the plain mean.
        let s = [grey(0.5); 16];
        assert_eq!(gmon(&s, 8), [0.5; 3]);
        // Means 1..=8: G = Σ (2i - 7) (i + 1) / (8 * 36) = 84 / 288 = 0.2917, c = 1:
        // the mean of 2..=7 is 4.5.
        let s: Vec<[f32; 3]> = (1..=8).map(|v| grey(v as f32)).collect();
        assert!((gini(&(1..=8).map(f64::from).collect::<Vec<_>>()) - 84.0 / 288.0).abs() < 1e-12);
        assert_eq!(gmon(&s, 8), [4.5; 3]);
    }
}
