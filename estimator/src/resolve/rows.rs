//! The resolve's row pass, [`LANES`] pixels at a time.
//!
//! Two steps per row, both over groups of [`LANES`] neighbouring pixels held lane by lane
//! (`x[lane]`), in straight-line loops the compiler turns into vector instructions:
//!
//! 1. *support* ([`Rows::load`]): each pixel's support counts `n_j` and sample count `N`, into
//!    one plane per cascade (so a group's values are contiguous), and their horizontal 3-pixel
//!    sums; three such rows are kept in a ring, so every row's counts are read and converted
//!    once however many rows pool them;
//! 2. *weights* ([`row`]): per group the 3x3 pooled counts (the vertical sum of three rows'
//!    horizontal sums), then the cascades from dim to bright with the weight of each, all
//!    [`LANES`] pixels at once.
//!
//! Every quantity is computed with the same `f64` operations, in the same order, as the
//! one-pixel-at-a-time resolve it replaces (kept as the test reference, `reference.rs`), so
//! the images are bit-identical to it: IEEE arithmetic gives the same bits in a vector lane as in
//! a scalar register, and Rust never fuses a multiply and an add. Three things differ and give
//! the same bits by construction:
//! * a cascade whose sums are zero in a pixel is weighed like the others (no branch per
//!   pixel): its value is `+0`, so it adds `+0` to every sum (the weights are finite), which
//!   changes no bit; and a cascade whose sums are zero in every pixel of a strip (most strips'
//!   brightest cascades: the fireflies' are rare) is not weighed at all, since it would only
//!   add `+0`, nor are its sums even read where its count is zero in every pixel of the strip
//!   (the support step sees the counts first; a state's cells hold no energy without count);
//! * `u64` words known to be below `2^52` are converted to `f64` by placing them in the mantissa
//!   of `2^52` and subtracting `2^52` (exact, like `as f64`, and two vector instructions instead
//!   of a long sequence without AVX-512). A pixel of `N <= 2^20` samples has every count below
//!   `2^46` and every sum of cascades `0 .. K-2` below `2^20 * LOW_SHARE_MAX < 2^52` (the
//!   state's bounds, checked on every cell that enters a state); groups with a larger `N` and
//!   the top cascade's 85-bit sums use `as f64`;
//! * `max` and `clamp` are written as comparisons; they differ from `f64::max` only in the sign
//!   of a zero result, and a weight of `-0` adds and removes exactly what `+0` does.
//!
//! On x86-64 CPUs with AVX2 the same code is compiled a second time with AVX2 enabled and chosen
//! at run time ([`Kernel`]), as the row splat does; the row pass and the support step a third
//! time with AVX-512 (F, DQ, VL, BW) as well, for [`Kernel::Avx512`]: the compiler's loops over
//! a strip then take 8 `f64`s an instruction, and the `if`s in them become masks. The same
//! operations on the same values, so the same bits. Measured with `bench speed`'s 1080p
//! 8-cascade state on one thread of an Intel Xeon (Emerald Rapids) VM, alternated runs, best of
//! 30 each: the default resolve 65.0-68.6 ns a pixel against 69.8-70.9 with AVX2 (5 runs),
//! `paper` 40.3-41.6 against 42.1-43.1. (When the resolve spent its time elsewhere, AVX-512 made
//! no difference. It still makes none to the spread stage, `resolve_spread.rs`: its two loops
//! compiled per kernel run their AVX2 form, and its streaming loop, compiled with AVX2 or
//! AVX-512, was no faster than in the target's baseline.)

// The group loops index several arrays by lane, as the vector code they become does.
#![allow(clippy::needless_range_loop)]

use std::mem::MaybeUninit;

use super::{support_samples, ResolveParams, Variant, KAPPA_TABLE, SHADER_E_MIN_FLOOR};
use crate::layout::{CascadeLayout, COUNT_ONE, FRAC_BITS, MAX_CASCADES};
use crate::resolve_spread::{support_word, Source};
use crate::state::{cell_len, Kernel, Lines, HI_BITS, HI_MASK};

/// Pixels per group of the support step.
pub(super) const LANES: usize = 8;

/// Pixels per strip (a multiple of [`LANES`]).
const STRIP: usize = 64;

/// Strips per column: a frame wider than `COLUMN_STRIPS * STRIP` pixels is resolved a column at
/// a time (each column top to bottom), so that a column's ring of support, the cells read
/// twice and the spread stage's rows stay in a core's L2 cache. Measured with `bench speed`'s
/// 8-cascade state, one thread, alternated runs: 8 strips against 16 took the default resolve
/// from 105-108 ms to 95-100 ms at 1920x1080 and from 483-531 ms to 425-449 ms at 3840x2160
/// (the `paper` stage alone the same); 4, 6, 10 and 12 strips were no better than 8, and 2
/// slower (the state is then read in short runs).
const COLUMN_STRIPS: usize = 8;

/// Groups ahead of the one being read whose cells the support step asks the CPU to load: the
/// support step is the first to read each cell of a resolve, and its loads waited on memory
/// (three quarters of its samples were on the instructions right after them) with the
/// hardware's prefetchers alone. Measured with `bench speed`'s 1080p 8-cascade state, one
/// thread: 1, 2, 4, 8 and 16 groups ahead took the `paper` resolve from 68 ms to 56-62 ms, 4
/// the best (8 KiB ahead).
///
/// A group's prefetches (its 33 lines) are spread over its cascades' loads, a few beside each
/// (`avx2::support_group`), as the record splat spreads its own (`FrameState::add_block`): all
/// in a row, they filled the core's queue of misses, and on the Zen 4 VM 21 % of the support
/// step's samples sat on the instruction after them. Spread, the `paper` resolve took 102-106
/// ms against 115-124 ms (one thread, 4 alternated runs, best of 9 each); 2 and 8 groups ahead
/// were no better than 4 there. Past the strip's column the prefetches fetch cells read only
/// with the next column; sending them to the start of the next row's column instead was
/// slower in 3 runs of 3 (101-104 ms against 96-102 ms), so they stay where they are.
const PREFETCH_GROUPS: usize = 4;

/// Rows ahead of the one being resolved whose cells the row pass asks the CPU to bring into
/// its L2 cache, a few lines beside each group it reads: row `y + 2`, which the support step
/// reads next (with row `y + 1`). The support step is the first to read each cell, and it has
/// little work to hide the wait for memory behind (with its own prefetches, a quarter of a
/// default resolve's samples were on it, most right after its loads of the count words); the
/// row pass has much, and reads cells already in the cache. Fetched during the row pass, the
/// cells are in L2 when the support step reads them, and the support step's share of a default
/// resolve's profile fell from a quarter to a tenth. Measured with `bench speed`'s 1080p
/// 8-cascade state, one thread, the best of 20 resolves in each of 5 alternated runs on the
/// 2-core Zen 4 VM: the default resolve 0.158-0.190 s against 0.181-0.238 s, `paper`
/// 0.092-0.103 s against 0.108-0.118 s. Each alternative, in runs beside this one (the default
/// resolve, this one's times first): into L1 (`T0`), 0.168-0.187 s against 0.176-0.205 s; every
/// other line, 0.150-0.170 s against 0.175-0.184 s; all of a strip's lines for a cascade in a
/// row after its sums, which stalled on a full queue of misses, 0.152-0.173 s against
/// 0.162-0.191 s; the next column's first rows as well at the end of a run, 0.162-0.192 s
/// against 0.161-0.188 s (no gain, so not kept).
const AHEAD_ROWS: usize = 2;

