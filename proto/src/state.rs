//! The accumulated state of a frame (or of a band of its rows), as exported by one splatd node and
//! imported by another: `GET`/`POST /v1/frames/{id}/state`, `splatd merge`, push deltas.
//!
//! A state is lossless: the server's fixed-point cascade sums and counts, verbatim. Two states
//! of the same frame (same size and cascade layout) merge by adding them cell by cell, which is
//! what makes a farm of nodes aggregate exactly, as if one server had seen every sample.
//!
//! # Byte layout (version 3)
//!
//! Little-endian throughout. After a 6-byte preamble (magic `b"SPLS"`, `u16` version), the header
//! is bincode 2 with `legacy()` configuration (fixed-width integers, `u64` lengths; the same
//! pinned configuration as batches) of:
//!
//! | field | type | meaning |
//! | --- | --- | --- |
//! | `frame` | string (`u64` length + UTF-8) | frame id |
//! | `width`, `height` | `u32`, `u32` | frame size |
//! | `rows_start`, `rows_end` | `u32`, `u32` | rows held (`0..height` for a whole frame) |
//! | `base` | `f64` | cascade base `b` |
//! | `cascades` | `u32` | cascade count `K` |
//! | `lowest_scale` | `f64` | `c0` |
//! | `luminance` | `3 x f64` | brightness weights |
//! | `frac_bits` | `u32` | fixed-point fractional bits (26) |
//! | `origin` | `u8` tag (0 none, 1 some) + string + `u64` | push delta id: sending node, sequence |
//!
//! **Cells.** Each pixel has `K` groups of `[r, g, b, count]` and then one *high word*: `4K + 1`
//! `u64` cells. A group holds the RGB sums of cascade `j` in units of `c_j * 2^-frac_bits`
//! (`c_j = lowest_scale * base^j`) and its fractional sample count in units of `2^-frac_bits`.
//! The high word holds the bits above 64 of the top cascade's (`j = K - 1`) r, g and b sums,
//! 21 bits each (r in bits 0..21, g in 21..42, b in 42..63; bit 63 is 0): its sums are
//! `hi * 2^64 + lo`. A pixel's sample count is the sum of its counts divided by `2^frac_bits`
//! (exact: every sample adds exactly one), at most `2^32`. A receiver checks every pixel against
//! these bounds (see `splatd_estimator`'s state module).
//!
//! Pixels are numbered row-major from 0 within the rows held, and only pixels holding something
//! (some cell not 0) are sent, in *runs* of consecutive such pixels:
//!
//! | field | type | meaning |
//! | --- | --- | --- |
//! | `first` | `u32` | number of the run's first pixel |
//! | `pixels` | `u32` | pixels in the run, at least 1 |
//! | cells | `pixels * (4K + 1)` x `u64` | the run's pixels, in order |
//!
//! Runs are maximal: every pixel in a run holds something, and between two runs lies at least
//! one empty pixel. A run header with `pixels = 0` and `first` = the number of pixels held ends
//! the list. So a push delta in which 1 % of the pixels changed is about 1 % of a full state,
//! and a full frame costs 8 bytes more than its cells.
//!
//! **Applied batches.** Last, the batches whose samples the state holds, so that a receiver can
//! refuse a state that would count a batch twice (a worker that resent a batch to another node
//! when its first node failed leaves the batch in both nodes' states). A `u64` count of
//! workers, then per worker, in increasing worker order:
//!
//! | field | type | meaning |
//! | --- | --- | --- |
//! | `worker` | `u64` | the worker id of the batches |
//! | `ranges` | `u64` | number of ranges that follow |
//! | ranges | `ranges` x (`u64` start, `u64` end) | sequence numbers `start..end`, increasing, non-empty, with a gap between two ranges |
//! | digests | one `u64` per sequence number, in order | the batch's content digest (`0`: not recorded) |
//!
//! A state that holds only some rows of a frame lists every batch with samples in those rows.
//! Snapshot bands list none: a snapshot keeps the frame's applied batches itself.
//!
//! **AOVs** (version 3). Last, the frame's AOVs: a `u64` count, then per AOV its name (`u64`
//! length and UTF-8), a `u64` channel count (at least 1) and the channel names (each a `u64`
//! length and UTF-8). When there is an AOV, the AOV words of the rows held follow as runs laid out like
//! the cells' (`first`, `pixels`, the pixels' words; ended by `first` = pixels held,
//! `pixels` = 0), `1 + 2C` `u64` words per pixel for the `C` channels of all AOVs: the pixel's
//! AOV sample count, then per channel the sum's low and high words (an `i128` in units of
//! `2^-20`; see `splatd_estimator`'s aov module for the bounds a receiver checks).
//!
//! Version 2 is version 3 without the AOV section; [`StateDump::decode`] reads it as a state
//! without AOVs.
//!
//! Version 1 (`frac_bits` 32, `4 * K` dense cells per pixel after a `u64` count in the header,
//! sums that saturated, no batches) is refused by [`StateDump::decode`], naming both versions;
//! [`StateDump::decode_v1`] reads it for servers that convert old snapshots.
//!
//! Decoding checks the geometry against the receiver's limit before it allocates anything, and
//! every count against the bytes present.

use std::ops::Range;

use bincode::config::{Configuration, Fixint, Limit, LittleEndian};
use serde::{Deserialize, Serialize};

use crate::api::AovSpec;

/// The four bytes every state starts with.
pub const STATE_MAGIC: [u8; 4] = *b"SPLS";

/// The state format version this crate writes; it reads this one and [`STATE_VERSION_2`].
pub const STATE_VERSION: u16 = 3;

/// The previous state format version, without the AOV section; still read by
/// [`StateDump::decode`] (as a state without AOVs).
pub const STATE_VERSION_2: u16 = 2;

/// The previous state format version, read only by [`StateDump::decode_v1`].
pub const STATE_VERSION_1: u16 = 1;

/// `Content-Type` of a state body.
pub const STATE_CONTENT_TYPE: &str = "application/x-splatd-state";

/// Headers are small; anything near this is garbage.
const HEADER_LIMIT: usize = 64 * 1024;

type HeaderConfig = Configuration<LittleEndian, Fixint, Limit<HEADER_LIMIT>>;
const HEADER_CONFIG: HeaderConfig = bincode::config::legacy().with_limit::<HEADER_LIMIT>();

/// Identifies one pushed delta, so a receiver applies a retried push once.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Origin {
    /// The pushing node's id (stable across its restarts).
    pub node: String,
    /// The node's delta sequence number for this frame, increasing by one per push.
    pub seq: u64,
}

/// A frame's accumulated cascades, verbatim.
#[derive(Debug, Clone, PartialEq)]
pub struct StateDump {
    /// Frame id.
    pub frame: String,
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// First row held.
    pub rows_start: u32,
    /// One past the last row held.
    pub rows_end: u32,
    /// Cascade base `b`.
    pub base: f64,
    /// Cascade count `K`.
    pub cascades: u32,
    /// Scale of the lowest cascade `c0`.
    pub lowest_scale: f64,
    /// Brightness weights.
    pub luminance: [f64; 3],
    /// Fixed-point fractional bits.
    pub frac_bits: u32,
    /// Set on push deltas: who sent it, and which of its deltas it is.
    pub origin: Option<Origin>,
    /// The cells: `width * rows * (4 * cascades + 1)` values (`4 * cascades` in version 1),
    /// empty pixels included.
    pub cells: Vec<u64>,
    /// The batches whose samples the state holds, by increasing worker id.
    pub batches: Vec<Applied>,
    /// The frame's AOVs (none in a version 2 state).
    pub aovs: Vec<AovSpec>,
    /// The AOV words: `width * rows * (1 + 2C)` values for the `C` channels of all `aovs`
    /// together, empty pixels included (empty when there are no AOVs).
    pub aov_cells: Vec<u64>,
}

/// The batches of one worker that a state holds.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Applied {
    /// The worker id.
    pub worker: u64,
    /// Sequence numbers, as increasing, non-empty ranges with a gap between two of them.
    pub ranges: Vec<Range<u64>>,
    /// The content digest of each batch, one per sequence number in `ranges`, in order; `0`
    /// where none was recorded.
    pub digests: Vec<u64>,
}

