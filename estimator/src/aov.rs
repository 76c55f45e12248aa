//! Arbitrary output variables (AOVs): the other layers of a rendered pass (albedo, normal,
//! depth, any named layer), accumulated as plain per-pixel means beside the cascades.
//!
//! A denoiser wants the reweighted beauty *and* its guides. AOVs are smooth where the beauty is
//! noisy, so they are not reweighted: each channel is the plain mean of the values the passes
//! carried. Like the cascades they are exact and mergeable: every value is rounded once to a
//! fixed-point integer (units of `2^-AOV_FRAC_BITS`) and sums are integer additions, so the
//! same passes give the same sums in any order, split over any number of nodes.
//!
//! # Bounds
//!
//! A value must be finite with `|v| <= AOV_MAX_ABS` (`2^40`, about `1.1e12`: Cycles writes
//! `1e10` as the depth of the background). It is stored as `round(v * 2^20)` (half away from
//! zero), an integer of at most 61 bits with its sign; a pixel holds at most
//! [`MAX_PIXEL_SAMPLES`] (`2^32`) of them, so a sum stays below `2^92`, held as an `i128`.
//! The step `2^-20` (about `9.5e-7`) is far below what a guide needs; a mean is exact to within
//! half a step of the true mean of the values as stored (`f32`).
//!
//! # Words
//!
//! A pixel is `1 + 2C` `u64` words for `C` channels: its AOV sample count, then per channel the
//! sum's low and high 64 bits (two's complement). This is also the state format's layout, so
//! states carry the words verbatim.

use std::ops::Range;

use crate::layout::MAX_PIXEL_SAMPLES;
use crate::state::zeroed_in;

/// Fractional bits of the AOV fixed point: values are stored in units of `2^-20`.
pub const AOV_FRAC_BITS: u32 = 20;

/// Largest magnitude an AOV value may have: `2^40`.
pub const AOV_MAX_ABS: f64 = (1u64 << 40) as f64;

/// Largest stored magnitude of one value: `AOV_MAX_ABS * 2^AOV_FRAC_BITS`.
const MAX_UNITS: i128 = 1 << 60;

/// Words per pixel for `channels` AOV channels.
pub fn aov_words(channels: usize) -> usize {
    1 + 2 * channels
}

/// Why an AOV value was refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum AovValueError {
    /// NaN or infinite.
    #[error("AOV value {0} is not finite")]
    NotFinite(f32),
    /// Outside `[-2^40, 2^40]`.
    #[error("AOV value {0} is outside [-2^40, 2^40] (about 1.1e12)")]
    TooLarge(f32),
}

/// A value in fixed point, or why it cannot be stored.
pub fn aov_units(v: f32) -> Result<i128, AovValueError> {
    if !v.is_finite() {
        return Err(AovValueError::NotFinite(v));
    }
    if f64::from(v).abs() > AOV_MAX_ABS {
        return Err(AovValueError::TooLarge(v));
    }
    Ok(i128::from(units_within_bounds(v)))
}

/// Checks every value of a pass (`channels` values per pixel): the first value [`aov_units`]
/// refuses, as its pixel number, channel and error.
pub fn check_aov_values(
    values: &[f32],
    channels: usize,
) -> Result<(), (usize, usize, AovValueError)> {
    if aov_values_accepted(values) {
        return Ok(());
    }
    let channels = channels.max(1);
    for (i, &v) in values.iter().enumerate() {
        aov_units(v).map_err(|e| (i / channels, i % channels, e))?;
    }
    Ok(())
}

/// Whether [`aov_units`] accepts every value: a test of each value's bits without a branch (a
/// loop that becomes vector instructions; a pass's AOV values checked one by one with their
/// reasons took 3 % of the server's CPU under `loadgen --kind passes --aovs`). Without its sign
/// bit a finite value's bits grow with its magnitude, and infinities and NaN lie above every
/// finite value's.
pub fn aov_values_accepted(values: &[f32]) -> bool {
    const LIMIT: u32 = (AOV_MAX_ABS as f32).to_bits();
    values
        .iter()
        .fold(true, |ok, v| ok & (v.to_bits() & 0x7fff_ffff <= LIMIT))
}