/// Length of a support plane: a strip and the pixel on each side.
const OWN: usize = STRIP + 2;

const K_MAX: usize = MAX_CASCADES as usize;

/// `2^52`: a `u64` below it, placed in the mantissa of `2^52`, is `2^52` plus that integer.
const TWO_52: f64 = 4_503_599_627_370_496.0;

/// `2^64`, the weight of the top cascade's high word.
const TWO_64: f64 = 18_446_744_073_709_551_616.0;

/// Largest `N` for which every word of cascades `0 .. K-2` is below `2^52`:
/// `2^20 * LOW_SHARE_MAX = 2^20 * (2^31 + 2^30) < 2^52`.
const SMALL_N: f64 = (1u64 << 20) as f64;

/// Largest sum of a pixel's counts with every count below `2^52`.
const SMALL_COUNTS: u64 = (1 << 52) - 1;

/// `x as f64` for `x < 2^52`, in two operations that have vector forms.
#[inline(always)]
fn small_to_f64(x: u64) -> f64 {
    f64::from_bits(x | TWO_52.to_bits()) - TWO_52
}

/// The weight formulas, as const generic arguments of the row loop.
const PAPER: u8 = 0;
const SHADER: u8 = 1;
const OFF: u8 = 2;

/// What the row loop needs of the layout and the parameters, padded to [`MAX_CASCADES`].
pub(crate) struct Consts {
    k: usize,
    luminance: [f64; 3],
    unit_value: [f64; K_MAX],
    inv_scale: [f64; K_MAX],
    params: ResolveParams,
    base: f64,
    /// `kappa(N)` ([`ResolveParams::kappa_table`]) and its reciprocal for `N < KAPPA_TABLE` (a
    /// scalar division per pixel with its branchy lookup was 11 % of the `paper` row loop's
    /// samples).
    kap_table: Vec<[f64; 2]>,
}

impl Consts {
    /// The layout's cascades.
    pub(crate) fn cascades(&self) -> usize {
        self.k
    }

    pub(crate) fn new(layout: &CascadeLayout, params: &ResolveParams) -> Self {
        let k = layout.cascades();
        let mut c = Consts {
            k,
            luminance: layout.luminance_weights(),
            unit_value: [0.0; K_MAX],
            inv_scale: [0.0; K_MAX],
            params: *params,
            base: layout.base(),
            kap_table: Vec::new(),
        };
        if params.kappa_exponent != 0.0 {
            c.kap_table = params
                .kappa_table()
                .into_iter()
                .map(|kap| [kap, 1.0 / kap])
                .collect();
        }
        for j in 0..k {
            c.unit_value[j] = layout.unit_value(j);
            c.inv_scale[j] = layout.inv_scale(j);
        }
        c
    }
}

/// Some rows of a resolve's layers, as memory the resolve writes before it reads any of it:
/// every pixel is written by the row pass, and the spread stage reads a row back only after
/// that. Their earlier contents are never read, so new layers need not be zeroed first.
pub(crate) struct Layers<'o> {
    pub(crate) reweighted: &'o mut [MaybeUninit<[f32; 3]>],
    pub(crate) mean: &'o mut [MaybeUninit<[f32; 3]>],
    pub(crate) removed: &'o mut [MaybeUninit<[f32; 3]>],
    pub(crate) spp: &'o mut [MaybeUninit<u64>],
}

impl<'o> Layers<'o> {
    /// Room for `pixels` new pixels in each of `out`'s layers: in the memory they have where it
    /// is enough, else in new memory (not zeroed). Their lengths are 0 until
    /// [`Layers::written`].
    pub(crate) fn room(out: &'o mut super::Resolved, pixels: usize) -> Self {
        fn room<T>(layer: &mut Vec<T>, pixels: usize) -> &mut [MaybeUninit<T>] {
            layer.clear();
            if layer.capacity() < pixels {
                // Not `reserve`, which would copy the old contents over.
                *layer = Vec::with_capacity(pixels);
            }
            &mut layer.spare_capacity_mut()[..pixels]
        }
        Layers {
            reweighted: room(&mut out.reweighted, pixels),
            mean: room(&mut out.mean, pixels),
            removed: room(&mut out.removed, pixels),
            spp: room(&mut out.spp, pixels),
        }
    }

    /// Gives `out`'s layers the length `pixels` once a resolve has written their room.
    ///
    /// # Safety
    /// Every pixel of the room of [`Layers::room`]`(out, pixels)` must have been written.
    pub(crate) unsafe fn written(out: &mut super::Resolved, pixels: usize) {
        // SAFETY: the room holds `pixels` values (capacity), all written (the caller).
        unsafe {
            out.reweighted.set_len(pixels);
            out.mean.set_len(pixels);
            out.removed.set_len(pixels);
            out.spp.set_len(pixels);
        }
    }

    /// The first `at` pixels and the rest.
    pub(crate) fn split_at(self, at: usize) -> (Self, Self) {
        let (reweighted, r) = self.reweighted.split_at_mut(at);
        let (mean, m) = self.mean.split_at_mut(at);
        let (removed, d) = self.removed.split_at_mut(at);
        let (spp, s) = self.spp.split_at_mut(at);
        let first = Layers {
            reweighted,
            mean,
            removed,
            spp,
        };
        let rest = Layers {
            reweighted: r,
            mean: m,
            removed: d,
            spp: s,
        };
        (first, rest)
    }

    /// The same rows, borrowed.
    pub(crate) fn reborrow(&mut self) -> Layers<'_> {
        Layers {
            reweighted: self.reweighted,
            mean: self.mean,
            removed: self.removed,
            spp: self.spp,
        }
    }
}

/// Pixels of a layer that the row pass has written, as values.
///
/// # Safety
/// Every pixel of `pixels` must have been written.
pub(crate) unsafe fn pixels_written<T>(pixels: &mut [MaybeUninit<T>]) -> &mut [T] {
    // SAFETY: `MaybeUninit<T>` has `T`'s layout, and the caller says every value is written.
    unsafe { &mut *(pixels as *mut [MaybeUninit<T>] as *mut [T]) }
}

/// The rows `y0..` of the output that one [`Rows`] fills.
pub(crate) struct Part<'o> {
    pub(crate) y0: usize,
    pub(crate) out: Layers<'o>,
    /// For the spread stage, per band: a ring of `support_rows` rows of support words (row `y`
    /// at `y % support_rows`), or empty.
    pub(crate) support: Vec<&'o mut [f32]>,
    pub(crate) support_rows: usize,
    /// For the spread stage, per column of strips and band: the pixels where energy was
    /// removed (row-major within the column; [`Rows::run`] adds each row's).
    pub(crate) sources: Vec<Vec<Vec<Source>>>,
    /// The column being resolved.
    pub(crate) column: usize,
}