impl Applied {
    /// Number of batches.
    pub fn len(&self) -> u64 {
        self.ranges.iter().map(|r| r.end - r.start).sum()
    }

    /// Whether it names no batch.
    pub fn is_empty(&self) -> bool {
        self.ranges.is_empty()
    }

    /// Every `(seq, digest)`, in increasing `seq` order; digest `None` where none was recorded.
    pub fn batches(&self) -> impl Iterator<Item = (u64, Option<u64>)> + '_ {
        self.ranges
            .iter()
            .flat_map(|r| r.clone())
            .zip(&self.digests)
            .map(|(seq, &d)| (seq, (d != 0).then_some(d)))
    }

    /// Builds the entry of `worker` from `(seq, digest)` pairs in strictly increasing `seq`
    /// order.
    pub fn from_batches(
        worker: u64,
        batches: impl IntoIterator<Item = (u64, Option<u64>)>,
    ) -> Applied {
        let mut applied = Applied {
            worker,
            ..Applied::default()
        };
        for (seq, digest) in batches {
            match applied.ranges.last_mut() {
                Some(last) if last.end == seq => last.end += 1,
                Some(last) => {
                    assert!(seq > last.end, "sequence numbers must increase");
                    applied.ranges.push(seq..seq + 1);
                }
                None => applied.ranges.push(seq..seq + 1),
            }
            applied.digests.push(digest.unwrap_or(0));
        }
        applied
    }

    /// Checks the invariants the encoding relies on.
    fn check(&self) -> Result<(), String> {
        let mut end = None;
        for r in &self.ranges {
            if r.start >= r.end || end.is_some_and(|e| r.start <= e) {
                return Err(format!(
                    "worker {}: sequence ranges must be non-empty, increasing and apart, found {}..{} after {:?}",
                    self.worker, r.start, r.end, end
                ));
            }
            end = Some(r.end);
        }
        Ok(())
    }
}

/// Why a state body was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum StateError {
    /// Not a state.
    #[error("not a splatd state: expected magic \"SPLS\", found \"{}\"", found.escape_ascii())]
    BadMagic {
        /// The first (up to) four bytes.
        found: Vec<u8>,
    },
    /// A state of a version this build cannot read.
    #[error(
        "unsupported state format version {found}; this build reads version {supported} \
         and version 2 (version 1 states, with 32 fractional bits, must be re-exported by a current server)"
    )]
    UnsupportedVersion {
        /// Version found.
        found: u16,
        /// Version supported.
        supported: u16,
    },
    /// The body ends before what its header declares.
    #[error("state is truncated: its header declares {needed} bytes, the body has {available}")]
    Truncated {
        /// Bytes needed.
        needed: u64,
        /// Bytes present.
        available: u64,
    },
    /// The declared cell count does not fit the declared geometry.
    #[error("state declares {count} cells, but a {width}x{rows} band with {cascades} cascades has {expected}")]
    Shape {
        /// Declared count.
        count: u64,
        /// Count the geometry implies.
        expected: u64,
        /// Width.
        width: u32,
        /// Rows held.
        rows: u32,
        /// Cascades.
        cascades: u32,
    },
    /// The state is larger than the receiver accepts.
    #[error("state has {count} cells; at most {max} are accepted")]
    TooLarge {
        /// Declared count.
        count: u64,
        /// The limit.
        max: u64,
    },
    /// Bytes after the end of the state.
    #[error("state has {count} unexpected bytes after its end")]
    TrailingBytes {
        /// Extra bytes.
        count: usize,
    },
    /// Anything else wrong with the header.
    #[error("malformed state: {0}")]
    Malformed(String),
}

impl StateError {
    /// Machine-readable code for [`crate::ErrorBody::error`].
    pub fn code(&self) -> &'static str {
        match self {
            StateError::BadMagic { .. } => "bad_magic",
            StateError::UnsupportedVersion { .. } => "unsupported_version",
            StateError::Truncated { .. } => "truncated_state",
            StateError::Shape { .. } => "state_shape_mismatch",
            StateError::TooLarge { .. } => "state_too_large",
            StateError::TrailingBytes { .. } => "trailing_bytes",
            StateError::Malformed(_) => "malformed_state",
        }
    }
}

#[derive(Serialize, Deserialize)]
struct Header {
    frame: String,
    width: u32,
    height: u32,
    rows_start: u32,
    rows_end: u32,
    base: f64,
    cascades: u32,
    lowest_scale: f64,
    luminance: [f64; 3],
    frac_bits: u32,
    origin: Option<Origin>,
}

/// The header of version 1, which declared its (dense) cell count.
#[derive(Serialize, Deserialize)]
struct HeaderV1 {
    header: Header,
    count: u64,
}

impl StateDump {
    /// Cells a state of this geometry holds, empty pixels included.
    pub fn expected_cells(&self) -> u64 {
        expected_cells(
            self.width,
            self.rows_start,
            self.rows_end,
            self.cascades,
            STATE_VERSION,
        )
    }

