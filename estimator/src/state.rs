//! Per-frame accumulation state: `K` cascade sums and counts plus the exact sample count of every
//! pixel, all in fixed point so that accumulation and merging are exact and order-independent.
//!
//! Storage is pixel-major: a pixel's cell is `K` groups of `[r, g, b, count]`, `4K` `u64`s or
//! `32K` bytes. The pixel's sample count `N_p` is not stored: every sample adds exactly
//! [`COUNT_ONE`] to the counts of its cascades (the two shares of a split add to it by
//! construction), so `N_p = (Σ_j count_j) >> FRAC_BITS`, exactly. Leaving it out saves 8 bytes per
//! pixel and, more importantly, a cache line per splat: a splat touches only the 64 contiguous
//! bytes of cascades `lo` and `lo + 1` of one cell. Resolve reads the cells row by row.
//!
//! A state may hold a horizontal band of a frame (rows `y0 .. y0 + rows`), so that a service
//! can shard a frame across locks; a state that holds the whole frame is just the band starting
//! at row 0 with all rows.

use super::layout::{to_fixed, CascadeLayout, COUNT_ONE, FRAC_BITS};

/// Why a sample was not accumulated. Nothing of a rejected sample reaches the state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
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

/// Checks a sample's value (not its pixel): finite and non-negative. `-0.0` is accepted as zero.
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
}

impl SplatReport {
    /// Samples not accumulated.
    pub fn rejected(&self) -> u64 {
        self.non_finite + self.negative + self.out_of_frame
    }

