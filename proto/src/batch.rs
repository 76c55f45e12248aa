//! The binary sample batch a render worker POSTs to `/v1/frames/{id}/samples`.
//!
//! # Why a binary format
//!
//! A batch is mostly a long run of fixed-size records (one Monte Carlo sample
//! each), and the server ingests millions of them per second. JSON would
//! triple the bytes on the wire and spend most of the server's time parsing
//! floats, so the body is a fixed little-endian layout that a worker in any
//! language can produce with one array copy (see `proto/python/` for numpy).
//!
//! # Byte layout (version 1)
//!
//! All integers and floats are little-endian; `n` is the record count and
//! `len` the byte length of the frame id.
//!
//! | offset          | size   | field                                    |
//! |-----------------|--------|------------------------------------------|
//! | 0               | 4      | magic `b"SPLB"`                          |
//! | 4               | 2      | format version, `u16` = 1                |
//! | 6               | 8      | `len`: frame id length in bytes, `u64`   |
//! | 14              | len    | frame id, UTF-8 (see [`validate_frame_id`]) |
//! | 14+len          | 8      | worker id, `u64`                         |
//! | 22+len          | 8      | sequence number, `u64`                   |
//! | 30+len          | 8      | `n`: record count, `u64`                 |
//! | 38+len + 20·i   | 4      | record i: pixel `x`, `u32`               |
//! | 42+len + 20·i   | 4      | record i: pixel `y`, `u32`               |
//! | 46+len + 20·i   | 4      | record i: red, `f32`                     |
//! | 50+len + 20·i   | 4      | record i: green, `f32`                   |
//! | 54+len + 20·i   | 4      | record i: blue, `f32`                    |
//!
//! Total size: `4 + 2 + 8 + len + 8 + 8 + 8 + 20·n` bytes; nothing may follow
//! the last record. Everything after the 6-byte preamble is exactly
//! `bincode` 2 with [`bincode::config::legacy()`] (little-endian, fixed-width
//! integers, `u64` length prefixes) applied to the struct
//! `(frame: String, worker: u64, seq: u64, records: Vec<Record>)`. The
//! preamble exists so that a server can refuse a body that is not a batch, or
//! is a batch of a future version, before interpreting any length field.
//!
//! # Decoding untrusted bodies
//!
//! [`Batch::decode`] never trusts a length prefix: the frame id length is
//! checked against [`DecodeLimits::max_frame_id_len`] and the record count
//! against the bytes actually present *before* anything is allocated, so a
//! 40-byte body that declares 2⁴⁰ records fails with [`WireError::Truncated`]
//! without touching the allocator. The header goes through bincode; the
//! records are decoded by a hand-written loop over the 20-byte records
//! because it is several times faster than bincode's serde path (numbers in
//! `PROTOCOL.md`). [`Batch::decode_reference`] keeps the all-bincode decoder
//! so tests can prove the two agree.

use bincode::config::{Configuration, Fixint, Limit, LittleEndian};
use serde::{Deserialize, Serialize};

/// The four bytes every batch starts with.
pub const MAGIC: [u8; 4] = *b"SPLB";

/// The only batch format version this crate reads and writes.
pub const VERSION: u16 = 1;

/// Size of one encoded [`Record`] in bytes.
pub const RECORD_SIZE: usize = 20;

/// Size of the magic and version that precede the bincode body.
pub const PREAMBLE_SIZE: usize = MAGIC.len() + 2;

/// Size of a batch with an empty frame id and no records:
/// magic, version, frame id length, worker, seq and record count.
pub const FIXED_OVERHEAD: usize = PREAMBLE_SIZE + 8 + 8 + 8 + 8;

/// Longest frame id [`validate_frame_id`] accepts, in characters (= bytes).
pub const MAX_FRAME_ID_LEN: usize = 128;

/// Default for [`DecodeLimits::max_records`]: 4 Mi records (80 MiB of records).
pub const DEFAULT_MAX_RECORDS: usize = 4 * 1024 * 1024;

/// Upper bound on the bytes any single bincode decode call may consume.
///
/// This is a backstop inside bincode itself, not the policy knob: the policy
/// is [`DecodeLimits`], and [`Batch::decode`] checks every length prefix
/// before bincode sees it. Because this bound is a compile-time constant,
/// [`DecodeLimits::max_records`] is clamped to [`HARD_MAX_RECORDS`] so that
/// both decoders always accept exactly the same inputs.
pub const BINCODE_DECODE_LIMIT: usize = 1 << 30;

/// The largest record count any [`DecodeLimits`] can allow (about 53 Mi).
pub const HARD_MAX_RECORDS: usize =
    (BINCODE_DECODE_LIMIT - (FIXED_OVERHEAD + MAX_FRAME_ID_LEN)) / RECORD_SIZE;

/// The bincode configuration of the wire format: the one place it is pinned.
///
/// `legacy()` is bincode 1's layout (little-endian, fixed-width integers,
/// `u64` lengths), which is trivial to reproduce in other languages; the
/// varint encoding of `standard()` is not.
type WireConfig = Configuration<LittleEndian, Fixint, Limit<BINCODE_DECODE_LIMIT>>;

const WIRE_CONFIG: WireConfig = bincode::config::legacy().with_limit::<BINCODE_DECODE_LIMIT>();

/// One Monte Carlo sample: the radiance a path contributed to pixel `(x, y)`.
///
/// The server counts every record as one sample of its pixel; workers must
/// not pre-average several samples into one record.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[repr(C)]
pub struct Record {
    /// Column, `0..width`, left to right.
    pub x: u32,
    /// Row, `0..height`, top to bottom.
    pub y: u32,
    /// Linear RGB radiance; the server rejects NaN, infinities and negatives.
    pub rgb: [f32; 3],
}

