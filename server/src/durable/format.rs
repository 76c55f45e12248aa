//! The snapshot file format: magic, version, metadata, the bands' states and a CRC-32.

use std::collections::HashMap;
use std::fs::File;
use std::io::{self, Read, Write};
use std::path::Path;
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use splatd_estimator::{AovSums, FrameState};
use splatd_proto::StateDump;

use super::error::{io_err, DurableError};
use crate::frame::dedup::Seen;
use crate::frame::{CounterValues, FrameCut, FrameSpec, ShardedFrame};

pub(super) const SNAPSHOT_MAGIC: [u8; 4] = *b"SPLC";
/// 2 added the content digest of every applied batch (see `dedup`); version 1 snapshots are
/// still read, their batches without digests. 3 holds states of state format version 2
/// (`frac_bits` 26, a high word per pixel); the version 1 states of snapshots 1 and 2 are
/// converted when read, and a frame whose old state had a saturated sum (which cannot be
/// converted honestly) is quarantined. 4 holds states of format version 3, whose AOV section
/// carries each band's rows of the frame's AOV sums; snapshots 3 (version 2 states, no AOVs)
/// are still read, as frames without AOV samples.
pub(super) const SNAPSHOT_VERSION: u16 = 4;
/// Largest snapshot metadata section accepted when reading one back.
const MAX_META_BYTES: u64 = 1 << 30;

/// What a snapshot stores besides the cascades.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct SnapshotMeta {
    /// Frame id (checked against the directory).
    pub(super) frame: String,
    /// The frame's version when the snapshot was taken.
    pub(super) version: u64,
    pub(super) counters: CounterValues,
    pub(super) seen: Seen,
}

/// [`SnapshotMeta`] as version 1 wrote it, before batches had digests.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct SnapshotMetaV1 {
    pub(super) frame: String,
    pub(super) version: u64,
    pub(super) counters: CounterValues,
    pub(super) workers: HashMap<u64, crate::frame::dedup::SeqSet>,
    pub(super) nodes: HashMap<String, crate::frame::dedup::SeqSet>,
}

impl From<SnapshotMetaV1> for SnapshotMeta {
    fn from(v1: SnapshotMetaV1) -> SnapshotMeta {
        SnapshotMeta {
            frame: v1.frame,
            version: v1.version,
            counters: v1.counters,
            seen: Seen {
                workers: v1.workers,
                nodes: v1.nodes,
                digests: HashMap::new(),
            },
        }
    }
}

/// A snapshot of a cut of `frame` ready to be written: its metadata is encoded, its bands are
/// encoded as they are written, each straight to the file rather than through a copy of the
/// whole snapshot in memory.
///
/// It owns the cut's bands and AOV sums and lets go of each band as soon as it is written
/// (and of the sums after the last band), before the file is synced: while the snapshot holds
/// a band, a writer changing it copies it first, and the sync of a 1080p frame's 400 MB takes
/// longer than encoding it. So writers copy only the bands not written yet, and none while the
/// disk catches up.
pub(super) struct Snapshot<'a> {
    frame: &'a ShardedFrame,
    bands: Vec<Arc<FrameState>>,
    aovs: Option<Arc<AovSums>>,
    meta: Vec<u8>,
}

impl<'a> Snapshot<'a> {
    /// The snapshot of `cut`, taken of `frame`; the cut's applied set goes back, to be marked
    /// durable once the snapshot is on disk.
    pub(super) fn new(frame: &'a ShardedFrame, mut cut: FrameCut) -> (Snapshot<'a>, Seen) {
        // The snapshot holds the bands itself, to let each go as soon as it is written.
        let bands = std::mem::take(&mut cut.bands);
        let seen = std::mem::take(&mut cut.seen);
        let aovs = cut.aovs.take();
        let (counters, version) = (cut.counters, cut.version);
        let meta = SnapshotMeta {
            frame: frame.id().to_owned(),
            version,
            counters,
            seen,
        };
        let encoded = bincode::serde::encode_to_vec(&meta, bincode::config::legacy())
            .expect("snapshot metadata serialises");
        let snapshot = Snapshot {
            frame,
            bands,
            aovs,
            meta: encoded,
        };
        (snapshot, meta.seen)
    }

    /// Writes the snapshot file's bytes, its CRC-32 last, dropping each band once written.
    pub(super) fn write_to(self, w: impl Write) -> io::Result<()> {
        let Snapshot {
            frame,
            bands,
            aovs,
            meta,
        } = self;
        let mut w = CrcWriter::new(w);
        w.write_all(&SNAPSHOT_MAGIC)?;
        w.write_all(&SNAPSHOT_VERSION.to_le_bytes())?;
        w.write_all(&(meta.len() as u64).to_le_bytes())?;
        w.write_all(&meta)?;
        w.write_all(&(bands.len() as u32).to_le_bytes())?;
        for band in bands {
            // The band's rows of the frame's sums, written from where they lie.
            let band_aovs = aovs
                .as_deref()
                .map(|sums| (frame.spec().request.aovs.as_slice(), sums));
            // Length-prefixed, so a reader can bound each band before decoding it.
            w.write_all(&encoded_len(&band, band_aovs, frame.id())?.to_le_bytes())?;
            splatd_formats::state::write(&band, band_aovs, frame.id(), None, &mut w)?;
            // The frame's writers no longer copy it; if they made a copy meanwhile, its
            // cells serve their next copy.
            frame.recycle(band);
        }
        // Likewise the AOV sums, once every band's rows of them are written.
        if let Some(sums) = aovs {
            frame.recycle_aovs(sums);
        }
        let crc = w.crc.clone().finalize();
        w.inner.write_all(&crc.to_le_bytes())
    }
}