    /// Encodes the state in the layout of the module docs.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(256 + 8 * self.cells.len());
        self.write_with_cells(&self.cells, &mut out)
            .expect("writing into a Vec<u8> is infallible");
        out
    }

    /// Writes the encoding of this state with `cells` in place of `self.cells`, so a large state
    /// held elsewhere (a server's frame bands) can be streamed out without first being copied
    /// into a `StateDump`. `self.cells` is ignored; `cells` must fit the geometry.
    pub fn write_with_cells(
        &self,
        cells: &[u64],
        out: &mut impl std::io::Write,
    ) -> std::io::Result<()> {
        self.write_with_cell_parts(&[cells], out)
    }

    /// Like [`StateDump::write_with_cells`], with the cells given as consecutive parts (a
    /// frame's row bands, top to bottom, each of whole pixels), so they need not be gathered
    /// into one buffer first.
    pub fn write_with_cell_parts(
        &self,
        parts: &[&[u64]],
        out: &mut impl std::io::Write,
    ) -> std::io::Result<()> {
        self.write_with_parts(parts, &[&self.aov_cells], out)
    }

    /// Like [`StateDump::write_with_cell_parts`], with the AOV words given as consecutive parts
    /// too (each of whole pixels), in place of `self.aov_cells`: a server's AOV sums are written
    /// from where they lie, not copied into a `StateDump` first.
    pub fn write_with_parts(
        &self,
        parts: &[&[u64]],
        aov_parts: &[&[u64]],
        out: &mut impl std::io::Write,
    ) -> std::io::Result<()> {
        self.write_version(STATE_VERSION, parts, aov_parts, &mut Copying(out))
    }

    /// [`StateDump::write_with_cell_parts`] to a [`StateWrite`], which is handed the long
    /// stretches of the parts' cells by where they lie ([`StateWrite::write_cells`]), so that a
    /// writer holding the parts can send them without copying them.
    pub fn write_with_cell_parts_to(
        &self,
        parts: &[&[u64]],
        out: &mut impl StateWrite,
    ) -> std::io::Result<()> {
        self.write_with_parts_to(parts, &[&self.aov_cells], out)
    }

    /// [`StateDump::write_with_parts`] to a [`StateWrite`] (see
    /// [`StateDump::write_with_cell_parts_to`]; the AOV words are written through
    /// [`std::io::Write`]).
    pub fn write_with_parts_to(
        &self,
        parts: &[&[u64]],
        aov_parts: &[&[u64]],
        out: &mut impl StateWrite,
    ) -> std::io::Result<()> {
        self.write_version(STATE_VERSION, parts, aov_parts, out)
    }

    /// Encodes the state in version 2's layout (no AOV section; `aovs` must be empty), for
    /// tests of the migration.
    #[doc(hidden)]
    pub fn encode_v2(&self) -> Vec<u8> {
        assert!(self.aovs.is_empty(), "version 2 has no AOVs");
        let mut out = Vec::new();
        self.write_version(STATE_VERSION_2, &[&self.cells], &[], &mut Copying(&mut out))
            .expect("writing into a Vec<u8> is infallible");
        out
    }

    fn write_version(
        &self,
        version: u16,
        parts: &[&[u64]],
        aov_parts: &[&[u64]],
        out: &mut impl StateWrite,
    ) -> std::io::Result<()> {
        out.write_all(&STATE_MAGIC)?;
        out.write_all(&version.to_le_bytes())?;
        out.write_all(&self.header_bytes())?;
        let pixels = Pixels::new(parts, self.cell_len());
        // Run headers and short runs are gathered into a 64 KiB block, one write per block
        // rather than one per run; a stretch of cells at least as long as the block goes to
        // `out` as it lies, so it is copied once at most (by `out`), not first into the block.
        let mut block = Block {
            bytes: vec![0; 8 * PIECE_CELLS],
            used: 0,
        };
        for run in pixels.runs() {
            block.put(&[run.start as u32, (run.end - run.start) as u32], out)?;
            for (part, words, cells) in pixels.cells(run) {
                if cells.len() >= PIECE_CELLS {
                    block.flush(out)?;
                    out.write_cells(part, words, cells)?;
                } else {
                    block.put_cells(cells, out)?;
                }
            }
        }
        block.put(&[pixels.count() as u32, 0], out)?;
        block.flush(out)?;
        out.write_all(&self.batches_bytes())?;
        if version < 3 {
            return Ok(());
        }
        out.write_all(&self.aov_names_bytes())?;
        let channels = self.aov_channels();
        if channels == 0 {
            return Ok(());
        }
        // Laid out like the cells' runs; the words go through `Write` (a `StateWrite`'s parts
        // are the cells').
        let pixels = Pixels::new(aov_parts, 1 + 2 * channels);
        for run in pixels.runs() {
            block.put(&[run.start as u32, (run.end - run.start) as u32], out)?;
            for (_, _, words) in pixels.cells(run) {
                if words.len() >= PIECE_CELLS {
                    block.flush(out)?;
                    write_le_cells(words, out)?;
                } else {
                    block.put_cells(words, out)?;
                }
            }
        }
        block.put(&[pixels.count() as u32, 0], out)?;
        block.flush(out)
    }

    /// Channels of all AOVs together.
    pub fn aov_channels(&self) -> usize {
        self.aovs.iter().map(|a| a.channels.len()).sum()
    }

    /// Encodes the state (version 3) with its cells and AOV words given pixel by pixel:
    /// `cells` and `aov_words` are `(pixel, words)` in strictly increasing pixel order (numbered
    /// row-major from 0 within the rows held), each pixel holding something, and
    /// `self.cells` and `self.aov_cells` are ignored. The same bytes as [`StateDump::encode`]
    /// of the state with those pixels and every other one empty, for a holder of a sparse
    /// state (the offline merge), whose frame may be far larger than what it holds.
    pub fn encode_sparse<'c>(
        &self,
        cells: impl IntoIterator<Item = (u64, &'c [u64])>,
        aov_words: impl IntoIterator<Item = (u64, &'c [u64])>,
    ) -> Vec<u8> {
        let pixels = (self.rows_end - self.rows_start) as u64 * self.width as u64;
        let mut out = STATE_MAGIC.to_vec();
        out.extend_from_slice(&STATE_VERSION.to_le_bytes());
        out.extend_from_slice(&self.header_bytes());
        sparse_runs(&mut out, cells, pixels);
        out.extend_from_slice(&self.batches_bytes());
        out.extend_from_slice(&self.aov_names_bytes());
        if self.aov_channels() > 0 {
            sparse_runs(&mut out, aov_words, pixels);
        }
        out
    }

    /// The AOV declarations of the AOV section: count, then names and channels.
    fn aov_names_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        let string = |out: &mut Vec<u8>, s: &str| {
            out.extend_from_slice(&(s.len() as u64).to_le_bytes());
            out.extend_from_slice(s.as_bytes());
        };
        out.extend_from_slice(&(self.aovs.len() as u64).to_le_bytes());
        for aov in &self.aovs {
            string(&mut out, &aov.name);
            out.extend_from_slice(&(aov.channels.len() as u64).to_le_bytes());
            for c in &aov.channels {
                string(&mut out, c);
            }
        }
        out
    }

    /// The length of [`StateDump::write_with_cell_parts`]'s output, without writing it.
    pub fn encoded_len_with_cell_parts(&self, parts: &[&[u64]]) -> u64 {
        self.encoded_len_with_parts(parts, &[&self.aov_cells])
    }

    /// The length of [`StateDump::write_with_parts`]'s output, without writing it.
    pub fn encoded_len_with_parts(&self, parts: &[&[u64]], aov_parts: &[&[u64]]) -> u64 {
        let mut len = 6 + self.header_bytes().len() as u64 + runs_len(parts, self.cell_len());
        len += self.batches_bytes().len() as u64 + self.aov_names_bytes().len() as u64;
        let channels = self.aov_channels();
        if channels > 0 {
            len += runs_len(aov_parts, 1 + 2 * channels);
        }
        len
    }

    fn cell_len(&self) -> usize {
        4 * self.cascades as usize + 1
    }

    fn header(&self) -> Header {
        Header {
            frame: self.frame.clone(),
            width: self.width,
            height: self.height,
            rows_start: self.rows_start,
            rows_end: self.rows_end,
            base: self.base,
            cascades: self.cascades,
            lowest_scale: self.lowest_scale,
            luminance: self.luminance,
            frac_bits: self.frac_bits,
            origin: self.origin.clone(),
        }
    }

    fn header_bytes(&self) -> Vec<u8> {
        bincode::serde::encode_to_vec(self.header(), HEADER_CONFIG)
            .expect("bincode encoding of a state header is infallible")
    }

    fn batches_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(&(self.batches.len() as u64).to_le_bytes());
        for a in &self.batches {
            out.extend_from_slice(&a.worker.to_le_bytes());
            out.extend_from_slice(&(a.ranges.len() as u64).to_le_bytes());
            for r in &a.ranges {
                out.extend_from_slice(&r.start.to_le_bytes());
                out.extend_from_slice(&r.end.to_le_bytes());
            }
            for d in &a.digests {
                out.extend_from_slice(&d.to_le_bytes());
            }
        }
        out
    }

    /// Encodes the state in version 1's layout (dense cells, as they are; no batches), for
    /// tests of the conversion of old snapshots.
    #[doc(hidden)]
    pub fn encode_v1(&self) -> Vec<u8> {
        let mut out = STATE_MAGIC.to_vec();
        out.extend_from_slice(&STATE_VERSION_1.to_le_bytes());
        let header = HeaderV1 {
            header: self.header(),
            count: self.cells.len() as u64,
        };
        out.extend(
            bincode::serde::encode_to_vec(&header, HEADER_CONFIG)
                .expect("bincode encoding of a state header is infallible"),
        );
        out.extend(self.cells.iter().flat_map(|c| c.to_le_bytes()));
        out
    }

    /// Decodes an untrusted state body whose geometry holds at most `max_cells` cells.
    ///
    /// Reads version 3 and version 2 (a state without AOVs); `max_cells` bounds the cells and
    /// the AOV words together.
    pub fn decode(bytes: &[u8], max_cells: u64) -> Result<StateDump, StateError> {
        let (mut dump, runs, aov_runs) = StateDump::decode_runs(bytes, max_cells)?;
        dump.cells = runs.expand()?;
        if let Some(aov_runs) = aov_runs {
            dump.aov_cells = aov_runs.expand()?;
        }
        Ok(dump)
    }

    /// Decodes an untrusted state body like [`StateDump::decode`], except its cells and AOV
    /// words: the dump comes back with neither (its `aovs` are set), and the runs of each are
    /// returned as they lie in `bytes` (the AOV runs when the state declares an AOV channel),
    /// for a receiver that checks and adds them piece by piece instead of expanding a whole
    /// frame of cells first. Everything but the values is checked here (preamble, header,
    /// limit, the run lists' order and bounds, every length against the bytes present, the
    /// applied batches, the AOV declarations, nothing after them); [`Runs`] checks the values
    /// as it hands them out.
    #[allow(clippy::type_complexity)]
    pub fn decode_runs(
        bytes: &[u8],
        max_cells: u64,
    ) -> Result<(StateDump, Runs<'_>, Option<Runs<'_>>), StateError> {
        let (body, version) = match preamble(bytes, STATE_VERSION) {
            Err(StateError::UnsupportedVersion { found, .. }) if found == STATE_VERSION_2 => {
                (preamble(bytes, STATE_VERSION_2)?, STATE_VERSION_2)
            }
            other => (other?, STATE_VERSION),
        };
        let (header, header_len): (Header, usize) = decode_header(body, bytes.len())?;
        let mut dump = StateDump::with_header(header)?;
        let count = dump.expected_cells();
        if count > max_cells {
            return Err(StateError::TooLarge {
                count,
                max: max_cells,
            });
        }
        let mut rest = Reader {
            bytes: &body[header_len..],
            at: 6 + header_len,
            total: bytes.len(),
        };
        let runs = rest.runs(count, dump.cell_len())?;
        dump.batches = rest.batches()?;
        let mut aov_runs = None;
        if version >= 3 {
            dump.aovs = rest.aovs()?;
            let channels = dump.aov_channels();
            if channels > 0 {
                let pixels = count / dump.cell_len() as u64;
                let words = pixels.saturating_mul(1 + 2 * channels as u64);
                if words.saturating_add(count) > max_cells {
                    return Err(StateError::TooLarge {
                        count: words.saturating_add(count),
                        max: max_cells,
                    });
                }
                aov_runs = Some(rest.runs(words, 1 + 2 * channels)?);
            }
        }
        if !rest.bytes.is_empty() {
            return Err(StateError::TrailingBytes {
                count: rest.bytes.len(),
            });
        }
        Ok((dump, runs, aov_runs))
    }

    /// Decodes an untrusted state body of the previous format version 1 (`4 * K` cells per
    /// pixel in units of `2^-32`, see the module docs), for converting old snapshots. Its cells
    /// are returned as they are: they do not fit a current state.
    pub fn decode_v1(bytes: &[u8], max_cells: u64) -> Result<StateDump, StateError> {
        let available = bytes.len() as u64;
        let body = preamble(bytes, STATE_VERSION_1)?;
        let (HeaderV1 { header, count }, header_len): (HeaderV1, usize) =
            decode_header(body, bytes.len())?;
        let mut dump = StateDump::with_header(header)?;
        let expected = expected_cells(
            dump.width,
            dump.rows_start,
            dump.rows_end,
            dump.cascades,
            STATE_VERSION_1,
        );
        if count != expected {
            return Err(StateError::Shape {
                count,
                expected,
                width: dump.width,
                rows: dump.rows_end - dump.rows_start,
                cascades: dump.cascades,
            });
        }
        if count > max_cells {
            return Err(StateError::TooLarge {
                count,
                max: max_cells,
            });
        }
        let cells_bytes = &body[header_len..];
        let needed = count.saturating_mul(8);
        if (cells_bytes.len() as u64) < needed {
            return Err(StateError::Truncated {
                needed: (6 + header_len as u64).saturating_add(needed),
                available,
            });
        }
        // needed <= len, so it fits in usize.
        if cells_bytes.len() as u64 > needed {
            return Err(StateError::TrailingBytes {
                count: cells_bytes.len() - needed as usize,
            });
        }
        dump.cells = cells_bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().expect("8-byte chunk")))
            .collect();
        Ok(dump)
    }

    fn with_header(header: Header) -> Result<StateDump, StateError> {
        if header.rows_start > header.rows_end || header.rows_end > header.height {
            return Err(StateError::Malformed(format!(
                "rows {}..{} do not lie in a frame of height {}",
                header.rows_start, header.rows_end, header.height
            )));
        }
        Ok(StateDump {
            frame: header.frame,
            width: header.width,
            height: header.height,
            rows_start: header.rows_start,
            rows_end: header.rows_end,
            base: header.base,
            cascades: header.cascades,
            lowest_scale: header.lowest_scale,
            luminance: header.luminance,
            frac_bits: header.frac_bits,
            origin: header.origin,
            cells: Vec::new(),
            batches: Vec::new(),
            aovs: Vec::new(),
            aov_cells: Vec::new(),
        })
    }
}

