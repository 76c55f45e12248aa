//! The row splat: samples of consecutive pixels of one row (a rendered pass, a tile's scan line,
//! any batch in scan order), with the per-sample arithmetic done a block of samples at a time.
//!
//! A block of [`BLOCK`] samples goes through straight-line loops over the block, one quantity at
//! a time (luminance, cascade index, split weights, fixed-point units), which the compiler turns
//! into vector instructions; only the additions into the cells are done sample by sample.
//! Every quantity is computed with the same `f64` operations, in the same order, as the
//! one-sample path ([`CascadeLayout::split`] and `apply`), so the result is bit-identical to
//! splatting the samples one by one: IEEE arithmetic gives the same bits in a vector lane as in a
//! scalar register, and Rust never fuses a multiply and an add behind our back.
//!
//! On x86-64 the same code is compiled twice more and chosen at run time ([`Kernel`]): with AVX2
//! (4 `f64` lanes instead of SSE2's 2) and with AVX-512 (8 lanes); [`Kernel::Portable`] is the
//! fallback, and the tests run each kernel the CPU has on the same samples and compare the bits.

// The block loops index several arrays by lane, as the vector code they become does.
#![allow(clippy::needless_range_loop)]

use crate::layout::{samples_accepted, CascadeLayout, COUNT_ONE, MAX_CASCADES};

/// Samples per block.
pub(crate) const BLOCK: usize = 16;

const K_MAX: usize = MAX_CASCADES as usize;

/// `2^52`: adding it to a non-negative `f64` below `2^52` rounds that value to an integer.
const TWO_52: f64 = 4_503_599_627_370_496.0;

/// Which compilation of the block arithmetic to run. More may come with new CPUs: a match on
/// it outside this crate needs an arm for the others.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Kernel {
    /// The code as compiled for the target's baseline (SSE2 on x86-64); runs everywhere.
    Portable,
    /// The same code compiled with AVX2 (x86-64 only; only where the CPU has it).
    Avx2,
    /// The splat's block arithmetic, and the resolve's row pass and support step, compiled with
    /// AVX-512 (F, DQ, VL and BW) as well (x86-64 only; only where the CPU has them and AVX2,
    /// and is of a generation whose clock 512-bit code does not lower much: see
    /// [`Kernel::detect`]). The other loops compiled per kernel (the resolve's spread stage, the
    /// server's record check) run their AVX2 compilation under it: AVX-512 made them no faster.
    /// The splat, measured on one thread of an Intel Xeon (Emerald Rapids) VM, alternated runs
    /// of a harness splatting 1080p passes: rows 40-48 M samples/s with AVX2 and 46-52 with
    /// AVX-512 (`bench speed`: 46.1 and 49.9), records in random order 25-31 and 31-33; on a
    /// Zen 4 VM an AVX-512 build of the splat was about 5 % faster. The resolve's figures are in
    /// the docs of its row pass (`resolve/rows.rs`).
    Avx512,
}

impl Kernel {
    /// The fastest kernel this CPU runs.
    ///
    /// [`Kernel::Avx512`] only on CPUs with AVX-512 VBMI2 as well, which the kernel does not
    /// use: it marks the generations (Intel's from Ice Lake on, AMD's from Zen 4 on) where
    /// 512-bit code lowers the core's clock little or not at all. On the Xeons before them
    /// (Skylake-SP, Cascade Lake, Cooper Lake) it lowers it for every thread of the core for a
    /// while, which could cost a head's resolves and requests more than the splat gains
    /// (simdjson, for that reason, runs its AVX-512 code only from Ice Lake and Zen 4 on, with
    /// the same marker; LLVM prefers 256-bit vectors on those Xeons). They run
    /// [`Kernel::Avx2`].
    ///
    /// Worked out once per process: [`Kernel::available`] asks for it before every block of
    /// samples and every strip of a resolve, and the AVX-512 kernel takes six feature tests.
    pub fn detect() -> Self {
        static DETECTED: std::sync::OnceLock<Kernel> = std::sync::OnceLock::new();
        *DETECTED.get_or_init(|| {
            #[cfg(target_arch = "x86_64")]
            {
                use std::arch::is_x86_feature_detected as has;
                if has!("avx2") {
                    let avx512 = has!("avx512f") && has!("avx512dq") && has!("avx512vl");
                    if avx512 && has!("avx512bw") && has!("avx512vbmi2") {
                        return Kernel::Avx512;
                    }
                    return Kernel::Avx2;
                }
            }
            Kernel::Portable
        })
    }

