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
//! * it reads only the state: bit-identical for any arrival order or merge, and the same `f64`
//!   sums in the same order whatever the resolve's thread count (see [`spread`]);
//! * it is local, to the last bit: a pixel's result depends only on the state within
//!   `2 max_radius` of its give-back tile ([`Grid`]), so a part of the frame can be resolved
//!   again on its own (`resolve_region_into`; the derivation is in `resolve/region.rs`).

use std::mem::MaybeUninit;

use super::layout::{ParamError, COUNT_ONE};
use super::resolve::rows::{pixels_written, Consts, Layers, Part, Rows};
use super::resolve::{ResolveParams, Resolved};
use super::state::Kernel;

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
    pub(crate) support: f64,
    pub(crate) solid_share: f64,
    pub(crate) max_radius: usize,
    pub(crate) edge_share: Option<f64>,
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

/// A pixel where the first (paper) stage removed energy of one band, and what the spread stage
/// may give back, in pixel-value units (RGB; the band's support there is in the band's support
/// plane). The paper stage lists them per band in row-major order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Source {
    pub(crate) x: u32,
    pub(crate) y: u32,
    pub(crate) removed: [f32; 3],
    /// Whether the band holds `edge_share` of the pixel's samples (the edge rule's test, see
    /// the module docs).
    pub(crate) edge: bool,
}

/// A band's support at a pixel as the paper stage stores it for the spread stage: the support
/// (`f32`, never negative) with the sign bit set where the band is solid.
#[inline(always)]
pub(crate) fn support_word(own: f32, solid: bool) -> f32 {
    f32::from_bits(own.to_bits() | (solid as u32) << 31)
}

const SIGN: u32 = 1 << 31;

/// Largest window: 33x33 pixels.
const MAX_AREA: usize = (2 * SPREAD_RADII[SPREAD_RADII.len() - 1] + 1).pow(2);

/// Side of the give-back's tiles, in pixels (see [`Grid`]).
pub(crate) const GIVE_BACK_TILE: usize = 32;

/// The give-back's tiles: squares of [`GIVE_BACK_TILE`] pixels on a grid fixed to the frame's
/// top-left corner, held here relative to the pixels being resolved (a whole frame, or a crop
/// of it whose top-left pixel is `origin`).
///
/// The difference array's prefix sums restart at every tile's top-left pixel, each window's
/// event cut into the tiles it covers, so a pixel's given-back energy, to its last bit, is a
/// function of the events whose windows meet its tile, added in source order (row by row, band
/// by band within a row): it does not depend on anything far away in the frame. With prefix
/// sums over the whole frame (as first written) the rounding of the running sums carried every
/// earlier event's residue (`(a + v) - v != a`) to the right and down to the frame's far edge,
/// so no part of the frame could be resolved on its own to the same bits
/// (`resolve_region_into` needs that). The cost:
/// an event is added once more per tile boundary its window crosses (a window is at most 33
/// pixels wide, so at most two more per row), and the sums restart at a boundary.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Grid {
    /// `origin % GIVE_BACK_TILE`, per axis.
    ox: usize,
    oy: usize,
}

impl Grid {
    /// The grid of pixels whose top-left one is the frame's pixel `origin`.
    pub(crate) fn at(origin: (usize, usize)) -> Self {
        Self {
            ox: origin.0 % GIVE_BACK_TILE,
            oy: origin.1 % GIVE_BACK_TILE,
        }
    }

    /// The first tile column boundary after column `x`.
    #[inline(always)]
    fn next_x(self, x: usize) -> usize {
        x + GIVE_BACK_TILE - (x + self.ox) % GIVE_BACK_TILE
    }

    /// The first tile row boundary after row `y`.
    #[inline(always)]
    fn next_y(self, y: usize) -> usize {
        y + GIVE_BACK_TILE - (y + self.oy) % GIVE_BACK_TILE
    }

    #[inline(always)]
    fn column_starts_tile(self, x: usize) -> bool {
        (x + self.ox).is_multiple_of(GIVE_BACK_TILE)
    }

    #[inline(always)]
    fn row_starts_tile(self, y: usize) -> bool {
        (y + self.oy).is_multiple_of(GIVE_BACK_TILE)
    }
}

/// What a [`Resolved`] keeps for the next resolve into it, besides its layers.
#[derive(Default)]
pub(crate) struct Scratch {
    /// The parameters of the resolve these buffers hold (`None`: unknown, as in a clone), so
    /// that `resolve_region_into` resolves the whole frame rather than patch a resolve made
    /// with other parameters.
    pub(crate) resolved_with: Option<ResolveParams>,
    /// The buffers that `resolve_region_into` resolves crops into.
    pub(crate) crop: Option<Box<Resolved>>,
}

impl Scratch {
    /// Bytes held (capacity, not length).
    pub(crate) fn bytes(&self) -> u64 {
        use std::mem::size_of;
        self.crop.as_ref().map_or(0, |c| {
            ((c.reweighted.capacity() + c.mean.capacity() + c.removed.capacity())
                * size_of::<[f32; 3]>()
                + c.spp.capacity() * size_of::<u64>()) as u64
                + c.scratch.bytes()
        })
    }
}