/// One row's support, strip by strip ([`STRIP`] pixels; the last one padded): for each strip,
/// planes `0 .. K` of `n_j` and plane `K` of `N` over the strip and the pixel on each side of
/// it ([`OWN`] long: pixel `x0 - 1 + i` at `i`, the frame's edge pixels standing in for their
/// missing neighbours), and the same planes summed over 3 pixels horizontally ([`STRIP`] long:
/// pixel `x0 + i` at `i`).
struct Support {
    own: Vec<f64>,
    pooled: Vec<f64>,
    /// Per strip, the cascades with a count in any of its pixels (bit `j`): the others hold no
    /// energy there either (the state's cells never do without count), and the row pass does
    /// not read them.
    occupied: Vec<u32>,
}

const _: () = assert!(K_MAX <= 32, "a strip's cascades are the bits of a u32");

/// Working memory of one thread of a resolve: a ring of three rows' support, indexed by row,
/// and room for the cells of a strip at the frame's right edge.
///
/// Each column of strips has its own rows in the ring: `held[c][y % 3] == y` where slot
/// `y % 3` holds row `y`'s support over column `c`. The spread stage resolves a block of rows
/// at a time, every column in turn, so the next block of a column starts with the rows its
/// last block left (with one ring for all columns, each column loaded them again: in the
/// default resolve, 2 of every 18 rows the support step converted).
pub(crate) struct Rows<'a> {
    kernel: Kernel,
    c: &'a Consts,
    width: usize,
    ring: [Support; 3],
    held: Vec<[usize; 3]>,
    tail: Vec<u64>,
}

impl<'a> Rows<'a> {
    pub(crate) fn new(kernel: Kernel, c: &'a Consts, width: usize) -> Self {
        let strips = width.div_ceil(STRIP);
        let row = || Support {
            own: vec![0.0; strips * (c.k + 1) * OWN],
            pooled: vec![0.0; strips * (c.k + 1) * STRIP],
            occupied: vec![0; strips],
        };
        Self {
            kernel,
            c,
            width,
            ring: [row(), row(), row()],
            held: vec![[usize::MAX; 3]; strips.div_ceil(COLUMN_STRIPS)],
            tail: vec![0; STRIP * cell_len(c.k)],
        }
    }

    /// Makes ring slot `y % 3` hold row `y`'s support over the column of `strips`.
    fn load(&mut self, y: usize, strips: std::ops::Range<usize>, rows: &[&[u64]]) {
        let held = &mut self.held[strips.start / COLUMN_STRIPS][y % 3];
        if *held == y {
            return;
        }
        *held = y;
        for s in strips {
            self.load_strip(y, s, rows);
        }
    }

    /// Fills strip `s` of ring slot `y % 3` with row `y`'s support.
    fn load_strip(&mut self, y: usize, s: usize, rows: &[&[u64]]) {
        let kernel = self.kernel;
        match kernel {
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 => {
                assert!(kernel.available(), "AVX2 kernel on a CPU without AVX2");
                // SAFETY: the CPU has AVX2, checked just above (a cached feature test).
                unsafe { support_avx2(self, y, s, rows[y]) }
            }
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx512 => {
                assert!(kernel.available(), "AVX-512 kernel on a CPU without it");
                // SAFETY: the CPU has what the kernel needs, checked just above (cached).
                unsafe { support_avx512(self, y, s, rows[y]) }
            }
            _ => self.support_strip::<false>(y, s, rows[y]),
        }
    }

    /// [`Rows::load_strip`] from row `y`'s `cells` ([`support`]).
    #[inline(always)]
    fn support_strip<const AVX2: bool>(&mut self, y: usize, s: usize, cells: &[u64]) {
        let (k, w) = (self.c.k, self.width);
        let slot = &mut self.ring[y % 3];
        let own = &mut slot.own[s * (k + 1) * OWN..][..(k + 1) * OWN];
        let pooled = &mut slot.pooled[s * (k + 1) * STRIP..][..(k + 1) * STRIP];
        let (x0, tail) = (s * STRIP, &mut self.tail);
        slot.occupied[s] = support::<AVX2>(k, cells, w, x0, own, pooled, tail);
    }

    /// Resolves the rows `ys` of the frame `rows` (every row of the frame, top to bottom) into
    /// `part` (which holds them), a column of [`COLUMN_STRIPS`] strips at a time; with the spread
    /// stage's support rows it also adds the rows' sources to `part`'s lists.
    pub(crate) fn run(&mut self, rows: &[&[u64]], part: &mut Part<'_>, ys: std::ops::Range<usize>) {
        let (k, w, h) = (self.c.k, self.width, rows.len());
        let len = cell_len(k);
        let strips = w.div_ceil(STRIP);
        let bands = part.support.len();
        part.sources
            .resize_with(strips.div_ceil(COLUMN_STRIPS), Vec::new);
        for column in &mut part.sources {
            column.resize_with(bands, Vec::new);
        }
        for c0 in (0..strips).step_by(COLUMN_STRIPS) {
            part.column = c0 / COLUMN_STRIPS;
            let column = c0..(c0 + COLUMN_STRIPS).min(strips);
            for y in ys.clone() {
                let (up, down) = (y.saturating_sub(1), (y + 1).min(h - 1));
                self.load(up, column.clone(), rows);
                self.load(y, column.clone(), rows);
                self.load(down, column.clone(), rows);
                for s in column.clone() {
                    let x0 = s * STRIP;
                    let ring = &self.ring;
                    let pooled =
                        |r: usize| &ring[r % 3].pooled[s * (k + 1) * STRIP..][..(k + 1) * STRIP];
                    let row_at = RowAt {
                        cells: group_cells(rows[y], x0, w, len, STRIP, &mut self.tail),
                        own: &ring[y % 3].own[s * (k + 1) * OWN..][..(k + 1) * OWN],
                        occupied: ring[y % 3].occupied[s],
                        pooled: [pooled(up), pooled(y), pooled(down)],
                        count: STRIP.min(w - x0),
                        first: (y - part.y0) * w + x0,
                        support: if bands > 0 {
                            (y % part.support_rows) * w + x0
                        } else {
                            0
                        },
                        x0,
                        y,
                    };
                    // Up to the row below the run, which its last row's support reads. A row
                    // further down is read with this column's next run (the spread stage's),
                    // after the other columns' runs have pushed it out of L2 again.
                    let next = y + AHEAD_ROWS;
                    let mut ahead = match rows.get(next) {
                        Some(row) if next <= ys.end => Lines::of(row, x0 * len, row_at.count * len),
                        _ => Lines::of(&[], 0, 0),
                    };
                    let kernel = self.kernel;
                    match kernel {
                        #[cfg(target_arch = "x86_64")]
                        Kernel::Avx2 => {
                            assert!(kernel.available(), "AVX2 kernel on a CPU without AVX2");
                            // SAFETY: the CPU has AVX2, checked just above (a cached feature test).
                            unsafe { row_avx2(self.c, &row_at, part, &mut ahead) }
                        }
                        #[cfg(target_arch = "x86_64")]
                        Kernel::Avx512 => {
                            assert!(kernel.available(), "AVX-512 kernel on a CPU without it");
                            // SAFETY: the CPU has what the kernel needs, checked just above.
                            unsafe { row_avx512(self.c, &row_at, part, &mut ahead) }
                        }
                        _ => row_any::<false>(self.c, &row_at, part, &mut ahead),
                    }
                }
            }
        }
    }
}

