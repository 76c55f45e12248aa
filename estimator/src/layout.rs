//! The cascade layout: which brightness band each cascade covers, and how one sample is split
//! between the two cascades around its brightness.
//!
//! Bounds that follow from the layout (documented in full in the `state` module): a sample
//! component may be at most [`CascadeLayout::max_component`] `= c_{K-1} * 2^26`; a share in
//! cascade `j` is stored to `2^-26` of `c_j` ([`FRAC_BITS`]); luminance weights are in
//! `[1/32, 1]` ([`MIN_LUMINANCE_WEIGHT`]); a pixel holds at most `2^32` samples
//! ([`MAX_PIXEL_SAMPLES`]) in a `32 K + 8`-byte cell.
//!
//! The layout is fixed for a frame once samples arrive and must be identical on every node that
//! accumulates the frame; otherwise partial states cannot be merged. It is therefore a value type
//! that compares equal field by field, and [`CascadeLayout::new`] is the only way to build one.

use std::fmt;

use crate::state::{check_sample, SampleError};

/// Fractional bits of every fixed-point quantity in a frame state.
///
/// A cascade's RGB sums are stored as integers in units of `c_j * 2^-FRAC_BITS`, its sample count
/// in units of `2^-FRAC_BITS`. Integer sums are associative, so the state, and every image
/// resolved from it, is bit-identical whatever order samples arrive in or however they are split
/// across nodes.
///
/// 26 bits is the most that keeps every sum exact for [`MAX_PIXEL_SAMPLES`] samples in one pixel
/// in a `u64`: a sample's share in cascade `j` has luminance at most `c_j` (see
/// [`CascadeLayout::split`]), so each of its channels is at most `c_j / MIN_LUMINANCE_WEIGHT =
/// 32 c_j`, i.e. at most `2^31` units (plus rounding), and `2^32` such shares stay below `2^64`.
/// Counts add exactly [`COUNT_ONE`] per sample, at most `2^58` per pixel. Each share is rounded
/// once, to `2^-26` of its cascade's scale (relative `1.5e-8`, finer than the `f32` sample).
/// The top cascade is the exception (it takes every sample above `c_{K-1}` whole); its RGB sums
/// get 21 more bits (see the `state` module).
pub const FRAC_BITS: u32 = 26;

/// One sample count in fixed point.
pub const COUNT_ONE: u64 = 1 << FRAC_BITS;

/// Most samples one pixel may hold: `2^32`. A batch or merge that would go past it is refused.
pub const MAX_PIXEL_SAMPLES: u64 = 1 << 32;

/// Largest sample component relative to the top cascade's scale: a component may be at most
/// `c_{K-1} * 2^TOP_HEADROOM_BITS` ([`CascadeLayout::max_component`]).
///
/// Such a component is `2^(FRAC_BITS + 26) = 2^52` units of the top cascade, and
/// [`MAX_PIXEL_SAMPLES`] of them are `2^84` (plus rounding), inside the top cascade's 85-bit sums.
/// (`2^27` would give exactly `2^85`, one past the range.)
pub const TOP_HEADROOM_BITS: u32 = 26;

/// Largest cascade count accepted; 16 cascades of base 8 span 8^15 ≈ 3.5e13 in brightness.
pub const MAX_CASCADES: u32 = 16;

/// Smallest luminance weight a layout accepts; the largest is 1.
pub const MIN_LUMINANCE_WEIGHT: f64 = 1.0 / 32.0;

/// Rec.709 / sRGB relative luminance weights, the default brightness function.
pub const REC709_LUMINANCE: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Rec.709 relative luminance of a linear RGB colour: what previews, tone mapping and the
/// energy metrics weigh colours by (a frame's own weights are [`CascadeLayout::luminance`]).
#[inline]
pub fn rec709_luminance(rgb: [f64; 3]) -> f64 {
    REC709_LUMINANCE[0] * rgb[0] + REC709_LUMINANCE[1] * rgb[1] + REC709_LUMINANCE[2] * rgb[2]
}