// SAFETY: `Record` is `repr(C)` with five 4-byte fields, so it has no padding (its size is
// checked below), and every value of its 20 bytes is a valid `Record` (two `u32`, three `f32`).
unsafe impl bytemuck::Zeroable for Record {}
// SAFETY: as above; it is `Copy` and `'static`.
unsafe impl bytemuck::Pod for Record {}
const _: () = assert!(std::mem::size_of::<Record>() == RECORD_SIZE);

/// Whether a record's wire bytes are its bytes in memory: on a little-endian machine, where
/// records are hashed where they lie.
const WIRE_IS_MEMORY: bool = cfg!(target_endian = "little");

impl Record {
    /// A sample of pixel `(x, y)` with radiance `rgb`.
    pub const fn new(x: u32, y: u32, rgb: [f32; 3]) -> Record {
        Record { x, y, rgb }
    }

    /// The record's 20 wire bytes.
    #[inline(always)]
    fn to_wire(self) -> [u8; RECORD_SIZE] {
        let mut b = [0u8; RECORD_SIZE];
        b[0..4].copy_from_slice(&self.x.to_le_bytes());
        b[4..8].copy_from_slice(&self.y.to_le_bytes());
        for (c, v) in self.rgb.iter().enumerate() {
            b[8 + 4 * c..12 + 4 * c].copy_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// Decodes one record from its 20 wire bytes.
    #[inline(always)]
    fn from_wire(b: &[u8; RECORD_SIZE]) -> Record {
        let [x0, x1, x2, x3, y0, y1, y2, y3, r0, r1, r2, r3, g0, g1, g2, g3, b0, b1, b2, b3] = *b;
        Record {
            x: u32::from_le_bytes([x0, x1, x2, x3]),
            y: u32::from_le_bytes([y0, y1, y2, y3]),
            rgb: [
                f32::from_le_bytes([r0, r1, r2, r3]),
                f32::from_le_bytes([g0, g1, g2, g3]),
                f32::from_le_bytes([b0, b1, b2, b3]),
            ],
        }
    }
}

/// [`Batch::content_digest`] of a batch with these records.
pub fn records_digest(records: &[Record]) -> u64 {
    let mut digest = RecordsDigest::new();
    digest.update(records);
    digest.finish()
}

/// [`records_digest`] of records that come a slice at a time (say, as [`Batch::decode_visiting`]
/// decodes them): the same digest as of all of them in one slice.
pub struct RecordsDigest(WireDigest);

impl RecordsDigest {
    /// The digest of no records yet.
    pub fn new() -> RecordsDigest {
        RecordsDigest(WireDigest::new())
    }

    /// Adds `records`, after every record added before.
    pub fn update(&mut self, records: &[Record]) {
        if WIRE_IS_MEMORY {
            // Their bytes as they lie are their wire bytes: straight to the hasher.
            self.0.flush();
            self.0.hasher.update(bytemuck::cast_slice(records));
        } else {
            for &record in records {
                self.0.push(record);
            }
        }
    }

    /// The digest of every record added, as [`records_digest`] of them.
    pub fn finish(self) -> u64 {
        self.0.finish()
    }
}

impl Default for RecordsDigest {
    fn default() -> Self {
        RecordsDigest::new()
    }
}

impl std::fmt::Debug for RecordsDigest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RecordsDigest")
    }
}

/// [`records_digest`] of records made on the fly (say, the pixels of a rendered pass), without
/// collecting them first: the same digest as of the slice of the same records.
pub fn records_digest_of(records: impl IntoIterator<Item = Record>) -> u64 {
    let mut digest = WireDigest::new();
    for record in records {
        digest.push(record);
    }
    digest.finish()
}

/// [`records_digest`] of a whole pass of a `width`-pixel-wide frame: one record per pixel of
/// `rgb`, row-major. The same digest as of those records, made row by row (no division per
/// pixel to find its coordinates: that took most of a 1080p pass's digest) and handed to a
/// [`RecordsDigest`] a run of up to 1024 pixels of a row at a time. Pushed into the digest a
/// record at a time, each with a check for a full buffer, a 1080p pass took 6.9-7.1 ms on one
/// core of a 2-core Intel Xeon VM; this way 3.9-4.1 ms, 2.3-2.5 of them hashing the 41 MB of
/// wire bytes. (The server digests a pass on one thread before it splats it.)
///
/// # Panics
/// If `width` is 0.
pub fn pass_digest(width: usize, rgb: &[[f32; 3]]) -> u64 {
    let mut digest = RecordsDigest::new();
    let mut records = [Record::new(0, 0, [0.0; 3]); PASS_DIGEST_RUN];
    for (y, row) in rgb.chunks(width).enumerate() {
        for (r, run) in row.chunks(PASS_DIGEST_RUN).enumerate() {
            let x0 = r * PASS_DIGEST_RUN;
            for (i, (record, &c)) in records.iter_mut().zip(run).enumerate() {
                *record = Record::new((x0 + i) as u32, y as u32, c);
            }
            digest.update(&records[..run.len()]);
        }
    }
    digest.finish()
}

/// Pixels of a row [`pass_digest`] makes into records at once (20 KiB of them, in L1).
const PASS_DIGEST_RUN: usize = 1024;

/// An xxh3 of records' wire bytes, fed through a small buffer, so the digest is the same on
/// every platform and costs one pass over the records.
struct WireDigest {
    hasher: xxhash_rust::xxh3::Xxh3,
    buffer: [u8; WireDigest::CHUNK * RECORD_SIZE],
    filled: usize,
}

impl WireDigest {
    const CHUNK: usize = 1024;

    fn new() -> WireDigest {
        WireDigest {
            hasher: xxhash_rust::xxh3::Xxh3::new(),
            buffer: [0; WireDigest::CHUNK * RECORD_SIZE],
            filled: 0,
        }
    }

    #[inline(always)]
    fn push(&mut self, record: Record) {
        self.buffer[self.filled..self.filled + RECORD_SIZE].copy_from_slice(&record.to_wire());
        self.filled += RECORD_SIZE;
        if self.filled == self.buffer.len() {
            self.hasher.update(&self.buffer);
            self.filled = 0;
        }
    }