/// One pixel's `n_j` and `N` (at `K`), `stride` apart in `out`: the same arithmetic as the
/// group loop in [`support`], for the pixels on each side of a strip.
fn pixel_support(k: usize, cell: &[u64], out: &mut [f64], stride: usize) {
    let one = 1.0 / COUNT_ONE as f64;
    let mut counts = [0.0f64; K_MAX + 2];
    let mut total = 0u64;
    for j in 0..k {
        let c = cell[4 * j + 3];
        total += c;
        counts[j + 1] = c as f64 * one;
    }
    for j in 0..k {
        out[j * stride] = counts[j] + counts[j + 1] + counts[j + 2];
    }
    out[k * stride] = (total >> FRAC_BITS) as f64;
}

/// One row's support counts in the strip at `x0` (see [`Support`]), and the cascades with a
/// count in any of its pixels (bit `j`); `tail` holds a copy of the cells of a group at the
/// frame's right edge (room for [`LANES`] cells; a buffer kept from strip to strip: zeroing one
/// per strip was 3 % of a resolve's instructions). `AVX2`: only in the AVX2 and AVX-512 kernels,
/// where a group's counts go to vectors without a trip through memory.
#[inline(always)]
fn support<const AVX2: bool>(
    k: usize,
    cells: &[u64],
    w: usize,
    x0: usize,
    own: &mut [f64],
    pooled: &mut [f64],
    tail: &mut [u64],
) -> u32 {
    let len = cell_len(k);
    let one = 1.0 / COUNT_ONE as f64;
    let mut occupied = 0;
    for g in (0..STRIP).step_by(LANES) {
        let at = 1 + g;
        if x0 + g >= w {
            // Past the frame's right edge: never shown, but kept finite.
            for plane in 0..=k {
                own[plane * OWN + at..][..LANES].fill(0.0);
            }
            continue;
        }
        let group = group_cells(cells, x0 + g, w, len, LANES, tail);
        let mut ahead = Lines::of(cells, (x0 + g + PREFETCH_GROUPS * LANES) * len, LANES * len);
        if AVX2 {
            #[cfg(target_arch = "x86_64")]
            {
                // SAFETY: only compiled with AVX2 enabled (`compiled_with!`).
                occupied |= unsafe { avx2::support_group(group, len, k, own, at, &mut ahead) };
                continue;
            }
        }
        ahead.prefetch(usize::MAX);
        // Word by word: faster here than 256-bit loads of whole cascades (measured), since the
        // counts are a quarter of the words these first reads of the cells bring in.
        let mut count = [[0u64; LANES]; K_MAX];
        for l in 0..LANES {
            let cell = &group[l * len..(l + 1) * len];
            for j in 0..k {
                count[j][l] = cell[4 * j + 3];
            }
        }
        let mut total = [0u64; LANES];
        for j in 0..k {
            for l in 0..LANES {
                // At most 2^58 per pixel (see the state module): exact.
                total[l] += count[j][l];
            }
            occupied |= (count[j].iter().any(|&c| c != 0) as u32) << j;
        }
        let small = total.iter().all(|&t| t <= SMALL_COUNTS);
        // counts[0] and counts[k + 1] stay 0: the missing neighbours at the ends.
        let mut counts = [[0.0f64; LANES]; K_MAX + 2];
        for j in 0..k {
            for l in 0..LANES {
                let c = if small {
                    small_to_f64(count[j][l])
                } else {
                    count[j][l] as f64
                };
                counts[j + 1][l] = c * one;
            }
        }
        for j in 0..k {
            let plane = &mut own[j * OWN + at..][..LANES];
            for l in 0..LANES {
                plane[l] = counts[j][l] + counts[j + 1][l] + counts[j + 2][l];
            }
        }
        let plane = &mut own[k * OWN + at..][..LANES];
        for l in 0..LANES {
            plane[l] = small_to_f64(total[l] >> FRAC_BITS);
        }
    }
    // The pixels on each side: the neighbours' own, or at the frame's edges the edge pixel
    // itself (the 3x3 neighbourhood is clamped to the frame).
    if x0 == 0 {
        for plane in 0..=k {
            own[plane * OWN] = own[plane * OWN + 1];
        }
    } else {
        pixel_support(k, &cells[(x0 - 1) * len..x0 * len], own, OWN);
    }
    let right = x0 + STRIP;
    if right < w {
        pixel_support(
            k,
            &cells[right * len..(right + 1) * len],
            &mut own[STRIP + 1..],
            OWN,
        );
    } else {
        let edge = w - x0;
        for plane in 0..=k {
            own[plane * OWN + edge + 1] = own[plane * OWN + edge];
        }
    }
    for (own, pooled) in own.chunks_exact(OWN).zip(pooled.chunks_exact_mut(STRIP)) {
        // As arrays, so the loop is vector instructions without bounds checks (it was scalar:
        // 3 % of a resolve's instructions).
        let own: &[f64; OWN] = own.try_into().expect("a plane of OWN");
        let pooled: &mut [f64; STRIP] = pooled.try_into().expect("a plane of STRIP");
        for i in 0..STRIP {
            pooled[i] = own[i] + own[i + 1] + own[i + 2];
        }
    }
    occupied
}

/// The cells of pixels `x0 .. x0 + count` of a row of `w` cells of `len` words: the row's own
/// words, or at the end of a row, a copy padded with empty cells.
#[inline(always)]
fn group_cells<'c>(
    cells: &'c [u64],
    x0: usize,
    w: usize,
    len: usize,
    count: usize,
    tail: &'c mut [u64],
) -> &'c [u64] {
    if x0 + count <= w {
        &cells[x0 * len..(x0 + count) * len]
    } else {
        let n = (w - x0) * len;
        tail[..n].copy_from_slice(&cells[x0 * len..w * len]);
        tail[n..count * len].fill(0);
        &tail[..count * len]
    }
}

/// One strip of one row to resolve: its cells, its support, the horizontally pooled planes of
/// the rows above, at and below it, its width and where its first pixel goes in the part.
struct RowAt<'r> {
    cells: &'r [u64],
    own: &'r [f64],
    /// The cascades with a count in any pixel of the strip (bit `j`).
    occupied: u32,
    pooled: [&'r [f64]; 3],
    count: usize,
    first: usize,
    /// Where its first pixel's support word goes in a band's ring of support rows.
    support: usize,
    /// The frame's column of the first pixel, and its row.
    x0: usize,
    y: usize,
}