/// `round(v * 2^AOV_FRAC_BITS)`, half away from zero, for a finite `v` with `|v| <= 2^40` (so
/// `|v * 2^20| <= 2^60` fits an `i64`).
///
/// Exact: `f32` to `f64` and a power-of-two scale lose nothing; the `as i64` truncation is exact
/// in that range, and so is the fraction it leaves (`x - trunc(x)`: 0 from `2^52` up, where
/// every `f64` is an integer). The same integer as `f64::round` and `as i128`, which cost a
/// library call each (`round` without SSE4.1, and the 128-bit conversion): 60 ms of the 88 ms
/// that adding a 1080p pass of 6 AOV channels took, five times the pass's splat.
#[inline(always)]
fn units_within_bounds(v: f32) -> i64 {
    let x = f64::from(v) * (1u64 << AOV_FRAC_BITS) as f64;
    let t = x as i64;
    let fraction = x - t as f64;
    t + i64::from(fraction >= 0.5) - i64::from(fraction <= -0.5)
}

/// AOV words that no checked values could have made.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AovCellsError {
    /// The word count does not fit the geometry.
    #[error(
        "AOV section has {count} words, but {pixels} pixels of {channels} channels need {expected}"
    )]
    Shape {
        /// Words given.
        count: usize,
        /// Words expected.
        expected: usize,
        /// Pixels held.
        pixels: usize,
        /// Channels.
        channels: usize,
    },
    /// A pixel's words break the bounds of the module docs.
    #[error("AOV of pixel ({x}, {y}): {reason}")]
    Invalid {
        /// Column.
        x: u32,
        /// Row.
        y: u32,
        /// What is wrong.
        reason: String,
    },
    /// Two AOV states of different geometry were merged.
    #[error("AOV states differ: {0}")]
    Mismatch(String),
    /// A merge would take a pixel past [`MAX_PIXEL_SAMPLES`] AOV samples.
    #[error("AOV of pixel ({x}, {y}) would hold more than 2^32 samples")]
    Full {
        /// Column.
        x: u32,
        /// Row.
        y: u32,
    },
}

/// The AOV sums of a frame, or of a band of its rows.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AovSums {
    width: u32,
    rows: Range<u32>,
    channels: usize,
    words: Vec<u64>,
    /// The largest sample count of any pixel held, kept by every change, so that whether a
    /// pass fits is known without reading every pixel's count (a pass through all the sums,
    /// 4 % of the server's CPU while it took passes with 6 AOV channels).
    most: u64,
}

fn get(words: &[u64], at: usize) -> i128 {
    (((words[at + 1] as u128) << 64) | words[at] as u128) as i128
}

/// `get(words, at) as f64`: the same rounding of the same integer, through `i64` where the sum
/// fits one (any sum below `2^63` units), which is one instruction where the `i128` conversion
/// is a library call (`__floattidf`). The means of a 1080p frame's 6 AOV channels, which every
/// `image.exr` with AOV layers and every denoise computes, took 63-70 ms with it, 33-45 ms
/// without.
#[inline(always)]
fn sum_as_f64(words: &[u64], at: usize) -> f64 {
    let (lo, hi) = (words[at], words[at + 1]);
    if hi == ((lo as i64) >> 63) as u64 {
        lo as i64 as f64
    } else {
        get(words, at) as f64
    }
}

fn set(words: &mut [u64], at: usize, v: i128) {
    words[at] = v as u64;
    words[at + 1] = ((v as u128) >> 64) as u64;
}

/// Why one pixel's AOV words (exactly [`aov_words`] of its channels: the count, then each
/// channel's 128-bit sum) cannot be what checked values made, if they cannot: the bounds that
/// [`AovSums::from_words`] checks for every pixel.
pub fn check_aov_pixel(px: &[u64]) -> Result<(), String> {
    let count = px[0];
    if count > MAX_PIXEL_SAMPLES {
        return Err(format!("{count} samples, more than 2^32"));
    }
    for c in 0..(px.len() - 1) / 2 {
        let sum = get(px, 1 + 2 * c);
        if sum.unsigned_abs() > (count as u128) * MAX_UNITS as u128 {
            return Err(format!(
                "channel {c}: sum {sum} is more than {count} values of at most 2^60 units"
            ));
        }
    }
    Ok(())
}