    /// Hashes the records buffered so far.
    fn flush(&mut self) {
        self.hasher.update(&self.buffer[..self.filled]);
        self.filled = 0;
    }

    fn finish(mut self) -> u64 {
        self.flush();
        self.hasher.digest()
    }
}

/// A batch of samples for one frame from one worker.
///
/// `(worker, seq)` identifies the batch: a worker that retries must resend
/// the same bytes with the same `seq`, so that the server can recognise and
/// drop the duplicate.
#[derive(Debug, Clone, PartialEq)]
pub struct Batch {
    /// Frame id, see [`validate_frame_id`].
    pub frame: String,
    /// Id of the sending worker, chosen by the worker (e.g. random at start-up).
    pub worker: u64,
    /// Per-worker sequence number of this batch.
    pub seq: u64,
    /// The samples.
    pub records: Vec<Record>,
}

/// Limits [`Batch::decode`] enforces on untrusted input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodeLimits {
    /// Most records one batch may carry (clamped to [`HARD_MAX_RECORDS`]).
    pub max_records: usize,
    /// Longest frame id in bytes (ids are also capped at [`MAX_FRAME_ID_LEN`]
    /// by [`validate_frame_id`]).
    pub max_frame_id_len: usize,
}

impl Default for DecodeLimits {
    fn default() -> Self {
        DecodeLimits {
            max_records: DEFAULT_MAX_RECORDS,
            max_frame_id_len: MAX_FRAME_ID_LEN,
        }
    }
}

impl DecodeLimits {
    /// The record limit actually applied.
    pub fn effective_max_records(&self) -> usize {
        self.max_records.min(HARD_MAX_RECORDS)
    }

    /// The largest body these limits can accept, in bytes: a server can
    /// refuse longer bodies (HTTP 413) before reading them.
    pub fn max_body_len(&self) -> usize {
        let id_len = self.max_frame_id_len.min(MAX_FRAME_ID_LEN);
        FIXED_OVERHEAD + id_len + self.effective_max_records() * RECORD_SIZE
    }
}

/// Why a batch (or a frame id) was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// The body does not start with [`MAGIC`].
    #[error("not a splatd batch: expected magic \"SPLB\", found \"{}\"", found.escape_ascii())]
    BadMagic {
        /// The first (up to) four bytes of the body.
        found: Vec<u8>,
    },
    /// The body is a batch of a format version this build cannot read.
    #[error("unsupported batch format version {found}; this build reads version {supported}")]
    UnsupportedVersion {
        /// Version in the body.
        found: u16,
        /// Version this build supports.
        supported: u16,
    },
    /// The body ends before the data its header declares.
    #[error(
        "batch is truncated: its header declares at least {needed} bytes, the body has {available}"
    )]
    Truncated {
        /// Bytes the body would need (saturating at `u64::MAX`).
        needed: u64,
        /// Bytes the body has.
        available: u64,
    },
    /// The batch declares more records than the limits allow.
    #[error("batch declares {count} records; at most {max} are accepted per batch")]
    TooManyRecords {
        /// Declared record count.
        count: u64,
        /// The applied limit.
        max: usize,
    },
    /// Bytes follow the last declared record.
    #[error("batch has {count} unexpected bytes after its last record")]
    TrailingBytes {
        /// Number of extra bytes.
        count: usize,
    },
    /// The frame id breaks the rules of [`validate_frame_id`].
    #[error("invalid frame id: {reason}")]
    InvalidFrameId {
        /// What is wrong with it.
        reason: String,
    },
    /// Anything else the decoder rejects, e.g. a frame id that is not UTF-8.
    #[error("malformed batch: {0}")]
    Malformed(String),
}

impl WireError {
    /// Machine-readable code for [`crate::ErrorBody::error`].
    pub fn code(&self) -> &'static str {
        match self {
            WireError::BadMagic { .. } => "bad_magic",
            WireError::UnsupportedVersion { .. } => "unsupported_version",
            WireError::Truncated { .. } => "truncated_batch",
            WireError::TooManyRecords { .. } => "too_many_records",
            WireError::TrailingBytes { .. } => "trailing_bytes",
            WireError::InvalidFrameId { .. } => "invalid_frame_id",
            WireError::Malformed(_) => "malformed_batch",
        }
    }
}

/// Checks a frame id: 1 to [`MAX_FRAME_ID_LEN`] characters from
/// `[A-Za-z0-9._-]`, and not `.` or `..`.
///
/// The ids end up in URL paths and possibly file names, so they are kept to
/// characters that need no escaping anywhere; `.` and `..` are refused
/// because URL libraries collapse them as path segments.
pub fn validate_frame_id(id: &str) -> Result<(), WireError> {
    let invalid = |reason: String| Err(WireError::InvalidFrameId { reason });
    if id.is_empty() {
        return invalid("frame id is empty".into());
    }
    if let Some((pos, c)) = id
        .chars()
        .enumerate()
        .find(|&(_, c)| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')))
    {
        return invalid(format!(
            "character {c:?} at position {pos} is not allowed; use only A-Z, a-z, 0-9, '.', '_' and '-'"
        ));
    }
    // All characters are ASCII now, so bytes = characters.
    if id.len() > MAX_FRAME_ID_LEN {
        return invalid(format!(
            "frame id is {} characters long; at most {MAX_FRAME_ID_LEN} are allowed",
            id.len()
        ));
    }
    if id == "." || id == ".." {
        return invalid(format!("{id:?} is reserved as a path segment"));
    }
    Ok(())
}

/// The bincode body of a batch, borrowed for encoding.
#[derive(Serialize)]
struct BodyRef<'a> {
    frame: &'a str,
    worker: u64,
    seq: u64,
    records: &'a [Record],
}

/// The bincode body of a batch, owned; used by [`Batch::decode_reference`].
#[derive(Deserialize)]
struct BodyOwned {
    frame: String,
    worker: u64,
    seq: u64,
    records: Vec<Record>,
}