/// [`Rows::support_strip`] and [`row_any`] compiled with `$features` enabled (the code as it is,
/// the compiler's choice of instructions): the kernels of the module docs.
macro_rules! compiled_with {
    ($features:literal, $support:ident, $row:ident) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $features)]
        unsafe fn $support(rows: &mut Rows<'_>, y: usize, s: usize, cells: &[u64]) {
            rows.support_strip::<true>(y, s, cells)
        }

        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $features)]
        unsafe fn $row(c: &Consts, at: &RowAt<'_>, part: &mut Part<'_>, ahead: &mut Lines) {
            row_any::<true>(c, at, part, ahead)
        }
    };
}

compiled_with!("avx2", support_avx2, row_avx2);
compiled_with!(
    "avx2,avx512f,avx512dq,avx512vl,avx512bw",
    support_avx512,
    row_avx512
);

#[inline(always)]
fn row_any<const AVX2: bool>(c: &Consts, at: &RowAt<'_>, part: &mut Part<'_>, ahead: &mut Lines) {
    let bands = !part.support.is_empty();
    match (c.params.variant, bands) {
        (Variant::Off, false) => row::<OFF, false, AVX2>(c, at, part, ahead),
        (Variant::Off, true) => row::<OFF, true, AVX2>(c, at, part, ahead),
        (Variant::Shader, false) => row::<SHADER, false, AVX2>(c, at, part, ahead),
        (Variant::Shader, true) => row::<SHADER, true, AVX2>(c, at, part, ahead),
        (Variant::Paper | Variant::Spread, false) => row::<PAPER, false, AVX2>(c, at, part, ahead),
        (Variant::Paper | Variant::Spread, true) => row::<PAPER, true, AVX2>(c, at, part, ahead),
    }
}