/// A run list (see the module docs) of the `(pixel, words)` given in strictly increasing pixel
/// order, each holding something, of a state of `pixels` pixels: maximal runs of consecutive
/// pixels, then the end header.
fn sparse_runs<'c>(
    out: &mut Vec<u8>,
    words: impl IntoIterator<Item = (u64, &'c [u64])>,
    pixels: u64,
) {
    // The open run: where its header is and its first pixel and length.
    let mut run: Option<(usize, u64, u64)> = None;
    let close = |out: &mut Vec<u8>, run: Option<(usize, u64, u64)>| {
        if let Some((at, first, n)) = run {
            out[at..at + 4].copy_from_slice(&(first as u32).to_le_bytes());
            out[at + 4..at + 8].copy_from_slice(&(n as u32).to_le_bytes());
        }
    };
    for (pixel, cells) in words {
        debug_assert!(pixel < pixels && cells.iter().any(|&w| w != 0));
        match &mut run {
            Some((_, first, n)) if *first + *n == pixel => *n += 1,
            _ => {
                close(out, run.take());
                run = Some((out.len(), pixel, 1));
                out.extend_from_slice(&[0; 8]);
            }
        }
        out.extend(cells.iter().flat_map(|w| w.to_le_bytes()));
    }
    close(out, run);
    out.extend_from_slice(&(pixels as u32).to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
}

/// Checks the magic and the version; returns the bytes after them.
fn preamble(bytes: &[u8], wanted: u16) -> Result<&[u8], StateError> {
    let magic_len = bytes.len().min(4);
    if bytes[..magic_len] != STATE_MAGIC[..magic_len] {
        return Err(StateError::BadMagic {
            found: bytes[..magic_len].to_vec(),
        });
    }
    let Some((&[_, _, _, _, v0, v1], body)) = bytes.split_first_chunk::<6>() else {
        return Err(StateError::Truncated {
            needed: 6,
            available: bytes.len() as u64,
        });
    };
    let version = u16::from_le_bytes([v0, v1]);
    if version != wanted {
        return Err(StateError::UnsupportedVersion {
            found: version,
            supported: wanted,
        });
    }
    Ok(body)
}

fn decode_header<H: serde::de::DeserializeOwned>(
    body: &[u8],
    total: usize,
) -> Result<(H, usize), StateError> {
    bincode::serde::decode_from_slice(body, HEADER_CONFIG).map_err(|e| match e {
        bincode::error::DecodeError::UnexpectedEnd { additional } => StateError::Truncated {
            needed: (total as u64).saturating_add(additional as u64),
            available: total as u64,
        },
        other => StateError::Malformed(other.to_string()),
    })
}

/// Reads the parts after the header, checking every count against the bytes left.
struct Reader<'a> {
    bytes: &'a [u8],
    /// Offset of `bytes` in the whole body, and the body's length, for error messages.
    at: usize,
    total: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: u64) -> Result<&'a [u8], StateError> {
        if (self.bytes.len() as u64) < n {
            return Err(StateError::Truncated {
                needed: (self.at as u64).saturating_add(n),
                available: self.total as u64,
            });
        }
        let (head, rest) = self.bytes.split_at(n as usize);
        self.bytes = rest;
        self.at += n as usize;
        Ok(head)
    }

    fn u32(&mut self) -> Result<u32, StateError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }

    fn u64(&mut self) -> Result<u64, StateError> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }

    /// The run list of a state of `count` cells, `cell_len` per pixel: its headers checked
    /// (order, bounds, lengths against the bytes present), its cells left where they are.
    fn runs(&mut self, count: u64, cell_len: usize) -> Result<Runs<'a>, StateError> {
        let pixels = count / cell_len as u64;
        let (start, at) = (self.bytes, self.at);
        let mut next = 0u64; // the first pixel a run may start at
        loop {
            let first = self.u32()? as u64;
            let n = self.u32()? as u64;
            if n == 0 {
                if first != pixels {
                    return Err(StateError::Malformed(format!(
                        "the run list ends with pixel {first}, not with the {pixels} pixels held"
                    )));
                }
                return Ok(Runs {
                    bytes: &start[..self.at - at],
                    cell_len,
                    pixels,
                });
            }
            if first < next || first + n > pixels {
                return Err(StateError::Malformed(format!(
                    "a run of {n} pixels from pixel {first} does not lie after the previous run \
                     (with a gap) in the {pixels} pixels held"
                )));
            }
            self.take(n * 8 * cell_len as u64)?;
            next = first + n + 1;
        }
    }

    fn string(&mut self, what: &str) -> Result<String, StateError> {
        let len = self.u64()?;
        let bytes = self.take(len)?;
        String::from_utf8(bytes.to_vec())
            .map_err(|_| StateError::Malformed(format!("{what} is not UTF-8")))
    }

    /// The AOV names and channels of a version 3 state.
    fn aovs(&mut self) -> Result<Vec<AovSpec>, StateError> {
        let count = self.u64()?;
        // Each AOV takes at least 16 bytes: no allocation by what the count claims.
        if count > self.bytes.len() as u64 / 16 {
            return Err(StateError::Truncated {
                needed: (self.at as u64).saturating_add(count.saturating_mul(16)),
                available: self.total as u64,
            });
        }
        let mut aovs = Vec::with_capacity(count as usize);
        for _ in 0..count {
            let name = self.string("an AOV name")?;
            let channels = self.u64()?;
            if channels == 0 || channels > self.bytes.len() as u64 / 8 {
                return Err(StateError::Malformed(format!(
                    "AOV {name:?} declares {channels} channels"
                )));
            }
            let channels = (0..channels)
                .map(|_| self.string("an AOV channel name"))
                .collect::<Result<Vec<String>, StateError>>()?;
            aovs.push(AovSpec { name, channels });
        }
        Ok(aovs)
    }

    fn batches(&mut self) -> Result<Vec<Applied>, StateError> {
        let workers = self.u64()?;
        // Each worker takes at least 16 bytes: no allocation by what the count claims.
        if workers > self.bytes.len() as u64 / 16 {
            return Err(StateError::Truncated {
                needed: (self.at as u64).saturating_add(workers.saturating_mul(16)),
                available: self.total as u64,
            });
        }
        let mut all: Vec<Applied> = Vec::with_capacity(workers as usize);
        for _ in 0..workers {
            let worker = self.u64()?;
            if all.last().is_some_and(|a| a.worker >= worker) {
                return Err(StateError::Malformed(format!(
                    "applied batches: worker {worker} is out of order"
                )));
            }
            let n = self.u64()?;
            let bytes = self.take(n.saturating_mul(16))?;
            let ranges: Vec<Range<u64>> = bytes
                .chunks_exact(16)
                .map(|c| {
                    let start = u64::from_le_bytes(c[..8].try_into().expect("8 bytes"));
                    let end = u64::from_le_bytes(c[8..].try_into().expect("8 bytes"));
                    start..end
                })
                .collect();
            let mut applied = Applied {
                worker,
                ranges,
                digests: Vec::new(),
            };
            applied.check().map_err(StateError::Malformed)?;
            let digests = self.take(applied.len().saturating_mul(8))?;
            applied.digests = digests
                .chunks_exact(8)
                .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect();
            all.push(applied);
        }
        Ok(all)
    }
}