/// The bincode body up to and including the record count.
#[derive(Deserialize)]
struct Header {
    frame: String,
    worker: u64,
    seq: u64,
    count: u64,
}

/// A checked header, and where the body's records start: it holds exactly `count` of them
/// from there to its end.
struct Parsed {
    header: Header,
    records_start: usize,
}

/// The most bytes a batch's header (preamble, frame id and the three counts) takes: a body's
/// first `HEAD_MAX` bytes are all [`parse`] reads.
const HEAD_MAX: usize = FIXED_OVERHEAD + MAX_FRAME_ID_LEN;

impl Batch {
    /// A batch whose frame id has been checked with [`validate_frame_id`].
    pub fn new(
        frame: impl Into<String>,
        worker: u64,
        seq: u64,
        records: Vec<Record>,
    ) -> Result<Batch, WireError> {
        let frame = frame.into();
        validate_frame_id(&frame)?;
        Ok(Batch {
            frame,
            worker,
            seq,
            records,
        })
    }

    /// Size of [`Batch::encode`]'s output in bytes.
    pub fn encoded_len(&self) -> usize {
        FIXED_OVERHEAD + self.frame.len() + RECORD_SIZE * self.records.len()
    }

    /// What the batch contains, in 64 bits: XXH3 of its records' wire bytes in order (the frame,
    /// worker and sequence number are not part of it). The server keeps it per applied
    /// `(worker, seq)`, so that a retry (same id, same records) is told apart from a different
    /// batch sent under an id that was already used. Stable across versions and platforms: it is
    /// stored in snapshots.
    pub fn content_digest(&self) -> u64 {
        records_digest(&self.records)
    }

    /// Checks what [`Batch::decode`] would check about the batch itself,
    /// i.e. the frame id (the record count is a receiver's policy).
    pub fn validate(&self) -> Result<(), WireError> {
        validate_frame_id(&self.frame)
    }

    /// Encodes the batch in the layout described in the module docs.
    ///
    /// Encoding does not validate: call [`Batch::validate`] (or build with
    /// [`Batch::new`]) to catch a bad frame id before the server does.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.encoded_len());
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        let body = BodyRef {
            frame: &self.frame,
            worker: self.worker,
            seq: self.seq,
            records: &self.records,
        };
        // Writing into a Vec cannot fail, and these types serialise without
        // custom errors (the slice reports its length), so an error here is
        // a bug in this crate, not bad input.
        bincode::serde::encode_into_std_write(&body, &mut out, WIRE_CONFIG)
            .expect("bincode encoding of a batch into a Vec<u8> is infallible");
        debug_assert_eq!(out.len(), self.encoded_len());
        out
    }

    /// Decodes and checks an untrusted batch body.
    ///
    /// Checks, in order: magic, version, frame id length, header, frame id,
    /// record count against the bytes present, record count against
    /// `limits`, trailing bytes. Record values are not checked here (NaN or
    /// out-of-range pixels are the server's business).
    pub fn decode(bytes: &[u8], limits: &DecodeLimits) -> Result<Batch, WireError> {
        Batch::decode_visiting(bytes, limits, |_| {})
    }

    /// [`Batch::decode`], calling `visit` with each run of up to [`DECODE_RUN`] records as soon
    /// as it is decoded (in order; together, all of them), while those records are still in the
    /// CPU's cache: a receiver that checks or hashes every record does it in the same pass over
    /// memory as the decoding, not in passes of its own over a batch larger than the cache.
    /// `visit` is not called for a body that fails a check.
    pub fn decode_visiting(
        bytes: &[u8],
        limits: &DecodeLimits,
        visit: impl FnMut(&[Record]),
    ) -> Result<Batch, WireError> {
        Batch::decode_pieces_visiting(&[bytes], limits, visit)
    }

    /// [`Batch::decode_visiting`] of a body held in the pieces it arrived in (a request body's
    /// frames, in order): the same batch, or the same error, as of the pieces joined, and the
    /// same runs visited, with each record decoded straight from its piece (a record cut
    /// between two pieces is put together first). Joining the pieces into one buffer before
    /// decoding copied every byte of every batch once more.
    pub fn decode_pieces_visiting<P: AsRef<[u8]>>(
        pieces: &[P],
        limits: &DecodeLimits,
        mut visit: impl FnMut(&[Record]),
    ) -> Result<Batch, WireError> {
        let total: usize = pieces.iter().map(|p| p.as_ref().len()).sum();
        // The header is in the first piece but for a body cut up very finely.
        let head_len = total.min(HEAD_MAX);
        let first = pieces.first().map_or(&[][..], |p| p.as_ref());
        let gathered: Vec<u8>;
        let head = if first.len() >= head_len {
            &first[..head_len]
        } else {
            gathered = pieces
                .iter()
                .flat_map(|p| p.as_ref())
                .copied()
                .take(head_len)
                .collect();
            &gathered
        };
        let Parsed {
            header,
            records_start,
        } = parse(head, total, limits)?;
        // `parse` checked that the body holds exactly `count` records after the header.
        let count = header.count as usize;
        let mut out = Vec::with_capacity(count);
        let mut visited = 0;
        // Visits the records decoded since the last visit once there are DECODE_RUN of them.
        let mut visit_full = |out: &Vec<Record>, visited: &mut usize| {
            if out.len() - *visited == DECODE_RUN {
                visit(&out[*visited..]);
                *visited = out.len();
            }
        };
        let mut cut = [0u8; RECORD_SIZE];
        let mut cut_len = 0;
        let mut skip = records_start;
        for piece in pieces {
            let mut bytes = piece.as_ref();
            if skip >= bytes.len() {
                skip -= bytes.len();
                continue;
            }
            bytes = &bytes[skip..];
            skip = 0;
            if cut_len > 0 {
                // The rest of a record the piece before ended in.
                let take = (RECORD_SIZE - cut_len).min(bytes.len());
                cut[cut_len..cut_len + take].copy_from_slice(&bytes[..take]);
                cut_len += take;
                bytes = &bytes[take..];
                if cut_len < RECORD_SIZE {
                    continue;
                }
                out.push(Record::from_wire(&cut));
                visit_full(&out, &mut visited);
            }
            while bytes.len() >= RECORD_SIZE {
                let room = DECODE_RUN - (out.len() - visited);
                let whole = (bytes.len() / RECORD_SIZE).min(room);
                let (now, rest) = bytes.split_at(whole * RECORD_SIZE);
                decode_records(now, &mut out);
                bytes = rest;
                visit_full(&out, &mut visited);
            }
            cut[..bytes.len()].copy_from_slice(bytes);
            cut_len = bytes.len();
        }
        debug_assert!(
            cut_len == 0 && out.len() == count,
            "parse counted the records"
        );
        if visited < out.len() {
            visit(&out[visited..]);
        }
        Ok(Batch {
            frame: header.frame,
            worker: header.worker,
            seq: header.seq,
            records: out,
        })
    }

    /// Same as [`Batch::decode`], but decodes the whole body, records
    /// included, with bincode's serde path.
    ///
    /// Slower; kept as the reference the fast decoder is tested and
    /// benchmarked against.
    pub fn decode_reference(bytes: &[u8], limits: &DecodeLimits) -> Result<Batch, WireError> {
        // Run every check of the fast path first, so both accept exactly the
        // same inputs and bincode never sees an unchecked length.
        parse(&bytes[..bytes.len().min(HEAD_MAX)], bytes.len(), limits)?;
        let (body, _): (BodyOwned, usize) =
            bincode::serde::decode_from_slice(&bytes[PREAMBLE_SIZE..], WIRE_CONFIG)
                .map_err(|e| bincode_error(e, bytes.len()))?;
        Ok(Batch {
            frame: body.frame,
            worker: body.worker,
            seq: body.seq,
            records: body.records,
        })
    }
}

