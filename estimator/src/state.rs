//! Per-frame accumulation state: `K` cascade sums and counts per pixel, all in fixed point so that
//! accumulation and merging are exact and order-independent.
//!
//! Storage is pixel-major: a pixel's cell is `K` groups of `[r, g, b, count]` followed by one
//! *high word*, `4K + 1` `u64`s or `32K + 8` bytes ([`cell_len`]). The pixel's sample count `N_p`
//! is not stored: every sample adds exactly [`COUNT_ONE`] to the counts of its cascades (the two
//! shares of a split add to it by construction), so `N_p = (Σ_j count_j) >> FRAC_BITS`, exactly.
//! A splat touches the 64 contiguous bytes of cascades `lo` and `lo + 1` of one cell (and the
//! high word right after them, rarely, on a carry). Resolve reads the cells row by row.
//!
//! # Exact bounds
//!
//! Values are in units of `c_j * 2^-26` ([`FRAC_BITS`]), counts in units of `2^-26`.
//!
//! * A sample component must be finite, `>= 0` (`-0.0` is zero) and at most
//!   `c_{K-1} * 2^26` ([`CascadeLayout::max_component`]; `2^38 ≈ 2.7e11` with the default layout
//!   `c0 = 1/8, b = 8, K = 6`). Anything else is refused ([`SampleError`]), never altered.
//! * A pixel holds at most `2^32` samples ([`MAX_PIXEL_SAMPLES`]): a splat, batch or merge that
//!   would go past it is refused ([`SampleError::PixelFull`], [`MergeError::TooManySamples`]).
//! * Cascades `0 .. K-2` receive shares of luminance at most `c_j`, so with weights in
//!   `[1/32, 1]` each channel of a share is at most `32 c_j = 2^31` units: `2^32` samples stay
//!   below `2^63 + 2^62` ([`LOW_SHARE_MAX`] per sample), inside a `u64`.
//! * The top cascade `K-1` takes every sample brighter than `c_{K-1}` whole: a share is at most
//!   `2^52` units, `2^32` of them `2^84`. Its r, g, b sums are 85-bit integers
//!   `hi * 2^64 + lo`: `lo` is the cascade's ordinary word, `hi` a 21-bit field of the cell's high
//!   word (r in bits 0..21, g in 21..42, b in 42..63).
//! * Counts: at most `2^32 * 2^26 = 2^58` per pixel.
//! * A cascade without count holds no energy: every share a sample gives a cascade carries at
//!   least `2^26 / 32 = 2^21` units of count.
//!
//! Within these bounds no sum can overflow, so every addition is exact (overflow is
//! debug-asserted); [`FrameState::from_cells`] checks that imported cells respect them per pixel.
//!
//! A state may hold a horizontal band of a frame (rows `y0 .. y0 + rows`), so that a service
//! can shard a frame across locks; a state that holds the whole frame is just the band starting
//! at row 0 with all rows.

use std::ops::Range;

use super::layout::{to_fixed, CascadeLayout, COUNT_ONE, FRAC_BITS, MAX_PIXEL_SAMPLES};

mod row;

pub use row::Kernel;
use row::{Shares, Tables, BLOCK};

/// Bits of each top-cascade channel held in the cell's high word.
pub(crate) const HI_BITS: u32 = 21;
pub(crate) const HI_MASK: u64 = (1 << HI_BITS) - 1;

/// Largest units a checked sample's share adds to one channel of cascades `0 .. K-2`, with slack
/// for `f64` rounding: `2^31 + 2^30` (the exact bound is `2^31`).
pub const LOW_SHARE_MAX: u64 = (1 << 31) + (1 << 30);

/// Largest units a checked sample's share adds to one channel of the top cascade, with slack for
/// `f64` rounding: `2^52 + 2^51` (the exact bound is `2^52`).
pub const TOP_SHARE_MAX: u64 = (1 << 52) + (1 << 51);

/// Why a sample was not accumulated. Nothing of a rejected sample reaches the state.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum SampleError {
    /// A component is NaN or infinite.
    #[error("sample has a non-finite component (NaN or infinity)")]
    NonFinite,
    /// A component is negative. A Monte Carlo radiance estimate is never negative; accepting one
    /// would break the non-negativity that the unsigned fixed-point sums and the guarantee
    /// "removed energy >= 0" rely on, and silently clamping it would bias the mean. Rejected and
    /// counted, like non-finite samples.
    #[error("sample has a negative component")]
    Negative,
    /// A component is larger than the frame's layout represents exactly
    /// ([`CascadeLayout::max_component`]). Refused, never clamped.
    #[error(
        "component {value:e} exceeds this frame's largest representable sample {max:e}; \
         create the frame with more cascades or a larger lowest_scale"
    )]
    TooBright {
        /// The offending component.
        value: f32,
        /// The largest component accepted.
        max: f64,
    },
    /// The pixel already holds the most samples a pixel may hold ([`MAX_PIXEL_SAMPLES`]).
    #[error("pixel ({x}, {y}) already holds {MAX_PIXEL_SAMPLES} samples, the most a pixel holds")]
    PixelFull {
        /// Column of the sample.
        x: u32,
        /// Row of the sample.
        y: u32,
    },
    /// The pixel lies outside the frame (or outside the band this state holds).
    #[error("pixel ({x}, {y}) is outside the {width}x{height} frame")]
    OutOfFrame {
        /// Column of the sample.
        x: u32,
        /// Row of the sample.
        y: u32,
        /// Frame width.
        width: u32,
        /// Frame height.
        height: u32,
    },
}

/// Checks a sample's value (not its pixel) independently of any layout: finite and non-negative.
/// `-0.0` is accepted as zero. [`CascadeLayout::check_sample`] also checks the brightness limit.
#[inline]
pub fn check_sample(rgb: [f32; 3]) -> Result<(), SampleError> {
    if !rgb.iter().all(|c| c.is_finite()) {
        Err(SampleError::NonFinite)
    } else if rgb.iter().any(|&c| c < 0.0) {
        Err(SampleError::Negative)
    } else {
        Ok(())
    }
}

/// Counts of what a batch splat did with its samples.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SplatReport {
    /// Samples accumulated.
    pub accepted: u64,
    /// Samples with a NaN or infinite component.
    pub non_finite: u64,
    /// Samples with a negative component.
    pub negative: u64,
    /// Samples whose pixel lies outside the state.
    pub out_of_frame: u64,
    /// Samples with a component above the layout's largest ([`SampleError::TooBright`]).
    pub too_bright: u64,
    /// Samples of a pixel that already held [`MAX_PIXEL_SAMPLES`].
    pub pixel_full: u64,
}

impl SplatReport {
    /// Samples not accumulated.
    pub fn rejected(&self) -> u64 {
        self.non_finite + self.negative + self.out_of_frame + self.too_bright + self.pixel_full
    }

    fn add(&mut self, other: &SplatReport) {
        self.accepted += other.accepted;
        self.non_finite += other.non_finite;
        self.negative += other.negative;
        self.out_of_frame += other.out_of_frame;
        self.too_bright += other.too_bright;
        self.pixel_full += other.pixel_full;
    }

    fn count(&mut self, result: Result<(), SampleError>) {
        match result {
            Ok(()) => self.accepted += 1,
            Err(SampleError::NonFinite) => self.non_finite += 1,
            Err(SampleError::Negative) => self.negative += 1,
            Err(SampleError::OutOfFrame { .. }) => self.out_of_frame += 1,
            Err(SampleError::TooBright { .. }) => self.too_bright += 1,
            Err(SampleError::PixelFull { .. }) => self.pixel_full += 1,
        }
    }
}

/// Two states that cannot be added, with what differs.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MergeError {
    /// Different frame sizes.
    #[error(
        "frame size differs: {ours_w}x{ours_h} here, {theirs_w}x{theirs_h} in the other state"
    )]
    Size {
        /// Our width.
        ours_w: u32,
        /// Our height.
        ours_h: u32,
        /// Their width.
        theirs_w: u32,
        /// Their height.
        theirs_h: u32,
    },
    /// Different cascade layouts (the same sample would have gone to different cascades).
    #[error("cascade layout differs: {ours} here, {theirs} in the other state")]
    Layout {
        /// Our layout, described.
        ours: String,
        /// Their layout, described.
        theirs: String,
    },
    /// Row ranges that only partly overlap: adding them would merge part of a state silently.
    #[error(
        "row ranges {ours:?} and {theirs:?} neither contain each other; \
         refusing to merge part of a state"
    )]
    Rows {
        /// Our rows.
        ours: std::ops::Range<u32>,
        /// Their rows.
        theirs: std::ops::Range<u32>,
    },
    /// The sum would hold more than [`MAX_PIXEL_SAMPLES`] samples in a pixel.
    #[error(
        "pixel ({x}, {y}) would hold more than {MAX_PIXEL_SAMPLES} samples, the most a pixel holds"
    )]
    TooManySamples {
        /// Column of the first such pixel.
        x: u32,
        /// Row of the first such pixel.
        y: u32,
    },
    /// [`FrameState::delta_since`] was given a state that is not an earlier copy of this one.
    #[error("pixel ({x}, {y}) holds less than in the earlier state: not an earlier copy")]
    NotEarlier {
        /// Column of the first such pixel.
        x: u32,
        /// Row of the first such pixel.
        y: u32,
    },
}

/// Cells that cannot be a state: they do not fit the geometry, or a pixel holds what no sequence
/// of checked samples could have produced.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CellsError {
    /// The cells do not fit the geometry.
    #[error(transparent)]
    Shape(#[from] ShapeError),
    /// A pixel's cell breaks the bounds of the module docs.
    #[error("pixel ({x}, {y}): {reason}")]
    Invalid {
        /// Column.
        x: u32,
        /// Row.
        y: u32,
        /// What is wrong.
        reason: String,
    },
}

/// A state's cells do not fit its geometry (an imported state that was cut or padded).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "state holds {found} cells, a {width}x{rows} band with {cascades} cascades needs {expected}"
)]
pub struct ShapeError {
    /// Cells found.
    pub found: usize,
    /// Cells needed.
    pub expected: usize,
    /// Width.
    pub width: u32,
    /// Rows.
    pub rows: u32,
    /// Cascade count.
    pub cascades: usize,
}

/// Accumulated cascades of a frame, or of a band of its rows.
#[derive(PartialEq)]
pub struct FrameState {
    width: u32,
    height: u32,
    y0: u32,
    rows: u32,
    layout: CascadeLayout,
    cells: Vec<u64>,
    /// Samples held in all pixels (a function of `cells`, kept so that the common case "no pixel
    /// can be full" is checked without reading any cell).
    samples: u64,
}

impl Clone for FrameState {
    fn clone(&self) -> Self {
        Self {
            layout: self.layout.clone(),
            cells: self.cells.clone(),
            ..*self
        }
    }

    /// Reuses this state's cells when they have room: a copy taken again and again (a frame's
    /// cut) then costs a memcpy, not a fresh allocation faulted in page by page.
    fn clone_from(&mut self, source: &Self) {
        self.layout.clone_from(&source.layout);
        self.cells.clone_from(&source.cells);
        (self.width, self.height, self.y0, self.rows, self.samples) = (
            source.width,
            source.height,
            source.y0,
            source.rows,
            source.samples,
        );
    }
}

impl std::fmt::Debug for FrameState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameState")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("rows", &(self.y0..self.y0 + self.rows))
            .field("layout", &self.layout)
            .field("samples", &self.total_samples())
            .finish()
    }
}