/// The cells of a decoded state body, as the runs of pixels holding something, read in place
/// from the body ([`StateDump::decode_runs`]). Their headers are checked already; the cells'
/// values are checked as they are handed out: a pixel in a run that holds nothing is refused
/// (`Malformed`) before any of its piece is.
#[derive(Debug, Clone, Copy)]
pub struct Runs<'a> {
    /// From the first run's header to the end of the list.
    bytes: &'a [u8],
    cell_len: usize,
    pixels: u64,
}

/// Cells converted at a time by [`Runs::try_for_each`]: 64 KiB, which stays in the cache.
const PIECE_CELLS: usize = 8192;

impl<'a> Runs<'a> {
    /// Cells per pixel (`4K + 1`).
    pub fn cell_len(&self) -> usize {
        self.cell_len
    }

    /// Pixels of the rows held, empty ones included.
    pub fn pixels(&self) -> u64 {
        self.pixels
    }

    /// The runs' cells as little-endian bytes, in pieces of whole pixels: `f(first, bytes)`
    /// with the number of the piece's first pixel, for the pixels of `within` only. The headers
    /// were checked by the decoder.
    fn pieces<E: From<StateError>>(
        &self,
        max_pixels: usize,
        within: Range<u64>,
        mut f: impl FnMut(u64, &'a [u8]) -> Result<(), E>,
    ) -> Result<(), E> {
        let pixel_bytes = 8 * self.cell_len;
        let mut rest = self.bytes;
        loop {
            let (head, tail) = rest.split_at(8);
            let first = u32::from_le_bytes(head[..4].try_into().expect("4 bytes")) as u64;
            let n = u32::from_le_bytes(head[4..].try_into().expect("4 bytes")) as usize;
            if n == 0 || first >= within.end {
                return Ok(());
            }
            let (cells, tail) = tail.split_at(n * pixel_bytes);
            rest = tail;
            // The part of the run inside `within`.
            let skip = within.start.saturating_sub(first).min(n as u64) as usize;
            let take = (within.end - first).min(n as u64) as usize;
            if skip >= take {
                continue;
            }
            let cells = &cells[skip * pixel_bytes..take * pixel_bytes];
            let first = first + skip as u64;
            for (i, piece) in cells.chunks(max_pixels * pixel_bytes).enumerate() {
                let first = first + (i * max_pixels) as u64;
                // A run's pixels all hold something (the runs are maximal).
                // Eight bytes at a time: a pixel's first word that is not 0 settles it.
                let empty = |p: &[u8]| {
                    p.chunks_exact(8)
                        .all(|w| u64::from_ne_bytes(w.try_into().expect("8 bytes")) == 0)
                };
                if let Some(p) = piece.chunks_exact(pixel_bytes).position(empty) {
                    return Err(StateError::Malformed(format!(
                        "pixel {} is in a run but holds nothing",
                        first + p as u64
                    ))
                    .into());
                }
                f(first, piece)?;
            }
        }
    }

    /// Hands the runs' cells to `f` in order, in pieces of whole pixels (at most 64 KiB,
    /// converted into one reused buffer): `f(first, cells)` gets the number of the piece's first
    /// pixel (row-major from 0 within the rows held) and its `cell_len` cells per pixel. The
    /// first error, `f`'s or a pixel holding nothing, stops the visit and is returned.
    pub fn try_for_each<E: From<StateError>>(
        &self,
        f: impl FnMut(u64, &[u64]) -> Result<(), E>,
    ) -> Result<(), E> {
        self.try_for_each_in(0..self.pixels, f)
    }

    /// [`Runs::try_for_each`] for the pixels of `within` only (numbered like `first`): so
    /// several threads can each take a share of the pixels, the same pieces cut at its ends.
    pub fn try_for_each_in<E: From<StateError>>(
        &self,
        within: Range<u64>,
        mut f: impl FnMut(u64, &[u64]) -> Result<(), E>,
    ) -> Result<(), E> {
        let max_pixels = (PIECE_CELLS / self.cell_len).max(1);
        let mut buf = vec![0u64; max_pixels * self.cell_len];
        self.pieces(max_pixels, within, |first, bytes| {
            let cells = &mut buf[..bytes.len() / 8];
            le_cells(bytes, cells);
            f(first, cells)
        })
    }

    /// All the cells of the rows held, in a new buffer (empty pixels zero).
    pub fn expand(&self) -> Result<Vec<u64>, StateError> {
        let mut cells = vec![0u64; (self.pixels * self.cell_len as u64) as usize];
        self.expand_into(&mut cells)?;
        Ok(cells)
    }

    /// Writes the runs' cells into `cells`, all the cells of the rows held (empty pixels are
    /// left as they are: zero in a fresh buffer).
    ///
    /// # Panics
    /// If `cells` is not `pixels * cell_len` long.
    pub fn expand_into(&self, cells: &mut [u64]) -> Result<(), StateError> {
        assert_eq!(cells.len() as u64, self.pixels * self.cell_len as u64);
        let max_pixels = (PIECE_CELLS / self.cell_len).max(1);
        self.pieces(max_pixels, 0..self.pixels, |first, bytes| {
            let at = first as usize * self.cell_len;
            le_cells(bytes, &mut cells[at..at + bytes.len() / 8]);
            Ok(())
        })
    }
}

/// `bytes` (little-endian `u64`s) into `cells`, which is exactly as long: a plain copy on a
/// little-endian machine.
fn le_cells(bytes: &[u8], cells: &mut [u64]) {
    for (c, b) in cells.iter_mut().zip(bytes.chunks_exact(8)) {
        *c = u64::from_le_bytes(b.try_into().expect("8 bytes"));
    }
}

/// Where a state's encoding is written ([`StateDump::write_with_cell_parts_to`]): its bytes
/// through [`std::io::Write`], and the long stretches of its cells through
/// [`StateWrite::write_cells`], which names where they lie in the parts being written, so a
/// writer that holds those parts may send them from there instead of copying them.
pub trait StateWrite: std::io::Write {
    /// Writes `cells` as little-endian bytes, in order after everything written before: the
    /// words `words` of part `part` of the parts being written. By default, a copy through
    /// [`std::io::Write::write_all`].
    fn write_cells(
        &mut self,
        part: usize,
        words: Range<usize>,
        cells: &[u64],
    ) -> std::io::Result<()> {
        let _ = (part, words);
        write_le_cells(cells, self)
    }
}

impl StateWrite for Vec<u8> {}

/// A [`std::io::Write`] as a [`StateWrite`] that copies every cell.
struct Copying<W>(W);

impl<W: std::io::Write> std::io::Write for Copying<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.0.write_all(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.0.flush()
    }
}

