//! Frame states to and from their wire form ([`StateDump`]), for exporting, importing, pushing
//! and the offline `splatd merge`.
//!
//! The dump is the state's fixed-point cells verbatim, so export followed by import is exact, and
//! importing into a frame that has samples of its own adds the two exactly.

use splatd_proto::api::AovSpec;
use splatd_proto::{Applied, Origin, Runs, StateDump, StateError, StateWrite};

use splatd_estimator::{
    add_aov_pixel, add_cell, aov_words, cell_spp, check_aov_pixel, check_pixels, AovCellsError,
    AovSums, CascadeLayout, CellsError, FrameState, MergeError, ParamError, FRAC_BITS,
    MAX_PIXEL_SAMPLES,
};

/// What [`Importable::pieces`] hands each piece to: the number of the piece's first pixel and
/// its cells.
pub type PieceVisitor<'a> = dyn FnMut(u64, &[u64]) -> Result<(), PieceError> + 'a;

/// Why a visit of an importing state's pieces stopped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PieceError {
    /// The state's cells cannot be used: a pixel holds what no checked samples could have made,
    /// or a pixel in a run holds nothing.
    #[error(transparent)]
    Invalid(#[from] ImportError),
    /// The piece does not fit the frame it is being added to.
    #[error(transparent)]
    Merge(#[from] MergeError),
}

impl From<CellsError> for PieceError {
    fn from(e: CellsError) -> PieceError {
        PieceError::Invalid(e.into())
    }
}

impl From<StateError> for PieceError {
    fn from(e: StateError) -> PieceError {
        PieceError::Invalid(e.into())
    }
}

/// A state that a server frame's import adds to the frame: held whole ([`FrameState`], whose
/// cells are valid by construction) or as the runs of a body being decoded ([`Decoded`]), whose
/// cells the import checks as it adds them.
pub trait Importable: Sync {
    /// Width, height and cascade layout of its frame.
    fn geometry(&self) -> (u32, u32, &CascadeLayout);
    /// The first row it holds: its pixels are numbered row-major from 0 there.
    fn first_row(&self) -> u32;
    /// The pixels of the rows it holds, empty ones included.
    fn pixels(&self) -> u64;
    /// Whether its cells are known to be valid ([`check_pixels`]) already: if not, whoever adds
    /// them checks each piece first.
    fn checked(&self) -> bool;
    /// Hands the cells of its pixels numbered in `within` to `f` in order, in pieces of
    /// consecutive whole pixels with the number of each piece's first pixel; stops at `f`'s
    /// first error, or at a piece that is malformed (a pixel in a run that holds nothing), and
    /// returns it. Handing out the same pixels again gives the same pieces. Threads may each
    /// visit a share of the pixels.
    fn pieces_in(
        &self,
        within: std::ops::Range<u64>,
        f: &mut PieceVisitor<'_>,
    ) -> Result<(), PieceError>;
    /// [`Importable::pieces_in`] for all its pixels.
    fn pieces(&self, f: &mut PieceVisitor<'_>) -> Result<(), PieceError> {
        self.pieces_in(0..u64::MAX, f)
    }
}

impl Importable for FrameState {
    fn geometry(&self) -> (u32, u32, &CascadeLayout) {
        (self.width(), self.height(), self.layout())
    }

    fn first_row(&self) -> u32 {
        self.rows().start
    }

    fn pixels(&self) -> u64 {
        self.width() as u64 * self.rows().len() as u64
    }

    fn checked(&self) -> bool {
        true
    }

    fn pieces_in(
        &self,
        within: std::ops::Range<u64>,
        f: &mut PieceVisitor<'_>,
    ) -> Result<(), PieceError> {
        let pixels = Importable::pixels(self);
        let stride = 4 * self.layout().cascades() + 1;
        let (start, end) = (within.start.min(pixels), within.end.min(pixels));
        if start >= end {
            return Ok(());
        }
        f(
            start,
            &self.cells()[start as usize * stride..end as usize * stride],
        )
    }
}

/// A frame's AOVs as a state carries them: the declarations and the sums of the rows held
/// (when writing, sums of any rows that include them: a band is written with its rows of the
/// frame's sums, which are not copied).
pub type Aovs<'a> = Option<(&'a [AovSpec], &'a AovSums)>;

/// A state's AOVs, owned: `None` for a state without AOVs.
pub type OwnedAovs = Option<(Vec<AovSpec>, AovSums)>;

/// An imported state that cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ImportError {
    /// Its cascade parameters make no sense.
    #[error("state has invalid cascade parameters: {0}")]
    Params(#[from] ParamError),
    /// It was written with another fixed-point precision.
    #[error("state uses {found} fractional bits; this build uses {FRAC_BITS}")]
    FracBits {
        /// Bits in the state.
        found: u32,
    },
    /// Its cells do not fit its geometry, or hold what no checked samples could have made.
    #[error(transparent)]
    Cells(#[from] CellsError),
    /// Its AOV words do not fit its geometry, or hold what no checked values could have made.
    #[error(transparent)]
    Aovs(#[from] AovCellsError),
    /// Its run list is malformed (a pixel in a run holds nothing).
    #[error(transparent)]
    State(#[from] StateError),
}

/// The wire form of a state (a whole frame or a band) holding the samples of `batches`.
pub fn dump(
    state: &FrameState,
    aovs: Aovs<'_>,
    frame: &str,
    origin: Option<Origin>,
    batches: Vec<Applied>,
) -> StateDump {
    with_aovs(
        StateDump {
            cells: state.cells().to_vec(),
            batches,
            ..header(state, state.rows(), frame, origin)
        },
        aovs,
    )
}

/// `dump` with the AOVs (declarations and words) set.
fn with_aovs(dump: StateDump, aovs: Aovs<'_>) -> StateDump {
    let aov_cells = aov_words_of_rows(&dump, aovs).to_vec();
    StateDump {
        aov_cells,
        ..with_aov_specs(dump, aovs)
    }
}

/// `dump` with the AOV declarations set, not their words (which are written from where they
/// lie: [`aov_words_of_rows`]).
fn with_aov_specs(dump: StateDump, aovs: Aovs<'_>) -> StateDump {
    match aovs {
        None => dump,
        Some((specs, _)) => StateDump {
            aovs: specs.to_vec(),
            ..dump
        },
    }
}

/// The AOV words of `dump`'s rows in `aovs`' sums (none without AOVs).
fn aov_words_of_rows<'a>(dump: &StateDump, aovs: Aovs<'a>) -> &'a [u64] {
    aovs.map_or(&[], |(_, sums)| {
        sums.rows_words(dump.rows_start..dump.rows_end)
    })
}

/// Takes the AOVs out of a decoded state: `None` for a state without AOVs (version 2, or a
/// frame that declares none), else its declarations and checked sums.
pub fn take_aovs(dump: &mut StateDump) -> Result<Option<(Vec<AovSpec>, AovSums)>, ImportError> {
    let specs = std::mem::take(&mut dump.aovs);
    let words = std::mem::take(&mut dump.aov_cells);
    aov_sums(dump, specs, words)
}

/// The checked AOV sums of a state of `dump`'s rows from its declarations and words: `None`
/// when they declare no channel.
fn aov_sums(
    dump: &StateDump,
    specs: Vec<AovSpec>,
    words: Vec<u64>,
) -> Result<Option<(Vec<AovSpec>, AovSums)>, ImportError> {
    let channels: usize = specs.iter().map(|a| a.channels.len()).sum();
    if channels == 0 {
        return Ok(None);
    }
    let sums = AovSums::from_words(dump.width, dump.rows_start..dump.rows_end, channels, words)?;
    Ok(Some((specs, sums)))
}

/// Streams the wire form of a state (a whole frame or a band) to `out` without copying its cells,
/// naming no applied batches (a snapshot band: the snapshot keeps the frame's batches itself).
pub fn write(
    state: &FrameState,
    aovs: Aovs<'_>,
    frame: &str,
    origin: Option<Origin>,
    out: &mut impl std::io::Write,
) -> std::io::Result<()> {
    let dump = with_aov_specs(header(state, state.rows(), frame, origin), aovs);
    dump.write_with_parts(&[state.cells()], &[aov_words_of_rows(&dump, aovs)], out)
}

/// The length of what [`write()`] writes, without encoding it.
pub fn encoded_len(state: &FrameState, aovs: Aovs<'_>, frame: &str) -> u64 {
    let dump = with_aov_specs(header(state, state.rows(), frame, None), aovs);
    dump.encoded_len_with_parts(&[state.cells()], &[aov_words_of_rows(&dump, aovs)])
}

/// Streams the wire form of a whole frame held as row bands (top to bottom, tiling the frame) and
/// holding the samples of `batches` to `out`: the same bytes as [`dump`] of the merged frame,
/// without merging or copying the bands. `out` is handed the long stretches of cells by the
/// number of their band in `bands` ([`StateWrite::write_cells`]), so that a writer holding
/// the bands can send those from where they lie.
///
/// # Panics
/// If `bands` is empty.
pub fn write_bands(
    bands: &[&FrameState],
    aovs: Aovs<'_>,
    frame: &str,
    origin: Option<Origin>,
    batches: Vec<Applied>,
    out: &mut impl StateWrite,
) -> std::io::Result<()> {
    let first = &bands[0];
    debug_assert!(
        bands
            .windows(2)
            .all(|w| w[0].rows().end == w[1].rows().start),
        "bands tile the frame in order"
    );
    let rows = first.rows().start..bands[bands.len() - 1].rows().end;
    let parts: Vec<&[u64]> = bands.iter().map(|b| b.cells()).collect();
    let dump = with_aov_specs(
        StateDump {
            batches,
            ..header(first, rows, frame, origin)
        },
        aovs,
    );
    dump.write_with_parts_to(&parts, &[aov_words_of_rows(&dump, aovs)], out)
}

/// A dump without cells describing `state`'s frame and layout for `rows`.
fn header(
    state: &FrameState,
    rows: std::ops::Range<u32>,
    frame: &str,
    origin: Option<Origin>,
) -> StateDump {
    let layout = state.layout();
    StateDump {
        frame: frame.to_owned(),
        width: state.width(),
        height: state.height(),
        rows_start: rows.start,
        rows_end: rows.end,
        base: layout.base(),
        cascades: layout.cascades() as u32,
        lowest_scale: layout.lowest_scale(),
        luminance: layout.luminance_weights(),
        frac_bits: FRAC_BITS,
        origin,
        cells: Vec::new(),
        batches: Vec::new(),
        aovs: Vec::new(),
        aov_cells: Vec::new(),
    }
}

/// A state from its wire form, validated like a newly created frame.
pub fn load(dump: StateDump) -> Result<FrameState, ImportError> {
    if dump.frac_bits != FRAC_BITS {
        return Err(ImportError::FracBits {
            found: dump.frac_bits,
        });
    }
    let layout = CascadeLayout::new(dump.base, dump.cascades, dump.lowest_scale, dump.luminance)?;
    Ok(FrameState::from_cells(
        dump.width,
        dump.height,
        dump.rows_start..dump.rows_end,
        layout,
        dump.cells,
    )?)
}

/// A state body decoded for import without expanding its cells ([`StateDump::decode_runs`]):
/// its header, its checked AOVs, and its runs read in place from the body. Its cells are not
/// checked yet: importing it checks each piece of them as it adds it straight into the frame's
/// bands (the server frame's `import`, which takes back what it added if a later piece is
/// refused), so the body is read once, and the only full-size buffer of an import is the
/// body itself (and the AOV sums of a state that has AOVs).
pub struct Decoded<'a> {
    /// The header (no cells, no AOVs).
    pub dump: StateDump,
    /// The state's AOV declarations and checked sums, `None` for a state without AOVs.
    pub aovs: Option<(Vec<AovSpec>, AovSums)>,
    layout: CascadeLayout,
    runs: Runs<'a>,
}

impl Decoded<'_> {
    /// The AOVs, as a server frame's `import` takes them.
    pub fn aovs(&self) -> Aovs<'_> {
        self.aovs
            .as_ref()
            .map(|(specs, sums)| (specs.as_slice(), sums))
    }
}