/// Adds one pixel's AOV words `src` to `dst` (both checked, [`check_aov_pixel`]), exactly, as
/// [`AovSums::merge_overlap`] does. The caller checks that the counts add to at most
/// [`MAX_PIXEL_SAMPLES`]; then no sum can overflow.
pub fn add_aov_pixel(dst: &mut [u64], src: &[u64]) {
    dst[0] += src[0];
    for c in 0..(dst.len() - 1) / 2 {
        let at = 1 + 2 * c;
        let sum = get(dst, at) + get(src, at);
        set(dst, at, sum);
    }
}

impl AovSums {
    /// Empty sums of `channels` channels for rows `rows` of a frame `width` wide.
    pub fn new(width: u32, rows: Range<u32>, channels: usize) -> AovSums {
        Self::new_in(width, rows, channels, |_| Vec::new())
    }

    /// [`AovSums::new`] in the memory `words(len)` gives for its `len` words (the words of
    /// earlier sums) if it has room, zeroed; else in new memory, zeroed by the allocator and
    /// untouched until the first pass.
    pub fn new_in(
        width: u32,
        rows: Range<u32>,
        channels: usize,
        words: impl FnOnce(usize) -> Vec<u64>,
    ) -> AovSums {
        let len = width as usize * rows.len() * aov_words(channels);
        let words = zeroed_in(words(len), len);
        AovSums {
            width,
            rows,
            channels,
            words,
            most: 0,
        }
    }

    /// Sums from words (a state's AOV section), checked against the bounds of the module docs.
    ///
    /// # Errors
    /// [`AovCellsError::Shape`] for a wrong word count, [`AovCellsError::Invalid`] naming the
    /// first pixel whose words no checked values could have made.
    pub fn from_words(
        width: u32,
        rows: Range<u32>,
        channels: usize,
        words: Vec<u64>,
    ) -> Result<AovSums, AovCellsError> {
        let pixels = width as usize * rows.len();
        let expected = pixels * aov_words(channels);
        if words.len() != expected {
            return Err(AovCellsError::Shape {
                count: words.len(),
                expected,
                pixels,
                channels,
            });
        }
        let mut sums = AovSums {
            width,
            rows,
            channels,
            words,
            most: 0,
        };
        for p in 0..pixels {
            if let Err(reason) = sums.check_pixel(p) {
                let (x, y) = sums.position(p);
                return Err(AovCellsError::Invalid { x, y, reason });
            }
        }
        sums.most = sums.count_most();
        Ok(sums)
    }

    fn check_pixel(&self, p: usize) -> Result<(), String> {
        let n = aov_words(self.channels);
        check_aov_pixel(&self.words[p * n..(p + 1) * n])
    }

    fn position(&self, p: usize) -> (u32, u32) {
        let w = self.width.max(1) as usize;
        ((p % w) as u32, self.rows.start + (p / w) as u32)
    }

    /// Channels per pixel.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Rows held.
    pub fn rows(&self) -> Range<u32> {
        self.rows.clone()
    }

    /// The words, pixel by pixel (see the module docs).
    pub fn words(&self) -> &[u64] {
        &self.words
    }

    /// AOV samples of the pixel `(x, y)` (a row held).
    pub fn count(&self, x: u32, y: u32) -> u64 {
        let p = (y - self.rows.start) as usize * self.width as usize + x as usize;
        self.words[p * aov_words(self.channels)]
    }

    /// Checks every value of a pass: `values` holds the rows held, pixel by pixel, `channels`
    /// values per pixel. Returns the first bad value's pixel number, channel and error.
    pub fn check_values(&self, values: &[f32]) -> Result<(), (usize, usize, AovValueError)> {
        check_aov_values(values, self.channels)
    }

    /// Whether every pixel can take one more AOV sample.
    pub fn has_room_for_pass(&self) -> bool {
        self.most < MAX_PIXEL_SAMPLES
    }

    /// The largest sample count of any pixel, read from every pixel.
    fn count_most(&self) -> u64 {
        let n = aov_words(self.channels);
        self.words
            .chunks_exact(n)
            .map(|px| px[0])
            .max()
            .unwrap_or(0)
    }

    /// Adds one pass: one value per channel for every pixel held (see
    /// [`AovSums::check_values`]), each pixel's count going up by one.
    ///
    /// # Panics
    /// If `values` has the wrong length or holds a value [`aov_units`] refuses: check first.
    pub fn add_pass(&mut self, values: &[f32]) {
        let n = aov_words(self.channels);
        assert_eq!(
            values.len(),
            self.words.len() / n * self.channels,
            "one value per channel and pixel"
        );
        if self.channels == 0 {
            return;
        }
        if !self.words.is_empty() {
            self.most += 1;
        }
        for (px, vals) in self
            .words
            .chunks_exact_mut(n)
            .zip(values.chunks_exact(self.channels))
        {
            px[0] += 1;
            for (c, &v) in vals.iter().enumerate() {
                let units = aov_units(v).expect("AOV values are checked before they are added");
                let at = 1 + 2 * c;
                let sum = get(px, at) + units;
                set(px, at, sum);
            }
        }
    }