/// Resolves one strip of a row, cascade by cascade (so that the pixels of the strip are
/// independent steps the CPU overlaps, while each pixel's own steps from dim to bright depend on
/// each other): weights `V` (with [`Variant::Spread`] being the paper's
/// weights), and with `BANDS` each band's removed energy and support for the spread stage.
#[inline(always)]
fn row<const V: u8, const BANDS: bool, const AVX2: bool>(
    c: &Consts,
    at: &RowAt<'_>,
    part: &mut Part<'_>,
    ahead: &mut Lines,
) {
    let k = c.k;
    // The lines of `ahead` asked for beside each group of 4 pixels' sums of the cascades read.
    let read = at.occupied.count_ones() as usize;
    let per = ahead.left().div_ceil(read.max(1) * STRIP / 4);
    let len = cell_len(k);
    let [l0, l1, l2] = c.luminance;
    let kmin = c.params.kappa_min;
    let shader_energy = 0.4 + 0.6 * c.base;
    let cells = at.cells;
    {
        let own = |j: usize| -> &[f64; STRIP] {
            at.own[j * OWN + 1..][..STRIP].try_into().expect("a strip")
        };
        let pool = |j: usize| -> [&[f64; STRIP]; 3] {
            at.pooled
                .map(|p| p[j * STRIP..(j + 1) * STRIP].try_into().expect("a strip"))
        };
        let n = own(k);
        let mut inv_kappa = [1.0 / c.params.kappa; STRIP];
        // kappa(N), for the weights and the spread stage's solid test.
        let mut kap = [c.params.kappa; STRIP];
        if c.params.kappa_exponent != 0.0 {
            let table: &[[f64; 2]; KAPPA_TABLE] = c.kap_table[..].try_into().expect("a table");
            if n.iter().all(|&n| n < KAPPA_TABLE as f64) {
                for x in 0..STRIP {
                    // `N` is a whole number below `2^52`: in the mantissa of `N + 2^52`. The mask
                    // keeps the index in the table without a branch (`N < KAPPA_TABLE`, above).
                    let at = (n[x] + TWO_52).to_bits() as usize & (KAPPA_TABLE - 1);
                    [kap[x], inv_kappa[x]] = table[at];
                }
            } else {
                for x in 0..STRIP {
                    [kap[x], inv_kappa[x]] = if n[x] < KAPPA_TABLE as f64 {
                        table[n[x] as usize]
                    } else {
                        let kap = c.params.kappa_at(n[x]);
                        [kap, 1.0 / kap]
                    };
                }
            }
        }
        // Support relative to each pixel's own sample count (see the module docs of resolve);
        // with the paper's weights (`paper`, and `spread`'s first stage), a pixel counted as
        // having at least twice the samples full weight needs (`support_samples`).
        let [na, nb, nc] = pool(k);
        let mut pool_scale = [0.0; STRIP];
        for x in 0..STRIP {
            let pooled_n = na[x] + nb[x] + nc[x];
            let own_n = if V == PAPER {
                support_samples(n[x], kap[x] + kmin, kmin * pooled_n)
            } else {
                n[x]
            };
            let s = own_n / pooled_n;
            pool_scale[x] = if pooled_n > 0.0 { s } else { 0.0 };
        }
        // The spread stage's solid test: a band is solid where its support reaches this (the
        // same f32 comparison as the plain computation's).
        let mut solid_from = [0.0f32; STRIP];
        if BANDS {
            let solid_share = c.params.spread().solid_share();
            for x in 0..STRIP {
                solid_from[x] = (kap[x] + kmin).max(solid_share * n[x]) as f32;
            }
        }
        let small = n.iter().all(|&n| n <= SMALL_N);
        // `1 / N`, which scales every layer and source of the pixel (infinite where `N` is 0,
        // and then never used).
        let mut inv_n = [0.0f64; STRIP];
        for x in 0..STRIP {
            inv_n[x] = 1.0 / n[x];
        }
        let mut f = [[0.0f64; STRIP]; 3];
        let mut total = [[0.0f64; STRIP]; 3];
        let mut removed = [[0.0f64; STRIP]; 3];
        let mut b = [[0.0f64; STRIP]; 3];
        let mut weight = [1.0f64; STRIP];
        for j in 0..k {
            // A cascade without count in any pixel of the strip holds no energy there: its sums
            // are not read (nor its lines asked for), and it is empty (below). In `bench
            // speed`'s 1080p state about half a strip's cascades: the default resolve 72.6-76.1
            // ns a pixel against 77.1-78.5, `paper` 41.8-42.7 against 44.8-45.6 (one thread, 4
            // and 2 alternated runs, best of 30 each).
            let occupied = at.occupied >> j & 1 == 1;
            // The cascade's sums in units, then in value.
            let u = c.unit_value[j];
            if occupied {
                if AVX2 {
                    #[cfg(target_arch = "x86_64")]
                    for x in (0..STRIP).step_by(4) {
                        // SAFETY: only compiled with AVX2 enabled (`compiled_with!`).
                        unsafe { avx2::sums4(cells, x, len, j, k, small, u, &mut b) }
                        ahead.prefetch_l2(per);
                    }
                } else if j + 1 == k {
                    // The top cascade: 85-bit sums, the high word's field times 2^64.
                    for x in 0..STRIP {
                        let cell = &cells[x * len..(x + 1) * len];
                        let hi = cell[4 * k];
                        for ch in 0..3 {
                            let field = (hi >> (HI_BITS * ch as u32)) & HI_MASK;
                            b[ch][x] = (cell[4 * j + ch] as f64 + small_to_f64(field) * TWO_64) * u;
                        }
                    }
                } else if small {
                    for x in 0..STRIP {
                        let sums = &cells[x * len + 4 * j..x * len + 4 * j + 3];
                        for ch in 0..3 {
                            b[ch][x] = small_to_f64(sums[ch]) * u;
                        }
                    }
                } else {
                    for x in 0..STRIP {
                        let sums = &cells[x * len + 4 * j..x * len + 4 * j + 3];
                        for ch in 0..3 {
                            b[ch][x] = sums[ch] as f64 * u;
                        }
                    }
                }
                if !AVX2 {
                    ahead.prefetch_l2(per * STRIP / 4);
                }
            }
            // A cascade with no value in any pixel of the strip adds `+0` to every sum, whatever
            // its weights: they are not computed (measured with `bench speed`'s 1080p state,
            // where a strip has values in 4 of its 8 cascades on average: the default resolve
            // 7 % faster). The values are `+0` or positive, so their bits are zero only if
            // every value is `+0`.
            let mut bits = 0u64;
            if occupied {
                for x in 0..STRIP {
                    bits |= b[0][x].to_bits() | b[1][x].to_bits() | b[2][x].to_bits();
                }
            }
            let empty = bits == 0;
            if V != OFF && !empty {
                let [pa, pb, pc] = pool(j);
                let own = own(j);
                let inv_c = c.inv_scale[j];
                for x in 0..STRIP {
                    let pooled = pa[x] + pb[x] + pc[x];
                    let lf = l0 * f[0][x] + l1 * f[1][x] + l2 * f[2][x];
                    let w_c = (pooled * pool_scale[x] - kmin) * inv_kappa[x];
                    let v = if V == SHADER {
                        let w_c = if w_c >= 0.0 {
                            (own[x] - kmin) * inv_kappa[x]
                        } else {
                            w_c
                        };
                        let t = if inv_kappa[x] < 1.0 {
                            inv_kappa[x]
                        } else {
                            1.0
                        };
                        let energy = (1.0 - t) * shader_energy + t;
                        let floor = SHADER_E_MIN_FLOOR * n[x];
                        let e = if lf > floor { lf } else { floor };
                        let w_v = e * inv_kappa[x] * inv_c * energy;
                        (w_c + w_v) * 0.5
                    } else {
                        let w_v = lf * inv_kappa[x] * inv_c;
                        if w_c > w_v {
                            w_c
                        } else {
                            w_v
                        }
                    };
                    let v = if v < 0.0 { 0.0 } else { v };
                    let wx = if v > 1.0 { 1.0 } else { v };
                    weight[x] = wx;
                    for ch in 0..3 {
                        f[ch][x] += wx * b[ch][x];
                        total[ch][x] += b[ch][x];
                        removed[ch][x] += (1.0 - wx) * b[ch][x];
                    }
                }
            } else if !empty {
                for ch in 0..3 {
                    for x in 0..STRIP {
                        f[ch][x] += b[ch][x];
                        total[ch][x] += b[ch][x];
                        removed[ch][x] += 0.0 * b[ch][x];
                    }
                }
            }
            if BANDS {
                // Straight-line loops over the strip first (the divisions and the solid test
                // as vector instructions), then the sources pushed one by one.
                let own = own(j);
                // Energy is removed only where the weight is below 1 and the band has some.
                // (None in an empty cascade, whose weights were not computed.)
                let mut any = false;
                if !empty {
                    for x in 0..STRIP {
                        // `&` and `|`, not `&&` and `||`: no branch per pixel, so a vector loop.
                        any |= (weight[x] < 1.0)
                            & ((b[0][x] != 0.0) | (b[1][x] != 0.0) | (b[2][x] != 0.0));
                    }
                }
                // The support words, straight into the ring: a whole strip as one array (a
                // copy through a call to `memcpy` was 2-3 % of a default resolve's samples; with
                // 64-row blocks, 69.8-70.4 ns a pixel against 71.2-72.8, 4 alternated runs).
                let word = |x: usize| {
                    let own = own[x] as f32;
                    let word = support_word(own, own >= solid_from[x]);
                    if n[x] != 0.0 {
                        word
                    } else {
                        0.0
                    }
                };
                let words = &mut part.support[j][at.support..at.support + at.count];
                match <&mut [f32; STRIP]>::try_from(&mut *words) {
                    Ok(words) => {
                        for x in 0..STRIP {
                            words[x] = word(x);
                        }
                    }
                    Err(_) => {
                        for (x, w) in words.iter_mut().enumerate() {
                            *w = word(x);
                        }
                    }
                }
                if any {
                    // Each channel's removed energy (zeroed only in a strip that has some).
                    let mut removed = [[0.0f32; STRIP]; 3];
                    for ch in 0..3 {
                        for x in 0..STRIP {
                            // Not used where `n` is 0.
                            removed[ch][x] = ((1.0 - weight[x]) * b[ch][x] * inv_n[x]) as f32;
                        }
                    }
                    // The pixels that are sources as bits (a vector loop), then only those
                    // visited: whether a band is a source in a pixel is a coin toss at low
                    // sample counts, a branch per pixel mispredicted.
                    const _: () = assert!(STRIP <= 64, "a strip's pixels are bits of a u64");
                    let mut is_source = 0u64;
                    for x in 0..STRIP {
                        let source = (n[x] != 0.0)
                            & ((removed[0][x] != 0.0)
                                | (removed[1][x] != 0.0)
                                | (removed[2][x] != 0.0));
                        is_source |= (source as u64) << x;
                    }
                    debug_assert!(
                        at.count == STRIP || is_source >> at.count == 0,
                        "pixels past the frame's edge are empty (n is 0)"
                    );
                    let sources = &mut part.sources[part.column][j];
                    while is_source != 0 {
                        let x = is_source.trailing_zeros() as usize;
                        is_source &= is_source - 1;
                        // The edge rule's test, on the support as its word holds it.
                        let edge = c
                            .params
                            .spread()
                            .edge_share()
                            .is_some_and(|share| (own[x] as f32) as f64 >= share * n[x]);
                        sources.push(Source {
                            x: (at.x0 + x) as u32,
                            y: at.y as u32,
                            removed: [removed[0][x], removed[1][x], removed[2][x]],
                            edge,
                        });
                    }
                }
            }
        }
        // The lines of `ahead` not asked for yet (all of them in a strip without samples).
        ahead.prefetch_l2(usize::MAX);
        let i = at.first;
        // Four pixels at a time in the AVX2 and AVX-512 kernels; the rest (and the portable
        // kernel's) one by one, the same values.
        let mut x0 = 0;
        if AVX2 {
            #[cfg(target_arch = "x86_64")]
            {
                x0 = at.count / 4 * 4;
                // SAFETY: only compiled with AVX2 enabled (`compiled_with!`).
                unsafe { avx2::store_pixels(&[&f, &total, &removed], &inv_n, n, x0, part, i) }
            }
        }
        for x in x0..at.count {
            if n[x] == 0.0 {
                // No samples: nothing to show (the outputs may hold an earlier resolve).
                part.out.reweighted[i + x].write([0.0; 3]);
                part.out.mean[i + x].write([0.0; 3]);
                part.out.removed[i + x].write([0.0; 3]);
                part.out.spp[i + x].write(0);
                continue;
            }
            let inv = inv_n[x];
            let px = |v: &[[f64; STRIP]; 3]| {
                [
                    (v[0][x] * inv) as f32,
                    (v[1][x] * inv) as f32,
                    (v[2][x] * inv) as f32,
                ]
            };
            part.out.reweighted[i + x].write(px(&f));
            part.out.mean[i + x].write(px(&total));
            part.out.removed[i + x].write(px(&removed));
            part.out.spp[i + x].write(n[x] as u64);
        }
    }
}