/// Pixels below which a share of the pixels is not worth a thread of its own.
const MIN_SHARE_PIXELS: u64 = 1 << 14;

/// `pixels` cut into at most `threads` consecutive shares of at least `MIN_SHARE_PIXELS`
/// (one share when there are fewer).
pub fn shares(pixels: u64, threads: usize) -> Vec<std::ops::Range<u64>> {
    let n = (threads as u64).min(pixels / MIN_SHARE_PIXELS).max(1);
    let step = pixels.div_ceil(n);
    (0..n)
        .map(|i| (i * step).min(pixels)..((i + 1) * step).min(pixels))
        .collect()
}

/// Checks a state decoded without its cells ([`StateDump::decode_runs`]) like [`load`] and
/// [`take_aovs`] check a whole one, except its cells: the precision, the cascade parameters
/// and the AOV words (the AOV runs, expanded into the sums of the rows held). Its cells are
/// checked by whoever adds them ([`Importable::checked`] is false): a pass over them here would
/// read the whole body once more.
pub fn load_runs<'a>(
    mut dump: StateDump,
    runs: Runs<'a>,
    aov_runs: Option<Runs<'_>>,
) -> Result<Decoded<'a>, ImportError> {
    if dump.frac_bits != FRAC_BITS {
        return Err(ImportError::FracBits {
            found: dump.frac_bits,
        });
    }
    let layout = CascadeLayout::new(dump.base, dump.cascades, dump.lowest_scale, dump.luminance)?;
    let words = aov_runs.map(|r| r.expand()).transpose()?;
    let specs = std::mem::take(&mut dump.aovs);
    let aovs = aov_sums(&dump, specs, words.unwrap_or_default())?;
    Ok(Decoded {
        dump,
        aovs,
        layout,
        runs,
    })
}