    /// Whether this CPU can run the kernel.
    pub fn available(self) -> bool {
        match self {
            Kernel::Portable => true,
            Kernel::Avx2 => Kernel::detect() != Kernel::Portable,
            Kernel::Avx512 => Kernel::detect() == Kernel::Avx512,
        }
    }
}

/// A layout's constants, padded to [`MAX_CASCADES`], for the block loops.
pub(crate) struct Tables {
    k: usize,
    base: f64,
    luminance: [f64; 3],
    /// [`CascadeLayout::component_limit_bits`].
    component_limit_bits: u32,
    scales: [f64; K_MAX],
    /// Per lower cascade `j`: `[c_{j+1}, 1 / c_j, units of j, units of j + 1]`, looked up by a
    /// lane's `j` (one load where a select over every `j` would take `K` compares and
    /// branches that a random `j` mispredicts).
    by_lo: [[f64; 4]; K_MAX],
}

impl Tables {
    pub(crate) fn new(layout: &CascadeLayout) -> Self {
        let k = layout.cascades();
        let mut t = Tables {
            k,
            base: layout.base(),
            luminance: layout.luminance_weights(),
            component_limit_bits: layout.component_limit_bits(),
            scales: [0.0; K_MAX],
            by_lo: [[0.0; 4]; K_MAX],
        };
        for j in 0..k {
            t.scales[j] = layout.scales()[j];
        }
        for j in 0..k - 1 {
            t.by_lo[j] = [
                layout.scales()[j + 1],
                layout.inv_scale(j),
                layout.units_per_value(j),
                layout.units_per_value(j + 1),
            ];
        }
        t
    }

    /// Whether every sample is one [`CascadeLayout::check_sample`] accepts: finite, not
    /// negative, no component above the largest.
    pub(crate) fn all_valid(&self, rgb: &[[f32; 3]]) -> bool {
        samples_accepted(rgb, self.component_limit_bits)
    }

    /// [`Tables::all_valid`] if `CHECK`; else the caller knows the samples are valid (a debug
    /// build still asserts it).
    #[inline(always)]
    pub(crate) fn valid<const CHECK: bool>(&self, rgb: &[[f32; 3]]) -> bool {
        if CHECK {
            self.all_valid(rgb)
        } else {
            debug_assert!(self.all_valid(rgb), "samples said valid");
            true
        }
    }
}

/// What a block of samples adds: per sample its lower cascade and the `[r, g, b, count]` units
/// for it and for the cascade above.
/// Stored lane by lane (`low[c][i]` is channel `c`, or the count for `c = 3`, of sample `i`) so
/// that the block loops write whole vectors.
pub(crate) struct Shares {
    pub(crate) lo: [u64; BLOCK],
    pub(crate) low: [[u64; BLOCK]; 4],
    pub(crate) high: [[u64; BLOCK]; 4],
}

impl Shares {
    pub(crate) fn new() -> Self {
        Shares {
            lo: [0; BLOCK],
            low: [[0; BLOCK]; 4],
            high: [[0; BLOCK]; 4],
        }
    }
}