/// `u64`s per pixel for `k` cascades: `[r, g, b, count]` per cascade, then the high word of the
/// top cascade's r, g, b sums.
pub const fn cell_len(k: usize) -> usize {
    4 * k + 1
}

/// Samples in a pixel from its cell: the exact sum of its fixed-point counts.
#[inline]
pub fn cell_spp(cell: &[u64]) -> u64 {
    let k = cell.len() / 4;
    let units = (0..k).fold(0u64, |a, j| a.wrapping_add(cell[4 * j + 3]));
    units >> FRAC_BITS
}

/// The top cascade's channel `c` (0..3) of one cell (exactly [`cell_len`]`(K)` words), as the
/// 85-bit integer `hi * 2^64 + lo`.
#[inline]
pub fn top_sum(cell: &[u64], c: usize) -> u128 {
    let k = cell.len() / 4;
    let hi = (cell[4 * k] >> (HI_BITS * c as u32)) & HI_MASK;
    ((hi as u128) << 64) | cell[4 * (k - 1) + c] as u128
}

/// Channel `c` of cascade `j` of one cell (exactly [`cell_len`]`(K)` words) in fixed-point units,
/// exactly (the top cascade's 85-bit sum with its field of the high word).
fn cascade_sum(cell: &[u64], j: usize, c: usize) -> u128 {
    if j + 1 == cell.len() / 4 {
        top_sum(cell, c)
    } else {
        cell[4 * j + c] as u128
    }
}

/// Channel `c` of cascade `j` of one cell (exactly [`cell_len`]`(K)` words) in fixed-point units,
/// as an `f64` (for the top cascade, its 85-bit sum to `f64` precision).
#[inline]
pub fn cascade_units(cell: &[u64], j: usize, c: usize) -> f64 {
    let k = cell.len() / 4;
    let lo = cell[4 * j + c] as f64;
    if j + 1 == k {
        let hi = (cell[4 * k] >> (HI_BITS * c as u32)) & HI_MASK;
        lo + hi as f64 * 18446744073709551616.0
    } else {
        lo
    }
}

/// Adds cell `src` to cell `dst` (same `K`), exactly: the top cascade's sums with carry into the
/// high word. The caller guarantees that both are valid cells ([`check_pixels`]) and that the
/// result holds at most [`MAX_PIXEL_SAMPLES`] samples ([`cell_spp`]), so nothing overflows
/// (debug-asserted). For a holder of cells other than a [`FrameState`] (a sparse merge).
#[inline]
pub fn add_cell(dst: &mut [u64], src: &[u64]) {
    let k = dst.len() / 4;
    let top = 4 * (k - 1);
    for (d, s) in dst[..top].iter_mut().zip(&src[..top]) {
        debug_assert!(d.checked_add(*s).is_some(), "cell sum overflows");
        *d = d.wrapping_add(*s);
    }
    let mut hi = dst[4 * k].wrapping_add(src[4 * k]);
    for c in 0..3 {
        let (sum, carry) = dst[top + c].overflowing_add(src[top + c]);
        dst[top + c] = sum;
        hi = hi.wrapping_add(u64::from(carry) << (HI_BITS * c as u32));
    }
    debug_assert!(dst[top + 3].checked_add(src[top + 3]).is_some());
    dst[top + 3] = dst[top + 3].wrapping_add(src[top + 3]);
    debug_assert_eq!(hi >> (3 * HI_BITS), 0, "top cascade sum overflows 85 bits");
    dst[4 * k] = hi;
}

/// Subtracts cell `src` from cell `dst` (same `K`): the exact inverse of [`add_cell`], so
/// `dst` is again what it was before `src` was added to it, bit for bit (the top cascade's sums
/// borrow from the high word as adding carried into it). For a holder that takes back an
/// addition.
#[inline]
pub fn sub_cell(dst: &mut [u64], src: &[u64]) {
    let k = dst.len() / 4;
    let top = 4 * (k - 1);
    for (d, s) in dst[..top].iter_mut().zip(&src[..top]) {
        *d = d.wrapping_sub(*s);
    }
    let mut hi = dst[4 * k].wrapping_sub(src[4 * k]);
    for c in 0..3 {
        let (diff, borrow) = dst[top + c].overflowing_sub(src[top + c]);
        dst[top + c] = diff;
        hi = hi.wrapping_sub(u64::from(borrow) << (HI_BITS * c as u32));
    }
    dst[top + 3] = dst[top + 3].wrapping_sub(src[top + 3]);
    dst[4 * k] = hi;
}

/// Checks the cells of consecutive whole pixels of a state with `cascades` cascades
/// (`cell_len(cascades)` words each) against the bounds of the module docs, as
/// [`FrameState::from_cells`] does, and returns the samples they hold; `first` is the number of
/// the first pixel, row-major from 0 within the rows from `y0` of a `width`-wide frame, to name
/// a bad pixel. For a receiver that checks a state piece by piece as it decodes it.
pub fn check_pixels(
    width: u32,
    y0: u32,
    cascades: usize,
    first: u64,
    cells: &[u64],
) -> Result<u64, CellsError> {
    let stride = cell_len(cascades);
    debug_assert_eq!(cells.len() % stride, 0, "whole pixels");
    let mut samples = 0u64;
    for (i, cell) in cells.chunks_exact(stride).enumerate() {
        check_cell(cell).map_err(|reason| {
            let pixel = first + i as u64;
            CellsError::Invalid {
                x: (pixel % width as u64) as u32,
                y: y0 + (pixel / width as u64) as u32,
                reason,
            }
        })?;
        samples += cell_spp(cell);
    }
    Ok(samples)
}

/// Why `cell` (of pixel `x`, `y`) cannot hold what checked samples produce, if it cannot.
fn check_cell(cell: &[u64]) -> Result<(), String> {
    let k = cell.len() / 4;
    let counts = (0..k).try_fold(0u64, |a, j| a.checked_add(cell[4 * j + 3]));
    let Some(counts) = counts else {
        return Err("its counts overflow".into());
    };
    if counts % COUNT_ONE != 0 {
        return Err(format!(
            "its counts add to {counts} units, not a whole number of samples"
        ));
    }
    let n = counts >> FRAC_BITS;
    if n > MAX_PIXEL_SAMPLES {
        return Err(format!(
            "it holds {n} samples, more than {MAX_PIXEL_SAMPLES}"
        ));
    }
    if cell[4 * k] >> (3 * HI_BITS) != 0 {
        return Err("its high word has bits beyond the three 21-bit fields".into());
    }
    for j in 0..k {
        // Every share a sample gives a cascade carries at least 1/32 of a sample's count, so a
        // cascade without count never got a share, and holds no energy (the resolve does not
        // read the sums of a cascade without count in a whole strip of pixels).
        if cell[4 * j + 3] == 0 && (0..3).any(|c| cascade_sum(cell, j, c) != 0) {
            return Err(format!("cascade {j} holds energy but no samples"));
        }
        let max = if j + 1 == k {
            n as u128 * TOP_SHARE_MAX as u128
        } else {
            n as u128 * LOW_SHARE_MAX as u128
        };
        for c in 0..3 {
            let units = cascade_sum(cell, j, c);
            if units > max {
                return Err(format!(
                    "cascade {j} channel {c} holds {units} units, more than {n} samples can add"
                ));
            }
        }
    }
    Ok(())
}

impl FrameState {
    /// An empty state for a whole `width x height` frame.
    pub fn new(width: u32, height: u32, layout: CascadeLayout) -> Self {
        Self::band(width, height, 0..height, layout)
    }

    /// An empty state for rows `rows` of a `width x height` frame.
    ///
    /// # Panics
    /// If the rows do not lie inside the frame (a programming error, not an input error).
    pub fn band(
        width: u32,
        height: u32,
        rows: std::ops::Range<u32>,
        layout: CascadeLayout,
    ) -> Self {
        Self::band_in(width, height, rows, layout, Vec::new())
    }

    /// [`band`](Self::band) in the memory of `cells`, the cells of an earlier state
    /// ([`into_cells`](Self::into_cells)): overwritten with zeros if they have room for the
    /// band, else dropped for new ones. Memory a process has used before is cheaper to zero
    /// than fresh pages are to fault in, which the kernel zeroes too.
    ///
    /// # Panics
    /// If the rows do not lie inside the frame (a programming error, not an input error).
    pub fn band_in(
        width: u32,
        height: u32,
        rows: std::ops::Range<u32>,
        layout: CascadeLayout,
        cells: Vec<u64>,
    ) -> Self {
        assert!(
            rows.start <= rows.end && rows.end <= height,
            "band {rows:?} outside a frame of height {height}"
        );
        let len = width as usize * rows.len() * cell_len(layout.cascades());
        let cells = zeroed_in(cells, len);
        Self {
            width,
            height,
            y0: rows.start,
            rows: rows.end - rows.start,
            layout,
            cells,
            samples: 0,
        }
    }

    /// The state's cells, whose memory [`band_in`](Self::band_in) can reuse.
    pub fn into_cells(self) -> Vec<u64> {
        self.cells
    }

    /// A copy of this state in the memory of `cells` (the cells of an earlier state; grown if
    /// they are too small), like [`clone`](Clone::clone) into memory already mapped.
    pub fn clone_in(&self, mut cells: Vec<u64>) -> Self {
        cells.clear();
        cells.extend_from_slice(&self.cells);
        Self {
            layout: self.layout.clone(),
            cells,
            ..*self
        }
    }

    /// Splits a frame into `n` bands of (nearly) equal height that tile it top to bottom.
    pub fn bands(width: u32, height: u32, n: u32, layout: &CascadeLayout) -> Vec<Self> {
        Self::bands_in(width, height, n, layout, |_| Vec::new())
    }

    /// [`bands`](Self::bands), each band in the memory `cells(len)` gives for its `len` words
    /// ([`band_in`](Self::band_in)).
    pub fn bands_in(
        width: u32,
        height: u32,
        n: u32,
        layout: &CascadeLayout,
        mut cells: impl FnMut(usize) -> Vec<u64>,
    ) -> Vec<Self> {
        let n = n.clamp(1, height.max(1));
        let stride = width as usize * cell_len(layout.cascades());
        (0..n)
            .map(|i| {
                let start = (height as u64 * i as u64 / n as u64) as u32;
                let end = (height as u64 * (i as u64 + 1) / n as u64) as u32;
                let memory = cells(stride * (end - start) as usize);
                Self::band_in(width, height, start..end, layout.clone(), memory)
            })
            .collect()
    }

    /// Rebuilds a state from exported cells, checking that they fit the geometry and that every
    /// pixel respects the bounds of the module docs (so that merging it can never overflow).
    pub fn from_cells(
        width: u32,
        height: u32,
        rows: std::ops::Range<u32>,
        layout: CascadeLayout,
        cells: Vec<u64>,
    ) -> Result<Self, CellsError> {
        let stride = cell_len(layout.cascades());
        let expected = width as usize * rows.len() * stride;
        if cells.len() != expected || rows.end > height {
            return Err(ShapeError {
                found: cells.len(),
                expected,
                width,
                rows: rows.end.saturating_sub(rows.start),
                cascades: layout.cascades(),
            }
            .into());
        }
        let samples = check_pixels(width, rows.start, layout.cascades(), 0, &cells)?;
        Ok(Self {
            width,
            height,
            y0: rows.start,
            rows: rows.end - rows.start,
            layout,
            cells,
            samples,
        })
    }