impl<W: std::io::Write> StateWrite for Copying<W> {}

/// `cells` as their little-endian bytes, where those are their bytes in memory (a
/// little-endian machine): so they can be written, or sent, from where they lie.
pub fn le_bytes(cells: &[u64]) -> Option<&[u8]> {
    cfg!(target_endian = "little").then(|| bytemuck::cast_slice(cells))
}

/// Writes `cells` as little-endian bytes to `out`: as they lie on a little-endian machine,
/// else converted a 64 KiB block at a time.
fn write_le_cells(cells: &[u64], out: &mut (impl std::io::Write + ?Sized)) -> std::io::Result<()> {
    if let Some(bytes) = le_bytes(cells) {
        return out.write_all(bytes);
    }
    let mut block = vec![0u8; 8 * PIECE_CELLS];
    for chunk in cells.chunks(PIECE_CELLS) {
        let dst = &mut block[..8 * chunk.len()];
        for (d, c) in dst.chunks_exact_mut(8).zip(chunk) {
            d.copy_from_slice(&c.to_le_bytes());
        }
        out.write_all(dst)?;
    }
    Ok(())
}

/// A buffer that the run list is encoded into before it is written.
struct Block {
    bytes: Vec<u8>,
    used: usize,
}

impl Block {
    /// Makes room for `n` more bytes (at most the block's size), writing out what it holds.
    fn room(&mut self, n: usize, out: &mut impl std::io::Write) -> std::io::Result<&mut [u8]> {
        if self.used + n > self.bytes.len() {
            self.flush(out)?;
        }
        let at = self.used;
        self.used += n;
        Ok(&mut self.bytes[at..at + n])
    }

    /// A run header: two `u32`s.
    fn put(&mut self, words: &[u32; 2], out: &mut impl std::io::Write) -> std::io::Result<()> {
        let dst = self.room(8, out)?;
        dst[..4].copy_from_slice(&words[0].to_le_bytes());
        dst[4..].copy_from_slice(&words[1].to_le_bytes());
        Ok(())
    }

    /// At most [`PIECE_CELLS`] cells, little-endian.
    fn put_cells(&mut self, cells: &[u64], out: &mut impl std::io::Write) -> std::io::Result<()> {
        let dst = self.room(8 * cells.len(), out)?;
        for (d, c) in dst.chunks_exact_mut(8).zip(cells) {
            d.copy_from_slice(&c.to_le_bytes());
        }
        Ok(())
    }

    fn flush(&mut self, out: &mut impl std::io::Write) -> std::io::Result<()> {
        out.write_all(&self.bytes[..self.used])?;
        self.used = 0;
        Ok(())
    }
}

/// Bytes of the runs of `parts`' pixels (of `stride` words) that hold something, with their
/// headers and the closing one. Counted, not collected: one pass over the occupancy (a pixel's
/// first word that is not 0 settles it), no list as long as the runs.
fn runs_len(parts: &[&[u64]], stride: usize) -> u64 {
    let pixels = Pixels::new(parts, stride);
    let (runs, held) = pixels
        .runs()
        .fold((0usize, 0usize), |(n, held), r| (n + 1, held + r.len()));
    (8 * (runs + 1) + 8 * held * stride) as u64
}

/// A state's pixels, held in consecutive parts of whole pixels.
struct Pixels<'a> {
    parts: &'a [&'a [u64]],
    cell_len: usize,
    /// The number of the first pixel of each part, and one past the last pixel.
    starts: Vec<usize>,
}

impl<'a> Pixels<'a> {
    fn new(parts: &'a [&'a [u64]], cell_len: usize) -> Pixels<'a> {
        let mut starts = vec![0];
        for p in parts {
            assert_eq!(p.len() % cell_len, 0, "parts hold whole pixels");
            starts.push(starts[starts.len() - 1] + p.len() / cell_len);
        }
        Pixels {
            parts,
            cell_len,
            starts,
        }
    }

    fn count(&self) -> usize {
        self.starts[self.starts.len() - 1]
    }

    /// The first pixel from `from` on that holds something (`holds`) or nothing (`!holds`), or
    /// the number of pixels if there is none: a scan of each part's cells in turn, a pixel's
    /// first word that is not 0 settling that it holds something.
    fn next(&self, from: usize, holds: bool) -> usize {
        // The part `from` lies in (the last of those starting there, if some are empty).
        let mut part = self
            .starts
            .partition_point(|&s| s <= from)
            .saturating_sub(1);
        let mut at = from;
        while part < self.parts.len() {
            let skip = (at - self.starts[part]) * self.cell_len;
            let found = self.parts[part][skip..]
                .chunks_exact(self.cell_len)
                .position(|cell| cell.iter().any(|&c| c != 0) == holds);
            if let Some(i) = found {
                return at + i;
            }
            part += 1;
            at = self.starts[part];
        }
        self.count()
    }

    /// The maximal runs of pixels that hold something.
    fn runs(&self) -> impl Iterator<Item = Range<usize>> + '_ {
        let mut next = 0;
        std::iter::from_fn(move || {
            let start = self.next(next, true);
            if start >= self.count() {
                return None;
            }
            next = self.next(start + 1, false);
            Some(start..next)
        })
    }

    /// The cells of the pixels `run`, as slices of the parts: each with the number of its part
    /// and where it lies in that part (in words).
    fn cells(
        &self,
        run: Range<usize>,
    ) -> impl Iterator<Item = (usize, Range<usize>, &'a [u64])> + '_ {
        self.parts.iter().enumerate().filter_map(move |(i, part)| {
            let (lo, hi) = (self.starts[i], self.starts[i + 1]);
            let (a, b) = (run.start.max(lo), run.end.min(hi));
            (a < b).then(|| {
                let words = (a - lo) * self.cell_len..(b - lo) * self.cell_len;
                (i, words.clone(), &part[words])
            })
        })
    }
}