/// A parameter that makes no sense, with the reason.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid parameter `{name}`: {reason}")]
pub struct ParamError {
    /// The parameter's name as it appears in the API.
    pub name: &'static str,
    /// What is wrong with it.
    pub reason: String,
}

impl ParamError {
    /// A refusal of parameter `name`, with the reason.
    pub fn new(name: &'static str, reason: impl Into<String>) -> Self {
        Self {
            name,
            reason: reason.into(),
        }
    }
}

/// The brightness bands of a frame: cascade `j` has scale `c_j = lowest_scale * base^j`.
///
/// Brightness `L(s) = luminance · s` is linear in the sample, so `L` of a sum is the sum of `L`s;
/// the count identity of the split relies on that.
#[derive(Clone, PartialEq)]
pub struct CascadeLayout {
    base: f64,
    cascades: u32,
    lowest_scale: f64,
    luminance: [f64; 3],
    /// `c_j` for every cascade.
    scales: Vec<f64>,
    /// `2^FRAC_BITS / c_j`: multiplies a value to get fixed-point units of cascade `j`.
    to_units: Vec<f64>,
    /// `c_j / 2^FRAC_BITS`: multiplies fixed-point units of cascade `j` back to a value.
    from_units: Vec<f64>,
    /// `1 / c_j`.
    inv_scales: Vec<f64>,
    /// `c_{K-1} * 2^TOP_HEADROOM_BITS`: the largest sample component accepted.
    max_component: f64,
}

impl fmt::Debug for CascadeLayout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("CascadeLayout")
            .field("base", &self.base)
            .field("cascades", &self.cascades)
            .field("lowest_scale", &self.lowest_scale)
            .field("luminance", &self.luminance)
            .finish()
    }
}

/// Where one sample goes: `lo` receives `w_lo * s` and `count_lo` count units, `lo + 1`
/// receives `(1 - w_lo) * s` and the rest of one count. `lo` is at most `K - 2`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Split {
    /// The lower cascade.
    pub lo: usize,
    /// Fraction of the sample's value that goes to `lo`; the rest goes to `lo + 1`.
    pub w_lo: f64,
    /// Fixed-point count units for `lo`; `COUNT_ONE - count_lo` go to `lo + 1`.
    pub count_lo: u64,
}

impl CascadeLayout {
    /// Builds and validates a layout.
    ///
    /// * `base` (`b`): ratio between neighbouring cascades, `1 < b <= 1024`. Paper default 8.
    /// * `cascades` (`K`): `2..=16`. Paper default 6.
    /// * `lowest_scale` (`c0`): scale of cascade 0, `> 0`; every `c_j` must stay a normal `f64`.
    /// * `luminance`: brightness weights, each in `[1/32, 1]` ([`MIN_LUMINANCE_WEIGHT`]). A
    ///   zero or tiny weight would let one channel grow far beyond the brightness that picks its
    ///   cascade (bounding a channel by `luminance / w_min` is what bounds every sum), and a huge
    ///   one would make every sample look like a firefly.
    pub fn new(
        base: f64,
        cascades: u32,
        lowest_scale: f64,
        luminance: [f64; 3],
    ) -> Result<Self, ParamError> {
        if !(base.is_finite() && base > 1.0 && base <= 1024.0) {
            return Err(ParamError::new(
                "base",
                format!("must be a number in (1, 1024], got {base}"),
            ));
        }
        if !(2..=MAX_CASCADES).contains(&cascades) {
            return Err(ParamError::new(
                "cascades",
                format!("must be between 2 and {MAX_CASCADES}, got {cascades}"),
            ));
        }
        if !(lowest_scale.is_finite() && lowest_scale > 0.0) {
            return Err(ParamError::new(
                "lowest_scale",
                format!("must be a positive number, got {lowest_scale}"),
            ));
        }
        if let Some(w) = luminance
            .iter()
            .find(|w| !(MIN_LUMINANCE_WEIGHT..=1.0).contains(*w))
        {
            return Err(ParamError::new(
                "luminance",
                format!(
                    "every weight must be in [1/32, 1] (Rec. 709 is [0.2126, 0.7152, 0.0722]), \
                     got {w} in {luminance:?}"
                ),
            ));
        }
        let scales: Vec<f64> = (0..cascades)
            .map(|j| lowest_scale * base.powi(j as i32))
            .collect();
        let (lowest, highest) = (scales[0], scales[scales.len() - 1]);
        if lowest < 1e-30 || highest > 1e30 {
            return Err(ParamError::new(
                "lowest_scale",
                format!(
                    "cascade scales must stay within [1e-30, 1e30], got {lowest:e} .. {highest:e}"
                ),
            ));
        }
        let one = COUNT_ONE as f64;
        Ok(Self {
            base,
            cascades,
            lowest_scale,
            luminance,
            to_units: scales.iter().map(|c| one / c).collect(),
            from_units: scales.iter().map(|c| c / one).collect(),
            inv_scales: scales.iter().map(|c| 1.0 / c).collect(),
            max_component: highest * (1u64 << TOP_HEADROOM_BITS) as f64,
            scales,
        })
    }