    /// Rebuilds a state from cells of the previous format (state format version 1: `FRAC_BITS`
    /// 32, `4K` `u64`s per pixel, sums that saturated at `u64::MAX`), converting them.
    ///
    /// Values are rounded to the nearest unit of `2^-26` (`v / 64`); counts are rounded too, and
    /// the rounding residual is put on each pixel's largest count so that the pixel still holds
    /// exactly its `N_p` samples. The top cascade's high word starts at 0. A value or count sum
    /// that saturated cannot be converted honestly: refused, naming the pixel.
    pub fn from_frac32_cells(
        width: u32,
        height: u32,
        rows: std::ops::Range<u32>,
        layout: CascadeLayout,
        old: &[u64],
    ) -> Result<Self, CellsError> {
        let k = layout.cascades();
        let pixels = width as usize * rows.len();
        if old.len() != pixels * 4 * k || rows.end > height {
            return Err(ShapeError {
                found: old.len(),
                expected: pixels * 4 * k,
                width,
                rows: rows.end.saturating_sub(rows.start),
                cascades: k,
            }
            .into());
        }
        let stride = cell_len(k);
        let mut cells = vec![0u64; pixels * stride];
        for (i, (src, dst)) in old
            .chunks_exact(4 * k)
            .zip(cells.chunks_exact_mut(stride))
            .enumerate()
        {
            let invalid = |reason: &str| CellsError::Invalid {
                x: (i % width as usize) as u32,
                y: rows.start + (i / width as usize) as u32,
                reason: reason.to_owned(),
            };
            if src.contains(&u64::MAX) {
                return Err(invalid(
                    "a sum saturated in the previous state format; it cannot be converted exactly",
                ));
            }
            let counts = (0..k).try_fold(0u64, |a, j| a.checked_add(src[4 * j + 3]));
            let counts = counts
                .filter(|c| c % (1u64 << 32) == 0)
                .ok_or_else(|| invalid("its counts are not a whole number of samples"))?;
            let shift = 32 - FRAC_BITS;
            for (d, &v) in dst.iter_mut().zip(src) {
                // Round to nearest: v / 64, plus the highest bit shifted out.
                *d = (v >> shift) + ((v >> (shift - 1)) & 1);
            }
            let target = (counts >> 32) << FRAC_BITS;
            let rounded: u64 = (0..k).map(|j| dst[4 * j + 3]).sum();
            let largest = (0..k)
                .max_by_key(|&j| dst[4 * j + 3])
                .expect("at least two cascades");
            let at = 4 * largest + 3;
            // Each count rounds by at most half a unit, so the residual is at most K / 2 units
            // and the largest count (at least 1/K of the total) absorbs it.
            dst[at] = (dst[at] + target)
                .checked_sub(rounded)
                .ok_or_else(|| invalid("its counts cannot be converted"))?;
        }
        Self::from_cells(width, height, rows, layout, cells)
    }

    /// Frame width.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Frame height (of the whole frame, not of this band).
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Rows held by this state.
    pub fn rows(&self) -> std::ops::Range<u32> {
        self.y0..self.y0 + self.rows
    }

    /// The cascade layout.
    pub fn layout(&self) -> &CascadeLayout {
        &self.layout
    }

    /// The raw fixed-point cells, pixel-major, `cell_len(K)` per pixel (for export).
    pub fn cells(&self) -> &[u64] {
        &self.cells
    }

    /// Bytes of accumulation state held.
    pub fn memory_bytes(&self) -> usize {
        self.cells.len() * std::mem::size_of::<u64>()
    }

    /// The cells of row `y` (which must lie in this state).
    #[inline]
    pub(crate) fn row(&self, y: u32) -> &[u64] {
        let len = self.width as usize * cell_len(self.layout.cascades());
        let start = (y - self.y0) as usize * len;
        &self.cells[start..start + len]
    }

    /// Samples accumulated in pixel `(x, y)`.
    pub fn spp(&self, x: u32, y: u32) -> u64 {
        let stride = cell_len(self.layout.cascades());
        cell_spp(&self.row(y)[x as usize * stride..(x as usize + 1) * stride])
    }

    /// Samples accumulated in all pixels of this state: exact (at most `2^32` per pixel, and a
    /// state holds fewer than `2^32` pixels: their cells alone would take over 200 GB).
    pub fn total_samples(&self) -> u64 {
        self.samples
    }

    /// Whether pixel `(x, y)` (which must lie in this state) can take `n` more samples.
    #[inline]
    pub fn has_room(&self, x: u32, y: u32, n: u64) -> bool {
        // No pixel holds more than the whole state: this reads no cell until the state holds
        // 2^32 samples.
        if self.samples.saturating_add(n) <= MAX_PIXEL_SAMPLES {
            return true;
        }
        self.spp(x, y).saturating_add(n) <= MAX_PIXEL_SAMPLES
    }

    /// Where `(x, y)` lives, or why it does not.
    #[inline]
    pub fn check_pixel(&self, x: u32, y: u32) -> Result<(), SampleError> {
        if x < self.width && y >= self.y0 && y - self.y0 < self.rows {
            Ok(())
        } else {
            Err(SampleError::OutOfFrame {
                x,
                y,
                width: self.width,
                height: self.height,
            })
        }
    }

    /// Accumulates one sample into pixel `(x, y)`. A rejected sample changes nothing.
    #[inline]
    pub fn splat(&mut self, x: u32, y: u32, rgb: [f32; 3]) -> Result<(), SampleError> {
        self.check_pixel(x, y)?;
        self.layout.check_sample(rgb)?;
        if !self.has_room(x, y, 1) {
            return Err(SampleError::PixelFull { x, y });
        }
        self.splat_checked(x, y, rgb);
        Ok(())
    }

    /// Accumulates every valid sample of `samples` (pixel, RGB) and counts the rest.
    ///
    /// For samples in a slice, [`FrameState::splat_records`] is faster (vectorized arithmetic a
    /// block at a time). Random pixels of a large frame miss every cache, so the work is
    /// pipelined: a sample's split is computed and the
    /// cascades it will touch are prefetched, and it is applied 16 samples later, by which time
    /// the memory is on its way. The result is identical to splatting the samples one by one.
    pub fn splat_all<I>(&mut self, samples: I) -> SplatReport
    where
        I: IntoIterator<Item = (u32, u32, [f32; 3])>,
    {
        // Samples in flight: prepared and prefetched, applied this many samples later.
        const AHEAD: usize = 16;
        let mut report = SplatReport::default();
        let mut ring = [Pending::default(); AHEAD];
        let (mut head, mut len) = (0, 0);
        for (x, y, rgb) in samples {
            let checked = self
                .check_pixel(x, y)
                .and_then(|()| self.layout.check_sample(rgb))
                .and_then(|()| {
                    // The `len` samples in flight are not applied yet: at first count them as if
                    // they all were in this pixel (exactly only near the limit).
                    let in_flight = (0..len).map(|i| &ring[(head + i) % AHEAD]);
                    if self.has_room(x, y, len as u64 + 1) || self.room_exact(x, y, in_flight) {
                        Ok(())
                    } else {
                        Err(SampleError::PixelFull { x, y })
                    }
                });
            report.count(checked);
            if checked.is_ok() {
                if len == AHEAD {
                    self.apply(&ring[head]);
                    head = (head + 1) % AHEAD;
                    len -= 1;
                }
                let p = self.prepare(x, y, rgb);
                prefetch(&self.cells, p.at, 8);
                ring[(head + len) % AHEAD] = p;
                len += 1;
            }
        }
        for i in 0..len {
            let p = ring[(head + i) % AHEAD];
            self.apply(&p);
        }
        report
    }

    /// Accumulates one sample in each of the consecutive pixels `x0, x0 + 1, ..` of row `y`
    /// (`rgb[i]` goes to `x0 + i`): a rendered pass row by row, a scan line of a tile. The
    /// arithmetic of a block of samples is vectorized (see [`Kernel`]); the state and the report
    /// are bit-identical to splatting the samples one by one, rejected samples included.
    pub fn splat_row(&mut self, x0: u32, y: u32, rgb: &[[f32; 3]]) -> SplatReport {
        self.splat_row_with(Kernel::detect(), x0, y, rgb)
    }

    /// [`FrameState::splat_row`] with a chosen kernel, for tests and benchmarks.
    ///
    /// # Panics
    /// If the CPU cannot run `kernel` ([`Kernel::available`]).
    pub fn splat_row_with(
        &mut self,
        kernel: Kernel,
        x0: u32,
        y: u32,
        rgb: &[[f32; 3]],
    ) -> SplatReport {
        self.splat_run::<true>(kernel, x0, y, rgb.len(), |i| rgb[i])
    }

    /// [`FrameState::splat_row`] of samples known to be valid for this state's layout, as
    /// [`FrameState::splat_valid_records_from`] takes them: for a caller that checked a whole
    /// pass before splatting it, each block's check of the samples is not made again (a debug
    /// build still asserts it).
    pub fn splat_valid_row(&mut self, x0: u32, y: u32, rgb: &[[f32; 3]]) -> SplatReport {
        self.splat_run::<false>(Kernel::detect(), x0, y, rgb.len(), |i| rgb[i])
    }

    /// Accumulates `records` (pixel, RGB) like [`FrameState::splat_all`], with the same state and
    /// report, a block of 16 records at a time with the arithmetic vectorized (see [`Kernel`])
    /// and the cells of a block fetched while the block before is added (for a scan-line run,
    /// on the CPUs that need it), in any order: scan order (a pass, a tile) gains most from the
    /// vector arithmetic, random order from the prefetching. Records are applied in their order,
    /// so which sample a full pixel refuses is the same too.
    pub fn splat_records(&mut self, records: &[(u32, u32, [f32; 3])]) -> SplatReport {
        self.splat_records_with(Kernel::detect(), records)
    }

    /// [`FrameState::splat_records`] with a chosen kernel, for tests and benchmarks.
    ///
    /// # Panics
    /// If the CPU cannot run `kernel` ([`Kernel::available`]).
    pub fn splat_records_with(
        &mut self,
        kernel: Kernel,
        records: &[(u32, u32, [f32; 3])],
    ) -> SplatReport {
        let mut pipe = Pipeline::new(kernel, &self.layout);
        let mut report = SplatReport::default();
        for (b, chunk) in records.chunks(BLOCK).enumerate() {
            // The records a block on, into L1 (see `RECORDS_AHEAD`).
            let ahead = records
                .get((b + RECORDS_AHEAD) * BLOCK..)
                .unwrap_or_default();
            Lines::over(&ahead[..BLOCK.min(ahead.len())]).prefetch(usize::MAX);
            self.splat_block::<true>(&mut pipe, chunk, &mut report);
        }
        pipe.flush(self);
        report
    }

    /// [`FrameState::splat_records`] of records as they come from `records`, with the same
    /// state and report: for records that are not in one slice (a batch's runs of rows that
    /// fall in this band, say), without copying them into one first. They are taken a block
    /// at a time.
    pub fn splat_records_from<I>(&mut self, records: I) -> SplatReport
    where
        I: IntoIterator<Item = (u32, u32, [f32; 3])>,
    {
        self.splat_blocks_from::<true, _>(records)
    }