    fn count(&mut self, result: Result<(), SampleError>) {
        match result {
            Ok(()) => self.accepted += 1,
            Err(SampleError::NonFinite) => self.non_finite += 1,
            Err(SampleError::Negative) => self.negative += 1,
            Err(SampleError::OutOfFrame { .. }) => self.out_of_frame += 1,
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
#[derive(Clone, PartialEq)]
pub struct FrameState {
    width: u32,
    height: u32,
    y0: u32,
    rows: u32,
    layout: CascadeLayout,
    cells: Vec<u64>,
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

/// `u64`s per pixel for `k` cascades: `[r, g, b, count]` per cascade.
pub const fn cell_len(k: usize) -> usize {
    4 * k
}

/// Samples in a pixel from its cell: the exact sum of its fixed-point counts.
#[inline]
pub fn cell_spp(cell: &[u64]) -> u64 {
    let units = cell
        .iter()
        .skip(3)
        .step_by(4)
        .fold(0u64, |a, &c| a.saturating_add(c));
    units >> FRAC_BITS
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
        assert!(
            rows.start <= rows.end && rows.end <= height,
            "band {rows:?} outside a frame of height {height}"
        );
        let len = width as usize * rows.len() * cell_len(layout.cascades());
        Self {
            width,
            height,
            y0: rows.start,
            rows: rows.end - rows.start,
            layout,
            cells: vec![0; len],
        }
    }

    /// Splits a frame into `n` bands of (nearly) equal height that tile it top to bottom.
    pub fn bands(width: u32, height: u32, n: u32, layout: &CascadeLayout) -> Vec<Self> {
        let n = n.clamp(1, height.max(1));
        (0..n)
            .map(|i| {
                let start = (height as u64 * i as u64 / n as u64) as u32;
                let end = (height as u64 * (i as u64 + 1) / n as u64) as u32;
                Self::band(width, height, start..end, layout.clone())
            })
            .collect()
    }

    /// Rebuilds a state from exported cells, checking that they fit the geometry.
    pub fn from_cells(
        width: u32,
        height: u32,
        rows: std::ops::Range<u32>,
        layout: CascadeLayout,
        cells: Vec<u64>,
    ) -> Result<Self, ShapeError> {
        let expected = width as usize * rows.len() * cell_len(layout.cascades());
        if cells.len() != expected || rows.end > height {
            return Err(ShapeError {
                found: cells.len(),
                expected,
                width,
                rows: rows.end.saturating_sub(rows.start),
                cascades: layout.cascades(),
            });
        }
        Ok(Self {
            width,
            height,
            y0: rows.start,
            rows: rows.end - rows.start,
            layout,
            cells,
        })
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

    /// Samples accumulated in all pixels of this state.
    pub fn total_samples(&self) -> u64 {
        let stride = cell_len(self.layout.cascades());
        self.cells
            .chunks_exact(stride)
            .fold(0u64, |a, cell| a.saturating_add(cell_spp(cell)))
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
        check_sample(rgb)?;
        self.splat_checked(x, y, rgb);
        Ok(())
    }

    /// Accumulates every valid sample of `samples` (pixel, RGB) and counts the rest.
    ///
    /// This is the fast path for batches. Random pixels of a large frame miss every cache, so the
    /// work is done in chunks: first the splits of a chunk are computed and the cascades they
    /// will touch are prefetched, then the adds are applied, by which time the memory is on its
    /// way. The result is identical to splatting the samples one by one.
    pub fn splat_all<I>(&mut self, samples: I) -> SplatReport
    where
        I: IntoIterator<Item = (u32, u32, [f32; 3])>,
    {
        const CHUNK: usize = 32;
        let mut report = SplatReport::default();
        let mut pending = [Pending::default(); CHUNK];
        let mut samples = samples.into_iter().peekable();
        while samples.peek().is_some() {
            let mut n = 0;
            for (x, y, rgb) in samples.by_ref() {
                let checked = self.check_pixel(x, y).and_then(|()| check_sample(rgb));
                report.count(checked);
                if checked.is_ok() {
                    pending[n] = self.prepare(x, y, rgb);
                    prefetch(&self.cells, pending[n].at);
                    n += 1;
                    if n == CHUNK {
                        break;
                    }
                }
            }
            for p in &pending[..n] {
                self.apply(p);
            }
        }
        report
    }

    /// Accumulates a sample already known to be valid and inside this state.
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
        add_share(high, p.s, units, COUNT_ONE - count_lo);
    }

    /// Checks that `other` is a state of a frame of the same size and cascade layout (its rows
    /// may differ).
    pub fn check_same_frame(&self, other: &FrameState) -> Result<(), MergeError> {
        if (self.width, self.height) != (other.width, other.height) {
            return Err(MergeError::Size {
                ours_w: self.width,
                ours_h: self.height,
                theirs_w: other.width,
                theirs_h: other.height,
            });
        }
        if self.layout != other.layout {
            return Err(MergeError::Layout {
                ours: format!("{:?}", self.layout),
                theirs: format!("{:?}", other.layout),
            });
        }
        Ok(())
    }

    /// Adds another state of the same frame into this one, exactly.
    ///
    /// The layouts and frame sizes must match. Row ranges must be equal, or one must contain the
    /// other; then the rows they share are added (so a whole-frame state can be merged into a
    /// band, and a band into a whole-frame state). Addition saturates instead of wrapping, which
    /// keeps it commutative and associative on the unsigned cells.
    pub fn merge(&mut self, other: &FrameState) -> Result<(), MergeError> {
        self.check_same_frame(other)?;
        let (ours, theirs) = (self.rows(), other.rows());
        let nested = |a: &std::ops::Range<u32>, b: &std::ops::Range<u32>| {
            a.start <= b.start && b.end <= a.end
        };
        if !nested(&ours, &theirs) && !nested(&theirs, &ours) {
            return Err(MergeError::Rows { ours, theirs });
        }
        self.add_shared_rows(other);
        Ok(())
    }

    /// Adds the rows this state shares with `other` (possibly none), for callers that hold a
    /// frame as bands tiling it: merging a state into every band with this adds all of it,
    /// whichever bands its rows fall in. Only the frame (size and layout) is checked, so once
    /// [`FrameState::check_same_frame`] passed for one band it cannot fail for another: a
    /// caller can check before it changes anything.
    pub fn merge_overlap(&mut self, other: &FrameState) -> Result<(), MergeError> {
        self.check_same_frame(other)?;
        self.add_shared_rows(other);
        Ok(())
    }

    fn add_shared_rows(&mut self, other: &FrameState) {
        let (ours, theirs) = (self.rows(), other.rows());
        let shared = ours.start.max(theirs.start)..ours.end.min(theirs.end);
        if shared.is_empty() {
            return;
        }
        let row_len = self.width as usize * cell_len(self.layout.cascades());
        let at = |start: u32| (shared.start - start) as usize * row_len;
        let len = shared.len() * row_len;
        let dst = &mut self.cells[at(ours.start)..at(ours.start) + len];
        let src = &other.cells[at(theirs.start)..at(theirs.start) + len];
        for (d, s) in dst.iter_mut().zip(src) {
            *d = d.saturating_add(*s);
        }
    }
}

impl FrameState {
    /// What this state holds beyond `earlier`, an earlier copy of it: `self - earlier`, cell by
    /// cell. Merging the result into `earlier` gives back `self` exactly, so a node can ship only
    /// what it accumulated since its last push. Cells only grow, so the difference is exact as
    /// long as no cell saturated (2^64 units: more than 4 billion samples in one pixel).
    pub fn delta_since(&self, earlier: &FrameState) -> Result<FrameState, MergeError> {
        self.check_same_frame(earlier)?;
        if self.rows() != earlier.rows() {
            return Err(MergeError::Rows {
                ours: self.rows(),
                theirs: earlier.rows(),
            });
        }
        let mut delta = self.clone();
        for (d, e) in delta.cells.iter_mut().zip(&earlier.cells) {
            *d = d.saturating_sub(*e);
        }
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
                        let c = &cell[4 * j..4 * j + 3];
                        [
                            (c[0] as f64 * scale) as f32,
                            (c[1] as f64 * scale) as f32,
                            (c[2] as f64 * scale) as f32,
                        ]
                    })
                    .collect()
            })
            .collect()
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

/// Asks the CPU to start loading the two cascades at `cells[at..at + 8]`. Only a hint: it never
/// faults and does not change the result.
#[inline(always)]
fn prefetch(cells: &[u64], at: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let first = cells[at..].as_ptr();
        let last = cells[at + 7..].as_ptr();
        // SAFETY: prefetch is a hint that never dereferences in a way that can fault; both
        // pointers are in bounds of `cells` anyway.
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>(first.cast());
            _mm_prefetch::<_MM_HINT_T0>(last.cast());
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (cells, at);
}

#[inline]
fn add_share(cascade: &mut [u64], s: [f64; 3], units: f64, count: u64) {
    cascade[0] = cascade[0].saturating_add(to_fixed(s[0], units));
    cascade[1] = cascade[1].saturating_add(to_fixed(s[1], units));
    cascade[2] = cascade[2].saturating_add(to_fixed(s[2], units));
    cascade[3] = cascade[3].saturating_add(count);
}

#[cfg(test)]
mod tests {
    use super::*;
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
            cell[4 * j] as f64 * u,
            cell[4 * j + 1] as f64 * u,
            cell[4 * j + 2] as f64 * u,
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
                (sum - rgb[c] as f64).abs() < 64.0 * 2.0f64.powi(-31),
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
        assert!((c0[1] - 1e-7).abs() < 1e-9);
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
                out_of_frame: 2
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

    #[test]
    fn from_cells_refuses_cells_that_do_not_fit() {
        let err = FrameState::from_cells(2, 2, 0..2, layout(), vec![0; 10]).unwrap_err();
        assert_eq!(err.expected, 2 * 2 * 24);
        let state = FrameState::new(2, 2, layout());
        let back = FrameState::from_cells(2, 2, 0..2, layout(), state.cells().to_vec()).unwrap();
        assert_eq!(back, state);
    }
}