    /// The paper's defaults (`b = 8`, `K = 6`) with splatd's default `c0` and Rec.709 weights.
    pub fn with_defaults() -> Self {
        Self::new(
            DEFAULT_CASCADE_BASE,
            DEFAULT_CASCADE_COUNT,
            DEFAULT_LOWEST_SCALE,
            REC709_LUMINANCE,
        )
        .expect("default layout is valid")
    }

    /// `b`.
    pub fn base(&self) -> f64 {
        self.base
    }

    /// `K`.
    pub fn cascades(&self) -> usize {
        self.cascades as usize
    }

    /// `c0`.
    pub fn lowest_scale(&self) -> f64 {
        self.lowest_scale
    }

    /// The brightness weights.
    pub fn luminance_weights(&self) -> [f64; 3] {
        self.luminance
    }

    /// `c_j` for every cascade.
    pub fn scales(&self) -> &[f64] {
        &self.scales
    }

    /// The largest sample component this layout represents exactly: `c_{K-1} * 2^26`
    /// (`4096 * 2^26 = 2.7e11` with the defaults). Larger components are refused
    /// ([`SampleError::TooBright`]), never clamped.
    pub fn max_component(&self) -> f64 {
        self.max_component
    }

    /// Checks a sample's value for this layout: finite, non-negative
    /// ([`crate::check_sample`]) and no component above [`CascadeLayout::max_component`].
    #[inline]
    pub fn check_sample(&self, rgb: [f32; 3]) -> Result<(), SampleError> {
        check_sample(rgb)?;
        match rgb.iter().find(|&&c| c as f64 > self.max_component) {
            Some(&value) => Err(SampleError::TooBright {
                value,
                max: self.max_component,
            }),
            None => Ok(()),
        }
    }

    /// The bits of the largest `f32` component [`CascadeLayout::check_sample`] accepts (the
    /// largest at most [`CascadeLayout::max_component`]), for [`component_bits_accepted`].
    #[inline]
    pub fn component_limit_bits(&self) -> u32 {
        let nearest = self.max_component as f32;
        let largest = if nearest as f64 > self.max_component {
            // Rounded up: the float below it (positive and finite, so one step of its bits).
            f32::from_bits(nearest.to_bits() - 1)
        } else {
            nearest
        };
        largest.to_bits()
    }

    /// Brightness of an RGB value.
    #[inline]
    pub fn luminance(&self, rgb: [f64; 3]) -> f64 {
        self.luminance[0] * rgb[0] + self.luminance[1] * rgb[1] + self.luminance[2] * rgb[2]
    }

