//! A synthetic, deterministic, firefly-heavy sample stream with an exactly known mean.
//!
//! Every pixel has a smooth true colour `m(x, y)`; a sample is `m * Z` with a scalar `Z >= 0`,
//! `E[Z] = 1`, drawn from one of three distributions by region:
//! * **heavy** (left half): Pareto with tail index `alpha` between 1.1 and 2, which has a finite
//!   mean and infinite variance, the textbook model of fireflies;
//! * **caustic** (a disc): `Z = 1/p` with probability `p = 1/48`, else 0; the light a path tracer
//!   finds only by chance through a specular chain;
//! * **tame** (elsewhere): Pareto with `alpha = 4` (finite variance; reweighting should leave it
//!   alone).
//!
//! The stream is a pure function of `(seed, pass, x, y)`, so any pass can be regenerated anywhere.

/// SplitMix64: a tiny, fast, well-mixed generator (Steele, Lea & Flood 2014). Deterministic
/// everywhere, which is all the synthetic stream needs.
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// The next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `(0, 1]` (never 0, so `u^(-1/alpha)` is finite).
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        ((self.next_u64() >> 11) + 1) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// The synthetic scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FireflyScene {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Seed of the stream.
    pub seed: u64,
}

enum Region {
    Heavy(f64),
    Caustic(f64),
    Tame,
}

impl FireflyScene {
    /// A scene of the given size.
    pub fn new(width: u32, height: u32, seed: u64) -> Self {
        Self {
            width,
            height,
            seed,
        }
    }

    /// The exact per-pixel mean of the stream.
    pub fn mean(&self, x: u32, y: u32) -> [f64; 3] {
        let u = (x as f64 + 0.5) / self.width as f64;
        let v = (y as f64 + 0.5) / self.height as f64;
        // A soft gradient with some structure, typical brightness around 0.1 .. 1.
        let stripes = 0.5 + 0.5 * (12.0 * u + 3.0 * v).sin();
        [
            0.08 + 0.5 * u * stripes + 0.1 * v,
            0.1 + 0.35 * v + 0.15 * stripes,
            0.12 + 0.4 * (1.0 - u) * (1.0 - v),
        ]
    }

    fn region(&self, x: u32, y: u32) -> Region {
        let u = (x as f64 + 0.5) / self.width as f64;
        let v = (y as f64 + 0.5) / self.height as f64;
        let (du, dv) = (u - 0.72, v - 0.5);
        if du * du + dv * dv < 0.2 * 0.2 {
            Region::Caustic(1.0 / 48.0)
        } else if u < 0.5 {
            Region::Heavy(1.1 + 0.9 * v)
        } else {
            Region::Tame
        }
    }

    /// Sample number `pass` of pixel `(x, y)`.
    pub fn sample(&self, pass: u64, x: u32, y: u32) -> [f32; 3] {
        let pixel = y as u64 * self.width as u64 + x as u64;
        let mut rng = SplitMix64::new(
            self.seed ^ pass.wrapping_mul(0xD1B5_4A32_D192_ED03) ^ pixel.wrapping_mul(0x9E37_79B9),
        );
        rng.next_u64();
        let z = match self.region(x, y) {
            Region::Heavy(alpha) => pareto(rng.next_f64(), alpha),
            Region::Tame => pareto(rng.next_f64(), 4.0),
            Region::Caustic(p) => {
                if rng.next_f64() <= p {
                    1.0 / p
                } else {
                    0.0
                }
            }
        };
        self.mean(x, y).map(|m| (m * z) as f32)
    }

    /// Every pixel's sample of one pass, row-major: `(x, y, rgb)`.
    pub fn pass(&self, pass: u64) -> impl Iterator<Item = (u32, u32, [f32; 3])> + '_ {
        (0..self.height)
            .flat_map(move |y| (0..self.width).map(move |x| (x, y, self.sample(pass, x, y))))
    }
}

/// Pareto with minimum `(alpha - 1) / alpha`, so that its mean is exactly 1.
#[inline]
fn pareto(u: f64, alpha: f64) -> f64 {
    (alpha - 1.0) / alpha * u.powf(-1.0 / alpha)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_deterministic_and_differ_by_pass() {
        let scene = FireflyScene::new(16, 16, 7);
        assert_eq!(scene.sample(3, 5, 9), scene.sample(3, 5, 9));
        assert_ne!(scene.sample(3, 5, 9), scene.sample(4, 5, 9));
    }

    #[test]
    fn sample_means_approach_the_exact_mean_in_the_tame_region() {
        let scene = FireflyScene::new(64, 64, 1);
        let (x, y) = (60, 5);
        let n = 20_000;
        let sum: f64 = (0..n).map(|p| scene.sample(p, x, y)[1] as f64).sum();
        let exact = scene.mean(x, y)[1];
        assert!(
            (sum / n as f64 - exact).abs() < 0.02 * exact,
            "{} vs {exact}",
            sum / n as f64
        );
    }
}