/// Bytes of a band's state encoding, without encoding it.
fn encoded_len(
    band: &FrameState,
    aovs: splatd_formats::state::Aovs<'_>,
    frame: &str,
) -> io::Result<u64> {
    Ok(splatd_formats::state::encoded_len(band, aovs, frame))
}

/// Counts a CRC-32 of everything written through it.
struct CrcWriter<W> {
    inner: W,
    crc: crc32fast::Hasher,
}

impl<W: Write> CrcWriter<W> {
    fn new(inner: W) -> Self {
        CrcWriter {
            inner,
            crc: crc32fast::Hasher::new(),
        }
    }
}

impl<W: Write> Write for CrcWriter<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc.update(&buf[..n]);
        Ok(n)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

/// Reads a snapshot back into a frame of `spec`.
pub(super) fn read_snapshot(path: &Path, spec: FrameSpec) -> Result<ShardedFrame, DurableError> {
    let damaged = |reason: String| DurableError::Damaged {
        path: path.to_owned(),
        reason,
    };
    let mut bytes = Vec::new();
    File::open(path)
        .and_then(|mut f| f.read_to_end(&mut bytes))
        .map_err(io_err("reading", path))?;
    if bytes.len() < 4 + 2 + 8 + 4 + 4 {
        return Err(damaged(format!("only {} bytes long", bytes.len())));
    }
    let (body, crc) = bytes.split_at(bytes.len() - 4);
    let crc = u32::from_le_bytes(crc.try_into().expect("4 bytes"));
    if crc32fast::hash(body) != crc {
        return Err(damaged("checksum mismatch".into()));
    }
    let version = u16::from_le_bytes([body[4], body[5]]);
    if body[..4] != SNAPSHOT_MAGIC || !(1..=SNAPSHOT_VERSION).contains(&version) {
        return Err(damaged("not a splatd snapshot of a known version".into()));
    }
    let mut at = 6;
    let mut take = |n: u64| -> Result<&[u8], DurableError> {
        let end = (at as u64)
            .checked_add(n)
            .filter(|&e| e <= body.len() as u64)
            .ok_or_else(|| damaged("truncated".into()))? as usize;
        let s = &body[at..end];
        at = end;
        Ok(s)
    };
    let meta_len = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes"));
    if meta_len > MAX_META_BYTES {
        return Err(damaged(format!("metadata of {meta_len} bytes")));
    }
    let config = bincode::config::legacy().with_limit::<{ MAX_META_BYTES as usize }>();
    let meta_bytes = take(meta_len)?;
    let meta: SnapshotMeta = if version == 1 {
        bincode::serde::decode_from_slice::<SnapshotMetaV1, _>(meta_bytes, config)
            .map(|(v1, _)| v1.into())
    } else {
        bincode::serde::decode_from_slice(meta_bytes, config).map(|(meta, _)| meta)
    }
    .map_err(|e| damaged(e.to_string()))?;
    if meta.frame != spec.request.id {
        return Err(damaged(format!(
            "holds frame {:?}, not {:?}",
            meta.frame, spec.request.id
        )));
    }
    let bands = u32::from_le_bytes(take(4)?.try_into().expect("4 bytes"));
    let cells = spec.memory_bytes() / 8;
    let mut whole = splatd_estimator::FrameState::new(
        spec.request.width,
        spec.request.height,
        spec.layout.clone(),
    );
    let mut aovs = None;
    for _ in 0..bands {
        let len = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes"));
        let band = if version >= 3 {
            let mut dump =
                StateDump::decode(take(len)?, cells).map_err(|e| damaged(e.to_string()))?;
            let band_aovs =
                splatd_formats::state::take_aovs(&mut dump).map_err(|e| damaged(e.to_string()))?;
            if let Some((specs, sums)) = band_aovs {
                if specs != spec.request.aovs {
                    return Err(damaged(format!(
                        "a band holds AOVs {}, the frame declares {}",
                        splatd_formats::names::describe_aovs(&specs),
                        splatd_formats::names::describe_aovs(&spec.request.aovs)
                    )));
                }
                aovs.get_or_insert_with(|| spec.empty_aovs().expect("the frame declares AOVs"))
                    .merge_overlap(&sums)
                    .map_err(|e| damaged(e.to_string()))?;
            }
            splatd_formats::state::load(dump)
        } else {
            let dump =
                StateDump::decode_v1(take(len)?, cells).map_err(|e| damaged(e.to_string()))?;
            splatd_formats::state::load_v1(dump)
        }
        .map_err(|e| damaged(e.to_string()))?;
        whole.merge(&band).map_err(|e| damaged(e.to_string()))?;
    }
    ShardedFrame::restore(
        spec,
        &whole,
        aovs.as_ref(),
        meta.seen,
        meta.counters,
        meta.version,
    )
    .map_err(damaged)
}