impl Clone for Scratch {
    /// Working memory is not part of a result: a clone starts without.
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl PartialEq for Scratch {
    /// Working memory is not part of a result.
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for Scratch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scratch").finish_non_exhaustive()
    }
}

/// Rows the paper stage resolves at a time, before the spread stage takes the sources whose
/// windows' support those rows complete.
///
/// The two stages' working sets do not fit a core's L2 cache together (the paper stage's
/// cells and support rings; the spread stage's summed-area tables, difference array and
/// lists), so each switch from one stage to the other reloads the other's; longer blocks
/// switch less often. Measured with `bench speed`'s 1080p 8-cascade state, one thread, the
/// default resolve in ns a pixel (alternated runs, best of 30 each): 16 rows 73.7-76.4, 32
/// 71.5-73.6, 64 69.0-72.0, 128 74.3-78.5 (4 runs each); in an earlier build 16 rows
/// 76.7-83.6, 24 76.4-79.4, 32 74.3-80.2, 64 74.2-79.1 (6 runs each). The ring of support
/// words grows with the block: `BLOCK_ROWS + 2 max_radius` rows of `K` words a pixel (4.9 MB
/// a thread at 1920x1080 with 8 cascades).
pub(crate) const BLOCK_ROWS: usize = 64;

/// Resolves the pixels whose cells `rows` holds (a frame, or a crop of one whose give-back
/// tiles `grid` places; `out`'s buffers that many pixels) with [`Variant::Spread`]: the paper's
/// weights, then the removed energy given back. `threads` share the rows, in runs of whole tile
/// rows.
///
/// The numbers are those of the plain dense computation (the paper's resolve of every pixel;
/// per band a summed-area table of the frame's support, exact; one 2D difference array of the
/// give-back of every band, its cells added to in source order, row by row and band by band
/// within a row, each window cut into the tiles it covers; then its prefix sums within each
/// tile; `resolve/reference.rs` and `resolve/reference_spread.rs` keep it for the tests), bit
/// for bit. The two stages stream down the frame together, so that nothing of the frame's size
/// is kept between them: the paper stage resolves [`BLOCK_ROWS`] rows at a time, leaving its
/// support words in a ring of rows and the pixels where it removed energy (the sources) in
/// lists; the spread stage then takes the sources whose windows' support is complete, a row
/// at a time, finds each one's window in its band's summed-area table (a ring of the rows the
/// widest window spans, summed only around sources), adds the window to a ring of rows of the
/// difference array, and gives back each row as soon as no later source can reach it. A
/// thread's rows are whole tile rows, where the column sums restart; it resolves the paper's
/// weights up to `2 max_radius + 1` rows beyond them too (not kept), for the sources whose
/// windows reach its rows and their support.
#[allow(clippy::too_many_arguments)]
pub(crate) fn resolve_spread(
    kernel: Kernel,
    consts: &Consts,
    rows: &[&[u64]],
    params: &ResolveParams,
    threads: usize,
    grid: Grid,
    (w, h): (usize, usize),
    out: Layers<'_>,
) {
    // Each thread's rows: a run of whole tile rows.
    let mut starts = vec![0];
    while let Some(&y) = starts.last().filter(|&&y| y < h) {
        starts.push(grid.next_y(y).min(h));
    }
    let tiles = starts.len() - 1;
    let per = tiles.div_ceil(threads.clamp(1, tiles));
    let cuts: Vec<usize> = starts.iter().copied().step_by(per).chain([h]).collect();
    let frame = Frame {
        kernel,
        consts,
        rows,
        w,
        h,
        grid,
        params,
    };
    std::thread::scope(|scope| {
        let mut rest = out;
        let mut strips = Vec::new();
        for c in cuts.windows(2).filter(|c| c[0] < c[1]) {
            let (strip, after) = rest.split_at((c[1] - c[0]) * w);
            rest = after;
            strips.push((c[0]..c[1], strip));
        }
        let frame = &frame;
        let run = move |(rows, mut out): (std::ops::Range<usize>, Layers<'_>)| {
            // Support sums in `u64` unless a pixel's support could overflow a box of them (see
            // `SatRing`); then the strip is resolved again, summing in `u128`.
            if !stream::<u64>(frame, rows.clone(), &mut out) {
                let exact = stream::<u128>(frame, rows, &mut out);
                debug_assert!(exact, "u128 holds any box");
            }
        };
        let mut strips = strips.into_iter();
        let first = strips.next().expect("one row at least");
        for strip in strips {
            scope.spawn(move || run(strip));
        }
        run(first);
    });
}

/// What every thread of a resolve reads.
struct Frame<'s> {
    kernel: Kernel,
    consts: &'s Consts,
    rows: &'s [&'s [u64]],
    w: usize,
    h: usize,
    grid: Grid,
    params: &'s ResolveParams,
}