impl Importable for Decoded<'_> {
    fn geometry(&self) -> (u32, u32, &CascadeLayout) {
        (self.dump.width, self.dump.height, &self.layout)
    }

    fn first_row(&self) -> u32 {
        self.dump.rows_start
    }

    fn pixels(&self) -> u64 {
        self.runs.pixels()
    }

    fn checked(&self) -> bool {
        false
    }

    fn pieces_in(
        &self,
        within: std::ops::Range<u64>,
        f: &mut PieceVisitor<'_>,
    ) -> Result<(), PieceError> {
        let within = within.start.min(self.runs.pixels())..within.end.min(self.runs.pixels());
        self.runs.try_for_each_in(within, f)
    }
}

/// A state held as only the pixels that hold something, for the offline tools (`splatd merge`,
/// `splatd resolve`): a state file declares its frame's size, and its runs list only the pixels
/// with samples, so a file of 100 bytes may declare 8192x8192 pixels with 16 cascades (35 GB of
/// cells). What this takes is bounded by the files' real size (their cells, plus 8 bytes per
/// pixel held), never by the frame they declare; a merge of such states is as small as they are.
/// The server's imports do not use it: they add a body's runs straight into the frame's bands.
#[derive(Debug, Clone)]
pub struct SparseState {
    /// The header, AOV declarations and applied batches (no cells, no AOV words).
    pub dump: StateDump,
    layout: CascadeLayout,
    cells: SparsePixels,
    aovs: SparsePixels,
    samples: u64,
}

