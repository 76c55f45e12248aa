//! The accumulated state of a frame (or of a band of its rows), as exported by one splatd node and
//! imported by another: `GET`/`POST /v1/frames/{id}/state`, `splatd merge`, push deltas.
//!
//! A state is lossless: the server's fixed-point cascade sums and counts, verbatim. Two states
//! of the same frame (same size and cascade layout) merge by adding them cell by cell, which is
//! what makes a farm of nodes aggregate exactly, as if one server had seen every sample.
//!
//! # Byte layout (version 2)
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
//! | `count` | `u64` | number of cells that follow |
//!
//! Then `count` cells, `u64` each. Pixels are row-major within the rows held; each pixel has `K`
//! groups of `[r, g, b, count]` and then one *high word*, so
//! `count == width * (rows_end - rows_start) * (4 * K + 1)`. A group holds the RGB sums of
//! cascade `j` in units of `c_j * 2^-frac_bits` (`c_j = lowest_scale * base^j`) and its
//! fractional sample count in units of `2^-frac_bits`. The high word holds the bits above 64 of
//! the top cascade's (`j = K - 1`) r, g and b sums, 21 bits each (r in bits 0..21, g in 21..42,
//! b in 42..63; bit 63 is 0): its sums are `hi * 2^64 + lo`. A pixel's sample count is the sum of
//! its counts divided by `2^frac_bits` (exact: every sample adds exactly one), at most `2^32`.
//! A receiver checks every pixel against these bounds (see `splatd_estimator`'s state module).
//!
//! Version 1 (`frac_bits` 32, `4 * K` cells per pixel, sums that saturated) is refused by
//! [`StateDump::decode`], naming both versions; [`StateDump::decode_v1`] reads it for servers
//! that convert old snapshots.
//!
//! Decoding checks the declared count against the geometry and the bytes present before it
//! allocates anything.

use bincode::config::{Configuration, Fixint, Limit, LittleEndian};
use serde::{Deserialize, Serialize};

/// The four bytes every state starts with.
pub const STATE_MAGIC: [u8; 4] = *b"SPLS";

/// The only state format version this crate reads and writes.
pub const STATE_VERSION: u16 = 2;

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
    /// The cells: `width * rows * (4 * cascades + 1)` values (`4 * cascades` in version 1).
    pub cells: Vec<u64>,
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
         (version 1 states, with 32 fractional bits, must be re-exported by a current server)"
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
    /// Bytes after the last cell.
    #[error("state has {count} unexpected bytes after its last cell")]
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
    count: u64,
}

impl StateDump {
    /// Cells a state of this geometry must hold.
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
    /// frame's row bands, top to bottom), so they need not be gathered into one buffer first.
    pub fn write_with_cell_parts(
        &self,
        parts: &[&[u64]],
        out: &mut impl std::io::Write,
    ) -> std::io::Result<()> {
        let count: usize = parts.iter().map(|p| p.len()).sum();
        let header = Header {
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
            count: count as u64,
        };
        out.write_all(&STATE_MAGIC)?;
        out.write_all(&STATE_VERSION.to_le_bytes())?;
        let header = bincode::serde::encode_to_vec(&header, HEADER_CONFIG)
            .expect("bincode encoding of a state header is infallible");
        out.write_all(&header)?;
        // Convert in blocks: one write per 64 KiB instead of one per cell.
        let mut block = [0u8; 8 * 8192];
        for chunk in parts.iter().flat_map(|p| p.chunks(8192)) {
            for (dst, cell) in block.chunks_exact_mut(8).zip(chunk) {
                dst.copy_from_slice(&cell.to_le_bytes());
            }
            out.write_all(&block[..8 * chunk.len()])?;
        }
        Ok(())
    }

    /// Decodes an untrusted state body holding at most `max_cells` cells.
    pub fn decode(bytes: &[u8], max_cells: u64) -> Result<StateDump, StateError> {
        Self::decode_version(bytes, max_cells, STATE_VERSION)
    }