    /// Checks that `other` (any rows of the same frame, same channels) can be added.
    ///
    /// # Errors
    /// [`AovCellsError::Mismatch`] for another width or channel count, [`AovCellsError::Full`]
    /// for a pixel that would hold more than 2^32 samples.
    pub fn check_room_for(&self, other: &AovSums) -> Result<(), AovCellsError> {
        if other.width != self.width || other.channels != self.channels {
            return Err(AovCellsError::Mismatch(format!(
                "{} channels of a frame {} wide here, {} channels of a frame {} wide in the state",
                self.channels, self.width, other.channels, other.width
            )));
        }
        let n = aov_words(self.channels);
        for y in self.rows.start.max(other.rows.start)..self.rows.end.min(other.rows.end) {
            for x in 0..self.width {
                let a = self.words[self.index(x, y) * n];
                let b = other.words[other.index(x, y) * n];
                if a + b > MAX_PIXEL_SAMPLES {
                    return Err(AovCellsError::Full { x, y });
                }
            }
        }
        Ok(())
    }

    fn index(&self, x: u32, y: u32) -> usize {
        (y - self.rows.start) as usize * self.width as usize + x as usize
    }

    /// Adds the rows `other` shares with `self`.
    ///
    /// # Errors
    /// As [`AovSums::check_room_for`]; nothing is added then.
    pub fn merge_overlap(&mut self, other: &AovSums) -> Result<(), AovCellsError> {
        self.check_room_for(other)?;
        let n = aov_words(self.channels);
        let w = self.width as usize;
        for y in self.rows.start.max(other.rows.start)..self.rows.end.min(other.rows.end) {
            let a = self.index(0, y) * n;
            let b = other.index(0, y) * n;
            let dst = &mut self.words[a..a + w * n];
            let src = &other.words[b..b + w * n];
            for (d, s) in dst.chunks_exact_mut(n).zip(src.chunks_exact(n)) {
                add_aov_pixel(d, s);
                // Counts only grow: the largest is the old one or one of these.
                self.most = self.most.max(d[0]);
            }
        }
        Ok(())
    }

    /// What was added since `base` (an earlier copy of the same sums): `self - base`, word by
    /// word, for push deltas.
    ///
    /// # Errors
    /// [`AovCellsError::Mismatch`] if `base` has another geometry or is not an earlier copy.
    pub fn delta_since(&self, base: &AovSums) -> Result<AovSums, AovCellsError> {
        if (base.width, &base.rows, base.channels) != (self.width, &self.rows, self.channels) {
            return Err(AovCellsError::Mismatch(
                "the base of a delta has another geometry".into(),
            ));
        }
        let n = aov_words(self.channels);
        let mut delta = self.clone();
        delta.most = 0;
        for (d, b) in delta
            .words
            .chunks_exact_mut(n)
            .zip(base.words.chunks_exact(n))
        {
            d[0] = d[0].checked_sub(b[0]).ok_or_else(|| {
                AovCellsError::Mismatch("the base of a delta holds more samples".into())
            })?;
            delta.most = delta.most.max(d[0]);
            for c in 0..self.channels {
                let at = 1 + 2 * c;
                let v = get(d, at) - get(b, at);
                set(d, at, v);
            }
        }
        Ok(delta)
    }

    /// The sums' words, whose memory [`AovSums::clone_in`] can reuse.
    pub fn into_words(self) -> Vec<u64> {
        self.words
    }

    /// A copy of these sums in the memory of `words` (the words of earlier sums; grown if they
    /// are too small), like [`clone`](Clone::clone) into memory already mapped.
    pub fn clone_in(&self, mut words: Vec<u64>) -> AovSums {
        words.clear();
        words.extend_from_slice(&self.words);
        AovSums {
            rows: self.rows.clone(),
            words,
            ..*self
        }
    }