    /// [`FrameState::splat_records_from`] of records whose every sample is known to be one
    /// this state's layout accepts ([`CascadeLayout::check_sample`], as [`splat_checked`]
    /// requires): for a caller that checked them as they arrived (the server checks a batch as
    /// it decodes it), each block's check of the samples is not made again (a debug build
    /// still asserts it). Records outside the state and pixels without room are handled as by
    /// [`FrameState::splat_records_from`]. An invalid sample given anyway corrupts the state
    /// (never memory).
    ///
    /// [`splat_checked`]: FrameState::splat_checked
    pub fn splat_valid_records_from<I>(&mut self, records: I) -> SplatReport
    where
        I: IntoIterator<Item = (u32, u32, [f32; 3])>,
    {
        self.splat_blocks_from::<false, _>(records)
    }

    /// [`FrameState::splat_records_from`], with each block's samples checked if `CHECK`.
    fn splat_blocks_from<const CHECK: bool, I>(&mut self, records: I) -> SplatReport
    where
        I: IntoIterator<Item = (u32, u32, [f32; 3])>,
    {
        let mut pipe = Pipeline::new(Kernel::detect(), &self.layout);
        let mut report = SplatReport::default();
        let mut records = records.into_iter();
        let mut chunk = [(0u32, 0u32, [0.0f32; 3]); BLOCK];
        loop {
            let mut len = 0;
            for (slot, record) in chunk.iter_mut().zip(records.by_ref()) {
                *slot = record;
                len += 1;
            }
            if len == 0 {
                break;
            }
            self.splat_block::<CHECK>(&mut pipe, &chunk[..len], &mut report);
        }
        pipe.flush(self);
        report
    }

    /// Splats a block of at most [`BLOCK`] records through `pipe`, adding to `report`: the
    /// vectorized path if every record is inside the state, valid (checked if `CHECK`, else
    /// known) and has room, else one by one (after what is in flight).
    #[inline(always)]
    fn splat_block<const CHECK: bool>(
        &mut self,
        pipe: &mut Pipeline,
        chunk: &[(u32, u32, [f32; 3])],
        report: &mut SplatReport,
    ) {
        let mut block = [[0.0f32; 3]; BLOCK];
        let mut pixel = [0usize; BLOCK];
        let len = chunk.len();
        let mut inside = true;
        for (i, &(x, y, rgb)) in chunk.iter().enumerate() {
            // `y - y0` wraps to a huge row for rows above the band.
            let row = y.wrapping_sub(self.y0);
            inside &= x < self.width && row < self.rows;
            // Only used if every record is inside (then this cannot wrap).
            pixel[i] = (row as usize)
                .wrapping_mul(self.width as usize)
                .wrapping_add(x as usize);
            block[i] = rgb;
        }
        let valid = pipe.tables.valid::<CHECK>(&block[..len]);
        if !(inside && valid) {
            pipe.flush(self);
            report.add(&self.splat_all(chunk.iter().copied()));
            return;
        }
        // Room for the block as if every sample in flight and in the block were in one
        // pixel: first against all samples of the state (no cell read), then, in a state
        // holding 2^32 samples or more, against the pixels' own counts.
        let others = pipe.in_flight() + len as u64;
        let room = self.samples + others <= MAX_PIXEL_SAMPLES || {
            let stride = cell_len(self.layout.cascades());
            pixel[..len].iter().all(|&p| {
                cell_spp(&self.cells[p * stride..(p + 1) * stride]) + others <= MAX_PIXEL_SAMPLES
            })
        };
        if !room {
            pipe.flush(self);
            report.add(&self.splat_all(chunk.iter().copied()));
            return;
        }
        // A block of consecutive pixels (a scan-line run, as workers send tiles and passes) is
        // pushed as a row's run is, prefetched only where the hardware's prefetchers do not
        // follow a row on their own ([`prefetch_runs`]); scattered records always are.
        let run = len > 0 && pixel[len - 1].wrapping_sub(pixel[0]) == len - 1;
        if run {
            pipe.push::<false>(self, &block[..len], |i| pixel[i]);
        } else {
            pipe.push::<true>(self, &block[..len], |i| pixel[i]);
        }
        report.accepted += len as u64;
    }

    /// Splats `rgb(i)` into pixel `(x0 + i, y)` for `i < n`, a block at a time, through a
    /// [`Pipeline`]; each block's samples are checked if `CHECK`, else known to be valid.
    fn splat_run<const CHECK: bool>(
        &mut self,
        kernel: Kernel,
        x0: u32,
        y: u32,
        n: usize,
        rgb: impl Fn(usize) -> [f32; 3],
    ) -> SplatReport {
        let one_by_one = |state: &mut Self, from: usize, to: usize| {
            state.splat_all((from..to).map(|i| (x0.saturating_add(i as u32), y, rgb(i))))
        };
        let in_frame = self.check_pixel(x0, y).is_ok() && x0 as u64 + n as u64 <= self.width as u64;
        if !in_frame {
            return one_by_one(self, 0, n);
        }
        let mut pipe = Pipeline::new(kernel, &self.layout);
        let row_start = (y - self.y0) as usize * self.width as usize;
        let mut report = SplatReport::default();
        let mut block = [[0.0f32; 3]; BLOCK];
        for from in (0..n).step_by(BLOCK) {
            let len = BLOCK.min(n - from);
            for (i, b) in block[..len].iter_mut().enumerate() {
                *b = rgb(from + i);
            }
            let x = x0 + from as u32;
            // One sample per pixel, and the pixels of a run are distinct (those in flight are
            // others): each pixel needs room for one.
            let room = self.samples + pipe.in_flight() + len as u64 <= MAX_PIXEL_SAMPLES
                || (x..x + len as u32).all(|x| self.has_room(x, y, 1));
            let valid = pipe.tables.valid::<CHECK>(&block[..len]);
            if !(room && valid) {
                pipe.flush(self);
                report.add(&one_by_one(self, from, from + len));
                continue;
            }
            let first = row_start + x as usize;
            pipe.push::<false>(self, &block[..len], |i| first + i);
            report.accepted += len as u64;
        }
        pipe.flush(self);
        report
    }

    /// Adds a block's shares to the two cascades starting at `at[i]` of each sample `i`, and
    /// prefetches the cascades at `ahead` (the next block's, if any), one beside each sample
    /// added.
    ///
    /// For records at random pixels, one prefetch per addition beats a block's prefetches in a
    /// row: 16 in a row (up to 32 cache lines, as a sample's two cascades mostly straddle two)
    /// fill the core's queue of misses, and the core stalls on them with nothing else to do (on
    /// the 2-core Zen 4 VM, 57 % of the profile samples of the loop that issued them). Spread
    /// among the additions, the additions run while the lines come in: in 10 alternated runs
    /// of `bench speed` there, the random splat took 22.2-33.7 M samples/s (median 31.8)
    /// against 18.7-24.8 (median 23.9) with the prefetches in a row.
    ///
    /// They ask for the lines into the L2 cache only (`T1`): the additions read them from there
    /// a block later. Into L1 (`T0`, as first written) the random splat took 28.6-33.7 M
    /// samples/s against 44.1-51.1 (6 alternated runs of `bench speed` on the same VM, in two
    /// sets, whose memory baseline was 56-64 M/s in each); into L2, the prefetches in a row
    /// were as fast (46.5-49.6, in the second set). The VM has no hardware counters to say
    /// why; the likely cause is that a prefetch into L1 holds one of the core's few buffers
    /// for misses to L1 until its line comes from memory.
    #[inline]
    fn add_block(&mut self, shares: &Shares, at: &[usize], ahead: &[usize]) {
        for (i, &at) in at.iter().enumerate() {
            if let Some(&next) = ahead.get(i) {
                prefetch_l2(&self.cells, next, 8);
            }
            let lo = shares.lo[i] as usize;
            let cascades = &mut self.cells[at..at + 8];
            let mut carry = 0;
            for (sum, low) in cascades[..4].iter_mut().zip(&shares.low) {
                debug_assert!(sum.checked_add(low[i]).is_some(), "cascade sum overflows");
                *sum = sum.wrapping_add(low[i]);
            }
            for c in 0..3 {
                let (sum, over) = cascades[4 + c].overflowing_add(shares.high[c][i]);
                cascades[4 + c] = sum;
                carry |= u64::from(over) << (HI_BITS * c as u32);
            }
            cascades[7] = cascades[7].wrapping_add(shares.high[3][i]);
            if carry != 0 {
                self.carry_at(lo, at, carry);
            }
        }
        for &next in ahead.iter().skip(at.len()) {
            prefetch_l2(&self.cells, next, 8);
        }
        self.samples += at.len() as u64;
    }