/// Records [`Batch::decode_visiting`] decodes between two visits: 80 KiB of them, which stay in
/// a core's L2 cache until visited.
pub const DECODE_RUN: usize = 4096;

/// Appends the records in `bytes` (a multiple of [`RECORD_SIZE`] long) to `out`.
fn decode_records(mut bytes: &[u8], out: &mut Vec<Record>) {
    while let Some((record, rest)) = bytes.split_first_chunk::<RECORD_SIZE>() {
        out.push(Record::from_wire(record));
        bytes = rest;
    }
    debug_assert!(bytes.is_empty(), "caller passes whole records only");
}

/// Every structural check of a batch body of `total` bytes, whose first
/// `min(total, HEAD_MAX)` bytes are `bytes`; allocates only the frame id,
/// after its length has been checked.
fn parse(bytes: &[u8], total: usize, limits: &DecodeLimits) -> Result<Parsed, WireError> {
    debug_assert_eq!(bytes.len(), total.min(HEAD_MAX), "the body's head");
    let available = total as u64;
    let truncated = |needed: u64| WireError::Truncated { needed, available };

    let magic_len = bytes.len().min(MAGIC.len());
    if bytes[..magic_len] != MAGIC[..magic_len] {
        return Err(WireError::BadMagic {
            found: bytes[..magic_len].to_vec(),
        });
    }
    let Some((&[_, _, _, _, v0, v1], _)) = bytes.split_first_chunk::<PREAMBLE_SIZE>() else {
        return Err(truncated(PREAMBLE_SIZE as u64));
    };
    let version = u16::from_le_bytes([v0, v1]);
    if version != VERSION {
        return Err(WireError::UnsupportedVersion {
            found: version,
            supported: VERSION,
        });
    }

    // Look at the frame id length before bincode allocates a String for it.
    let body = &bytes[PREAMBLE_SIZE..];
    let Some((id_len, _)) = body.split_first_chunk::<8>() else {
        return Err(truncated((PREAMBLE_SIZE + 8) as u64));
    };
    let id_len = u64::from_le_bytes(*id_len);
    let max_id_len = limits.max_frame_id_len.min(MAX_FRAME_ID_LEN);
    if id_len > max_id_len as u64 {
        return Err(WireError::InvalidFrameId {
            reason: format!("frame id is {id_len} bytes long; at most {max_id_len} are allowed"),
        });
    }

    // The header fits in the head (its frame id is at most MAX_FRAME_ID_LEN bytes, checked
    // above), so bincode runs out of bytes here only where the whole body ends.
    let (header, header_len): (Header, usize) =
        bincode::serde::decode_from_slice(body, WIRE_CONFIG)
            .map_err(|e| bincode_error(e, total))?;
    validate_frame_id(&header.frame)?;

    let records_start = PREAMBLE_SIZE + header_len;
    let records = total - records_start;
    let records_len = header.count.saturating_mul(RECORD_SIZE as u64);
    if (records as u64) < records_len {
        return Err(truncated(
            (records_start as u64).saturating_add(records_len),
        ));
    }
    let max = limits.effective_max_records();
    if header.count > max as u64 {
        return Err(WireError::TooManyRecords {
            count: header.count,
            max,
        });
    }
    // count <= max, so this fits in usize and does not overflow.
    let records_len = header.count as usize * RECORD_SIZE;
    if records > records_len {
        return Err(WireError::TrailingBytes {
            count: records - records_len,
        });
    }
    Ok(Parsed {
        header,
        records_start,
    })
}

