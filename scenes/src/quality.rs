//! Image error metrics used by the demo, the tests and the quality benchmark (docs/ALGORITHM.md).

/// Relative MSE, `mean((x - gt)^2 / (gt^2 + 0.01))` over every pixel and channel.
pub fn rel_mse(x: &[[f32; 3]], gt: &[[f32; 3]]) -> f64 {
    assert_eq!(x.len(), gt.len(), "images of different sizes");
    let sum: f64 = x
        .iter()
        .zip(gt)
        .flat_map(|(a, b)| (0..3).map(move |c| (a[c] as f64, b[c] as f64)))
        .map(|(a, b)| (a - b) * (a - b) / (b * b + 0.01))
        .sum();
    sum / (3 * x.len()).max(1) as f64
}

/// Energy bias `mean L(x) / mean L(gt) - 1` with brightness weights `w`.
pub fn energy_bias(x: &[[f32; 3]], gt: &[[f32; 3]], w: [f64; 3]) -> f64 {
    let lum = |img: &[[f32; 3]]| -> f64 {
        img.iter()
            .map(|p| w[0] * p[0] as f64 + w[1] * p[1] as f64 + w[2] * p[2] as f64)
            .sum()
    };
    lum(x) / lum(gt) - 1.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_match_hand_computed_values() {
        let gt = [[1.0, 0.0, 0.5]];
        let x = [[2.0, 0.25, 0.5]];
        let expected = (1.0 / 1.01 + 0.0625 / 0.01 + 0.0) / 3.0;
        assert!((rel_mse(&x, &gt) - expected).abs() < 1e-12);
        let w = [0.2126, 0.7152, 0.0722];
        let lx = 0.2126 * 2.0 + 0.7152 * 0.25 + 0.0722 * 0.5;
        let lg = 0.2126 + 0.0722 * 0.5;
        assert!((energy_bias(&x, &gt, w) - (lx / lg - 1.0)).abs() < 1e-12);
    }
}