/// A summed-area table of one band's support and solid pixels, kept as a ring of the rows that
/// the widest window around the current source row spans: row `i` (the sums over rows
/// `start..i`, plus whatever row `start`'s slot held: a box's sums are differences of the
/// table's and take it off) in slot `i & mask` (the ring's length a power of two), column 0
/// always zero. So the table may start again at any row, with the same box sums.
///
/// The support is summed in integers, in units of `2^-FRAC_BITS` samples ([`support_units`]),
/// so that a box sum is exact whatever lies above and left of the box: an `f64` table (as
/// first written) rounds once its sums pass `2^(53 - FRAC_BITS) = 2^27` samples (a 1080p frame
/// at 64 spp), and a box's sum then depended on the rest of the frame (a window of exactly 64
/// samples could fail a support of 64). The exact box sum rounded once to `f64` is what the
/// `f64` table gave wherever that was exact.
///
/// Each entry packs both sums into one integer ([`Packed`]), `units << SOLID_BITS | solid`, and
/// the sums wrap: packing is linear, so a box's packed sum is the packing of its two sums
/// whenever they fit their fields (a box holds at most `MAX_AREA < 2^SOLID_BITS` pixels, so
/// its solid count always does), and one load per corner reads both (two arrays, as first
/// written, took two loads and often two cache lines per corner, and 12 bytes per entry).
/// `u64` entries serve frames whose pixels hold up to about 120 000 samples each
/// ([`Packed::holds`]), `u128` any frame; either gives the same box sums, so the choice (per
/// resolve) changes no bit.
struct SatRing<T> {
    mask: usize,
    stride: usize,
    /// Table rows computed so far (`start ..= built`).
    built: usize,
    cells: Vec<T>,
    /// Per support row summed (in slot `y & mask`), its largest support in units: a bound on
    /// the support of any box over it, so the window search skips radii that cannot reach.
    peaks: Vec<u64>,
}

/// Low bits of a [`SatRing`] entry that count solid pixels: a box holds at most `MAX_AREA`.
const SOLID_BITS: u32 = 11;
const _: () = assert!(MAX_AREA < 1 << SOLID_BITS);

/// [`Packed::entries`] for `u64`, as [`Packed::of`] wherever the support is below `2^26`
/// samples (far above what `u64` entries hold), in instructions that work on vectors: the
/// units, an integer below `2^52`, are the low bits of `units + 2^52` as an `f64` (no `f64` to
/// `i64` conversion, which vectors lack before AVX-512); the largest word by its bits (the
/// words are never negative once their sign is cleared, and compare as their bits do).
#[inline(always)]
fn u64_entries(words: &[f32], out: &mut [u64]) -> f32 {
    const TWO_52: f64 = (1u64 << 52) as f64;
    let mut peak = 0u32;
    for (&word, out) in words.iter().zip(out) {
        let own = word.to_bits() & !SIGN;
        peak = peak.max(own);
        let units = (f32::from_bits(own) as f64 * COUNT_ONE as f64 + TWO_52)
            .to_bits()
            .wrapping_sub(TWO_52.to_bits());
        *out = units << SOLID_BITS | (word.to_bits() >> 31) as u64;
    }
    f32::from_bits(peak)
}

/// [`u64_entries`] compiled for AVX2: 4 words a vector instruction.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn u64_entries_avx2(words: &[f32], out: &mut [u64]) -> f32 {
    u64_entries(words, out)
}

/// The integers [`SatRing`] packs a band's support and solid pixels in (wrapping).
trait Packed: Copy + Default + Ord {
    /// A support word's entry: its support in units, and 1 if the band is solid there.
    fn of(word: f32) -> Self;
    /// The entries of `words`, into `out`; returns the largest support word (sign cleared),
    /// which may be too large for `Self` ([`Packed::holds`]): the entries are then not used.
    fn entries(_kernel: Kernel, words: &[f32], out: &mut [Self]) -> f32 {
        let mut peak = 0u32;
        for (&word, out) in words.iter().zip(out) {
            peak = peak.max(word.to_bits() & !SIGN);
            *out = Self::of(word);
        }
        f32::from_bits(peak)
    }
    fn add(self, other: Self) -> Self;
    fn sub(self, other: Self) -> Self;
    /// The solid pixels of a box's entry.
    fn solid(self) -> u32;
    /// The entry of `units` of support and no solid pixel, if the units fit: a box's entry
    /// reaches it exactly where its support does (the solid count is below `2^SOLID_BITS`).
    fn fit(units: u128) -> Option<Self>;
    /// Whether every box of pixels whose support is at most `peak`'s sums exactly.
    fn holds(peak: f32) -> bool;
}

impl Packed for u64 {
    #[inline(always)]
    fn of(word: f32) -> Self {
        (support_units(word) as u64) << SOLID_BITS | (word.to_bits() >> 31) as u64
    }
    fn entries(kernel: Kernel, words: &[f32], out: &mut [Self]) -> f32 {
        match kernel {
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 | Kernel::Avx512 => {
                assert!(kernel.available(), "AVX2 kernel on a CPU without AVX2");
                // SAFETY: the CPU has AVX2, checked just above (a cached feature test).
                unsafe { u64_entries_avx2(words, out) }
            }
            _ => u64_entries(words, out),
        }
    }
    #[inline(always)]
    fn add(self, other: Self) -> Self {
        self.wrapping_add(other)
    }
    #[inline(always)]
    fn sub(self, other: Self) -> Self {
        self.wrapping_sub(other)
    }
    #[inline(always)]
    fn solid(self) -> u32 {
        (self & ((1 << SOLID_BITS) - 1)) as u32
    }
    fn fit(units: u128) -> Option<Self> {
        (units < 1 << (64 - SOLID_BITS)).then_some((units as u64) << SOLID_BITS)
    }
    fn holds(peak: f32) -> bool {
        support_units(peak) * (MAX_AREA as u128) < 1 << (64 - SOLID_BITS)
    }
}