fn expected_cells(width: u32, rows_start: u32, rows_end: u32, cascades: u32, version: u16) -> u64 {
    let per_pixel = 4 * cascades as u64 + u64::from(version >= 2);
    (width as u64)
        .saturating_mul(rows_end.saturating_sub(rows_start) as u64)
        .saturating_mul(per_pixel)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dump() -> StateDump {
        StateDump {
            frame: "shot.0001".into(),
            width: 3,
            height: 2,
            rows_start: 0,
            rows_end: 2,
            base: 8.0,
            cascades: 2,
            lowest_scale: 0.125,
            luminance: [0.2126, 0.7152, 0.0722],
            frac_bits: 26,
            origin: Some(Origin {
                node: "node-a".into(),
                seq: 7,
            }),
            cells: (0..54)
                .map(|i| i * 0x0101_0101_0101 + u64::MAX / 3)
                .collect(),
            batches: vec![
                Applied::from_batches(3, [(0, Some(11)), (1, Some(12)), (5, None)]),
                Applied::from_batches(9, [(7, Some(u64::MAX))]),
            ],
            aovs: vec![],
            aov_cells: vec![],
        }
    }

    /// `dump()` with two AOVs (3 + 1 channels: 9 words per pixel), pixels 1 and 2 empty.
    fn with_aovs() -> StateDump {
        let mut aov_cells: Vec<u64> = (0..54).map(|i| i * 0x0123_4567 + 1).collect();
        aov_cells[9..27].fill(0);
        StateDump {
            aovs: vec![
                AovSpec::new("ViewLayer.Denoising Albedo", &["R", "G", "B"]),
                AovSpec::new("depth", &["Z"]),
            ],
            aov_cells,
            ..dump()
        }
    }

    #[test]
    fn aovs_round_trip_after_the_batches() {
        let d = with_aovs();
        let bytes = d.encode();
        assert_eq!(StateDump::decode(&bytes, u64::MAX).unwrap(), d);
        assert_eq!(
            bytes.len() as u64,
            d.encoded_len_with_cell_parts(&[&d.cells])
        );
        // The section is last: the state without AOVs is a prefix of it, up to the version.
        let plain = dump().encode();
        assert_eq!(bytes[6..plain.len() - 8], plain[6..plain.len() - 8]);
        assert_eq!(plain[plain.len() - 8..], 0u64.to_le_bytes());
        // Every truncation is refused, and the AOV words count against the limit.
        for len in plain.len() - 8..bytes.len() {
            assert!(StateDump::decode(&bytes[..len], u64::MAX).is_err(), "{len}");
        }
        assert!(matches!(
            StateDump::decode(&bytes, 107),
            Err(StateError::TooLarge { count: 108, .. })
        ));
        assert!(StateDump::decode(&bytes, 108).is_ok());
    }

    /// Writes what it is given, and notes each stretch handed over by where it lies.
    #[derive(Default)]
    struct Noting {
        bytes: Vec<u8>,
        stretches: Vec<(usize, Range<usize>, *const u64)>,
    }

    impl std::io::Write for Noting {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.bytes.write(buf)
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl StateWrite for Noting {
        fn write_cells(
            &mut self,
            part: usize,
            words: Range<usize>,
            cells: &[u64],
        ) -> std::io::Result<()> {
            self.stretches.push((part, words, cells.as_ptr()));
            self.bytes
                .extend(cells.iter().flat_map(|c| c.to_le_bytes()));
            Ok(())
        }
    }

    /// AOV words given in parts, wherever the parts are cut, encode to the bytes and the length
    /// of the same words held by the dump; long runs of them too, which go through `Write`,
    /// never as a stretch of the cells' parts.
    #[test]
    fn aov_words_in_parts_are_the_held_words() {
        // The small state of `with_aovs`, and one whose AOV runs are longer than a block (9
        // words a pixel, 3 x 2000 pixels, one empty pixel in the middle).
        let small = with_aovs();
        let (width, height) = (3u32, 2000u32);
        let mut large = StateDump {
            width,
            height,
            rows_end: height,
            cells: vec![0; (width * height) as usize * 9],
            aov_cells: (1..=(width * height) as u64 * 9).collect(),
            ..with_aovs()
        };
        large.aov_cells[3000 * 9..3001 * 9].fill(0);
        for d in [small, large] {
            let bytes = d.encode();
            let words = d.aov_cells.as_slice();
            let held = StateDump {
                aov_cells: vec![],
                ..d.clone()
            };
            let pixel = 9;
            for cut in [0, pixel, words.len() / 2 / pixel * pixel, words.len()] {
                let (a, b) = words.split_at(cut);
                let mut out = Vec::new();
                held.write_with_parts(&[&d.cells], &[a, &[], b], &mut out)
                    .unwrap();
                assert_eq!(out, bytes, "cut at word {cut}");
                let len = held.encoded_len_with_parts(&[&d.cells], &[a, b]);
                assert_eq!(len, bytes.len() as u64, "cut at word {cut}");
                let mut noting = Noting::default();
                held.write_with_parts_to(&[&d.cells], &[a, b], &mut noting)
                    .unwrap();
                assert_eq!(noting.bytes, bytes);
                assert!(
                    noting.stretches.is_empty(),
                    "AOV words are not cells' stretches"
                );
            }
        }
    }

    /// A version 2 state (no AOV section) is still read, as a state without AOVs.
    #[test]
    fn version_2_states_still_load_without_aovs() {
        let d = dump();
        let bytes = d.encode_v2();
        assert_eq!(&bytes[4..6], &2u16.to_le_bytes());
        assert_eq!(bytes.len(), d.encode().len() - 8);
        assert_eq!(StateDump::decode(&bytes, u64::MAX).unwrap(), d);
    }

    #[test]
    fn round_trip_is_lossless() {
        let d = dump();
        assert_eq!(StateDump::decode(&d.encode(), u64::MAX).unwrap(), d);
        let plain = StateDump { origin: None, ..d };
        assert_eq!(StateDump::decode(&plain.encode(), u64::MAX).unwrap(), plain);
    }

    #[test]
    fn every_truncation_and_extension_is_refused() {
        let bytes = dump().encode();
        for len in 0..bytes.len() {
            assert!(
                StateDump::decode(&bytes[..len], u64::MAX).is_err(),
                "prefix of {len} bytes accepted"
            );
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(matches!(
            StateDump::decode(&longer, u64::MAX),
            Err(StateError::TrailingBytes { count: 1 })
        ));
    }

    #[test]
    fn geometry_and_limits_are_checked_before_allocating() {
        // A header declaring a huge frame, with nothing behind it.
        let huge = StateDump {
            width: u32::MAX,
            height: u32::MAX,
            rows_end: u32::MAX,
            cells: vec![],
            batches: vec![],
            ..dump()
        };
        let mut bytes = STATE_MAGIC.to_vec();
        bytes.extend_from_slice(&STATE_VERSION.to_le_bytes());
        bytes.extend(huge.header_bytes());
        assert!(matches!(
            StateDump::decode(&bytes, 1 << 30),
            Err(StateError::TooLarge { .. })
        ));
        // Counts of applied batches are checked against the bytes present.
        let mut bytes = dump().encode();
        let at = bytes.len() - 8 - dump().batches_bytes().len();
        bytes[at..at + 8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(
            StateDump::decode(&bytes, u64::MAX),
            Err(StateError::Truncated { .. })
        ));
    }

    /// Empty pixels are not sent: runs of the pixels that hold something, and a state of a
    /// frame where 1 % of the pixels changed is about 1 % of the full state.
    #[test]
    fn only_pixels_holding_something_are_sent() {
        let cell = 4 * 2 + 1;
        let pixels = 100 * 100;
        let mut sparse = StateDump {
            width: 100,
            height: 100,
            rows_end: 100,
            cells: vec![0; pixels * cell],
            batches: vec![],
            ..dump()
        };
        for p in (0..pixels).step_by(100) {
            sparse.cells[p * cell + 3] = 1 << 26;
        }
        // Two neighbours make one run of 2 pixels; the last pixel is a run that ends the list.
        sparse.cells[101 * cell + 2] = 5;
        sparse.cells[(pixels - 1) * cell + cell - 1] = 1;
        let bytes = sparse.encode();
        assert_eq!(StateDump::decode(&bytes, u64::MAX).unwrap(), sparse);
        let full = StateDump {
            cells: vec![1; pixels * cell],
            ..sparse.clone()
        };
        let full_len = full.encode().len();
        assert_eq!(
            full_len as u64,
            full.encoded_len_with_cell_parts(&[&full.cells])
        );
        assert_eq!(
            bytes.len() as u64,
            sparse.encoded_len_with_cell_parts(&[&sparse.cells])
        );
        // 102 pixels of 72 bytes in 101 runs (8 bytes each), plus the header, the end of the
        // list and the (empty) batches; the full state is one run.
        let header = full_len - 8 * pixels * cell - 8 - 8 - 8;
        assert_eq!(bytes.len(), header + 101 * 8 + 102 * 8 * cell + 8 + 8);
        assert!((bytes.len() as f64) < 0.0125 * full_len as f64);
        // The same state split into parts (bands) encodes to the same bytes.
        let (a, b) = sparse.cells.split_at(37 * 100 * cell);
        let mut parts = Vec::new();
        sparse.write_with_cell_parts(&[a, b], &mut parts).unwrap();
        assert_eq!(parts, bytes);
        // Empty parts anywhere change nothing; nor does a seam inside a run (pixels 100, 101).
        let (c, d) = sparse.cells.split_at(101 * cell);
        for split in [vec![&[][..], a, &[], &[], b, &[]], vec![c, &[], d]] {
            let mut parts = Vec::new();
            sparse.write_with_cell_parts(&split, &mut parts).unwrap();
            assert_eq!(parts, bytes);
        }
    }

    /// A [`StateWrite`] is handed each stretch of cells at least a block long by where it lies
    /// in the parts, and everything else (headers, short runs) as bytes; in order, they are
    /// the bytes of the encoding.
    #[test]
    fn long_stretches_of_cells_are_handed_over_where_they_lie() {
        let cell = 4 * 2 + 1;
        let (width, height) = (1000, 40);
        let mut state = StateDump {
            width,
            height,
            rows_end: height,
            cells: vec![1; (width * height) as usize * cell],
            ..dump()
        };
        // Row 10 holds one short run (3 pixels) between empty pixels; the rest are long runs.
        let row = |y: usize| y * width as usize * cell..(y + 1) * width as usize * cell;
        state.cells[row(10)].fill(0);
        state.cells[row(10).start + 500 * cell..row(10).start + 503 * cell].fill(2);
        let (a, b) = state.cells.split_at(row(25).start);
        let mut noting = Noting::default();
        state
            .write_with_cell_parts_to(&[a, b], &mut noting)
            .unwrap();
        assert_eq!(noting.bytes, state.encode());
        // Rows 0..10, then rows 11.. up to the parts' seam, then the rest; the short run is
        // copied with the run headers.
        let next = row(11).start;
        assert_eq!(
            noting.stretches,
            vec![
                (0, 0..row(10).start, a.as_ptr()),
                (0, next..a.len(), a[next..].as_ptr()),
                (1, 0..b.len(), b.as_ptr()),
            ]
        );
    }

    /// A decoder accepts only the canonical encoding: runs apart and full, workers in order.
    /// The runs handed out piece by piece are the decoded cells, however the pieces fall:
    /// pixels of a run longer than one piece, runs split across pieces, gaps between runs.
    #[test]
    fn runs_in_pieces_are_the_decoded_cells() {
        let cell = 4 * 2 + 1;
        let (w, h) = (300u32, 40u32);
        let pixels = (w * h) as usize;
        let mut d = StateDump {
            width: w,
            height: h,
            rows_end: h,
            cells: vec![0; pixels * cell],
            batches: vec![],
            ..dump()
        };
        // A long run (more than a piece of 8192 cells), then every third pixel, then a tail.
        for p in (0..2000)
            .chain((2000..9000).step_by(3))
            .chain(pixels - 10..pixels)
        {
            for (i, c) in d.cells[p * cell..(p + 1) * cell].iter_mut().enumerate() {
                *c = (p * 31 + i) as u64 + 1;
            }
        }
        let bytes = d.encode();
        let (header, runs, aov_runs) = StateDump::decode_runs(&bytes, u64::MAX).unwrap();
        assert!(header.cells.is_empty() && aov_runs.is_none());
        assert_eq!((runs.pixels(), runs.cell_len()), (pixels as u64, cell));
        let mut pieced = vec![0u64; pixels * cell];
        let mut pieces = 0;
        runs.try_for_each(|first, cells| {
            assert_eq!(cells.len() % cell, 0);
            assert!(cells.len() <= PIECE_CELLS);
            let at = first as usize * cell;
            pieced[at..at + cells.len()].copy_from_slice(cells);
            pieces += 1;
            Ok::<(), StateError>(())
        })
        .unwrap();
        assert!(pieces > 2000, "the short runs come one by one");
        assert_eq!(pieced, d.cells);
        // Shares of the pixels, cut inside the long run, between short runs and inside the
        // tail, together hand out every cell once, each share only its own pixels.
        let cuts = [0, 1000, 2001, 5000, pixels as u64 - 5, pixels as u64];
        let mut shared = vec![0u64; pixels * cell];
        for share in cuts.windows(2) {
            runs.try_for_each_in(share[0]..share[1], |first, cells| {
                let end = first + (cells.len() / cell) as u64;
                assert!(share[0] <= first && end <= share[1]);
                let at = first as usize * cell;
                assert!(shared[at..at + cells.len()].iter().all(|&c| c == 0));
                shared[at..at + cells.len()].copy_from_slice(cells);
                Ok::<(), StateError>(())
            })
            .unwrap();
        }
        assert_eq!(shared, d.cells);
        assert_eq!(StateDump::decode(&bytes, u64::MAX).unwrap(), d);
        // The visit stops at the first error of the visitor and returns it.
        let mut seen = 0;
        let stop = runs.try_for_each(|_, _| {
            seen += 1;
            Err(StateError::Malformed("stop".into()))
        });
        assert_eq!((stop, seen), (Err(StateError::Malformed("stop".into())), 1));
    }

    #[test]
    fn non_canonical_runs_and_batches_are_refused() {
        let cell = 4 * 2 + 1;
        let mut d = StateDump {
            cells: vec![0; 54],
            batches: vec![],
            ..dump()
        };
        d.cells[0] = 1;
        d.cells[2 * cell] = 1;
        let bytes = d.encode();
        let runs_at = bytes.len() - 8 - 8 - 8 - 2 * (8 + 8 * cell);
        // Run 2 starts at pixel 2; moving it to pixel 1 makes it touch run 1.
        let mut touching = bytes.clone();
        touching[runs_at + 8 + 8 * cell..][..4].copy_from_slice(&1u32.to_le_bytes());
        assert!(matches!(
            StateDump::decode(&touching, u64::MAX),
            Err(StateError::Malformed(m)) if m.contains("previous run")
        ));
        // An empty pixel inside a run: refused by the decoder, and by the runs before their
        // visitor sees its piece.
        let mut hollow = bytes.clone();
        hollow[runs_at + 8..][..8].copy_from_slice(&0u64.to_le_bytes());
        assert!(matches!(
            StateDump::decode(&hollow, u64::MAX),
            Err(StateError::Malformed(m)) if m.contains("holds nothing")
        ));
        let (_, runs, _) = StateDump::decode_runs(&hollow, u64::MAX).unwrap();
        let mut visited = 0;
        let refused = runs.try_for_each(|_, _| {
            visited += 1;
            Ok::<(), StateError>(())
        });
        assert!(matches!(refused, Err(StateError::Malformed(m)) if m.contains("pixel 0")));
        assert_eq!(visited, 0);
        let mut swapped = dump();
        swapped.batches.reverse();
        assert!(matches!(
            StateDump::decode(&swapped.encode(), u64::MAX),
            Err(StateError::Malformed(m)) if m.contains("out of order")
        ));
        let mut touching = dump();
        touching.batches[0].ranges = vec![0..2, 2..3];
        assert!(matches!(
            StateDump::decode(&touching.encode(), u64::MAX),
            Err(StateError::Malformed(m)) if m.contains("apart")
        ));
    }

    #[test]
    fn wrong_magic_and_version_are_named() {
        let mut bytes = dump().encode();
        bytes[0] = b'X';
        assert!(matches!(
            StateDump::decode(&bytes, u64::MAX),
            Err(StateError::BadMagic { .. })
        ));
        let mut bytes = dump().encode();
        bytes[4] = 9;
        let err = StateDump::decode(&bytes, u64::MAX).unwrap_err();
        assert!(err.to_string().contains("version 9"), "{err}");
    }

    /// A version 1 state (4K cells per pixel, 32 fractional bits) is refused by name, and read
    /// by `decode_v1` only.
    #[test]
    fn version_1_states_are_refused_and_read_only_on_request() {
        let v1 = StateDump {
            frac_bits: 32,
            cells: (0..48).collect(),
            batches: vec![],
            ..dump()
        };
        // 48 = 3 * 2 * 4 * 2 cells: a version 1 count.
        let bytes = v1.encode_v1();
        let err = StateDump::decode(&bytes, u64::MAX).unwrap_err();
        assert_eq!(
            err,
            StateError::UnsupportedVersion {
                found: 1,
                supported: 3
            }
        );
        assert!(
            err.to_string().contains("version 1") && err.to_string().contains("version 3"),
            "{err}"
        );
        assert_eq!(StateDump::decode_v1(&bytes, u64::MAX).unwrap(), v1);
        assert!(matches!(
            StateDump::decode_v1(&dump().encode(), u64::MAX),
            Err(StateError::UnsupportedVersion { found: 3, .. })
        ));
    }
}