/// Pixels that hold something, in increasing order: their numbers (row-major over the whole
/// frame, so states of other rows line up) and their words, `stride` per pixel.
#[derive(Debug, Clone, Default)]
struct SparsePixels {
    stride: usize,
    at: Vec<u64>,
    words: Vec<u64>,
}

impl SparsePixels {
    fn new(stride: usize) -> SparsePixels {
        SparsePixels {
            stride,
            ..SparsePixels::default()
        }
    }

    fn push(&mut self, at: u64, words: &[u64]) {
        self.at.push(at);
        self.words.extend_from_slice(words);
    }

    fn iter(&self) -> impl Iterator<Item = (u64, &[u64])> + '_ {
        self.at
            .iter()
            .copied()
            .zip(self.words.chunks_exact(self.stride.max(1)))
    }

    /// `self + other` over the pixels of `keep`: pixels in both are added with `add` (which may
    /// refuse), the others taken as they are.
    fn merged<E>(
        &self,
        other: &SparsePixels,
        keep: std::ops::Range<u64>,
        mut add: impl FnMut(u64, &mut [u64], &[u64]) -> Result<(), E>,
    ) -> Result<SparsePixels, E> {
        let mut out = SparsePixels::new(self.stride);
        let (mut a, mut b) = (self.iter().peekable(), other.iter().peekable());
        loop {
            let take_a = match (a.peek(), b.peek()) {
                (None, None) => break,
                (Some(_), None) => true,
                (None, Some(_)) => false,
                (Some(&(pa, _)), Some(&(pb, _))) => {
                    if pa == pb {
                        let (p, wa) = a.next().expect("peeked");
                        let (_, wb) = b.next().expect("peeked");
                        out.push(p, wa);
                        let at = out.words.len() - self.stride;
                        add(p, &mut out.words[at..], wb)?;
                        continue;
                    }
                    pa < pb
                }
            };
            let (p, w) = if take_a { a.next() } else { b.next() }.expect("peeked");
            if keep.contains(&p) {
                out.push(p, w);
            }
        }
        Ok(out)
    }
}