/// The AVX2 form of the loop that reads a cascade's sums for the weights step: a cascade's
/// `[r, g, b, count]` is 4 words, one 256-bit load, and 4 pixels' loads transposed give each
/// channel of 4 pixels in one vector, converted to `f64` in a few vector instructions (the
/// portable loop reads and converts word by word). These functions are only inlined into the
/// AVX2 and AVX-512 kernels.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;
    use std::mem::MaybeUninit;

    use super::{
        Lines, Part, COUNT_ONE, FRAC_BITS, HI_BITS, HI_MASK, K_MAX, LANES, OWN, STRIP, TWO_52,
        TWO_64,
    };

    /// One group's support counts, as [`support`](super::support)'s group loop computes them
    /// with the same operations in the same order: planes `0 .. k` of `n_j` and plane `k` of
    /// `N`, pixels `at .. at + LANES` of `own`; returns the cascades with a count in any of the
    /// group's pixels (bit `j`). Each cascade's count words of 4 pixels go straight into a
    /// vector: the portable loop's copy of them into an array, read back as vectors, waited for
    /// its stores (a vector load of values stored one by one cannot take them from the store
    /// queue), a tenth of the support step.
    #[inline(always)]
    pub(super) unsafe fn support_group(
        group: &[u64],
        len: usize,
        k: usize,
        own: &mut [f64],
        at: usize,
        ahead: &mut Lines,
    ) -> u32 {
        const _: () = assert!(LANES == 8, "two vectors of 4 pixels");
        assert!(
            group.len() >= LANES * len && len >= 4 * k && k <= K_MAX,
            "a group's cells"
        );
        let word = |l: usize, j: usize| group[l * len + 4 * j + 3] as i64;
        // Only `count[..k]` is written and read: zeroing the whole array (and the converted
        // counts' array this loop once kept) was two calls to `memset` per group, 3 % of a
        // resolve's samples on the Zen 4 VM.
        let mut count = [[MaybeUninit::<__m256i>::uninit(); 2]; K_MAX];
        let mut total = [_mm256_setzero_si256(); 2];
        let per = ahead.left().div_ceil(k);
        let mut occupied = 0;
        for j in 0..k {
            ahead.prefetch(per);
            let mut any = _mm256_setzero_si256();
            for h in 0..2 {
                let l = 4 * h;
                let c =
                    _mm256_set_epi64x(word(l + 3, j), word(l + 2, j), word(l + 1, j), word(l, j));
                count[j][h].write(c);
                // At most 2^58 per pixel (see the state module): exact.
                total[h] = _mm256_add_epi64(total[h], c);
                any = _mm256_or_si256(any, c);
            }
            occupied |= ((_mm256_testz_si256(any, any) == 0) as u32) << j;
        }
        // Every total at most `SMALL_COUNTS = 2^52 - 1`: no bit from 52 up.
        let high = _mm256_or_si256(
            _mm256_srli_epi64::<52>(total[0]),
            _mm256_srli_epi64::<52>(total[1]),
        );
        let is_small = _mm256_testz_si256(high, high) == 1;
        let one = _mm256_set1_pd(1.0 / COUNT_ONE as f64);
        // Cascade `j`'s count in samples, 0 past the last cascade. (A macro: a closure is not
        // compiled with AVX2, and its intrinsics become calls.)
        macro_rules! samples {
            ($j:expr) => {{
                let j = $j;
                let mut c = [_mm256_setzero_pd(); 2];
                if j < k {
                    for h in 0..2 {
                        // SAFETY: `count[j]` for `j < k` was written in the loop above.
                        let words = unsafe { count[j][h].assume_init() };
                        let words = if is_small { small(words) } else { exact(words) };
                        c[h] = _mm256_mul_pd(words, one);
                    }
                }
                c
            }};
        }
        // `n_j = c_(j-1) + c_j + c_(j+1)`, three cascades rolled along (0 for the missing
        // neighbours at the ends).
        let (mut below, mut at_j) = ([_mm256_setzero_pd(); 2], samples!(0));
        for j in 0..=k {
            let above = samples!(j + 1);
            for h in 0..2 {
                let v = if j < k {
                    _mm256_add_pd(_mm256_add_pd(below[h], at_j[h]), above[h])
                } else {
                    small(_mm256_srli_epi64::<{ FRAC_BITS as i32 }>(total[h]))
                };
                let plane = &mut own[j * OWN + at + 4 * h..][..4];
                // SAFETY: 4 values fit in `plane` (a slice of 4).
                unsafe { _mm256_storeu_pd(plane.as_mut_ptr(), v) }
            }
            (below, at_j) = (at_j, above);
        }
        occupied
    }

    /// Pixels `0 .. count` (a multiple of 4) of the strip into the part's layers from pixel `i`:
    /// `layers` (the reweighted, mean and removed sums) times `1 / N` as `f32`, `[r, g, b]` per
    /// pixel, and `N` as an integer; zeros where `N` is 0. The same values as the portable
    /// loop in [`row`](super::row), which took 13 % of a default resolve's row pass in scalar
    /// instructions here too. Measured with `bench speed`'s 1080p 8-cascade state, one thread,
    /// alternated runs (best of 30 each): `off` 40.1-41.2 ns a pixel against 41.7-43.6, `paper`
    /// 45.2-46.2 against 47.9-48.2, the default 76.9-79.4 against 78.1-80.5.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[inline(always)]
    pub(super) unsafe fn store_pixels(
        layers: &[&[[f64; STRIP]; 3]; 3],
        inv_n: &[f64; STRIP],
        n: &[f64; STRIP],
        count: usize,
        part: &mut Part<'_>,
        i: usize,
    ) {
        assert!(
            count <= STRIP && count.is_multiple_of(4),
            "groups of 4 pixels in a strip"
        );
        let out = &mut part.out;
        let mut outs: [&mut [MaybeUninit<[f32; 3]>]; 3] = [
            &mut out.reweighted[i..i + count],
            &mut out.mean[i..i + count],
            &mut out.removed[i..i + count],
        ];
        let spp = &mut out.spp[i..i + count];
        let two_52 = _mm256_set1_pd(TWO_52);
        for x in (0..count).step_by(4) {
            // SAFETY (the loads and stores below): pixels `x .. x + 4` are inside every array
            // and slice (asserted above); unaligned accesses are allowed.
            let nx = unsafe { _mm256_loadu_pd(n[x..].as_ptr()) };
            let empty = _mm256_cmp_pd::<_CMP_EQ_OQ>(nx, _mm256_setzero_pd());
            let inv = unsafe { _mm256_loadu_pd(inv_n[x..].as_ptr()) };
            for (layer, out) in layers.iter().zip(outs.iter_mut()) {
                let channel = |c: usize| {
                    let v = unsafe { _mm256_loadu_pd(layer[c][x..].as_ptr()) };
                    _mm256_cvtpd_ps(_mm256_andnot_pd(empty, _mm256_mul_pd(v, inv)))
                };
                let (r, g, b) = (channel(0), channel(1), channel(2));
                // [r0 g0 b0 r1], [g1 b1 r2 g2], [b2 r3 g3 b3].
                let (rg_lo, rg_hi) = (_mm_unpacklo_ps(r, g), _mm_unpackhi_ps(r, g));
                let first = _mm_shuffle_ps::<0x84>(rg_lo, _mm_shuffle_ps::<0x50>(b, r));
                let second = _mm_shuffle_ps::<0x48>(_mm_shuffle_ps::<0x55>(g, b), rg_hi);
                let third = _mm_shuffle_ps::<0x88>(
                    _mm_shuffle_ps::<0xFA>(b, r),
                    _mm_shuffle_ps::<0xFF>(g, b),
                );
                let p = out[x..x + 4].as_mut_ptr().cast::<f32>();
                unsafe {
                    _mm_storeu_ps(p, first);
                    _mm_storeu_ps(p.add(4), second);
                    _mm_storeu_ps(p.add(8), third);
                }
            }
            // `N`, a whole number of at most 2^32: the mantissa of `N + 2^52`.
            let whole = _mm256_sub_epi64(
                _mm256_castpd_si256(_mm256_add_pd(nx, two_52)),
                _mm256_castpd_si256(two_52),
            );
            unsafe { _mm256_storeu_si256(spp[x..].as_mut_ptr().cast(), whole) }
        }
    }

    /// A cascade's `[r, g, b, count]` of the 4 cells at `at`, `at + len`, .. of `cells`,
    /// transposed: `[r of the 4 pixels, g, b, count]`.
    ///
    /// # Safety
    /// The CPU must have AVX2 (as for the other functions here).
    #[inline(always)]
    unsafe fn group4(cells: &[u64], at: usize, len: usize) -> [__m256i; 4] {
        assert!(at + 3 * len + 4 <= cells.len(), "4 cells");
        let p = cells[at..].as_ptr() as *const __m256i;
        // SAFETY: the 4 loads of 4 words each are inside `cells` (asserted above); unaligned
        // loads are allowed.
        let (a, b, c, d) = unsafe {
            (
                _mm256_loadu_si256(p),
                _mm256_loadu_si256(p.byte_add(8 * len)),
                _mm256_loadu_si256(p.byte_add(16 * len)),
                _mm256_loadu_si256(p.byte_add(24 * len)),
            )
        };
        let (ab_lo, ab_hi) = (_mm256_unpacklo_epi64(a, b), _mm256_unpackhi_epi64(a, b));
        let (cd_lo, cd_hi) = (_mm256_unpacklo_epi64(c, d), _mm256_unpackhi_epi64(c, d));
        [
            _mm256_permute2x128_si256::<0x20>(ab_lo, cd_lo),
            _mm256_permute2x128_si256::<0x20>(ab_hi, cd_hi),
            _mm256_permute2x128_si256::<0x31>(ab_lo, cd_lo),
            _mm256_permute2x128_si256::<0x31>(ab_hi, cd_hi),
        ]
    }

    /// `x as f64` for 4 words below `2^52`: the word in the mantissa of `2^52`, minus `2^52`.
    #[inline(always)]
    unsafe fn small(x: __m256i) -> __m256d {
        let magic = _mm256_set1_epi64x(TWO_52.to_bits() as i64);
        _mm256_sub_pd(
            _mm256_castsi256_pd(_mm256_or_si256(x, magic)),
            _mm256_set1_pd(TWO_52),
        )
    }

    /// `x as f64` for any 4 words, rounded once as `as` rounds: the high and low 32 bits as
    /// exact `f64`s (`2^84 + hi * 2^32` and `2^52 + lo`), the offsets taken off the high part
    /// exactly, then one rounded addition.
    #[inline(always)]
    unsafe fn exact(x: __m256i) -> __m256d {
        let lo = _mm256_blend_epi32::<0b1010_1010>(x, _mm256_set1_epi64x(TWO_52.to_bits() as i64));
        let two_84 = 19_342_813_113_834_066_795_298_816.0f64;
        let hi = _mm256_or_si256(
            _mm256_srli_epi64::<32>(x),
            _mm256_set1_epi64x(two_84.to_bits() as i64),
        );
        let hi = _mm256_sub_pd(_mm256_castsi256_pd(hi), _mm256_set1_pd(two_84 + TWO_52));
        _mm256_add_pd(hi, _mm256_castsi256_pd(lo))
    }

    /// `b[ch][x .. x + 4]`: cascade `j`'s sums of pixels `x ..` of a strip's cells, converted to
    /// `f64` (by `small` where every pixel of the strip has at most `2^20` samples; the top
    /// cascade `K - 1` with its high word) and times the cascade's unit value `u`.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn sums4(
        cells: &[u64],
        x: usize,
        len: usize,
        j: usize,
        k: usize,
        is_small: bool,
        u: f64,
        b: &mut [[f64; STRIP]; 3],
    ) {
        let [r, g, bl, _] = group4(cells, x * len + 4 * j, len);
        let u = _mm256_set1_pd(u);
        let values: [__m256d; 3] = if j + 1 == k {
            let hi = _mm256_set_epi64x(
                cells[(x + 3) * len + 4 * k] as i64,
                cells[(x + 2) * len + 4 * k] as i64,
                cells[(x + 1) * len + 4 * k] as i64,
                cells[x * len + 4 * k] as i64,
            );
            let mask = _mm256_set1_epi64x(HI_MASK as i64);
            let two_64 = _mm256_set1_pd(TWO_64);
            let g_hi = _mm256_srli_epi64::<{ HI_BITS as i32 }>(hi);
            let b_hi = _mm256_srli_epi64::<{ 2 * HI_BITS as i32 }>(hi);
            [
                _mm256_add_pd(
                    exact(r),
                    _mm256_mul_pd(small(_mm256_and_si256(hi, mask)), two_64),
                ),
                _mm256_add_pd(
                    exact(g),
                    _mm256_mul_pd(small(_mm256_and_si256(g_hi, mask)), two_64),
                ),
                _mm256_add_pd(
                    exact(bl),
                    _mm256_mul_pd(small(_mm256_and_si256(b_hi, mask)), two_64),
                ),
            ]
        } else if is_small {
            [small(r), small(g), small(bl)]
        } else {
            [exact(r), exact(g), exact(bl)]
        };
        for ch in 0..3 {
            let out = &mut b[ch][x..x + 4];
            // SAFETY: 4 values fit in `out` (a slice of 4).
            unsafe { _mm256_storeu_pd(out.as_mut_ptr(), _mm256_mul_pd(values[ch], u)) }
        }
    }
}