/// Computes the shares of up to [`BLOCK`] valid samples (lanes past `rgb.len()` are zeros).
#[inline]
pub(crate) fn shares(kernel: Kernel, t: &Tables, rgb: &[[f32; 3]], out: &mut Shares) {
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2 => {
            assert!(kernel.available(), "AVX2 kernel on a CPU without AVX2");
            // SAFETY: the CPU has AVX2, checked just above (a cached feature test).
            unsafe { shares_avx2(t, rgb, out) }
        }
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx512 => {
            assert!(
                kernel.available(),
                "AVX-512 kernel on a CPU without AVX-512"
            );
            // SAFETY: the CPU has AVX2 and these AVX-512 sets, checked just above (cached).
            unsafe { shares_avx512(t, rgb, out) }
        }
        _ => shares_block::<false>(t, rgb, out),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn shares_avx2(t: &Tables, rgb: &[[f32; 3]], out: &mut Shares) {
    shares_block::<true>(t, rgb, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,avx512f,avx512dq,avx512vl,avx512bw")]
unsafe fn shares_avx512(t: &Tables, rgb: &[[f32; 3]], out: &mut Shares) {
    shares_block::<true>(t, rgb, out)
}

/// `(value * units + 0.5) as u64` for a non-negative product, as the one-sample path's
/// `to_fixed` computes it. With `EXACT` false in operations that have vector forms: exact while
/// the rounded value stays below `2^52`; `big` is set otherwise (only a component within a few
/// units of the largest one comes near it), and the caller redoes the block with `EXACT`.
/// `ROUND`: the CPU has an instruction that truncates a vector of `f64` (SSE4.1's `roundpd`,
/// which every AVX2 CPU has); without it the truncation takes four operations.
#[inline(always)]
fn fixed<const EXACT: bool, const ROUND: bool>(value: f64, units: f64, big: &mut u64) -> u64 {
    let y = value * units + 0.5;
    if EXACT {
        return y as u64;
    }
    *big |= u64::from(y >= TWO_52);
    let t = if ROUND {
        y.trunc()
    } else {
        // Nearest integer (ties to even), then down one if that went up: the truncation of y.
        let r = (y + TWO_52) - TWO_52;
        if r > y {
            r - 1.0
        } else {
            r
        }
    };
    // t is an integer in [0, 2^52): the bits of 2^52 + t are those of 2^52 plus t.
    (t + TWO_52).to_bits().wrapping_sub(TWO_52.to_bits())
}

/// The block arithmetic, one quantity at a time across the block's lanes.
#[inline(always)]
fn shares_block<const ROUND: bool>(t: &Tables, rgb: &[[f32; 3]], out: &mut Shares) {
    if shares_with::<false, ROUND>(t, rgb, out) {
        redo_exactly(t, rgb, out);
    }
}

/// The same shares with plain `as u64` conversions, for a block holding a component so bright
/// that its units reach `2^52`.
#[cold]
#[inline(never)]
fn redo_exactly(t: &Tables, rgb: &[[f32; 3]], out: &mut Shares) {
    shares_with::<true, false>(t, rgb, out);
}

/// Fills `out`; returns whether a conversion went out of the fast conversion's range.
#[inline(always)]
fn shares_with<const EXACT: bool, const ROUND: bool>(
    t: &Tables,
    rgb: &[[f32; 3]],
    out: &mut Shares,
) -> bool {
    debug_assert!(rgb.len() <= BLOCK);
    let mut s = [[0.0f64; BLOCK]; 3];
    for (i, v) in rgb.iter().enumerate() {
        for c in 0..3 {
            s[c][i] = v[c] as f64;
        }
    }
    let k = t.k;
    let (c0, top) = (t.scales[0], t.scales[k - 1]);
    let [w0, w1, w2] = t.luminance;
    // Luminance and its clamp to [c0, c_{K-1}], as `CascadeLayout::luminance` and `split`.
    let mut l = [0.0f64; BLOCK];
    let mut lc = [0.0f64; BLOCK];
    for i in 0..BLOCK {
        l[i] = w0 * s[0][i] + w1 * s[1][i] + w2 * s[2][i];
        let x = if l[i] < c0 { c0 } else { l[i] };
        lc[i] = if x > top { top } else { x };
    }
    // The lower cascade: how many of c_1 .. c_{K-2} are <= lc.
    let mut j = [0u64; BLOCK];
    for &c in &t.scales[1..k - 1] {
        for i in 0..BLOCK {
            j[i] += u64::from(c <= lc[i]);
        }
    }
    // c_{j+1}, 1 / c_j and the units of j and j + 1 of every lane, looked up by j (which is at
    // most K - 2; the mask only spares a bounds check, K_MAX being a power of two).
    const _: () = assert!(K_MAX.is_power_of_two());
    let mut up = [0.0f64; BLOCK];
    let mut inv = [0.0f64; BLOCK];
    let mut u_lo = [0.0f64; BLOCK];
    let mut u_hi = [0.0f64; BLOCK];
    for i in 0..BLOCK {
        let [a, b, c, d] = t.by_lo[j[i] as usize & (K_MAX - 1)];
        (up[i], inv[i], u_lo[i], u_hi[i]) = (a, b, c, d);
    }
    let bm1 = t.base - 1.0;
    let one = COUNT_ONE as f64;
    let mut big = 0u64;
    for i in 0..BLOCK {
        let w = (up[i] / lc[i] - 1.0) / bm1;
        let n = (t.base - lc[i] * inv[i]) / bm1;
        let w = if w < 0.0 { 0.0 } else { w };
        let w = if w > 1.0 { 1.0 } else { w };
        let n = if n < 0.0 { 0.0 } else { n };
        let n = if n > 1.0 { 1.0 } else { n };
        // The pinned end points of `split`.
        let (w, n) = if l[i] <= c0 { (1.0, 1.0) } else { (w, n) };
        let (w, n) = if l[i] >= top && l[i] > c0 {
            (0.0, 0.0)
        } else {
            (w, n)
        };
        let count = fixed::<EXACT, ROUND>(n, one, &mut big);
        let (ulo, uhi) = (u_lo[i] * w, u_hi[i] * (1.0 - w));
        for c in 0..3 {
            out.low[c][i] = fixed::<EXACT, ROUND>(s[c][i], ulo, &mut big);
            out.high[c][i] = fixed::<EXACT, ROUND>(s[c][i], uhi, &mut big);
        }
        out.low[3][i] = count;
        out.high[3][i] = COUNT_ONE - count;
        out.lo[i] = j[i];
    }
    big != 0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vector-friendly conversion against `as u64` wherever it claims to be exact: at and
    /// around every integer and half-integer of each binade, and up to just below `2^52`.
    #[test]
    fn fast_conversion_is_truncation_below_2_pow_52() {
        let mut values = vec![0.0, -0.0, 0.25, 0.5, 1.0, 1.5, 2.5, 3.5];
        for e in 0..52 {
            let p = (1u64 << e) as f64;
            for v in [p, p + 0.5, p - 0.5, p + 1.5, 1.5 * p, 1.5 * p + 0.5] {
                let v = v.max(0.0);
                values.extend([v, f64::from_bits(v.to_bits() + 1)]);
                if v > 0.0 {
                    values.push(f64::from_bits(v.to_bits() - 1));
                }
            }
        }
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        for _ in 0..100_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Uniform in the exponent: every binade below 2^52 equally often.
            let e = (x % 52) as i32;
            values.push((1.0 + (x >> 11) as f64 / (1u64 << 53) as f64) * 2f64.powi(e));
        }
        for &value in &values {
            for units in [1.0, 0.5, 3.0, 1.0 / 3.0] {
                let y = value * units + 0.5;
                if y >= TWO_52 {
                    continue;
                }
                let mut big = 0;
                assert_eq!(
                    fixed::<false, false>(value, units, &mut big),
                    y as u64,
                    "{value} * {units}"
                );
                assert_eq!(
                    fixed::<false, true>(value, units, &mut big),
                    y as u64,
                    "{value} * {units}, truncated by rounding"
                );
                assert_eq!(big, 0);
            }
        }
        for round in [false, true] {
            let mut big = 0;
            if round {
                fixed::<false, true>(TWO_52, 1.0, &mut big);
            } else {
                fixed::<false, false>(TWO_52, 1.0, &mut big);
            }
            assert_eq!(big, 1, "out of range is flagged");
        }
        let mut big = 0;
        assert_eq!(fixed::<true, false>(TWO_52 * 3.0, 1.0, &mut big), 3 << 52);
    }
}