impl Packed for u128 {
    #[inline(always)]
    fn of(word: f32) -> Self {
        support_units(word) << SOLID_BITS | (word.to_bits() >> 31) as u128
    }
    #[inline(always)]
    fn add(self, other: Self) -> Self {
        self.wrapping_add(other)
    }
    #[inline(always)]
    fn sub(self, other: Self) -> Self {
        self.wrapping_sub(other)
    }
    #[inline(always)]
    fn solid(self) -> u32 {
        (self & ((1 << SOLID_BITS) - 1)) as u32
    }
    fn fit(units: u128) -> Option<Self> {
        (units < 1 << (128 - SOLID_BITS)).then_some(units << SOLID_BITS)
    }
    fn holds(peak: f32) -> bool {
        // At most 2^58 units a pixel and 2^11 pixels a box: far below 2^117.
        support_units(peak) * (MAX_AREA as u128) < 1 << (128 - SOLID_BITS)
    }
}

/// A support word's support in units of `2^-FRAC_BITS` samples, exactly: a support is the sum
/// of three fixed-point counts (each a multiple of `2^-FRAC_BITS`), rounded to `f64` and then
/// to `f32`, and rounding a multiple of a power of two to a coarser power-of-two grid keeps it
/// a multiple; at most `2^58` units (a pixel's counts) plus `f32` rounding.
#[inline(always)]
pub(crate) fn support_units(word: f32) -> u128 {
    let own = f32::from_bits(word.to_bits() & !SIGN) as f64 * COUNT_ONE as f64;
    debug_assert!(
        own.fract() == 0.0,
        "a support is a multiple of 2^-FRAC_BITS"
    );
    // Below 2^63: `as i64` is one instruction.
    own as i64 as u128
}

/// The fewest units whose sum, rounded once to `f64` samples ([`units_to_samples`]), reaches
/// `support`: a window's support reaches `support` exactly where its sum in units reaches this,
/// since rounding to nearest never reverses an order and scaling by a power of two is exact
/// (`units_to_samples` never decreases), so the window search compares integers, without a
/// conversion per box. `None`: no sum does (not with a support of at most `1e6`).
fn least_units(support: f64) -> Option<u128> {
    let (mut lo, mut hi) = (0u128, u128::MAX);
    if units_to_samples(hi) < support {
        return None;
    }
    while lo < hi {
        let mid = lo + (hi - lo) / 2;
        if units_to_samples(mid) >= support {
            hi = mid;
        } else {
            lo = mid + 1;
        }
    }
    Some(lo)
}

/// An exact support sum in units, rounded once to `f64` samples.
#[inline(always)]
pub(crate) fn units_to_samples(units: u128) -> f64 {
    // `u64 as f64` is a few instructions, `u128 as f64` a library call: the same rounding.
    let n = if units >> 64 == 0 {
        units as u64 as f64
    } else {
        units as f64
    };
    n * (1.0 / COUNT_ONE as f64)
}

impl<T: Packed> SatRing<T> {
    /// A table of no rows yet.
    fn new(w: usize, max_radius: usize) -> Self {
        let (mask, stride) = ring_shape(w, max_radius);
        Self {
            mask,
            stride,
            built: 0,
            cells: vec![T::default(); (mask + 1) * stride],
            peaks: vec![0; mask + 1],
        }
    }

    /// Makes the table hold rows `from ..= to` (`from` never decreasing from one call to the
    /// next, nor `to`) from a ring of `ring_rows` rows of the band's support words (row `y` at
    /// `y % ring_rows`): it goes on from the rows it holds, or starts again at `from` where that
    /// computes fewer rows (a band whose sources are far apart is summed only around them).
    /// Returns `false` if a pixel's support is too large for box sums in `T`.
    fn reach(
        &mut self,
        kernel: Kernel,
        plane: &[f32],
        ring_rows: usize,
        w: usize,
        from: usize,
        to: usize,
    ) -> bool {
        if self.built < from {
            // Whatever slot `from` holds is the new start's row: a box's sums take it off.
            self.built = from;
        }
        while self.built < to {
            let y = self.built;
            let (above, here) = (y & self.mask, (y + 1) & self.mask);
            let cells = &plane[(y % ring_rows) * w..][..w];
            let (above, here) = two_rows(&mut self.cells, above, here, self.stride);
            // The row's entries first (a loop of vector instructions), then their running sum.
            let peak = T::entries(kernel, cells, &mut here[1..]);
            if !T::holds(peak) {
                return false;
            }
            let mut row = T::default();
            for (above, here) in above[1..].iter().zip(&mut here[1..]) {
                row = row.add(*here);
                *here = above.add(row);
            }
            // At most 2^58 units (a pixel's samples), so a `u64`.
            self.peaks[y & self.mask] = support_units(peak) as u64;
            self.built += 1;
        }
        true
    }