    #[inline]
    pub(crate) fn units_per_value(&self, j: usize) -> f64 {
        self.to_units[j]
    }

    #[inline]
    pub(crate) fn unit_value(&self, j: usize) -> f64 {
        self.from_units[j]
    }

    #[inline]
    pub(crate) fn inv_scale(&self, j: usize) -> f64 {
        self.inv_scales[j]
    }

    /// How a sample of brightness `l >= 0` is split (the authors' `split.cpp`, with the energy of
    /// out-of-range samples kept):
    ///
    /// * `l <= c0`: all of it to cascade 0, with one full count (the luminance-derived count
    ///   would be `l / c0 < 1`; splatd keeps explicit counts, exact everywhere);
    /// * `c_j < l < c_{j+1}`: `w_lo = (c_{j+1}/l - 1) / (b - 1)` of the value to `j`, the rest
    ///   to `j + 1`; counts `w_lo * l / c_j = (b - l/c_j) / (b - 1)` and its complement, so
    ///   `L(B_j) / c_j` still counts samples;
    /// * `l >= c_{K-1}`: all of it to the top cascade `K-1` (returned as `lo = K-2`, `w_lo = 0`)
    ///   with weight 1 (the authors clamp it to
    ///   `c_{K-1}/l`, losing energy even in the plain mean; splatd keeps it so that the mean
    ///   layer is the true Monte Carlo mean).
    #[inline]
    pub fn split(&self, l: f64) -> Split {
        // Branch-free on purpose: sample brightness is heavy-tailed and unpredictable, and a
        // mispredicted branch per sample costs more than the arithmetic. Clamping `l` to
        // `[c0, c_{K-1}]` gives exactly the out-of-range rules: at `c0` the pair (0, 1) puts
        // everything in 0, at `c_{K-1}` the pair (K-2, K-1) puts everything in K-1.
        let k = self.scales.len();
        let lc = l.clamp(self.scales[0], self.scales[k - 1]);
        // Largest j in 0..=K-2 with c_j <= lc (so lc <= c_{j+1}).
        let j = self.scales[1..k - 1]
            .iter()
            .fold(0, |j, &c| j + usize::from(c <= lc));
        let w_lo = (self.scales[j + 1] / lc - 1.0) / (self.base - 1.0);
        let count = (self.base - lc * self.inv_scales[j]) / (self.base - 1.0);
        // c_{j+1} / c_j may round away from b; pin the end points so that in-range rounding
        // never leaks a sliver of a dim sample into cascade 1, or of a bright one into K-2.
        let (w_lo, count) = if l <= self.scales[0] {
            (1.0, 1.0)
        } else if l >= self.scales[k - 1] {
            (0.0, 0.0)
        } else {
            (w_lo.clamp(0.0, 1.0), count.clamp(0.0, 1.0))
        };
        Split {
            lo: j,
            w_lo,
            count_lo: to_fixed(count, COUNT_ONE as f64),
        }
    }
}

/// splatd's default ratio between the brightness ranges of adjacent cascades (the paper's `b`).
pub const DEFAULT_CASCADE_BASE: f64 = 8.0;

/// splatd's default number of cascades.
pub const DEFAULT_CASCADE_COUNT: u32 = 6;

/// splatd's default scale of the lowest cascade, chosen by the quality benchmark.
pub const DEFAULT_LOWEST_SCALE: f64 = 0.125;

/// Rounds `value * units` (non-negative) to the nearest integer.
///
/// `as u64` saturates and maps NaN to 0, so the result is defined for every input; callers pass
/// only checked samples, whose shares are at most `2^52` units (see [`FRAC_BITS`]), far from
/// saturation.
#[inline]
pub(crate) fn to_fixed(value: f64, units: f64) -> u64 {
    (value * units + 0.5) as u64
}