    /// The words of the rows `rows` (which these sums hold), without a copy.
    ///
    /// # Panics
    /// If `rows` are not all held.
    pub fn rows_words(&self, rows: Range<u32>) -> &[u64] {
        assert!(
            self.rows.start <= rows.start && rows.start <= rows.end && rows.end <= self.rows.end,
            "rows {rows:?} of AOV sums holding {:?}",
            self.rows
        );
        let n = aov_words(self.channels);
        let (a, b) = (self.index(0, rows.start), self.index(0, rows.end));
        &self.words[a * n..b * n]
    }

    /// The means, one plane per channel (pixels of the rows held, row-major); 0 where a pixel
    /// has no AOV sample.
    pub fn means(&self) -> Vec<Vec<f32>> {
        let n = aov_words(self.channels);
        let scale = (1u64 << AOV_FRAC_BITS) as f64;
        let mut planes = vec![Vec::with_capacity(self.words.len() / n); self.channels];
        for px in self.words.chunks_exact(n) {
            let count = px[0];
            for (c, plane) in planes.iter_mut().enumerate() {
                plane.push(if count == 0 {
                    0.0
                } else {
                    (sum_as_f64(px, 1 + 2 * c) / count as f64 / scale) as f32
                });
            }
        }
        planes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sums of rows `rows` of `sums`, as sums of their own (a band of a frame).
    fn band_of(sums: &AovSums, rows: Range<u32>) -> AovSums {
        let words = sums.rows_words(rows.clone()).to_vec();
        AovSums::from_words(sums.width, rows, sums.channels, words).unwrap()
    }

    /// The units are `f64::round` of the scaled value, as first written: at every halfway
    /// point and its neighbours, at the bounds, and over random values of every magnitude.
    #[test]
    fn units_are_the_rounded_scaled_value() {
        let scale = (1u64 << AOV_FRAC_BITS) as f64;
        let rounded = |v: f32| (f64::from(v) * scale).round() as i128;
        let mut values = vec![0.0f32, -0.0, f32::MIN_POSITIVE, -f32::MIN_POSITIVE, 1e-45];
        for k in -4..=4i64 {
            // k + 1/2 units, and the floats on each side of it.
            let half = ((k as f64 + 0.5) / scale) as f32;
            values.extend([half, f32::from_bits(half.to_bits() + 1)]);
            values.extend([f32::from_bits(half.to_bits() - 1), -half]);
        }
        let top = AOV_MAX_ABS as f32;
        values.extend([
            top,
            -top,
            f32::from_bits(top.to_bits() - 1),
            2f32.powi(32) + 0.5,
        ]);
        let mut bits = 0x9E37_79B9u32;
        for _ in 0..200_000 {
            bits = bits.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let v = f32::from_bits(bits);
            if v.is_finite() && f64::from(v).abs() <= AOV_MAX_ABS {
                values.push(v);
            }
        }
        for v in values {
            assert_eq!(
                aov_units(v).unwrap(),
                rounded(v),
                "{v:e} ({:#x})",
                v.to_bits()
            );
        }
    }

    /// A sum's `f64` through `i64` is the `i128` conversion's, on both sides of `i64`'s range
    /// and at the roundings in between.
    #[test]
    fn sums_convert_as_i128_does() {
        let mut sums: Vec<i128> = vec![0, 1, -1, i64::MAX as i128, i64::MIN as i128];
        sums.extend([
            i64::MAX as i128 + 1,
            i64::MIN as i128 - 1,
            1 << 91,
            -(1 << 91),
        ]);
        for shift in [52, 53, 54, 62] {
            for d in -3..=3i128 {
                sums.extend([(1i128 << shift) + d, -(1i128 << shift) + d]);
            }
        }
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        for _ in 0..100_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            sums.push((x as i64 >> (x % 40)) as i128);
            sums.push(((x as i128) << 28) >> (x % 30));
        }
        for sum in sums {
            let mut words = [0u64; 3];
            set(&mut words, 1, sum);
            assert_eq!(
                sum_as_f64(&words, 1).to_bits(),
                (sum as f64).to_bits(),
                "{sum}"
            );
        }
    }