    /// Decodes an untrusted state body of the previous format version 1 (`4 * K` cells per
    /// pixel in units of `2^-32`, see the module docs), for converting old snapshots. Its cells
    /// are returned as they are: they do not fit a current state.
    pub fn decode_v1(bytes: &[u8], max_cells: u64) -> Result<StateDump, StateError> {
        Self::decode_version(bytes, max_cells, STATE_VERSION_1)
    }

    fn decode_version(bytes: &[u8], max_cells: u64, wanted: u16) -> Result<StateDump, StateError> {
        let available = bytes.len() as u64;
        let magic_len = bytes.len().min(4);
        if bytes[..magic_len] != STATE_MAGIC[..magic_len] {
            return Err(StateError::BadMagic {
                found: bytes[..magic_len].to_vec(),
            });
        }
        let Some((&[_, _, _, _, v0, v1], body)) = bytes.split_first_chunk::<6>() else {
            return Err(StateError::Truncated {
                needed: 6,
                available,
            });
        };
        let version = u16::from_le_bytes([v0, v1]);
        if version != wanted {
            return Err(StateError::UnsupportedVersion {
                found: version,
                supported: wanted,
            });
        }
        let (header, header_len): (Header, usize) =
            bincode::serde::decode_from_slice(body, HEADER_CONFIG).map_err(|e| match e {
                bincode::error::DecodeError::UnexpectedEnd { additional } => {
                    StateError::Truncated {
                        needed: available.saturating_add(additional as u64),
                        available,
                    }
                }
                other => StateError::Malformed(other.to_string()),
            })?;
        if header.rows_start > header.rows_end || header.rows_end > header.height {
            return Err(StateError::Malformed(format!(
                "rows {}..{} do not lie in a frame of height {}",
                header.rows_start, header.rows_end, header.height
            )));
        }
        let expected = expected_cells(
            header.width,
            header.rows_start,
            header.rows_end,
            header.cascades,
            version,
        );
        if header.count != expected {
            return Err(StateError::Shape {
                count: header.count,
                expected,
                width: header.width,
                rows: header.rows_end - header.rows_start,
                cascades: header.cascades,
            });
        }
        if header.count > max_cells {
            return Err(StateError::TooLarge {
                count: header.count,
                max: max_cells,
            });
        }
        let cells_bytes = &body[header_len..];
        let needed = header.count.saturating_mul(8);
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
        let cells = cells_bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().expect("8-byte chunk")))
            .collect();
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
            cells,
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
        }
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
        let mut d = dump();
        d.cells.pop();
        assert!(matches!(
            StateDump::decode(&d.encode(), u64::MAX),
            Err(StateError::Shape { .. })
        ));
        // A header declaring a huge frame, with no cells behind it.
        let mut huge = dump();
        huge.width = u32::MAX;
        huge.height = u32::MAX;
        huge.rows_end = u32::MAX;
        let mut bytes = StateDump {
            cells: vec![],
            ..huge.clone()
        }
        .encode();
        // Patch the declared count to match the huge geometry.
        let count = huge.expected_cells();
        let at = bytes.len() - 8;
        bytes[at..].copy_from_slice(&count.to_le_bytes());
        assert!(matches!(
            StateDump::decode(&bytes, 1 << 30),
            Err(StateError::TooLarge { .. })
        ));
        assert!(matches!(
            StateDump::decode(&bytes, u64::MAX),
            Err(StateError::Truncated { .. })
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
            ..dump()
        };
        let mut bytes = v1.encode();
        bytes[4..6].copy_from_slice(&1u16.to_le_bytes());
        // The header's count is the encoder's, 48 = 3 * 2 * 4 * 2: a version 1 count.
        let err = StateDump::decode(&bytes, u64::MAX).unwrap_err();
        assert_eq!(
            err,
            StateError::UnsupportedVersion {
                found: 1,
                supported: 2
            }
        );
        assert!(
            err.to_string().contains("version 1") && err.to_string().contains("version 2"),
            "{err}"
        );
        assert_eq!(StateDump::decode_v1(&bytes, u64::MAX).unwrap(), v1);
        assert!(matches!(
            StateDump::decode_v1(&dump().encode(), u64::MAX),
            Err(StateError::UnsupportedVersion { found: 2, .. })
        ));
    }
}