    /// The entry of the box over columns `x0..x1` between the table rows in ring slots
    /// `r0 = (y0 & mask) * stride` and `r1` (see [`RowWindows`]).
    #[inline(always)]
    fn boxed(&self, x0: usize, x1: usize, r0: usize, r1: usize) -> T {
        self.cells[r1 + x1]
            .sub(self.cells[r0 + x1])
            .sub(self.cells[r1 + x0])
            .add(self.cells[r0 + x0])
    }
}

/// The shape of a [`SatRing`] of a frame `w` pixels wide for windows up to `max_radius`: the
/// mask of its ring of rows (the `2 max_radius + 2` rows a row of sources reads, rounded up to a
/// power of two) and its row length.
fn ring_shape(w: usize, max_radius: usize) -> (usize, usize) {
    ((2 * max_radius + 2).next_power_of_two() - 1, w + 1)
}

impl<T> SatRing<T> {
    /// The first of `windows` (by index) whose support may reach `least` units (`None`:
    /// none may), judging by the rows' peaks: a box of `2 r + 1` columns holds at most that
    /// many times each row's peak. Every smaller window holds less than `least`, whatever
    /// its columns; summed rows must cover the windows' rows.
    fn first_reachable(&self, windows: &RowWindows, least: Option<u128>) -> usize {
        let Some(least) = least else {
            return windows.radii.len();
        };
        let tried = windows.radii.iter().zip(&windows.rows);
        for (i, (&r, &(y0, y1))) in tried.enumerate() {
            let rows: u128 = (y0..y1).map(|y| self.peaks[y & self.mask] as u128).sum();
            if (2 * r as u128 + 1) * rows >= least {
                return i;
            }
        }
        windows.radii.len()
    }
}

/// Rows `a` and `b` (different) of a table of rows `stride` long, the first shared.
fn two_rows<T>(table: &mut [T], a: usize, b: usize, stride: usize) -> (&[T], &mut [T]) {
    if a < b {
        let (lo, hi) = table.split_at_mut(b * stride);
        (&lo[a * stride..(a + 1) * stride], &mut hi[..stride])
    } else {
        let (lo, hi) = table.split_at_mut(a * stride);
        (&hi[..stride], &mut lo[b * stride..(b + 1) * stride])
    }
}

/// The paper stage's sources not yet taken: per column of its strips and band, a list in
/// row-major order (rows added a block at a time) and how many of its first ones were taken.
#[derive(Default)]
struct Sources {
    lists: Vec<Vec<Vec<Source>>>,
    taken: Vec<Vec<usize>>,
}

impl Sources {
    /// The sources of band `j` in row `y` of column `c`, left to right: every row before it must
    /// have been taken.
    #[inline(always)]
    fn take_row(&mut self, c: usize, j: usize, y: usize) -> &[Source] {
        let taken = &mut self.taken[c][j];
        let rest = &self.lists[c][j][*taken..];
        debug_assert!(
            rest.first().is_none_or(|s| s.y as usize >= y),
            "rows in order"
        );
        let run = rest.iter().take_while(|s| s.y as usize == y).count();
        *taken += run;
        &rest[..run]
    }

    /// Forgets the sources taken.
    fn drop_taken(&mut self) {
        for (lists, taken) in self.lists.iter_mut().zip(&mut self.taken) {
            for (list, taken) in lists.iter_mut().zip(taken) {
                list.drain(..*taken);
                *taken = 0;
            }
        }
    }
}

/// The windows tried around the sources of one row, as every band's [`SatRing`] reads them:
/// per radius (smallest first), its rows clamped to the frame and where its first and last
/// table rows sit in a ring. The same for every source of the row and every band, so they are
/// worked out once a row.
struct RowWindows {
    radii: Vec<usize>,
    /// Per radius: rows `y0..y1`.
    rows: Vec<(usize, usize)>,
    /// Per radius: ring offsets of table rows `y0` and `y1`.
    offsets: Vec<(usize, usize)>,
    h: usize,
    mask: usize,
    stride: usize,
}

impl RowWindows {
    /// The windows of a frame of `w` x `h` pixels, radii up to `max_radius`.
    fn new(w: usize, h: usize, max_radius: usize) -> Self {
        let (mask, stride) = ring_shape(w, max_radius);
        let radii: Vec<usize> = SPREAD_RADII
            .iter()
            .copied()
            .filter(|&r| r <= max_radius)
            .collect();
        Self {
            rows: vec![(0, 0); radii.len()],
            offsets: vec![(0, 0); radii.len()],
            radii,
            h,
            mask,
            stride,
        }
    }

    /// Makes these the windows of row `y`'s sources.
    fn at(&mut self, y: usize) {
        for ((&r, rows), offsets) in self.radii.iter().zip(&mut self.rows).zip(&mut self.offsets) {
            let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(self.h));
            *rows = (y0, y1);
            *offsets = (
                (y0 & self.mask) * self.stride,
                (y1 & self.mask) * self.stride,
            );
        }
    }
}