    /// The bits test accepts exactly the values `aov_units` accepts.
    #[test]
    fn the_bits_test_is_aov_units_without_the_reason() {
        let top = AOV_MAX_ABS as f32;
        let above = f32::from_bits(top.to_bits() + 1);
        let mut values = vec![
            0.0f32, -0.0, 1e-45, -1e-45, 1.0, -1.0, top, -top, above, -above,
        ];
        values.extend([
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::MAX,
        ]);
        let mut bits = 0x2545_F491u32;
        for _ in 0..100_000 {
            bits = bits.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            values.push(f32::from_bits(bits));
        }
        for v in values {
            let one = aov_units(v).is_ok();
            assert_eq!(aov_values_accepted(&[v]), one, "{v:e} ({:#x})", v.to_bits());
            assert_eq!(
                aov_values_accepted(&[0.5, v, 2.0]),
                one,
                "{v:e} among good ones"
            );
        }
        assert!(aov_values_accepted(&[]));
    }

    #[test]
    fn values_are_rounded_once_and_bounded() {
        assert_eq!(aov_units(1.0).unwrap(), 1 << 20);
        assert_eq!(aov_units(-0.5).unwrap(), -(1 << 19));
        assert_eq!(
            aov_units(1e10).unwrap(),
            (1e10f32 as f64 * 1048576.0) as i128
        );
        assert_eq!(aov_units(2f32.powi(40)).unwrap(), MAX_UNITS);
        assert!(matches!(aov_units(2.2e12), Err(AovValueError::TooLarge(_))));
        assert!(matches!(
            aov_units(f32::NAN),
            Err(AovValueError::NotFinite(_))
        ));
        assert!(matches!(
            aov_units(f32::NEG_INFINITY),
            Err(AovValueError::NotFinite(_))
        ));
    }

    #[test]
    fn means_are_exact_and_merge_is_order_free() {
        // 2 channels, 3x2 frame; passes split over two "nodes" and a band.
        let passes: Vec<Vec<f32>> = (0..7)
            .map(|k| {
                (0..12)
                    .map(|i| ((k * 31 + i * 17) % 23) as f32 * 0.37 - 4.0)
                    .collect()
            })
            .collect();
        let mut one = AovSums::new(3, 0..2, 2);
        let (mut a, mut b) = (AovSums::new(3, 0..2, 2), AovSums::new(3, 0..2, 2));
        for (k, p) in passes.iter().enumerate() {
            one.check_values(p).unwrap();
            one.add_pass(p);
            if k % 2 == 0 { &mut a } else { &mut b }.add_pass(p);
        }
        a.merge_overlap(&b).unwrap();
        assert_eq!(a, one);
        let means = one.means();
        for c in 0..2 {
            for px in 0..6 {
                let exact: f64 = passes.iter().map(|p| p[px * 2 + c] as f64).sum::<f64>() / 7.0;
                let step = 1.0 / (1u64 << AOV_FRAC_BITS) as f64;
                assert!((means[c][px] as f64 - exact).abs() <= step, "{c} {px}");
            }
        }
        // A band of the lower row adds only to that row.
        let band = band_of(&one, 1..2);
        let mut twice = one.clone();
        twice.merge_overlap(&band).unwrap();
        assert_eq!(twice.count(0, 0), 7);
        assert_eq!(twice.count(2, 1), 14);
        // A delta against an earlier copy adds back to the later one.
        let mut later = a.clone();
        later.add_pass(&passes[0]);
        let delta = later.delta_since(&a).unwrap();
        assert_eq!(delta.count(1, 1), 1);
        a.merge_overlap(&delta).unwrap();
        assert_eq!(a, later);
        // Words survive a round trip through their checked constructor.
        let back = AovSums::from_words(3, 0..2, 2, one.words().to_vec()).unwrap();
        assert_eq!(back, one);
    }

    #[test]
    fn words_no_pass_could_make_are_refused() {
        let mut sums = AovSums::new(2, 4..5, 1);
        sums.add_pass(&[1.0, 2.0]);
        let mut words = sums.words().to_vec();
        words[3] = 0; // pixel 1's count: a sum with no samples
        let err = AovSums::from_words(2, 4..5, 1, words).unwrap_err();
        assert!(
            matches!(err, AovCellsError::Invalid { x: 1, y: 4, .. }),
            "{err}"
        );
        let err = AovSums::from_words(2, 4..5, 1, vec![0; 5]).unwrap_err();
        assert!(
            matches!(err, AovCellsError::Shape { expected: 6, .. }),
            "{err}"
        );
        let mut words = sums.words().to_vec();
        words[0] = MAX_PIXEL_SAMPLES + 1;
        assert!(AovSums::from_words(2, 4..5, 1, words).is_err());
        let err = AovSums::new(2, 0..1, 2).merge_overlap(&sums).unwrap_err();
        assert!(matches!(err, AovCellsError::Mismatch(_)), "{err}");
    }