    /// Whether pixel `(x, y)` can take one more sample besides those of `pending` in it.
    #[cold]
    fn room_exact<'p>(&self, x: u32, y: u32, pending: impl Iterator<Item = &'p Pending>) -> bool {
        let k = self.layout.cascades();
        let pixel = (y - self.y0) as usize * self.width as usize + x as usize;
        let here = pending
            .filter(|p| (p.at - 4 * p.split.lo) / cell_len(k) == pixel)
            .count() as u64;
        self.spp(x, y) + here < MAX_PIXEL_SAMPLES
    }

    /// Accumulates a sample already known to be valid for this layout
    /// ([`CascadeLayout::check_sample`]), inside this state, in a pixel with room for it
    /// ([`FrameState::has_room`]).
    #[inline]
    pub fn splat_checked(&mut self, x: u32, y: u32, rgb: [f32; 3]) {
        let p = self.prepare(x, y, rgb);
        self.apply(&p);
    }

    /// The split of a sample and where in `cells` its lower cascade starts.
    #[inline]
    fn prepare(&self, x: u32, y: u32, rgb: [f32; 3]) -> Pending {
        let k = self.layout.cascades();
        let pixel = (y - self.y0) as usize * self.width as usize + x as usize;
        let s = [rgb[0] as f64, rgb[1] as f64, rgb[2] as f64];
        let split = self.layout.split(self.layout.luminance(s));
        Pending {
            at: pixel * cell_len(k) + 4 * split.lo,
            split,
            s,
        }
    }

    #[inline]
    fn apply(&mut self, p: &Pending) {
        let lo = p.split.lo;
        let (w_lo, count_lo) = (p.split.w_lo, p.split.count_lo);
        let cascades = &mut self.cells[p.at..p.at + 8];
        let (low, high) = cascades.split_at_mut(4);
        add_share(low, p.s, self.layout.units_per_value(lo) * w_lo, count_lo);
        let units = self.layout.units_per_value(lo + 1) * (1.0 - w_lo);
        let carry = add_share_carry(high, p.s, units, COUNT_ONE - count_lo);
        if carry != 0 {
            self.carry_at(lo, p.at, carry);
        }
        self.samples += 1;
    }

    /// Adds carries out of the top cascade's words to its high word, which follows it.
    #[cold]
    fn carry_at(&mut self, lo: usize, at: usize, carry: u64) {
        debug_assert_eq!(
            lo + 2,
            self.layout.cascades(),
            "a carry below the top cascade"
        );
        let hi = &mut self.cells[at + 8];
        *hi += carry;
        debug_assert_eq!(*hi >> (3 * HI_BITS), 0, "top cascade sum overflows 85 bits");
    }

    /// Checks that `other` is a state of a frame of the same size and cascade layout (its rows
    /// may differ).
    pub fn check_same_frame(&self, other: &FrameState) -> Result<(), MergeError> {
        self.check_same_geometry(other.width, other.height, &other.layout)
    }

    /// Adds another state of the same frame into this one, exactly.
    ///
    /// The layouts and frame sizes must match. Row ranges must be equal, or one must contain the
    /// other; then the rows they share are added (so a whole-frame state can be merged into a
    /// band, and a band into a whole-frame state). A merge that would put more than
    /// [`MAX_PIXEL_SAMPLES`] samples in a pixel is refused ([`MergeError::TooManySamples`]);
    /// within that bound addition is exact (no saturation, no wrapping), hence commutative and
    /// associative. A refused merge changes nothing.
    pub fn merge(&mut self, other: &FrameState) -> Result<(), MergeError> {
        self.check_same_frame(other)?;
        let (ours, theirs) = (self.rows(), other.rows());
        let nested = |a: &std::ops::Range<u32>, b: &std::ops::Range<u32>| {
            a.start <= b.start && b.end <= a.end
        };
        if !nested(&ours, &theirs) && !nested(&theirs, &ours) {
            return Err(MergeError::Rows { ours, theirs });
        }
        self.check_room_for(other)?;
        self.add_shared_rows(other);
        Ok(())
    }

    /// Adds the rows this state shares with `other` (possibly none), for callers that hold a
    /// frame as bands tiling it: merging a state into every band with this adds all of it,
    /// whichever bands its rows fall in. The frame (size and layout) is checked, and that no
    /// shared pixel would hold more than [`MAX_PIXEL_SAMPLES`]; a caller holding several bands
    /// can run [`FrameState::check_same_frame`] and [`FrameState::check_room_for`] on every band
    /// first, so that nothing changes unless everything fits.
    pub fn merge_overlap(&mut self, other: &FrameState) -> Result<(), MergeError> {
        self.check_same_frame(other)?;
        self.check_room_for(other)?;
        self.add_shared_rows(other);
        Ok(())
    }

    /// Checks that a state of a `width x height` frame with `layout` (any rows of it) is of the
    /// same frame as this one: [`FrameState::check_same_frame`] for a state that is not held as
    /// a `FrameState` (one being decoded).
    pub fn check_same_geometry(
        &self,
        width: u32,
        height: u32,
        layout: &CascadeLayout,
    ) -> Result<(), MergeError> {
        if (self.width, self.height) != (width, height) {
            return Err(MergeError::Size {
                ours_w: self.width,
                ours_h: self.height,
                theirs_w: width,
                theirs_h: height,
            });
        }
        if self.layout != *layout {
            return Err(MergeError::Layout {
                ours: format!("{:?}", self.layout),
                theirs: format!("{layout:?}"),
            });
        }
        Ok(())
    }

    /// Where `cells`, consecutive whole pixels of another state of this frame starting at its
    /// pixel `first` (row-major within its rows from `y0`), meet this state's rows: the cells'
    /// range in this state and in `cells`, or `None` if none of them lie here.
    fn shared_pixels(
        &self,
        y0: u32,
        first: u64,
        cells: &[u64],
    ) -> Option<(Range<usize>, Range<usize>)> {
        let stride = cell_len(self.layout.cascades());
        let w = self.width as u64;
        let start = y0 as u64 * w + first;
        let end = start + (cells.len() / stride) as u64;
        let (ours, ours_end) = (self.y0 as u64 * w, (self.y0 + self.rows) as u64 * w);
        let (a, b) = (start.max(ours), end.min(ours_end));
        if a >= b {
            return None;
        }
        let cells_of = |from: u64| (a - from) as usize * stride..(b - from) as usize * stride;
        Some((cells_of(ours), cells_of(start)))
    }

    /// [`FrameState::check_room_for`] for a piece of another state of this frame (see
    /// [`FrameState::add_pixels`]): no pixel the two share would hold more than
    /// [`MAX_PIXEL_SAMPLES`] samples.
    pub fn check_room_for_pixels(
        &self,
        y0: u32,
        first: u64,
        cells: &[u64],
    ) -> Result<(), MergeError> {
        let Some((dst, src)) = self.shared_pixels(y0, first, cells) else {
            return Ok(());
        };
        let stride = cell_len(self.layout.cascades());
        let full = self.cells[dst.clone()]
            .chunks_exact(stride)
            .zip(cells[src].chunks_exact(stride))
            .position(|(d, s)| cell_spp(d) + cell_spp(s) > MAX_PIXEL_SAMPLES);
        match full {
            None => Ok(()),
            Some(i) => {
                let pixel = dst.start / stride + i;
                Err(MergeError::TooManySamples {
                    x: (pixel % self.width as usize) as u32,
                    y: self.y0 + (pixel / self.width as usize) as u32,
                })
            }
        }
    }

    /// Adds `cells`, consecutive whole pixels of another state of this frame starting at its
    /// pixel `first` (row-major within its rows from `y0`), to the pixels of them this state
    /// holds (possibly none), exactly; returns the samples added. For a receiver adding a state
    /// piece by piece as it decodes it: the caller has checked the pieces
    /// ([`check_pixels`]), the frame ([`FrameState::check_same_geometry`]) and the room
    /// ([`FrameState::check_room_for_pixels`]) first, so that nothing changes unless all fits.
    pub fn add_pixels(&mut self, y0: u32, first: u64, cells: &[u64]) -> u64 {
        let added = self.each_shared_pixel(y0, first, cells, add_cell);
        self.samples += added;
        added
    }

    /// Takes back [`FrameState::add_pixels`] of the same `cells` (at the same `y0` and
    /// `first`): the pixels are again what they were before, bit for bit; returns the samples
    /// taken back.
    pub fn sub_pixels(&mut self, y0: u32, first: u64, cells: &[u64]) -> u64 {
        let taken = self.each_shared_pixel(y0, first, cells, sub_cell);
        self.samples -= taken;
        taken
    }

    /// Applies `op` to each pixel of `cells` that this state holds (see
    /// [`FrameState::add_pixels`]) and its cell here; returns the samples of those pixels.
    fn each_shared_pixel(
        &mut self,
        y0: u32,
        first: u64,
        cells: &[u64],
        op: impl Fn(&mut [u64], &[u64]),
    ) -> u64 {
        let Some((dst, src)) = self.shared_pixels(y0, first, cells) else {
            return 0;
        };
        let stride = cell_len(self.layout.cascades());
        let mut samples = 0;
        let dst = self.cells[dst].chunks_exact_mut(stride);
        for (d, s) in dst.zip(cells[src].chunks_exact(stride)) {
            samples += cell_spp(s);
            op(d, s);
        }
        samples
    }

    /// The rows this state shares with `other`, as cell ranges of `self` and of `other`.
    fn shared_cells(&self, other: &FrameState) -> Option<(Range<usize>, Range<usize>)> {
        let (ours, theirs) = (self.rows(), other.rows());
        let shared = ours.start.max(theirs.start)..ours.end.min(theirs.end);
        if shared.is_empty() {
            return None;
        }
        let row_len = self.width as usize * cell_len(self.layout.cascades());
        let at = |start: u32| (shared.start - start) as usize * row_len;
        let len = shared.len() * row_len;
        Some((
            at(ours.start)..at(ours.start) + len,
            at(theirs.start)..at(theirs.start) + len,
        ))
    }

    /// Checks that adding the rows `other` (of the same frame) shares with this state leaves no
    /// pixel with more than [`MAX_PIXEL_SAMPLES`] samples.
    pub fn check_room_for(&self, other: &FrameState) -> Result<(), MergeError> {
        if self.samples.saturating_add(other.samples) <= MAX_PIXEL_SAMPLES {
            return Ok(());
        }
        let Some((dst, src)) = self.shared_cells(other) else {
            return Ok(());
        };
        let stride = cell_len(self.layout.cascades());
        let first = self.cells[dst]
            .chunks_exact(stride)
            .zip(other.cells[src.clone()].chunks_exact(stride))
            .position(|(d, s)| cell_spp(d) + cell_spp(s) > MAX_PIXEL_SAMPLES);
        match first {
            None => Ok(()),
            Some(i) => {
                let pixel = src.start / stride + i;
                Err(MergeError::TooManySamples {
                    x: (pixel % self.width as usize) as u32,
                    y: other.y0 + (pixel / self.width as usize) as u32,
                })
            }
        }
    }

    fn add_shared_rows(&mut self, other: &FrameState) {
        let Some((dst, src)) = self.shared_cells(other) else {
            return;
        };
        let stride = cell_len(self.layout.cascades());
        let mut added = 0;
        let dst = self.cells[dst].chunks_exact_mut(stride);
        for (d, s) in dst.zip(other.cells[src].chunks_exact(stride)) {
            added += cell_spp(s);
            add_cell(d, s);
        }
        self.samples += added;
    }
}

impl FrameState {
    /// What this state holds beyond `earlier`, an earlier copy of it: `self - earlier`, cell by
    /// cell (the top cascade's 85-bit sums with borrow). Merging the result into `earlier` gives
    /// back `self` exactly, so a node can ship only what it accumulated since its last push.
    /// Sums never saturate and only grow, so the difference is always exact; a state holding
    /// less than `earlier` in some sum is not a later copy of it and is refused
    /// ([`MergeError::NotEarlier`]).
    pub fn delta_since(&self, earlier: &FrameState) -> Result<FrameState, MergeError> {
        self.check_same_frame(earlier)?;
        if self.rows() != earlier.rows() {
            return Err(MergeError::Rows {
                ours: self.rows(),
                theirs: earlier.rows(),
            });
        }
        let mut delta = self.clone();
        let k = self.layout.cascades();
        let top = 4 * (k - 1);
        for (i, (d, e)) in delta
            .cells
            .chunks_exact_mut(cell_len(k))
            .zip(earlier.cells.chunks_exact(cell_len(k)))
            .enumerate()
        {
            let not_earlier = || MergeError::NotEarlier {
                x: (i % self.width as usize) as u32,
                y: self.y0 + (i / self.width as usize) as u32,
            };
            let tops: [u128; 3] = std::array::from_fn(|c| top_sum(d, c));
            for (a, b) in d[..top].iter_mut().zip(&e[..top]) {
                *a = a.checked_sub(*b).ok_or_else(not_earlier)?;
            }
            d[top + 3] = d[top + 3].checked_sub(e[top + 3]).ok_or_else(not_earlier)?;
            let mut hi = 0u64;
            for (c, t) in tops.into_iter().enumerate() {
                let diff = t.checked_sub(top_sum(e, c)).ok_or_else(not_earlier)?;
                d[top + c] = diff as u64;
                hi |= ((diff >> 64) as u64) << (HI_BITS * c as u32);
            }
            d[4 * k] = hi;
        }
        delta.samples = self.samples - earlier.samples;
        Ok(delta)
    }

    /// The mean contribution of each cascade, `B_j / N` per pixel (row-major over the rows held):
    /// the raw layers summed by the plain mean, for inspecting what the resolve reweights.
    pub fn cascade_means(&self) -> Vec<Vec<[f32; 3]>> {
        let k = self.layout.cascades();
        let stride = cell_len(k);
        (0..k)
            .map(|j| {
                let unit = self.layout.unit_value(j);
                self.cells
                    .chunks_exact(stride)
                    .map(|cell| {
                        let n = cell_spp(cell);
                        if n == 0 {
                            return [0.0; 3];
                        }
                        let scale = unit / n as f64;
                        [
                            (cascade_units(cell, j, 0) * scale) as f32,
                            (cascade_units(cell, j, 1) * scale) as f32,
                            (cascade_units(cell, j, 2) * scale) as f32,
                        ]
                    })
                    .collect()
            })
            .collect()
    }
}