/// The smallest supported window around `source` in a band (see the module docs), or `None`
/// where its energy stays removed: columns `x0..x1` and rows `y0..y1`. `windows` are those of
/// the source's row, of which those before `first` cannot reach `least`, the entry a box's
/// support must reach (`None`: never).
///
/// The search looks only from `first` on: where no window there holds a solid pixel, none
/// before it does either (they are inside it) and none reached `least`, so the search over
/// every window would have gone on to `first` too. Where the first one looked at holds a solid
/// pixel, the answer turns on whether the smallest window does (the edge rule).
#[inline(always)]
fn window<T: Packed>(
    sat: &SatRing<T>,
    windows: &RowWindows,
    first: usize,
    w: usize,
    least: Option<T>,
    source: &Source,
) -> Option<(usize, usize, usize, usize)> {
    let x = source.x as usize;
    let columns = |i: usize| {
        let r = windows.radii[i];
        (x.saturating_sub(r), (x + r + 1).min(w))
    };
    let boxed = |i: usize, (x0, x1): (usize, usize)| {
        let (r0, r1) = windows.offsets[i];
        sat.boxed(x0, x1, r0, r1)
    };
    // Where the band is solid in a pixel of a window, the energy was cut at the edge of a light
    // (module docs): given back right next to it (the smallest window holds the solid pixel)
    // if the band holds `edge_share` of the pixel's samples (`Source::edge`), else left
    // removed. Whether the smallest window holds one is known without a look only where it
    // was looked at, or where a window around it was and held none.
    let in_place = || {
        let y = source.y as usize;
        (x, x + 1, y, y + 1)
    };
    let smallest_is_solid = || boxed(0, columns(0)).solid() > 0;
    for i in first..windows.radii.len() {
        let (x0, x1) = columns(i);
        let found = boxed(i, (x0, x1));
        if found.solid() > 0 {
            return (source.edge && (i == 0 || (i == first && smallest_is_solid()))).then(in_place);
        }
        if least.is_some_and(|least| found >= least) {
            let (y0, y1) = windows.rows[i];
            return Some((x0, x1, y0, y1));
        }
    }
    if first == windows.radii.len() {
        // No window was looked at.
        return (source.edge && smallest_is_solid()).then(in_place);
    }
    None
}

/// The columns of the difference array a window adds to, in each of its rows (see
/// [`GiveBack::add`]).
struct Columns {
    first: usize,
    inside: Option<usize>,
    after: Option<usize>,
}

// A window crosses at most one tile boundary each way.
const _: () = assert!(2 * SPREAD_RADII[SPREAD_RADII.len() - 1] < GIVE_BACK_TILE + 1);

/// The give-back of some rows of a frame (whole tile rows): its 2D difference array, kept as a
/// ring of the rows that the sources of one row add to, and the running column sums of the
/// rows given back.
struct GiveBack {
    kernel: Kernel,
    w: usize,
    h: usize,
    grid: Grid,
    rows: std::ops::Range<usize>,
    /// Rows of the difference array kept, at least the `2 m + 2` a source of row `y` adds to
    /// (`y - m ..= y + m + 1`), a power of two so that row `y`'s slot is `y & mask`.
    mask: usize,
    diff: Vec<[f64; 3]>,
    touched: Vec<bool>,
    col: Vec<[f64; 3]>,
    col_zero: bool,
    /// The tiles' columns.
    segments: Vec<(usize, usize)>,
    /// `1 / area`, as the plain computation divides.
    shares: Vec<f64>,
}

impl GiveBack {
    fn new(
        kernel: Kernel,
        w: usize,
        h: usize,
        grid: Grid,
        rows: std::ops::Range<usize>,
        m: usize,
    ) -> Self {
        let slots = (2 * m + 2).next_power_of_two();
        let mut segments = Vec::new();
        let mut s = 0;
        while s < w {
            let e = grid.next_x(s).min(w);
            segments.push((s, e));
            s = e;
        }
        Self {
            kernel,
            w,
            h,
            grid,
            rows,
            mask: slots - 1,
            diff: vec![[0.0; 3]; slots * w],
            touched: vec![false; slots],
            col: vec![[0.0; 3]; w],
            col_zero: true,
            segments,
            shares: (0..=MAX_AREA).map(|a| 1.0 / a as f64).collect(),
        }
    }

    /// Gives `removed` back uniformly over the window `x0..x1`, `y0..y1` (clamped to the frame):
    /// added at its top row and again at the tile row boundary it may cross, taken off below
    /// its bottom row unless a tile boundary restarts the sums there ([`Grid`]); in these rows
    /// only. (A window is at most [`GIVE_BACK_TILE`]` + 1` pixels wide and high, so it crosses
    /// at most one boundary each way.)
    #[inline(always)]
    fn add(&mut self, (x0, x1, y0, y1): (usize, usize, usize, usize), removed: [f32; 3]) {
        let share = self.shares[(x1 - x0) * (y1 - y0)];
        let v = removed.map(|c| c as f64 * share);
        let grid = self.grid;
        // The same columns in every row: the window's first and the tile boundary inside it
        // (added to), the one after its last (taken off from) unless a boundary restarts there.
        let inside = grid.next_x(x0);
        let columns = Columns {
            first: x0,
            inside: (inside < x1).then_some(inside),
            after: (x1 < self.w && !grid.column_starts_tile(x1)).then_some(x1),
        };
        self.add_row(y0, &columns, v);
        let restart = grid.next_y(y0);
        if restart < y1 {
            self.add_row(restart, &columns, v);
        }
        if y1 < self.h && !grid.row_starts_tile(y1) {
            self.add_row(y1, &columns, v.map(|c| -c));
        }
    }