/// Translates a bincode decode error into a [`WireError`].
fn bincode_error(e: bincode::error::DecodeError, available: usize) -> WireError {
    use bincode::error::DecodeError;
    match e {
        DecodeError::UnexpectedEnd { additional } => WireError::Truncated {
            needed: (available as u64).saturating_add(additional as u64),
            available: available as u64,
        },
        DecodeError::Utf8 { inner } => {
            WireError::Malformed(format!("frame id is not valid UTF-8: {inner}"))
        }
        other => WireError::Malformed(other.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pass's digest is its records' digest, whatever the width (one column, one row, many
    /// rows, rows of exactly one run of the digest's buffer and one pixel more), and it changes
    /// with any value.
    #[test]
    fn a_pass_digest_is_the_digest_of_its_records() {
        for (w, h) in [
            (1, 1),
            (1, 7),
            (7, 1),
            (33, 65),
            (PASS_DIGEST_RUN, 2),
            (PASS_DIGEST_RUN + 1, 2),
            (1920, 3),
        ] {
            let rgb: Vec<[f32; 3]> = (0..w * h)
                .map(|i| [i as f32, (i * 3 % 17) as f32 * 0.5, 1.0 / (i + 1) as f32])
                .collect();
            let records: Vec<Record> = rgb
                .iter()
                .enumerate()
                .map(|(i, &c)| Record::new((i % w) as u32, (i / w) as u32, c))
                .collect();
            assert_eq!(pass_digest(w, &rgb), records_digest(&records), "{w}x{h}");
            let mut changed = rgb.clone();
            changed[w * h - 1][1] += 1.0;
            assert_ne!(pass_digest(w, &changed), pass_digest(w, &rgb), "{w}x{h}");
        }
    }

    fn sample() -> Batch {
        Batch::new(
            "f1",
            7,
            3,
            vec![
                Record::new(1, 2, [0.5, 1.0, 2.0]),
                Record::new(u32::MAX, 0, [0.0, -0.0, 65504.0]),
            ],
        )
        .expect("valid frame id")
    }

    fn limits() -> DecodeLimits {
        DecodeLimits::default()
    }

    use splatd_scenes::synth::SplitMix64;

    #[test]
    fn layout_is_as_documented() {
        let b = sample();
        let bytes = b.encode();
        assert_eq!(bytes.len(), 4 + 2 + 8 + 2 + 8 + 8 + 8 + 20 * 2);
        assert_eq!(bytes.len(), b.encoded_len());
        assert_eq!(&bytes[0..4], b"SPLB");
        assert_eq!(&bytes[4..6], &1u16.to_le_bytes());
        assert_eq!(&bytes[6..14], &2u64.to_le_bytes());
        assert_eq!(&bytes[14..16], b"f1");
        assert_eq!(&bytes[16..24], &7u64.to_le_bytes());
        assert_eq!(&bytes[24..32], &3u64.to_le_bytes());
        assert_eq!(&bytes[32..40], &2u64.to_le_bytes());
        let r1 = &bytes[40 + 20..];
        assert_eq!(&r1[0..4], &u32::MAX.to_le_bytes());
        assert_eq!(&r1[4..8], &0u32.to_le_bytes());
        assert_eq!(&r1[8..12], &0.0f32.to_le_bytes());
        assert_eq!(&r1[12..16], &(-0.0f32).to_le_bytes());
        assert_eq!(&r1[16..20], &65504.0f32.to_le_bytes());
    }

    #[test]
    fn round_trip() {
        let b = sample();
        let bytes = b.encode();
        assert_eq!(Batch::decode(&bytes, &limits()), Ok(b.clone()));
        assert_eq!(Batch::decode_reference(&bytes, &limits()), Ok(b));
    }

    #[test]
    fn empty_batch_round_trips() {
        let b = Batch::new("x", 0, 0, vec![]).expect("valid");
        let bytes = b.encode();
        assert_eq!(bytes.len(), FIXED_OVERHEAD + 1);
        assert_eq!(Batch::decode(&bytes, &limits()), Ok(b));
    }

    #[test]
    fn fast_and_reference_decoders_agree_on_random_batches() {
        let mut rng = SplitMix64::new(0x5EED);
        for round in 0..200 {
            let n = (rng.next_u64() % 300) as usize;
            let records = (0..n)
                .map(|_| {
                    let v = rng.next_u64();
                    let w = rng.next_u64();
                    // Arbitrary bit patterns: NaNs, infinities, subnormals.
                    Record::new(
                        v as u32,
                        (v >> 32) as u32,
                        [
                            f32::from_bits(w as u32),
                            f32::from_bits((w >> 32) as u32),
                            f32::from_bits(rng.next_u64() as u32),
                        ],
                    )
                })
                .collect();
            let frame = format!("frame-{round}.{}", rng.next_u64() % 1000);
            let b = Batch::new(frame, rng.next_u64(), rng.next_u64(), records).expect("valid");
            let bytes = b.encode();
            let fast = Batch::decode(&bytes, &limits()).expect("fast decode");
            let slow = Batch::decode_reference(&bytes, &limits()).expect("reference decode");
            // Compare through the encoding: NaN != NaN, but bits must agree.
            assert_eq!(fast.encode(), bytes, "fast decoder, round {round}");
            assert_eq!(slow.encode(), bytes, "reference decoder, round {round}");
            // Every corruption must be judged identically, too.
            let cut = (rng.next_u64() as usize) % bytes.len();
            assert_eq!(
                Batch::decode(&bytes[..cut], &limits()),
                Batch::decode_reference(&bytes[..cut], &limits()),
                "truncated at {cut}, round {round}"
            );
        }
    }

    #[test]
    fn bad_magic() {
        let mut bytes = sample().encode();
        bytes[0] = b'X';
        let err = Batch::decode(&bytes, &limits()).unwrap_err();
        assert_eq!(
            err,
            WireError::BadMagic {
                found: b"XPLB".to_vec()
            }
        );
        assert!(err.to_string().contains("XPLB"), "{err}");
        assert!(matches!(
            Batch::decode(b"{\"", &limits()),
            Err(WireError::BadMagic { .. })
        ));
    }

    #[test]
    fn short_prefix_of_magic_is_truncated() {
        assert_eq!(
            Batch::decode(b"SP", &limits()),
            Err(WireError::Truncated {
                needed: 6,
                available: 2
            })
        );
        assert!(matches!(
            Batch::decode(b"", &limits()),
            Err(WireError::Truncated { .. })
        ));
    }

    #[test]
    fn unsupported_version() {
        let mut bytes = sample().encode();
        bytes[4..6].copy_from_slice(&2u16.to_le_bytes());
        let err = Batch::decode(&bytes, &limits()).unwrap_err();
        assert_eq!(
            err,
            WireError::UnsupportedVersion {
                found: 2,
                supported: 1
            }
        );
        assert!(err.to_string().contains("version 2"), "{err}");
    }

    #[test]
    fn every_truncation_is_refused() {
        let bytes = sample().encode();
        for cut in 0..bytes.len() {
            match Batch::decode(&bytes[..cut], &limits()) {
                Err(WireError::Truncated { needed, available }) => {
                    assert_eq!(available, cut as u64);
                    assert!(needed > available, "cut {cut}: needed {needed}");
                }
                other => panic!("cut at {cut}: expected Truncated, got {other:?}"),
            }
        }
    }

    #[test]
    fn huge_record_count_in_tiny_body_is_refused_before_allocating() {
        let mut bytes = Batch::new("f", 1, 1, vec![]).expect("valid").encode();
        let count_at = bytes.len() - 8;
        bytes[count_at..].copy_from_slice(&(1u64 << 40).to_le_bytes());
        let err = Batch::decode(&bytes, &limits()).unwrap_err();
        assert_eq!(
            err,
            WireError::Truncated {
                needed: bytes.len() as u64 + (1u64 << 40) * 20,
                available: bytes.len() as u64
            }
        );
        bytes[count_at..].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(
            Batch::decode(&bytes, &limits()),
            Err(WireError::Truncated {
                needed: u64::MAX,
                ..
            })
        ));
        assert!(matches!(
            Batch::decode_reference(&bytes, &limits()),
            Err(WireError::Truncated { .. })
        ));
    }

    #[test]
    fn huge_frame_id_length_is_refused_before_allocating() {
        let mut bytes = sample().encode();
        bytes[6..14].copy_from_slice(&u64::MAX.to_le_bytes());
        let err = Batch::decode(&bytes, &limits()).unwrap_err();
        assert!(matches!(err, WireError::InvalidFrameId { .. }), "{err:?}");
        assert!(err.to_string().contains("at most 128"), "{err}");
    }

    #[test]
    fn too_many_records() {
        let b = sample();
        let small = DecodeLimits {
            max_records: 1,
            ..limits()
        };
        assert_eq!(
            Batch::decode(&b.encode(), &small),
            Err(WireError::TooManyRecords { count: 2, max: 1 })
        );
        let huge = DecodeLimits {
            max_records: usize::MAX,
            ..limits()
        };
        assert_eq!(huge.effective_max_records(), HARD_MAX_RECORDS);
        assert_eq!(Batch::decode(&b.encode(), &huge), Ok(b));
    }

    #[test]
    fn trailing_bytes() {
        let mut bytes = sample().encode();
        bytes.extend_from_slice(&[0, 0, 0]);
        assert_eq!(
            Batch::decode(&bytes, &limits()),
            Err(WireError::TrailingBytes { count: 3 })
        );
        assert_eq!(
            Batch::decode_reference(&bytes, &limits()),
            Err(WireError::TrailingBytes { count: 3 })
        );
    }

    #[test]
    fn invalid_utf8_frame_id_is_malformed() {
        let mut bytes = sample().encode();
        bytes[14] = 0xFF;
        let err = Batch::decode(&bytes, &limits()).unwrap_err();
        assert!(matches!(err, WireError::Malformed(_)), "{err:?}");
        assert!(err.to_string().contains("UTF-8"), "{err}");
    }

    #[test]
    fn invalid_frame_id_in_body() {
        let b = Batch {
            frame: "a/b".into(),
            worker: 1,
            seq: 1,
            records: vec![],
        };
        assert!(matches!(
            Batch::decode(&b.encode(), &limits()),
            Err(WireError::InvalidFrameId { .. })
        ));
        let tight = DecodeLimits {
            max_frame_id_len: 1,
            ..limits()
        };
        assert!(matches!(
            Batch::decode(&sample().encode(), &tight),
            Err(WireError::InvalidFrameId { .. })
        ));
    }

    #[test]
    fn frame_id_rules() {
        for ok in ["a", "shot_010.v2-final", "0", &"x".repeat(128), "..."] {
            assert_eq!(validate_frame_id(ok), Ok(()), "{ok:?}");
        }
        for bad in ["", ".", "..", "a/b", "a b", "é", "a%2F", &"x".repeat(129)] {
            let err = validate_frame_id(bad).expect_err(bad);
            assert!(matches!(err, WireError::InvalidFrameId { .. }));
            assert!(!err.to_string().is_empty());
        }
        let err = validate_frame_id("ab/c").unwrap_err();
        assert!(err.to_string().contains("'/' at position 2"), "{err}");
        assert!(Batch::new("a/b", 0, 0, vec![]).is_err());
    }

    #[test]
    fn limits_helpers() {
        let l = DecodeLimits::default();
        assert_eq!(l.max_records, 4 * 1024 * 1024);
        assert_eq!(l.max_body_len(), 38 + 128 + 20 * 4 * 1024 * 1024);
    }

    #[test]
    fn decoding_visits_every_record_once_in_runs_and_hashes_alike_in_pieces() {
        let limits = DecodeLimits {
            max_records: usize::MAX,
            ..DecodeLimits::default()
        };
        for n in [0, 1, DECODE_RUN - 1, DECODE_RUN, 2 * DECODE_RUN + 7] {
            let records: Vec<Record> = (0..n as u32)
                .map(|i| Record::new(i, i / 3, [i as f32, 0.25, 7.0]))
                .collect();
            let bytes = Batch::new("f", 1, 2, records.clone()).unwrap().encode();
            let (mut seen, mut runs) = (Vec::new(), 0);
            let mut digest = RecordsDigest::new();
            let batch = Batch::decode_visiting(&bytes, &limits, |run| {
                assert!(!run.is_empty() && run.len() <= DECODE_RUN, "{}", run.len());
                seen.extend_from_slice(run);
                digest.update(run);
                runs += 1;
            })
            .unwrap();
            assert_eq!(batch.records, records);
            assert_eq!(seen, records, "every record once, in order");
            assert_eq!(runs, n.div_ceil(DECODE_RUN));
            assert_eq!(digest.finish(), batch.content_digest(), "{n} records");
        }
        // A body that fails a check is not visited.
        let bytes = sample().encode();
        let cut = &bytes[..bytes.len() - 1];
        let mut visited = false;
        assert!(Batch::decode_visiting(cut, &limits, |_| visited = true).is_err());
        assert!(!visited);
    }

    /// Decodes `bytes` cut into `pieces` at the given points, and whole; returns both results
    /// and the runs each visited.
    #[allow(clippy::type_complexity)]
    fn whole_and_in_pieces(
        bytes: &[u8],
        cuts: &[usize],
        limits: &DecodeLimits,
    ) -> (
        (Result<Batch, WireError>, Vec<Vec<Record>>),
        (Result<Batch, WireError>, Vec<Vec<Record>>),
    ) {
        let mut at: Vec<usize> = cuts.iter().map(|&c| c.min(bytes.len())).collect();
        at.sort_unstable();
        let pieces: Vec<&[u8]> = std::iter::once(0)
            .chain(at.iter().copied())
            .zip(at.iter().copied().chain(std::iter::once(bytes.len())))
            .map(|(a, b)| &bytes[a..b])
            .collect();
        let mut runs = Vec::new();
        let whole = Batch::decode_visiting(bytes, limits, |r| runs.push(r.to_vec()));
        let mut piece_runs = Vec::new();
        let split = Batch::decode_pieces_visiting(&pieces, limits, |r| piece_runs.push(r.to_vec()));
        ((whole, runs), (split, piece_runs))
    }

    #[test]
    fn a_body_in_pieces_decodes_as_the_whole_body() {
        let limits = DecodeLimits {
            max_records: 3 * DECODE_RUN,
            ..DecodeLimits::default()
        };
        let mut rng = SplitMix64::new(0x91EC);
        for round in 0..400 {
            let n = match round % 4 {
                0 => (rng.next_u64() % 40) as usize,
                1 => DECODE_RUN + (rng.next_u64() % 3) as usize - 1,
                _ => (rng.next_u64() % (3 * DECODE_RUN as u64 + 2)) as usize,
            };
            let records: Vec<Record> = (0..n as u32)
                .map(|i| Record::new(i, (round as u32) ^ i, [i as f32, 0.5, f32::from_bits(i)]))
                .collect();
            // Frame ids from 1 byte to the longest, so the header ends anywhere in a piece.
            let id_len = if round % 8 == 5 {
                MAX_FRAME_ID_LEN
            } else {
                1 + (rng.next_u64() % MAX_FRAME_ID_LEN as u64) as usize
            };
            let id = "f".repeat(id_len);
            let mut bytes = Batch::new(id, 1, round, records).unwrap().encode();
            // Whole, cut short, with bytes after the records, or with a byte of the header
            // changed (magic, version, id length, id, counts).
            match rng.next_u64() % 5 {
                0 => {
                    let cut = (rng.next_u64() as usize) % bytes.len();
                    bytes.truncate(cut);
                }
                1 => bytes.extend_from_slice(&[7; 3]),
                2 => {
                    let at = (rng.next_u64() as usize) % (FIXED_OVERHEAD + id_len);
                    bytes[at] ^= 1 << (rng.next_u64() % 8);
                }
                _ => {}
            }
            // Pieces as a request's frames come (a few large ones), or cut finely (1-byte
            // pieces and empty ones among them).
            let pieces = 1 + rng.next_u64() % 12;
            let mut cuts: Vec<usize> = (0..pieces)
                .map(|_| (rng.next_u64() as usize) % (bytes.len() + 1))
                .collect();
            if round % 3 == 0 {
                cuts.extend((0..40).map(|i| i * 3 + (round as usize % 3)));
                cuts.push(cuts[0]);
            }
            let ((whole, runs), (split, piece_runs)) = whole_and_in_pieces(&bytes, &cuts, &limits);
            assert_eq!(split, whole, "round {round}, cut at {cuts:?}");
            assert_eq!(
                whole,
                Batch::decode_reference(&bytes, &limits),
                "round {round}"
            );
            assert_eq!(piece_runs, runs, "round {round}: the same runs visited");
        }
        // No pieces at all: the empty body.
        let none: [&[u8]; 0] = [];
        assert_eq!(
            Batch::decode_pieces_visiting(&none, &limits, |_| panic!("no records")),
            Batch::decode(&[], &limits)
        );
    }

    #[test]
    fn the_digest_is_of_the_wire_bytes_of_the_records() {
        let records: Vec<Record> = (0..2500)
            .map(|i| Record::new(i, i * 3, [i as f32, 0.5, 1e9]))
            .collect();
        let batch = Batch::new("f", 1, 2, records.clone()).unwrap();
        let bytes = batch.encode();
        let wire = &bytes[bytes.len() - RECORD_SIZE * records.len()..];
        assert_eq!(
            batch.content_digest(),
            xxhash_rust::xxh3::xxh3_64(wire),
            "digest of the record section as sent"
        );
        // Made on the fly, a whole number of its buffers (the last one ends exactly full).
        assert_eq!(
            records_digest_of(records[..2048].iter().copied()),
            xxhash_rust::xxh3::xxh3_64(&wire[..2048 * RECORD_SIZE])
        );
        let other = Batch::new("g", 9, 9, records.clone()).unwrap();
        assert_eq!(
            other.content_digest(),
            batch.content_digest(),
            "ids are not content"
        );
        let mut changed = records;
        changed[1234].rgb[2] = 1e9 + 64.0;
        assert_ne!(records_digest(&changed), batch.content_digest());
    }
}