/// The block splat's two stages: a block's shares are computed (vectorized, [`row::shares`])
/// and the cascades they go to are prefetched, one beside each addition of the block before
/// ([`Pipeline::push`]; for a run of a row's pixels, only where [`prefetch_runs`] says so);
/// they are added when the next block has been through the first stage, so the memory of one
/// block is on its way while the one before is added.
/// Blocks are added in the order they were pushed, so the cells end up exactly as if each
/// sample were splatted one by one.
struct Pipeline {
    kernel: Kernel,
    tables: Tables,
    /// [`prefetch_runs`] on this CPU.
    prefetch_runs: bool,
    /// Two blocks: `blocks[current]` is in flight (computed, not added) if `pending`.
    blocks: [Block; 2],
    current: usize,
    pending: bool,
}

/// A computed block: its shares, and where each sample's lower cascade starts in the cells.
struct Block {
    shares: Shares,
    at: [usize; BLOCK],
    len: usize,
}

impl Pipeline {
    fn new(kernel: Kernel, layout: &CascadeLayout) -> Self {
        let block = || Block {
            shares: Shares::new(),
            at: [0; BLOCK],
            len: 0,
        };
        Pipeline {
            kernel,
            tables: Tables::new(layout),
            prefetch_runs: prefetch_runs(),
            blocks: [block(), block()],
            current: 0,
            pending: false,
        }
    }

    /// Samples computed but not yet added to the state.
    fn in_flight(&self) -> u64 {
        if self.pending {
            self.blocks[self.current].len as u64
        } else {
            0
        }
    }

    /// Computes the shares of `rgb` (valid samples, at most [`BLOCK`]) going to the cells of
    /// pixels `pixel(i)` (indices into this state's cells, each with room for its sample),
    /// then adds the block pushed before. This block's cascades are prefetched one beside each
    /// addition if `SPREAD` (records scattered over the frame: see [`FrameState::add_block`]);
    /// a run of a row's pixels (not `SPREAD`) only where [`prefetch_runs`] says so.
    #[inline]
    fn push<const SPREAD: bool>(
        &mut self,
        state: &mut FrameState,
        rgb: &[[f32; 3]],
        pixel: impl Fn(usize) -> usize,
    ) {
        let next = if self.pending {
            1 - self.current
        } else {
            self.current
        };
        let stride = cell_len(state.layout.cascades());
        let [first, second] = &mut self.blocks;
        let (b, before) = if next == 0 {
            (first, &*second)
        } else {
            (second, &*first)
        };
        row::shares(self.kernel, &self.tables, rgb, &mut b.shares);
        for i in 0..rgb.len() {
            b.at[i] = pixel(i) * stride + 4 * b.shares.lo[i] as usize;
        }
        b.len = rgb.len();
        let added = if self.pending {
            &before.at[..before.len]
        } else {
            &[]
        };
        let ahead = if SPREAD || self.prefetch_runs {
            &b.at[..b.len]
        } else {
            &[]
        };
        state.add_block(&before.shares, added, ahead);
        self.current = next;
        self.pending = true;
    }

    /// Adds the block in flight, if any.
    #[inline]
    fn flush(&mut self, state: &mut FrameState) {
        if self.pending {
            let b = &self.blocks[self.current];
            state.add_block(&b.shares, &b.at[..b.len], &[]);
            self.pending = false;
        }
    }
}

/// A sample whose split is computed and whose cascades are being fetched.
#[derive(Clone, Copy)]
struct Pending {
    at: usize,
    split: super::layout::Split,
    s: [f64; 3],
}

impl Default for Pending {
    fn default() -> Self {
        Self {
            at: 0,
            split: super::layout::Split {
                lo: 0,
                w_lo: 1.0,
                count_lo: COUNT_ONE,
            },
            s: [0.0; 3],
        }
    }
}

/// `len` zeroed words in the memory of `words` (the words of an earlier state or sums) if it
/// has room, else in new memory, zeroed by the allocator and untouched until the first sample
/// lands.
pub(crate) fn zeroed_in(mut words: Vec<u64>, len: usize) -> Vec<u64> {
    if words.capacity() >= len {
        words.clear();
        words.resize(len, 0);
        words
    } else {
        vec![0; len]
    }
}

/// Asks the CPU to start loading the words `at .. at + words` of `cells` (those inside it) into
/// its caches, every cache line they touch. Only a hint: it never faults and changes no result.
#[inline(always)]
pub(crate) fn prefetch(cells: &[u64], at: usize, words: usize) {
    Lines::of(cells, at, words).prefetch(usize::MAX);
}

/// Blocks ahead of the one being splatted whose records [`FrameState::splat_records`] asks the
/// CPU to load into L1. The prefetches of scattered records' cells keep the core's queue of
/// misses full, and its own prefetchers then fell behind on the records, read in order: in a
/// profile of a random-order splat of 8.3 M records (166 MB) on a 2-core Intel Xeon VM, the
/// loop reading a block's records was a sixth of the samples, most of them on its loads.
/// `bench speed` there, three alternated runs of each build: records in random order 32.6-32.9
/// M samples/s without, 35.1-38.2 with the records one block ahead, 34.1-36.7 two blocks ahead,
/// 33.3-35.6 four; records in scan order 46.2-48.3 without and 46.9-50.3 one block ahead. (A
/// batch the server splats was just decoded, and is still in the caches.)
const RECORDS_AHEAD: usize = 1;

/// Whether the splat prefetches the cells of a run of a row's pixels (a pass's rows, records
/// in scan order) as it does those of scattered records ([`Pipeline::push`]): everywhere but on
/// AMD's CPUs, whose prefetchers follow the run on their own.
///
/// A run walks its cells in order, a sample adding to 64 bytes of its pixel's cell (200 bytes
/// with six cascades) at an offset that depends on its brightness. On the 2-core Zen 4 VM
/// (`bench speed`, huge pages, 4 alternated runs) the hardware's prefetchers kept up with that
/// on their own, and prefetching cost a loop per sample for nothing: whole passes took 51.6-65.5
/// M samples/s with the lines asked for before the additions and 62.6-70.4 without, records in
/// scan order 52.0-64.8 and 62.4-70.5 (one prefetch beside each addition, as for scattered
/// records, was slower still: passes 49.9-62.8 against 61.9-64.8). On a 2-core Intel Xeon VM
/// (2 MiB of L2 per core, 260 MiB of L3), the additions waited on memory instead: a 1080p
/// pass's rows took 30.6-33.0 M samples/s without and 43.1-47.0 with one prefetch beside each
/// addition (a harness splatting 4 passes a round, runs of 4 rounds alternating); in `bench
/// speed` whole passes 33.7 against 44.4, records in scan order 33.5 against 43.6. Asking for
/// the lines two to four blocks ahead instead of one was no faster there (41.6-46.3).
#[inline]
fn prefetch_runs() -> bool {
    static RUNS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *RUNS.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            // The vendor string of CPUID leaf 0, in EBX, EDX, ECX. (`__cpuid` is a safe
            // function in newer Rust, an `unsafe fn` in older ones.)
            // SAFETY: every x86-64 CPU has the `cpuid` instruction and its leaf 0.
            #[allow(unused_unsafe)]
            let id = unsafe { std::arch::x86_64::__cpuid(0) };
            let vendor = [id.ebx, id.edx, id.ecx].map(u32::to_le_bytes).concat();
            vendor != b"AuthenticAMD"
        }
        // Elsewhere a prefetch is no instruction at all.
        #[cfg(not(target_arch = "x86_64"))]
        false
    })
}

/// [`prefetch`] into the L2 cache only ([`Lines::prefetch_l2`]).
#[inline(always)]
pub(crate) fn prefetch_l2(cells: &[u64], at: usize, words: usize) {
    Lines::of(cells, at, words).prefetch_l2(usize::MAX);
}

/// The cache lines of some words, to prefetch a few at a time among other work: prefetches of
/// many lines in a row fill the core's queue of misses, and the core stalls on them with
/// nothing else to do (see [`FrameState::add_block`]).
pub(crate) struct Lines {
    /// The first word; never dereferenced, only handed to the prefetch instruction.
    first: *const i8,
    /// Offset in bytes of the next line to ask for, from `first`.
    line: isize,
    /// Bytes from `first` to the end of the last word.
    end: isize,
}

impl Lines {
    /// The lines of the words `at .. at + words` of `cells` (those inside it).
    #[inline(always)]
    pub(crate) fn of(cells: &[u64], at: usize, words: usize) -> Self {
        let ahead = cells.get(at..).unwrap_or_default();
        Self::over(&ahead[..words.min(ahead.len())])
    }

    /// The lines of `items`.
    #[inline(always)]
    pub(crate) fn over<T>(items: &[T]) -> Self {
        // Each line's start, from the line of the first item to the line of the last byte (none
        // for no items): a counted loop (an iterator over the words' chunks was a fifth of the
        // resolve's support step).
        let first = items.as_ptr().cast::<i8>();
        let end = size_of_val(items) as isize;
        let line = if end == 0 {
            0
        } else {
            -((first as usize & 63) as isize)
        };
        Self { first, line, end }
    }

    /// Lines not yet asked for (by which the AVX2 support step and the row pass spread their
    /// prefetches).
    #[inline(always)]
    pub(crate) fn left(&self) -> usize {
        ((self.end - self.line).max(0) as usize).div_ceil(64)
    }

    /// [`Lines::prefetch`] into the L2 cache only (`T1`), for lines read a while later: the
    /// cells of the next block of random records ([`FrameState::add_block`]) and of the rows a
    /// resolve reads next (its row pass, `AHEAD_ROWS`), where asking for them into L1 was
    /// slower.
    #[inline(always)]
    pub(crate) fn prefetch_l2(&mut self, n: usize) {
        self.ask::<false>(n);
    }

    /// Asks the CPU to start loading the next `n` lines (or those left); a no-op where the
    /// instruction is not used (outside x86-64), without even walking the lines.
    #[inline(always)]
    pub(crate) fn prefetch(&mut self, n: usize) {
        self.ask::<true>(n);
    }

    /// The next `n` lines into L1 (`T0`) if `L1`, else into L2 only (`T1`).
    #[inline(always)]
    fn ask<const L1: bool>(&mut self, n: usize) {
        #[cfg(target_arch = "x86_64")]
        for _ in 0..n {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0, _MM_HINT_T1};
            if self.line >= self.end {
                break;
            }
            let line = self.first.wrapping_offset(self.line);
            // SAFETY: a prefetch never faults (the address is a line the words touch).
            unsafe {
                if L1 {
                    _mm_prefetch::<_MM_HINT_T0>(line)
                } else {
                    _mm_prefetch::<_MM_HINT_T1>(line)
                }
            }
            self.line += 64;
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (n, self.first, self.line, self.end);
    }
}

/// Adds a share to a cascade below the top: cannot overflow within the bounds (debug-asserted).
#[inline]
fn add_share(cascade: &mut [u64], s: [f64; 3], units: f64, count: u64) {
    for c in 0..3 {
        let v = to_fixed(s[c], units);
        debug_assert!(cascade[c].checked_add(v).is_some(), "cascade sum overflows");
        cascade[c] = cascade[c].wrapping_add(v);
    }
    debug_assert!(cascade[3].checked_add(count).is_some(), "count overflows");
    cascade[3] = cascade[3].wrapping_add(count);
}