    /// The largest count kept with the sums is the largest count read from them after every
    /// change, and says whether a pass fits, up to the last sample.
    #[test]
    fn the_largest_count_is_kept_by_every_change() {
        let kept = |s: &AovSums| {
            assert_eq!(s.most, s.count_most(), "rows {:?}", s.rows);
            s.most
        };
        let values =
            |k: usize| -> Vec<f32> { (0..2 * 12).map(|i| (i + k) as f32 * 0.25).collect() };
        let mut whole = AovSums::new(3, 0..4, 2);
        assert_eq!(kept(&whole), 0);
        let base = whole.clone();
        for k in 0..3 {
            whole.add_pass(&values(k));
            assert_eq!(kept(&whole), k as u64 + 1);
        }
        let mut band = AovSums::new(3, 1..3, 2);
        band.add_pass(&values(9)[..12]);
        for _ in 0..4 {
            band.merge_overlap(&whole).unwrap();
            kept(&band);
        }
        assert_eq!(kept(&band), 13);
        whole.merge_overlap(&band).unwrap();
        assert_eq!(kept(&whole), 16);
        let delta = whole.delta_since(&base).unwrap();
        assert_eq!(kept(&delta), 16);
        let since = whole.delta_since(&whole.clone()).unwrap();
        assert_eq!(kept(&since), 0);
        assert_eq!(
            kept(&band_of(&whole, 0..1)),
            3,
            "row 0 holds the passes only"
        );
        assert_eq!(kept(&whole.clone_in(Vec::new())), 16);
        let read = AovSums::from_words(3, 0..4, 2, whole.words().to_vec()).unwrap();
        assert_eq!(kept(&read), 16);
        // A pass fits while every pixel is below the cap, and not once one reaches it.
        let mut words = vec![0u64; 5 * 2];
        words[5] = MAX_PIXEL_SAMPLES - 1;
        let mut near = AovSums::from_words(2, 0..1, 2, words).unwrap();
        assert!(near.has_room_for_pass());
        near.add_pass(&[0.5; 4]);
        assert_eq!(kept(&near), MAX_PIXEL_SAMPLES);
        assert!(!near.has_room_for_pass());
    }

    /// A copy into given memory is a clone that keeps that memory; a band's rows are the
    /// words of its own sums, whole or copied out.
    #[test]
    fn copies_go_into_given_memory_and_rows_are_views() {
        let mut sums = AovSums::new(3, 0..4, 2);
        let values: Vec<f32> = (0..24).map(|i| i as f32 * 0.5 - 3.0).collect();
        sums.add_pass(&values);
        let memory = vec![7u64; 100];
        let at = memory.as_ptr();
        let copy = sums.clone_in(memory);
        assert_eq!(copy, sums);
        let words = copy.into_words();
        assert_eq!(words.as_ptr(), at, "the given memory");
        let empty = AovSums::new_in(3, 0..4, 2, |len| {
            assert_eq!(len, 12 * 5, "4 x 3 pixels of 5 words");
            words
        });
        assert_eq!(empty, AovSums::new(3, 0..4, 2), "zeroed");
        assert_eq!(empty.words().as_ptr(), at, "in the given memory");
        let small = AovSums::new_in(3, 0..4, 2, |_| vec![7; 3]);
        assert_eq!(small, AovSums::new(3, 0..4, 2), "too small: new memory");
        let band = band_of(&sums, 1..3);
        assert_eq!(sums.rows_words(1..3), band.words());
        assert_eq!(band.rows_words(1..3), band.words());
        assert_eq!(sums.rows_words(0..4), sums.words());
        assert!(sums.rows_words(2..2).is_empty());
        let outside = std::panic::catch_unwind(|| band.rows_words(0..2).len());
        assert!(outside.is_err(), "rows the sums do not hold");
    }

    #[test]
    fn negative_sums_keep_their_sign_across_words() {
        let mut sums = AovSums::new(1, 0..1, 1);
        for _ in 0..3 {
            sums.add_pass(&[-1e12]);
        }
        assert_eq!(sums.means()[0][0], -1e12);
        assert!(sums.words()[2] == u64::MAX, "high word of a negative sum");
    }
}