    /// Adds `v` at `columns` of row `y` of the difference array (taken off at the column after
    /// the window).
    #[inline(always)]
    fn add_row(&mut self, y: usize, columns: &Columns, v: [f64; 3]) {
        if !self.rows.contains(&y) {
            return;
        }
        let slot = y & self.mask;
        self.touched[slot] = true;
        let diff = &mut self.diff[slot * self.w..][..self.w];
        let add = |cell: &mut [f64; 3]| {
            for c in 0..3 {
                cell[c] += v[c];
            }
        };
        add(&mut diff[columns.first]);
        if let Some(x) = columns.inside {
            add(&mut diff[x]);
        }
        if let Some(x) = columns.after {
            for c in 0..3 {
                diff[x][c] -= v[c];
            }
        }
    }

    /// Gives back row `y` (the one after the row given back before, and no source still to
    /// come adds to it) into its reweighted and removed pixels `f`, `r`: the difference array's
    /// prefix sums, along the row and down each column, both restarted at every tile boundary.
    /// Adding an exact 0 changes nothing, so a row that got nothing, below a tile boundary or
    /// below rows that got nothing, is skipped.
    ///
    /// In two passes: the running sums along the row, in place in its row of the difference
    /// array (one chain of additions a tile), then every value on its own ([`give_values`]: the
    /// column sums and the pixels, a loop of vector instructions). A pixel's channels are each
    /// given back whether or not the others get anything, as the plain computation does (adding
    /// `+0` to a value that is never `-0` changes no bit). One scalar loop over both, as first
    /// written, took 5 % of a default resolve's samples; measured with `bench speed`'s 1080p
    /// 8-cascade state, one thread, 4 alternated runs (best of 30 each): the default resolve
    /// 76.7-79.4 ns a pixel against 78.6-82.7.
    fn give(&mut self, y: usize, f: &mut [[f32; 3]], r: &mut [[f32; 3]]) {
        let slot = y & self.mask;
        if self.grid.row_starts_tile(y) && !self.col_zero {
            // A new row of tiles: its sums start from nothing.
            self.col.fill([0.0; 3]);
            self.col_zero = true;
        }
        if !self.touched[slot] && self.col_zero {
            return;
        }
        self.col_zero = false;
        let d = &mut self.diff[slot * self.w..][..self.w];
        if self.touched[slot] {
            // Along the row, in place: each tile's running sums (a row that got nothing keeps
            // its zeros).
            for &(s, e) in &self.segments {
                let mut run = [0.0f64; 3];
                for d in &mut d[s..e] {
                    for c in 0..3 {
                        run[c] += d[c];
                    }
                    *d = run;
                }
            }
            self.touched[slot] = false;
        }
        give_values(
            self.kernel,
            self.col.as_flattened_mut(),
            d.as_flattened_mut(),
            f.as_flattened_mut(),
            r.as_flattened_mut(),
        );
    }
}

/// The second pass of [`GiveBack::give`]: down the columns and into the pixels, every value on
/// its own (the channels of a row's pixels as one slice); `row`, the row's running sums, is
/// left zeroed for the rows after.
#[inline(always)]
fn give_values_any(col: &mut [f64], row: &mut [f64], f: &mut [f32], r: &mut [f32]) {
    let n = col.len();
    let (row, f, r) = (&mut row[..n], &mut f[..n], &mut r[..n]);
    for i in 0..n {
        col[i] += row[i];
        row[i] = 0.0;
        // Rounding of the running sums may leave a hair below 0 where nothing was given;
        // nothing is ever taken.
        let given = if col[i] > 0.0 { col[i] } else { 0.0 };
        f[i] = (f[i] as f64 + given) as f32;
        r[i] = (r[i] as f64 - given) as f32;
    }
}

/// [`give_values_any`] compiled for AVX2: 4 values a vector instruction.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn give_values_avx2(col: &mut [f64], row: &mut [f64], f: &mut [f32], r: &mut [f32]) {
    give_values_any(col, row, f, r)
}

/// [`give_values_any`] in `kernel`'s instructions.
fn give_values(kernel: Kernel, col: &mut [f64], row: &mut [f64], f: &mut [f32], r: &mut [f32]) {
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2 | Kernel::Avx512 => {
            assert!(kernel.available(), "AVX2 kernel on a CPU without AVX2");
            // SAFETY: the CPU has AVX2, checked just above (a cached feature test).
            unsafe { give_values_avx2(col, row, f, r) }
        }
        _ => give_values_any(col, row, f, r),
    }
}