/// Why a state could not be expanded into a whole frame ([`SparseState::into_dense`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DenseError {
    /// The frame it declares does not fit in memory.
    #[error(
        "the state declares a {width}x{height} frame (rows {rows_start}..{rows_end}) with \
         {what}: {bytes} bytes, which could not be allocated (the state holds {held} pixels \
         with samples)"
    )]
    TooLarge {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
        /// First row held.
        rows_start: u32,
        /// End of the rows held.
        rows_end: u32,
        /// What was to be allocated (`6 cascades`, `7 AOV channels`).
        what: String,
        /// Bytes it takes.
        bytes: u128,
        /// Pixels the state holds.
        held: usize,
    },
    /// Its cells or AOV words do not make a state.
    #[error(transparent)]
    Import(#[from] ImportError),
}

/// Why two states could not be added ([`SparseState::merge`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SparseMergeError {
    /// Their frames differ, or a pixel would hold too many samples.
    #[error(transparent)]
    Cells(#[from] MergeError),
    /// A pixel's AOVs would hold too many samples.
    #[error(transparent)]
    Aovs(#[from] AovCellsError),
    /// They declare different AOVs.
    #[error("it has AOVs {theirs}, but the states before it have {ours}")]
    AovMismatch {
        /// Ours, described.
        ours: String,
        /// Theirs, described.
        theirs: String,
    },
}

impl SparseState {
    /// Decodes and checks a state body like [`StateDump::decode`], [`load`] and [`take_aovs`]
    /// do, holding only the pixels its runs list.
    pub fn decode(bytes: &[u8]) -> Result<SparseState, ImportError> {
        let (mut dump, runs, aov_runs) = StateDump::decode_runs(bytes, u64::MAX)?;
        if dump.frac_bits != FRAC_BITS {
            return Err(ImportError::FracBits {
                found: dump.frac_bits,
            });
        }
        let layout =
            CascadeLayout::new(dump.base, dump.cascades, dump.lowest_scale, dump.luminance)?;
        let w = dump.width as u64;
        let y0 = dump.rows_start;
        let origin = y0 as u64 * w;
        let mut cells = SparsePixels::new(runs.cell_len());
        let mut samples = 0;
        runs.try_for_each(|first, piece| {
            samples += check_pixels(dump.width, y0, layout.cascades(), first, piece)?;
            for (i, cell) in piece.chunks_exact(cells.stride).enumerate() {
                cells.push(origin + first + i as u64, cell);
            }
            Ok::<(), ImportError>(())
        })?;
        if dump.aovs.iter().all(|a| a.channels.is_empty()) {
            dump.aovs.clear();
        }
        let mut aovs = SparsePixels::new(aov_words(dump.aov_channels()));
        if let Some(aov_runs) = aov_runs {
            aov_runs.try_for_each(|first, piece| {
                for (i, px) in piece.chunks_exact(aovs.stride).enumerate() {
                    let pixel = first + i as u64;
                    check_aov_pixel(px).map_err(|reason| AovCellsError::Invalid {
                        x: (pixel % w) as u32,
                        y: y0 + (pixel / w) as u32,
                        reason,
                    })?;
                    aovs.push(origin + pixel, px);
                }
                Ok::<(), ImportError>(())
            })?;
        }
        Ok(SparseState {
            dump,
            layout,
            cells,
            aovs,
            samples,
        })
    }

    /// Samples held.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// The AOV declarations (empty: none).
    pub fn aov_specs(&self) -> &[AovSpec] {
        &self.dump.aovs
    }

    /// Adds another state of the same frame, exactly, like [`FrameState::merge`] (rows equal or
    /// nested; the rows this one holds are kept) and [`AovSums::merge_overlap`] (a state
    /// without AOVs adds none; if this one has none, it takes the other's).
    pub fn merge(&mut self, other: &SparseState) -> Result<(), SparseMergeError> {
        let d = &self.dump;
        let (ours_w, ours_h) = (d.width, d.height);
        if (ours_w, ours_h) != (other.dump.width, other.dump.height) {
            return Err(MergeError::Size {
                ours_w,
                ours_h,
                theirs_w: other.dump.width,
                theirs_h: other.dump.height,
            }
            .into());
        }
        if self.layout != other.layout {
            return Err(MergeError::Layout {
                ours: format!("{:?}", self.layout),
                theirs: format!("{:?}", other.layout),
            }
            .into());
        }
        let (ours, theirs) = (self.rows(), other.rows());
        let nested = |a: &std::ops::Range<u32>, b: &std::ops::Range<u32>| {
            a.start <= b.start && b.end <= a.end
        };
        if !nested(&ours, &theirs) && !nested(&theirs, &ours) {
            return Err(MergeError::Rows { ours, theirs }.into());
        }
        if !other.dump.aovs.is_empty()
            && !self.dump.aovs.is_empty()
            && self.dump.aovs != other.dump.aovs
        {
            return Err(SparseMergeError::AovMismatch {
                ours: crate::names::describe_aovs(&self.dump.aovs),
                theirs: crate::names::describe_aovs(&other.dump.aovs),
            });
        }
        let w = ours_w as u64;
        let keep = ours.start as u64 * w..ours.end as u64 * w;
        let position = |p: u64| ((p % w) as u32, (p / w) as u32);
        let cells = self
            .cells
            .merged(&other.cells, keep.clone(), |p, sum, cell| {
                if cell_spp(sum) + cell_spp(cell) > MAX_PIXEL_SAMPLES {
                    let (x, y) = position(p);
                    return Err(MergeError::TooManySamples { x, y });
                }
                add_cell(sum, cell);
                Ok(())
            })?;
        let aovs = match (self.dump.aovs.is_empty(), other.dump.aovs.is_empty()) {
            (_, true) => None,
            (true, false) => Some(SparsePixels::new(other.aovs.stride).merged(
                &other.aovs,
                keep,
                |_, _, _| Ok::<(), AovCellsError>(()),
            )?),
            (false, false) => Some(self.aovs.merged(&other.aovs, keep, |p, sum, px| {
                if sum[0] + px[0] > MAX_PIXEL_SAMPLES {
                    let (x, y) = position(p);
                    return Err(AovCellsError::Full { x, y });
                }
                add_aov_pixel(sum, px);
                Ok(())
            })?),
        };
        if let Some(aovs) = aovs {
            if self.dump.aovs.is_empty() {
                self.dump.aovs = other.dump.aovs.clone();
            }
            self.aovs = aovs;
        }
        self.samples = cells.iter().map(|(_, cell)| cell_spp(cell)).sum();
        self.cells = cells;
        Ok(())
    }

    fn rows(&self) -> std::ops::Range<u32> {
        self.dump.rows_start..self.dump.rows_end
    }

    /// The state's wire form, naming `batches` as applied: the bytes [`dump`] gives for the
    /// same state held whole.
    pub fn encode(&self, batches: Vec<Applied>) -> Vec<u8> {
        let origin = self.dump.rows_start as u64 * self.dump.width as u64;
        let header = StateDump {
            batches,
            origin: None,
            ..header_of(&self.dump)
        };
        header.encode_sparse(
            self.cells.iter().map(|(p, c)| (p - origin, c)),
            self.aovs.iter().map(|(p, c)| (p - origin, c)),
        )
    }

    /// The whole frame of rows held, for resolving: the one step whose memory follows the size
    /// the state declares (the image it resolves into is that size too). The buffers are
    /// reserved first, so a frame that does not fit is an error naming its size, not an abort.
    pub fn into_dense(self) -> Result<(FrameState, OwnedAovs), DenseError> {
        let d = &self.dump;
        let pixels = d.width as u128 * (d.rows_end - d.rows_start) as u128;
        let origin = d.rows_start as u64 * d.width as u64;
        let too_large = |what: String, words: u128| DenseError::TooLarge {
            width: d.width,
            height: d.height,
            rows_start: d.rows_start,
            rows_end: d.rows_end,
            what,
            bytes: words * 8,
            held: self.cells.at.len(),
        };
        let expand = |sparse: &SparsePixels, what: String| -> Result<Vec<u64>, DenseError> {
            let words = pixels * sparse.stride as u128;
            let mut dense = Vec::new();
            usize::try_from(words)
                .ok()
                .and_then(|n| dense.try_reserve_exact(n).ok().map(|()| n))
                .ok_or_else(|| too_large(what, words))?;
            dense.resize(words as usize, 0);
            for (p, w) in sparse.iter() {
                let at = (p - origin) as usize * sparse.stride;
                dense[at..at + sparse.stride].copy_from_slice(w);
            }
            Ok(dense)
        };
        let cells = expand(&self.cells, format!("{} cascades", d.cascades))?;
        let aovs = if d.aovs.is_empty() {
            None
        } else {
            let words = expand(&self.aovs, format!("{} AOV channels", d.aov_channels()))?;
            let sums = AovSums::from_words(d.width, self.rows(), d.aov_channels(), words)
                .map_err(ImportError::from)?;
            Some((d.aovs.clone(), sums))
        };
        let state =
            FrameState::from_cells(d.width, d.height, self.rows(), self.layout.clone(), cells)
                .map_err(ImportError::from)?;
        Ok((state, aovs))
    }
}

/// A copy of `dump`'s header, declarations and batches, without cells or AOV words.
fn header_of(dump: &StateDump) -> StateDump {
    StateDump {
        frame: dump.frame.clone(),
        origin: dump.origin.clone(),
        batches: dump.batches.clone(),
        aovs: dump.aovs.clone(),
        cells: Vec::new(),
        aov_cells: Vec::new(),
        ..*dump
    }
}

/// Fractional bits of state format version 1.
const V1_FRAC_BITS: u32 = 32;

/// A state from its version 1 wire form ([`StateDump::decode_v1`]: 32 fractional bits, `4K`
/// cells per pixel), converted to the current cells
/// ([`FrameState::from_frac32_cells`]). A sum that saturated cannot be converted and is refused,
/// naming its pixel.
pub fn load_v1(dump: StateDump) -> Result<FrameState, ImportError> {
    if dump.frac_bits != V1_FRAC_BITS {
        return Err(ImportError::FracBits {
            found: dump.frac_bits,
        });
    }
    let layout = CascadeLayout::new(dump.base, dump.cascades, dump.lowest_scale, dump.luminance)?;
    Ok(FrameState::from_frac32_cells(
        dump.width,
        dump.height,
        dump.rows_start..dump.rows_end,
        layout,
        &dump.cells,
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use splatd_scenes::synth::FireflyScene;

    #[test]
    fn streaming_writes_the_same_bytes_as_dump() {
        let scene = FireflyScene::new(5, 4, 1);
        let mut state = FrameState::new(5, 4, CascadeLayout::with_defaults());
        state.splat_all(scene.pass(0));
        let origin = Some(Origin {
            node: "n".into(),
            seq: 2,
        });
        let mut streamed = Vec::new();
        write(&state, None, "f", origin.clone(), &mut streamed).unwrap();
        assert_eq!(streamed, dump(&state, None, "f", origin, vec![]).encode());
    }

    #[test]
    fn bands_stream_as_the_whole_frame() {
        let scene = FireflyScene::new(7, 20, 4);
        let layout = CascadeLayout::with_defaults();
        let mut whole = FrameState::new(7, 20, layout.clone());
        let mut bands = FrameState::bands(7, 20, 3, &layout);
        for pass in 0..3 {
            whole.splat_all(scene.pass(pass));
            for band in &mut bands {
                let rows = band.rows();
                band.splat_all(scene.pass(pass).filter(|s| rows.contains(&s.1)));
            }
        }
        let mut streamed = Vec::new();
        let bands: Vec<&FrameState> = bands.iter().collect();
        write_bands(&bands, None, "f", None, vec![], &mut streamed).unwrap();
        assert_eq!(streamed, dump(&whole, None, "f", None, vec![]).encode());
    }

    #[test]
    fn export_then_import_is_exact() {
        let scene = FireflyScene::new(9, 7, 3);
        let mut state = FrameState::new(9, 7, CascadeLayout::with_defaults());
        for pass in 0..20 {
            state.splat_all(scene.pass(pass));
        }
        let bytes = dump(&state, None, "f", None, vec![]).encode();
        let back = load(StateDump::decode(&bytes, u64::MAX).unwrap()).unwrap();
        assert_eq!(back, state);
    }

    /// The offline merge of sparse states is the dense merge, byte for byte: pixels in one
    /// state or both, a band nested in the frame (its rows added, the frame's kept), and the
    /// whole frame rebuilt for resolving.
    #[test]
    fn sparse_merge_writes_the_bytes_of_the_dense_merge() {
        let scene = FireflyScene::new(7, 6, 2);
        let layout = CascadeLayout::with_defaults();
        let mut a = FrameState::new(7, 6, layout.clone());
        a.splat_all(scene.pass(0).filter(|s| s.0 % 3 != 0));
        let mut b = FrameState::band(7, 6, 2..5, layout.clone());
        b.splat_all(
            scene
                .pass(1)
                .filter(|s| (2..5).contains(&s.1) && s.0 % 2 == 0),
        );
        let mut c = FrameState::new(7, 6, layout);
        c.splat_all(scene.pass(2).filter(|s| s.1 == 5));
        let bytes = |s: &FrameState| dump(s, None, "f", None, vec![]).encode();
        let mut sparse = SparseState::decode(&bytes(&a)).unwrap();
        for other in [&b, &c] {
            sparse
                .merge(&SparseState::decode(&bytes(other)).unwrap())
                .unwrap();
        }
        let mut dense = a.clone();
        dense.merge(&b).unwrap();
        dense.merge(&c).unwrap();
        assert_eq!(sparse.encode(vec![]), bytes(&dense));
        assert_eq!(sparse.samples(), dense.total_samples());
        let (back, aovs) = sparse.into_dense().unwrap();
        assert_eq!(back, dense);
        assert!(aovs.is_none());

        // A band takes only its own rows of a whole frame.
        let mut band = SparseState::decode(&bytes(&b)).unwrap();
        band.merge(&SparseState::decode(&bytes(&a)).unwrap())
            .unwrap();
        let mut dense = b.clone();
        dense.merge(&a).unwrap();
        assert_eq!(band.encode(vec![]), bytes(&dense));
    }

    #[test]
    fn nonsense_states_are_refused_by_name() {
        let state = FrameState::new(2, 2, CascadeLayout::with_defaults());
        let mut d = dump(&state, None, "f", None, vec![]);
        d.frac_bits = 16;
        assert_eq!(load(d).unwrap_err(), ImportError::FracBits { found: 16 });
        let mut d = dump(&state, None, "f", None, vec![]);
        d.base = 1.0;
        assert!(matches!(load(d), Err(ImportError::Params(p)) if p.name == "base"));
    }
}