/// Adds a share to a cascade that may be the top one; returns the carries out of its r, g, b
/// words, placed as they add to the high word (zero below the top cascade).
#[inline]
fn add_share_carry(cascade: &mut [u64], s: [f64; 3], units: f64, count: u64) -> u64 {
    let mut carry = 0;
    for c in 0..3 {
        let (sum, over) = cascade[c].overflowing_add(to_fixed(s[c], units));
        cascade[c] = sum;
        carry |= u64::from(over) << (HI_BITS * c as u32);
    }
    debug_assert!(cascade[3].checked_add(count).is_some(), "count overflows");
    cascade[3] = cascade[3].wrapping_add(count);
    carry
}

#[cfg(test)]
impl FrameState {
    /// A `w x h` frame of the default layout with `spp` samples of `rgb` in every pixel (for the
    /// crate's tests).
    pub(crate) fn flat(w: u32, h: u32, spp: u32, rgb: [f32; 3]) -> FrameState {
        let mut state = FrameState::new(w, h, CascadeLayout::with_defaults());
        for y in 0..h {
            for x in 0..w {
                for _ in 0..spp {
                    state.splat(x, y, rgb).unwrap();
                }
            }
        }
        state
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Subtracting a cell takes back adding it, bit for bit, carries into the high word
    /// included.
    #[test]
    fn sub_cell_takes_back_add_cell_exactly() {
        let k = 3;
        let top = 4 * (k - 1);
        let mut dst: Vec<u64> = (0..cell_len(k) as u64).map(|i| i * 1000 + 7).collect();
        let src: Vec<u64> = (0..cell_len(k) as u64).map(|i| i * 31 + 1).collect();
        // The top cascade's r and b sums carry into their high fields; g does not.
        dst[top] = u64::MAX - 5;
        dst[top + 2] = u64::MAX;
        let before = dst.clone();
        add_cell(&mut dst, &src);
        assert_eq!(
            dst[4 * k],
            before[4 * k] + src[4 * k] + 1 + (1 << (2 * HI_BITS))
        );
        sub_cell(&mut dst, &src);
        assert_eq!(dst, before);
    }
    use crate::layout::REC709_LUMINANCE;

    fn layout() -> CascadeLayout {
        CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap()
    }

    /// Value held in cascade `j` of pixel (x, y), converted back from fixed point.
    fn cascade(state: &FrameState, x: u32, y: u32, j: usize) -> [f64; 4] {
        let k = state.layout().cascades();
        let cell = &state.row(y)[x as usize * cell_len(k)..];
        let u = state.layout().unit_value(j);
        let c = COUNT_ONE as f64;
        [
            cascade_units(cell, j, 0) * u,
            cascade_units(cell, j, 1) * u,
            cascade_units(cell, j, 2) * u,
            cell[4 * j + 3] as f64 / c,
        ]
    }

    #[test]
    fn a_split_sample_keeps_its_energy_and_one_count_in_fixed_point() {
        let mut state = FrameState::new(1, 1, layout());
        let rgb = [3.0f32, 20.0, 0.5]; // L = 14.9, between c1 = 8 and c2 = 64
        state.splat(0, 0, rgb).unwrap();
        let (lo, hi) = (cascade(&state, 0, 0, 1), cascade(&state, 0, 0, 2));
        for c in 0..3 {
            let sum = lo[c] + hi[c];
            // One fixed-point unit of each cascade at most.
            assert!(
                (sum - rgb[c] as f64).abs() < 64.0 * 2.0f64.powi(1 - FRAC_BITS as i32),
                "{c}: {sum}"
            );
        }
        assert_eq!(
            state.row(0)[4 + 3] + state.row(0)[2 * 4 + 3],
            COUNT_ONE,
            "counts of the two shares must add to exactly one sample"
        );
        assert_eq!(state.spp(0, 0), 1);
    }

    #[test]
    fn zero_tiny_and_huge_samples_are_counted_and_kept() {
        let mut state = FrameState::new(1, 1, layout());
        state.splat(0, 0, [0.0, 0.0, 0.0]).unwrap();
        state.splat(0, 0, [-0.0, 1e-7, 0.0]).unwrap();
        state.splat(0, 0, [1e9, 1e9, 1e9]).unwrap();
        assert_eq!(state.spp(0, 0), 3);
        let c0 = cascade(&state, 0, 0, 0);
        assert_eq!(c0[3], 2.0, "two dim samples, two full counts in cascade 0");
        // Half a unit of cascade 0 (c0 = 1) at most.
        assert!((c0[1] - 1e-7).abs() <= 0.5 / COUNT_ONE as f64);
        let top = cascade(&state, 0, 0, 5);
        assert_eq!(
            cascade(&state, 0, 0, 4),
            [0.0; 4],
            "nothing of it leaks below the top"
        );
        assert_eq!(top[3], 1.0);
        assert!(
            (top[0] - 1e9).abs() / 1e9 < 1e-9,
            "huge sample keeps its energy: {}",
            top[0]
        );
    }

    #[test]
    fn invalid_samples_are_rejected_counted_and_change_nothing() {
        let mut state = FrameState::new(2, 2, layout());
        let before = state.clone();
        let report = state.splat_all([
            (0, 0, [f32::NAN, 0.0, 0.0]),
            (0, 0, [f32::INFINITY, 0.0, 0.0]),
            (1, 1, [0.0, f32::NEG_INFINITY, 0.0]),
            (1, 0, [1.0, -1e-6, 0.0]),
            (2, 0, [1.0, 1.0, 1.0]),
            (0, 2, [1.0, 1.0, 1.0]),
        ]);
        assert_eq!(
            report,
            SplatReport {
                accepted: 0,
                non_finite: 3,
                negative: 1,
                out_of_frame: 2,
                ..SplatReport::default()
            }
        );
        assert_eq!(state, before);
    }

    #[test]
    fn bands_tile_the_frame_and_merge_into_a_whole_state() {
        let layout = layout();
        let mut whole = FrameState::new(3, 7, layout.clone());
        let mut bands = FrameState::bands(3, 7, 3, &layout);
        assert_eq!(
            bands.iter().map(|b| b.rows()).collect::<Vec<_>>(),
            vec![0..2, 2..4, 4..7]
        );
        assert!(
            matches!(
                bands[0].splat(0, 2, [1.0; 3]),
                Err(SampleError::OutOfFrame { .. })
            ),
            "a band refuses rows it does not hold"
        );
        for y in 0..7 {
            for x in 0..3 {
                let rgb = [x as f32 * 10.0, y as f32, 0.25];
                whole.splat(x, y, rgb).unwrap();
                let band = bands.iter_mut().find(|b| b.rows().contains(&y)).unwrap();
                band.splat(x, y, rgb).unwrap();
            }
        }
        let mut assembled = FrameState::new(3, 7, layout.clone());
        for band in &bands {
            assembled.merge(band).unwrap();
        }
        assert_eq!(assembled, whole);
        // And back: a whole state merged into empty bands gives the bands.
        for band in &bands {
            let mut empty = FrameState::band(3, 7, band.rows(), layout.clone());
            empty.merge(&whole).unwrap();
            assert_eq!(&empty, band);
        }
    }

    #[test]
    fn merge_refuses_mismatches_and_changes_nothing() {
        let mut a = FrameState::new(4, 4, layout());
        a.splat(1, 1, [1.0, 2.0, 3.0]).unwrap();
        let before = a.clone();
        let other_layout = CascadeLayout::new(8.0, 6, 0.5, REC709_LUMINANCE).unwrap();
        assert!(matches!(
            a.merge(&FrameState::new(4, 4, other_layout)),
            Err(MergeError::Layout { .. })
        ));
        assert!(matches!(
            a.merge(&FrameState::new(4, 5, layout())),
            Err(MergeError::Size { .. })
        ));
        let mut band = FrameState::band(4, 4, 0..2, layout());
        assert!(matches!(
            band.merge(&FrameState::band(4, 4, 1..3, layout())),
            Err(MergeError::Rows { .. })
        ));
        assert_eq!(a, before);
    }

    /// A band made in the cells of another state is the empty band, whatever those held, in
    /// the same memory; cells too small for it are replaced; a state copied into used cells is
    /// the state.
    #[test]
    fn a_band_in_used_cells_is_empty() {
        let used_again = |band: &FrameState| {
            let mut copy = band.clone();
            copy.splat_row(1, 4, &[[0.5, 7.0, 1.0]; 2]);
            copy
        };
        let mut used = FrameState::band(4, 8, 2..6, layout());
        for y in 2..6 {
            used.splat_row(0, y, &[[3.0, 2.0, 900.0]; 4]);
        }
        let cells = used.into_cells();
        let pointer = cells.as_ptr();
        let band = FrameState::band_in(4, 8, 3..6, layout(), cells);
        assert_eq!(band, FrameState::band(4, 8, 3..6, layout()));
        assert_eq!(band.cells().as_ptr(), pointer, "the same memory");
        let want = used_again(&band);
        let copy = want.clone_in(band.into_cells());
        assert_eq!(copy, want, "a copy in used cells is the state");
        assert_eq!(copy.cells().as_ptr(), pointer, "in the same memory");
        let small = FrameState::band_in(4, 8, 0..8, layout(), copy.into_cells());
        assert_eq!(small, FrameState::band(4, 8, 0..8, layout()));
        let mut lengths = Vec::new();
        let bands = FrameState::bands_in(4, 8, 3, &layout(), |len| {
            lengths.push(len);
            vec![7; len]
        });
        assert_eq!(bands, FrameState::bands(4, 8, 3, &layout()));
        assert_eq!(
            lengths,
            bands.iter().map(|b| b.cells().len()).collect::<Vec<_>>()
        );
    }

    #[test]
    fn from_cells_refuses_cells_that_do_not_fit() {
        let err = FrameState::from_cells(2, 2, 0..2, layout(), vec![0; 10]).unwrap_err();
        assert!(
            matches!(err, CellsError::Shape(ShapeError { expected: 100, .. })),
            "{err}"
        );
        let state = FrameState::new(2, 2, layout());
        let back = FrameState::from_cells(2, 2, 0..2, layout(), state.cells().to_vec()).unwrap();
        assert_eq!(back, state);
    }

    fn largest() -> (CascadeLayout, f32) {
        let layout = CascadeLayout::with_defaults();
        let m = layout.max_component();
        assert_eq!(
            m,
            4096.0 * 2f64.powi(26),
            "c_{{K-1}} * 2^26 with the defaults"
        );
        assert_eq!(m as f32 as f64, m);
        (layout, m as f32)
    }

    fn mean(state: &FrameState) -> [f32; 3] {
        state.resolve(&crate::ResolveParams::off()).mean[0]
    }

    #[test]
    fn the_largest_component_is_exact_and_anything_brighter_is_refused_by_name() {
        let (layout, m) = largest();
        let mut state = FrameState::new(1, 1, layout.clone());
        state.splat(0, 0, [m, m, m]).unwrap();
        assert_eq!(mean(&state), [m; 3]);
        let mut state = FrameState::new(1, 1, layout.clone());
        state.splat(0, 0, [m, 0.0, 1.0]).unwrap();
        assert_eq!(mean(&state), [m, 0.0, 1.0]);

        let above = f32::from_bits(m.to_bits() + 1);
        let before = state.clone();
        for bad in [above, 1e14, 3e38, f32::MAX] {
            let err = state.splat(0, 0, [0.5, bad, 0.5]).unwrap_err();
            assert_eq!(
                err,
                SampleError::TooBright {
                    value: bad,
                    max: layout.max_component()
                }
            );
            assert!(
                err.to_string()
                    .contains("exceeds this frame's largest representable sample"),
                "{err}"
            );
        }
        let report = state.splat_all([(0, 0, [1e14, 0.0, 0.0]), (0, 0, [3e38, 3e38, 3e38])]);
        assert_eq!(report.too_bright, 2);
        assert_eq!(report.rejected(), 2);
        assert_eq!(state, before, "nothing of a refused sample is kept");
    }

    #[test]
    fn twenty_thousand_samples_of_1e9_keep_their_mean() {
        let mut state = FrameState::new(1, 1, CascadeLayout::with_defaults());
        let report = state.splat_all((0..20_000).map(|_| (0, 0, [1e9f32, 1e9, 1e9])));
        assert_eq!(report.accepted, 20_000);
        assert_eq!(state.total_samples(), 20_000);
        assert_eq!(mean(&state), [1e9; 3]);
        let top = state.cascade_means().pop().unwrap()[0];
        assert_eq!(top, [1e9; 3]);
    }

    /// 2^32 samples of the largest component in one pixel: the top sums reach 2^84 units and the
    /// mean is still exact; one more sample or merge is refused and changes nothing.
    #[test]
    fn a_pixel_holds_2_pow_32_of_the_largest_samples_and_no_more() {
        let (layout, m) = largest();
        let mut state = FrameState::new(2, 1, layout);
        state.splat(0, 0, [m, m, m]).unwrap();
        state.splat(1, 0, [1.0, 2.0, 3.0]).unwrap();
        for _ in 0..32 {
            let copy = state.clone();
            state.merge(&copy).unwrap();
        }
        assert_eq!(state.spp(0, 0), MAX_PIXEL_SAMPLES);
        assert_eq!(state.total_samples(), 2 * MAX_PIXEL_SAMPLES);
        let cell = &state.cells()[..cell_len(6)];
        for c in 0..3 {
            assert_eq!(top_sum(cell, c), 1u128 << 84);
        }
        assert_eq!(mean(&state), [m; 3]);
        let r = state.resolve(&crate::ResolveParams::off());
        assert_eq!(r.mean[1], [1.0, 2.0, 3.0]);
        assert_eq!(r.spp, [MAX_PIXEL_SAMPLES; 2]);

        let before = state.clone();
        let copy = state.clone();
        assert_eq!(
            state.merge(&copy),
            Err(MergeError::TooManySamples { x: 0, y: 0 })
        );
        let mut one = FrameState::new(2, 1, state.layout().clone());
        one.splat(1, 0, [0.0; 3]).unwrap();
        assert_eq!(
            state.merge(&one),
            Err(MergeError::TooManySamples { x: 1, y: 0 })
        );
        assert_eq!(
            state.splat(0, 0, [0.0; 3]),
            Err(SampleError::PixelFull { x: 0, y: 0 })
        );
        let report = state.splat_all([(1, 0, [0.0; 3]), (0, 0, [1.0; 3])]);
        assert_eq!(report.pixel_full, 2);
        assert_eq!(state, before);
    }

    /// Near the limit, `splat_all` counts the samples of a pixel within one chunk exactly.
    #[test]
    fn splat_all_fills_a_pixel_exactly_to_the_limit() {
        let mut state = FrameState::new(2, 1, CascadeLayout::with_defaults());
        state.splat(0, 0, [1.0; 3]).unwrap();
        for _ in 0..31 {
            let copy = state.clone();
            state.merge(&copy).unwrap();
        }
        // 2^31 samples; bring pixel 0 to 2^32 - 3 with a state of 2^31 - 3.
        let mut rest = FrameState::new(2, 1, CascadeLayout::with_defaults());
        rest.splat(0, 0, [1.0; 3]).unwrap();
        for _ in 0..30 {
            let copy = rest.clone();
            rest.merge(&copy).unwrap();
        }
        let mut three = FrameState::new(2, 1, CascadeLayout::with_defaults());
        three.splat_all([(0, 0, [1.0; 3]); 3]);
        let rest = rest.delta_since(&FrameState::new(2, 1, CascadeLayout::with_defaults()));
        let rest = rest.unwrap();
        let mut full = rest.clone();
        full.merge(&rest).unwrap();
        let short = full.delta_since(&three).unwrap();
        state.merge(&short).unwrap();
        assert_eq!(state.spp(0, 0), MAX_PIXEL_SAMPLES - 3);
        let report = state.splat_all([
            (0, 0, [2.0; 3]),
            (1, 0, [2.0; 3]),
            (0, 0, [2.0; 3]),
            (0, 0, [2.0; 3]),
            (0, 0, [2.0; 3]),
        ]);
        assert_eq!((report.accepted, report.pixel_full), (4, 1));
        assert_eq!(state.spp(0, 0), MAX_PIXEL_SAMPLES);
        assert_eq!(state.spp(1, 0), 1);
    }

    /// Splatting across 2^64 units carries into the high word exactly as merging does, and a
    /// delta across a carry (with a borrow) merges back to the original.
    #[test]
    fn carries_in_the_top_cascade_survive_deltas_and_merges() {
        let (layout, m) = largest();
        let mut splatted = FrameState::new(1, 1, layout.clone());
        for _ in 0..4097 {
            splatted.splat(0, 0, [m, m / 2.0, 0.0]).unwrap();
        }
        let mut merged = FrameState::new(1, 1, layout.clone());
        merged.splat(0, 0, [m, m / 2.0, 0.0]).unwrap();
        let one = merged.clone();
        for _ in 0..12 {
            let copy = merged.clone();
            merged.merge(&copy).unwrap();
        }
        merged.merge(&one).unwrap();
        assert_eq!(splatted, merged, "2^12 + 1 samples, by splats or by merges");
        let cell = splatted.cells();
        assert_eq!(top_sum(cell, 0), (1u128 << 64) + (1 << 52));
        assert_eq!(mean(&splatted), [m, m / 2.0, 0.0]);

        // v = 2^37 + 3 * 2^14 is 2^51 + 3 * 2^28 units: 2^12 of them are 2^63 + 3 * 2^40,
        // 2^13 are 2^64 + 3 * 2^41, whose low word is smaller than the earlier one's.
        let v = (2f64.powi(37) + 3.0 * 2f64.powi(14)) as f32;
        let mut earlier = FrameState::new(1, 2, layout.clone());
        earlier.splat(0, 0, [v, 1.0, v]).unwrap();
        earlier.splat(0, 1, [0.25, 8.0, 100.0]).unwrap();
        for _ in 0..12 {
            let copy = earlier.clone();
            earlier.merge(&copy).unwrap();
        }
        let mut later = earlier.clone();
        let copy = later.clone();
        later.merge(&copy).unwrap();
        later.splat(0, 0, [3.0, 1e9, 5e10]).unwrap();
        assert_eq!(
            top_sum(&later.cells()[..cell_len(6)], 0),
            (1 << 64) + 3 * (1 << 41) + 3 * (1 << 14)
        );
        let delta = later.delta_since(&earlier).unwrap();
        assert_eq!(
            delta.total_samples(),
            later.total_samples() - earlier.total_samples()
        );
        let mut back = earlier.clone();
        back.merge(&delta).unwrap();
        assert_eq!(back, later);
        assert_eq!(
            earlier.delta_since(&later).unwrap_err(),
            MergeError::NotEarlier { x: 0, y: 0 }
        );
    }

    #[test]
    fn from_cells_refuses_cells_no_samples_could_make() {
        let layout = layout();
        let mut state = FrameState::new(2, 1, layout.clone());
        state.splat(1, 0, [5.0, 50.0, 5000.0]).unwrap();
        let k = 6;
        let stride = cell_len(k);
        let bad = |f: &dyn Fn(&mut [u64])| {
            let mut cells = state.cells().to_vec();
            f(&mut cells[stride..]);
            FrameState::from_cells(2, 1, 0..1, layout.clone(), cells).unwrap_err()
        };
        // A cascade without samples in that pixel, given energy.
        let empty = (0..k - 1)
            .find(|&j| state.cells()[stride + 4 * j + 3] == 0)
            .expect("a cascade the sample left empty");
        for err in [
            bad(&|c| c[4 * empty + 1] = 7),
            bad(&|c| c[3] += 1),
            bad(&|c| c[4 * k] = 1 << 63),
            bad(&|c| c[0] = u64::MAX),
            bad(&|c| c[4 * (k - 1)] = TOP_SHARE_MAX + 1),
        ] {
            assert!(
                matches!(err, CellsError::Invalid { x: 1, y: 0, .. }),
                "{err}"
            );
        }
        let back = FrameState::from_cells(2, 1, 0..1, layout, state.cells().to_vec()).unwrap();
        assert_eq!(back.total_samples(), 1);
        assert_eq!(back, state);
    }

    /// Cells of the previous format (2^-32 units, 4K words per pixel) convert to the state the
    /// same samples give now, up to rounding of each sum; a saturated sum is refused by pixel.
    #[test]
    fn previous_format_cells_convert_and_saturated_ones_are_refused() {
        let layout = layout();
        let k = 6;
        let mut state = FrameState::new(3, 1, layout.clone());
        for (x, rgb) in [
            (0, [0.5f32, 0.25, 1.0]),
            (1, [10.0, 20.0, 30.0]),
            (1, [1e5, 1e5, 1e5]),
        ] {
            state.splat(x, 0, rgb).unwrap();
        }
        // The old cells of these samples: every value and count 64 times finer, plus some
        // sub-unit remainder that rounds away; counts still add to N * 2^32 exactly.
        let mut old = Vec::new();
        for cell in state.cells().chunks_exact(cell_len(k)) {
            let mut counts = 0;
            for j in 0..k {
                for c in 0..3 {
                    old.push((cascade_units(cell, j, c) as u64) * 64 + 31 - c as u64);
                }
                old.push(cell[4 * j + 3] * 64);
                counts += cell[4 * j + 3] * 64;
            }
            assert_eq!(counts % (1 << 32), 0);
        }
        // Move count units between the two cascades of pixel 1's split: the rounding of each
        // no longer adds up by itself, the residual goes to the larger count.
        let split: Vec<usize> = (0..k).filter(|&j| old[4 * k + 4 * j + 3] != 0).collect();
        old[4 * k + 4 * split[0] + 3] += 40;
        old[4 * k + 4 * split[1] + 3] -= 40;
        let back = FrameState::from_frac32_cells(3, 1, 0..1, layout.clone(), &old).unwrap();
        assert_eq!(back.total_samples(), 3);
        assert_eq!((back.spp(0, 0), back.spp(1, 0), back.spp(2, 0)), (1, 2, 0));
        for j in 0..k {
            for c in 0..3 {
                for p in 0..3 {
                    let at = p * cell_len(k);
                    assert_eq!(
                        cascade_units(&back.cells()[at..], j, c),
                        cascade_units(&state.cells()[at..], j, c),
                        "pixel {p} cascade {j} channel {c}"
                    );
                }
            }
        }
        let mut saturated = old.clone();
        saturated[4 * k + 4 * (k - 1)] = u64::MAX;
        let err = FrameState::from_frac32_cells(3, 1, 0..1, layout.clone(), &saturated);
        assert!(
            matches!(err, Err(CellsError::Invalid { x: 1, y: 0, .. })),
            "{err:?}"
        );
        let err = FrameState::from_frac32_cells(3, 1, 0..1, layout, &old[1..]);
        assert!(matches!(err, Err(CellsError::Shape(_))), "{err:?}");
    }
}