/// Both stages for the rows `ys` of the frame (whole tile rows), whose layers `out` holds (see
/// [`resolve_spread`]). Returns `false`, with `out` half done, if a pixel's support is too
/// large for box sums in `T`.
fn stream<T: Packed>(frame: &Frame, ys: std::ops::Range<usize>, out: &mut Layers) -> bool {
    let Frame {
        kernel,
        consts,
        rows,
        w,
        h,
        grid,
        params,
    } = *frame;
    let SpreadParams {
        support,
        max_radius: m,
        ..
    } = params.spread();
    // `n >= support` for a box of `n` units is `n >= least_units`, `entry >= least` (`None`:
    // never).
    let least_units = least_units(support);
    let least = least_units.and_then(T::fit);
    let k = consts.cascades();
    let (ya, yb) = (ys.start, ys.end);
    // A window reaches at most `m` rows up and `m + 1` down (its difference array's row below
    // it): the sources of rows `s0..s1` are those that reach `ya..yb`, and their windows read
    // the support of rows `q0..q1`, which the paper stage resolves.
    let (s0, s1) = (ya.saturating_sub(m + 1), (yb + m).min(h));
    let (q0, q1) = (s0.saturating_sub(m), (s1 + m).min(h));
    // Support rows kept: those of a block and the `2 m` before it, which the sources not yet
    // taken may still read.
    let ring_rows = BLOCK_ROWS + 2 * m;
    let mut support = vec![0.0f32; k * ring_rows * w];
    let mut sources = Sources::default();
    // Paper rows beyond `ya..yb` go to these, and are not kept.
    let spare = BLOCK_ROWS.min(q1 - q0) * w;
    let mut spare_layers = [(); 3].map(|_| vec![MaybeUninit::<[f32; 3]>::uninit(); spare]);
    let mut spare_spp = vec![MaybeUninit::<u64>::uninit(); spare];
    let mut paper = Rows::new(kernel, consts, w);
    let mut sats: Vec<SatRing<T>> = (0..k).map(|_| SatRing::new(w, m)).collect();
    let mut windows = RowWindows::new(w, h, m);
    let mut give_back = GiveBack::new(kernel, w, h, grid, ys, m);
    let (mut next_source, mut next_give) = (q0, ya);
    let mut y = q0;
    while y < q1 {
        // 1. The paper stage over a block of rows, all of `ya..yb` or none.
        let mut end = (y + BLOCK_ROWS).min(q1);
        if y < ya {
            end = end.min(ya);
        } else if y < yb {
            end = end.min(yb);
        }
        {
            let (layers, y0) = if (ya..yb).contains(&y) {
                (out.reborrow(), ya)
            } else {
                let n = (end - y) * w;
                let [sf, sm, sr] = &mut spare_layers;
                let spare = Layers {
                    reweighted: &mut sf[..n],
                    mean: &mut sm[..n],
                    removed: &mut sr[..n],
                    spp: &mut spare_spp[..n],
                };
                (spare, y)
            };
            let mut part = Part {
                y0,
                out: layers,
                support: support.chunks_mut(ring_rows * w).collect(),
                support_rows: ring_rows,
                sources: std::mem::take(&mut sources.lists),
                column: 0,
            };
            paper.run(rows, &mut part, y..end);
            sources.lists = part.sources;
        }
        sources
            .taken
            .resize_with(sources.lists.len(), || vec![0; k]);
        y = end;
        // 2. In turn, as each becomes possible: the rows no source still to come can reach
        // are given back, then the next row of sources whose windows' support is complete is
        // taken, band by band (giving back first keeps the difference array's ring to the rows
        // one row of sources adds to).
        loop {
            while next_give < yb && (next_give + m < next_source || next_source >= s1) {
                let at = (next_give - ya) * w;
                debug_assert!(next_give < end, "a row given back before it is resolved");
                // SAFETY: the paper stage has resolved the row (`next_give < end`, as every
                // source that reaches it has been taken), which writes each of its pixels.
                let (f, r) = unsafe {
                    (
                        pixels_written(&mut out.reweighted[at..][..w]),
                        pixels_written(&mut out.removed[at..][..w]),
                    )
                };
                give_back.give(next_give, f, r);
                next_give += 1;
            }
            if next_source >= s1 || (next_source + m + 1).min(h) > end {
                break;
            }
            let ys = next_source;
            next_source += 1;
            windows.at(ys);
            for (j, sat) in sats.iter_mut().enumerate() {
                let plane = &support[j * ring_rows * w..][..ring_rows * w];
                // Once the table rows this row's windows read are summed: the first window
                // that may reach the support.
                let mut reachable = None;
                for c in 0..sources.lists.len() {
                    let row = sources.take_row(c, j, ys);
                    if row.is_empty() || ys < s0 {
                        continue;
                    }
                    let first = match reachable {
                        Some(first) => first,
                        None => {
                            let (from, to) = (ys.saturating_sub(m), (ys + m + 1).min(h));
                            if !sat.reach(kernel, plane, ring_rows, w, from, to) {
                                return false;
                            }
                            *reachable.insert(sat.first_reachable(&windows, least_units))
                        }
                    };
                    for source in row {
                        if let Some(window) = window(sat, &windows, first, w, least, source) {
                            give_back.add(window, source.removed);
                        }
                    }
                }
            }
        }
        sources.drop_taken();
    }
    debug_assert!(next_give == yb, "every row given back");
    true
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
    fn the_least_units_reaching_a_support_are_where_the_f64_comparison_turns() {
        use super::{least_units, units_to_samples};
        for support in [
            1.0, 1.5, 3.3, 8.0, 63.999_999, 64.0, 64.000_001, 1000.1, 1e6,
        ] {
            let least = least_units(support).expect("reachable");
            assert!(units_to_samples(least) >= support, "{support}");
            assert!(units_to_samples(least - 1) < support, "{support}");
        }
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