/// Whether a sample's component with these `f32` bits is one a layout accepts (finite, not
/// negative, at most its largest), given the layout's
/// [`CascadeLayout::component_limit_bits`]: the same rule as [`CascadeLayout::check_sample`]'s,
/// on integers, without a branch (a loop over many samples becomes vector instructions). The
/// bits of a finite non-negative `f32` grow with its value, and every other pattern (negative
/// values, infinities, NaN) lies above the limit, except -0.0's, which is zero.
#[inline(always)]
pub fn component_bits_accepted(bits: u32, limit: u32) -> bool {
    const NEGATIVE_ZERO: u32 = 0x8000_0000;
    (bits <= limit) | (bits == NEGATIVE_ZERO)
}

/// Whether every component of every sample passes [`component_bits_accepted`] with `limit`:
/// a whole pass or block checked in one loop without a branch per sample.
#[inline]
pub fn samples_accepted(rgb: &[[f32; 3]], limit: u32) -> bool {
    rgb.iter().flatten().fold(true, |ok, c| {
        ok & component_bits_accepted(c.to_bits(), limit)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> CascadeLayout {
        CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap()
    }

    #[test]
    fn the_bits_rule_is_check_sample_without_the_reason() {
        // The defaults' largest component is a power of two, an `f32`; base 10's is not.
        for layout in [
            layout(),
            CascadeLayout::new(10.0, 5, 0.1, REC709_LUMINANCE).unwrap(),
        ] {
            let max = layout.max_component() as f32;
            let edge = [
                0.0,
                -0.0,
                1.0,
                f32::MIN_POSITIVE,
                f32::from_bits(1),
                max,
                f32::from_bits(max.to_bits() - 1),
                f32::from_bits(max.to_bits() + 1),
                f32::MAX,
                -f32::MIN_POSITIVE,
                -1.0,
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::NAN,
                -f32::NAN,
            ];
            for &r in &edge {
                for &g in &edge {
                    for &b in &edge {
                        let rgb = [r, g, b];
                        let limit = layout.component_limit_bits();
                        assert_eq!(
                            rgb.iter()
                                .all(|c| component_bits_accepted(c.to_bits(), limit)),
                            layout.check_sample(rgb).is_ok(),
                            "{rgb:?} with largest {}",
                            layout.max_component()
                        );
                        assert_eq!(
                            samples_accepted(&[[0.5; 3], rgb], limit),
                            layout.check_sample(rgb).is_ok(),
                            "{rgb:?} after a good sample"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn energy_and_count_identities_hold_inside_the_range() {
        let layout = layout();
        let b = layout.base();
        for &l in &[
            1.0001, 1.5, 7.99, 8.0, 8.5, 63.0, 100.0, 511.0, 4000.0, 32767.0,
        ] {
            let s = layout.split(l);
            let c = layout.scales();
            assert!(
                s.lo + 1 < layout.cascades(),
                "l={l} must split inside the range"
            );
            assert!((0.0..=1.0).contains(&s.w_lo), "w_lo={} at l={l}", s.w_lo);
            // The value shares sum to the sample by construction (w and 1 - w); the counts they
            // carry, read back from brightness, must sum to one sample.
            let count_from_luminance = s.w_lo * l / c[s.lo] + (1.0 - s.w_lo) * l / c[s.lo + 1];
            assert!(
                (count_from_luminance - 1.0).abs() < 1e-12,
                "count identity broken at l={l}: {count_from_luminance}"
            );
            let explicit = s.count_lo as f64 / COUNT_ONE as f64;
            // Rounded to 2^-FRAC_BITS of a count.
            assert!(
                (explicit - s.w_lo * l / c[s.lo]).abs() < 1.0 / COUNT_ONE as f64,
                "explicit count {explicit} disagrees with luminance count at l={l}"
            );
            // The same weight as the notes' form (b^j/L - 1/b) / (1 - 1/b), scaled by c_j.
            let notes = (c[s.lo] / l - 1.0 / b) / (1.0 - 1.0 / b);
            assert!(
                (notes - s.w_lo).abs() < 1e-12,
                "l={l}: {notes} vs {}",
                s.w_lo
            );
        }
    }

    #[test]
    fn split_is_continuous_at_cascade_boundaries() {
        let layout = layout();
        for j in 1..layout.cascades() - 1 {
            let c = layout.scales()[j];
            let below = layout.split(c * (1.0 - 1e-12));
            let at = layout.split(c);
            // Just below c_j everything goes to j (upper share of the pair j-1, j); at c_j
            // everything goes to j (lower share of the pair j, j+1).
            assert_eq!(below.lo, j - 1);
            assert!(below.w_lo < 1e-9);
            assert_eq!(at.lo, j);
            assert!((at.w_lo - 1.0).abs() < 1e-12);
            assert_eq!(at.count_lo, COUNT_ONE);
        }
    }

    #[test]
    fn out_of_range_samples_keep_their_energy_and_one_count() {
        let layout = layout();
        for l in [0.0, 1e-30, 0.5, 1.0] {
            assert_eq!(
                layout.split(l),
                Split {
                    lo: 0,
                    w_lo: 1.0,
                    count_lo: COUNT_ONE
                }
            );
        }
        // Beyond the top: all of it (and the whole count) to the upper cascade of the top pair.
        for l in [32768.0, 1e9, 1e30, f64::MAX] {
            assert_eq!(
                layout.split(l),
                Split {
                    lo: 4,
                    w_lo: 0.0,
                    count_lo: 0
                }
            );
        }
    }

    #[test]
    fn nonsense_parameters_are_refused_by_name() {
        let bad = [
            (CascadeLayout::new(1.0, 6, 1.0, REC709_LUMINANCE), "base"),
            (
                CascadeLayout::new(f64::NAN, 6, 1.0, REC709_LUMINANCE),
                "base",
            ),
            (
                CascadeLayout::new(8.0, 1, 1.0, REC709_LUMINANCE),
                "cascades",
            ),
            (
                CascadeLayout::new(8.0, 17, 1.0, REC709_LUMINANCE),
                "cascades",
            ),
            (
                CascadeLayout::new(8.0, 6, 0.0, REC709_LUMINANCE),
                "lowest_scale",
            ),
            (
                CascadeLayout::new(8.0, 6, -1.0, REC709_LUMINANCE),
                "lowest_scale",
            ),
            (
                CascadeLayout::new(8.0, 16, 1e20, REC709_LUMINANCE),
                "lowest_scale",
            ),
            (
                CascadeLayout::new(8.0, 6, 1.0, [0.3, 0.0, 0.1]),
                "luminance",
            ),
            (
                CascadeLayout::new(8.0, 6, 1.0, [0.3, f64::INFINITY, 0.1]),
                "luminance",
            ),
        ];
        for (result, name) in bad {
            let err = result.expect_err(name);
            assert_eq!(err.name, name, "{err}");
        }
    }

    #[test]
    fn luminance_weights_are_bounded() {
        for bad in [
            [1e308, 0.7, 0.07],
            [0.2, 0.7, 0.0],
            [0.2, 0.7, 0.03],
            [0.2, 1.01, 0.1],
        ] {
            let err = CascadeLayout::new(8.0, 6, 1.0, bad).unwrap_err();
            assert_eq!(err.name, "luminance", "{bad:?}");
            assert!(err.reason.contains("[1/32, 1]"), "{err}");
        }
        for good in [
            REC709_LUMINANCE,
            [0.2722, 0.6741, 0.0537],
            [1.0 / 32.0, 1.0, 1.0],
        ] {
            assert!(CascadeLayout::new(8.0, 6, 1.0, good).is_ok(), "{good:?}");
        }
    }
}
