//! Durability: frames survive a crash of the process (`splatd serve --data-dir DIR`).
//!
//! # Why snapshots and not a log of batches
//! A write-ahead log of raw batches would have to write 20 bytes per sample with `fdatasync`
//! before acknowledging it. The disks this runs on write about 320 MB/s synchronously, which caps
//! a log near 16 M samples/s, below what the server ingests over HTTP; and the log would grow
//! with every sample while the state it describes does not. So splatd makes the *state* durable
//! instead: a frame's cascades are a fixed size whatever the sample count, and a snapshot of them
//! (plus the set of batches they contain) is written atomically every `--snapshot-interval-ms`
//! when the frame changed. The price is a two-step acknowledgement:
//!
//! 1. `200` on `POST .../samples` means *applied*: the batch is in the frame and in every image
//!    resolved from now on, exactly once.
//! 2. The batch is *durable* once a snapshot contains it. Every acknowledgement carries
//!    `durable_floor`: every batch of this worker (for this frame) numbered below it is durable.
//!    It also carries `boot`, which changes when the server restarts.
//!
//! A worker keeps each batch until `durable_floor` passes it. If `boot` changes, the server lost
//! whatever was applied after its last snapshot, and the worker resends every batch it kept; the
//! ones that the snapshot already holds are recognised as duplicates (the set of applied
//! `(worker, seq)` is part of the snapshot), the rest are applied. Nothing acknowledged is lost,
//! nothing counts twice. `POST .../sync` forces a snapshot and returns once it is on disk, for a
//! worker that is about to exit. Frame creation, deletion and state imports (node merges and
//! pushes) are made durable before they are acknowledged.
//!
//! # Files
//! `DIR/frames/<id>/frame.json` is the create request. `DIR/frames/<id>/snapshot.bin` is the
//! latest snapshot, replaced atomically: it is written to `snapshot.tmp`, fsynced, renamed over
//! the old one and the directory fsynced, so a crash leaves either the old or the new snapshot,
//! never a torn one (and a CRC-32 at its end catches anything else). Recovery reads every frame
//! directory, so restart costs one read of each frame's state: bounded by the state size, not by
//! how many samples arrived.

use std::collections::HashMap;
use std::fs::{self, File};
use std::io::{self, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use splatd_proto::api::CreateFrame;
use splatd_proto::StateDump;

use splatd_estimator::FrameState;

use super::dedup::Seen;
use super::frame::{CounterValues, FrameCut, FrameSpec, ShardedFrame};
use super::store::FrameStore;

const SNAPSHOT_MAGIC: [u8; 4] = *b"SPLC";
/// 2 added the content digest of every applied batch (see `dedup`); version 1 snapshots are
/// still read, their batches without digests. 3 holds states of state format version 2
/// (`frac_bits` 26, a high word per pixel); the version 1 states of snapshots 1 and 2 are
/// converted when read, and a frame whose old state had a saturated sum (which cannot be
/// converted honestly) is quarantined. 4 holds states of format version 3, whose AOV section
/// carries each band's rows of the frame's AOV sums; snapshots 3 (version 2 states, no AOVs)
/// are still read, as frames without AOV samples.
const SNAPSHOT_VERSION: u16 = 4;
const SNAPSHOT_FILE: &str = "snapshot.bin";
const SNAPSHOT_TMP: &str = "snapshot.tmp";
const FRAME_FILE: &str = "frame.json";
/// Written (durably) before a frame's first snapshot: from then on a missing `snapshot.bin`
/// means a lost file, not a frame that never had samples.
const SNAPSHOT_MARKER: &str = "snapshotted";
/// Where damaged frames are moved at recovery, beside `frames/`.
const QUARANTINE_DIR: &str = "quarantine";
/// Largest snapshot metadata section accepted when reading one back.
const MAX_META_BYTES: u64 = 1 << 30;

/// What a snapshot stores besides the cascades.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct SnapshotMeta {
    /// Frame id (checked against the directory).
    frame: String,
    /// The frame's version when the snapshot was taken.
    version: u64,
    counters: CounterValues,
    seen: Seen,
}

/// [`SnapshotMeta`] as version 1 wrote it, before batches had digests.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct SnapshotMetaV1 {
    frame: String,
    version: u64,
    counters: CounterValues,
    workers: HashMap<u64, crate::dedup::SeqSet>,
    nodes: HashMap<String, crate::dedup::SeqSet>,
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

/// Why the data directory could not be used.
#[derive(Debug, thiserror::Error)]
pub enum DurableError {
    /// A file operation failed.
    #[error("{what} {path}: {source}")]
    Io {
        /// What was being done.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// The error.
        #[source]
        source: io::Error,
    },
    /// A file is not what splatd wrote.
    #[error("{path} is damaged: {reason}")]
    Damaged {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// A change to a frame (its creation, its deletion, what was applied to it) that could not be
/// made durable. The change is then not acknowledged: the client is told it failed and retries.
#[derive(Debug, thiserror::Error)]
#[error("{action}: {source}")]
pub struct DurabilityError {
    /// What was being made durable, e.g. "writing a snapshot".
    pub action: &'static str,
    /// Why the data directory refused it.
    #[source]
    pub source: DurableError,
}

impl DurabilityError {
    /// Wraps `source` with what was being done when it happened.
    pub fn new(action: &'static str) -> impl FnOnce(DurableError) -> DurabilityError {
        move |source| DurabilityError { action, source }
    }
}

impl DurableError {
    /// Whether the disk (or a file-size limit) has no room: full, over quota, or `ulimit -f`.
    pub fn is_out_of_space(&self) -> bool {
        const EDQUOT: i32 = 122; // Linux
        const EFBIG: i32 = 27;
        match self {
            DurableError::Io { source, .. } => {
                source.kind() == io::ErrorKind::StorageFull
                    || source.kind() == io::ErrorKind::QuotaExceeded
                    || source.kind() == io::ErrorKind::FileTooLarge
                    || matches!(source.raw_os_error(), Some(EDQUOT | EFBIG))
            }
            DurableError::Damaged { .. } => false,
        }
    }
}

fn io_err<'a>(what: &'static str, path: &'a Path) -> impl FnOnce(io::Error) -> DurableError + 'a {
    move |source| DurableError::Io {
        what,
        path: path.to_owned(),
        source,
    }
}

/// The data directory of a durable server.
#[derive(Debug)]
pub struct Durable {
    root: PathBuf,
    /// How often changed frames are snapshotted.
    pub interval: Duration,
    /// Serializes snapshots of one frame (the periodic ones and `sync`).
    locks: std::sync::Mutex<HashMap<String, Arc<tokio::sync::Mutex<()>>>>,
    /// Frames found damaged at recovery and moved aside.
    quarantined: std::sync::Mutex<Vec<Quarantined>>,
    /// Frames whose last snapshot failed (a full disk, say): their acknowledged batches are
    /// not becoming durable.
    failing: std::sync::Mutex<std::collections::BTreeSet<String>>,
}

/// A frame that could not be recovered, moved out of the way so the others could be.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Quarantined {
    /// The frame id (its directory's name).
    pub frame: String,
    /// Why it could not be read.
    pub reason: String,
    /// Where its files are now.
    pub moved_to: PathBuf,
}

impl Durable {
    /// Opens (creating if needed) the data directory.
    pub fn open(root: impl Into<PathBuf>, interval: Duration) -> Result<Durable, DurableError> {
        let root = root.into();
        let frames = root.join("frames");
        fs::create_dir_all(&frames).map_err(io_err("creating", &frames))?;
        Ok(Durable {
            root,
            interval,
            locks: std::sync::Mutex::new(HashMap::new()),
            quarantined: std::sync::Mutex::new(Vec::new()),
            failing: std::sync::Mutex::new(Default::default()),
        })
    }

    /// Frames found damaged at the last recovery, and where their files went.
    pub fn quarantined(&self) -> Vec<Quarantined> {
        self.quarantined
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Frames whose last snapshot attempt failed: acknowledged batches of theirs are not
    /// becoming durable, which `/healthz` reports.
    pub fn failing(&self) -> Vec<String> {
        self.failing_set().iter().cloned().collect()
    }

    /// Whether the last snapshot of `frame` failed: what it acknowledges now is applied but not
    /// becoming durable, which every acknowledgement of the frame then says.
    pub fn is_failing(&self, frame: &str) -> bool {
        self.failing_set().contains(frame)
    }

    /// Records a failed snapshot of `frame`: counted, reported by `/healthz` and the metrics.
    fn note_failure(&self, frame: &str) {
        let mut failing = self.failing_set();
        failing.insert(frame.to_owned());
        metrics::gauge!("splatd_frames_snapshot_failing").set(failing.len() as f64);
        metrics::counter!("splatd_snapshot_failures_total").increment(1);
    }

    fn failing_set(&self) -> std::sync::MutexGuard<'_, std::collections::BTreeSet<String>> {
        self.failing.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn frame_dir(&self, id: &str) -> PathBuf {
        // Frame ids are validated ([A-Za-z0-9._-], never "." or ".."), so they are safe names.
        self.root.join("frames").join(id)
    }

    /// Reads every frame back into `store`; returns how many frames were recovered.
    ///
    /// A frame whose files are damaged or missing is never read as empty: its directory is
    /// moved to `DIR/quarantine/` (listed by [`Durable::quarantined`], logged as an error) and
    /// the other frames are served. Only a data directory that cannot be listed, or a damaged
    /// frame that cannot be moved aside, stops the start.
    pub fn recover(&self, store: &FrameStore) -> Result<usize, DurableError> {
        let frames = self.root.join("frames");
        let mut recovered = 0;
        let entries = fs::read_dir(&frames).map_err(io_err("listing", &frames))?;
        for entry in entries {
            let dir = entry.map_err(io_err("listing", &frames))?.path();
            if !dir.join(FRAME_FILE).exists() {
                // A frame deleted (its marker goes first) or never fully created: not a frame.
                let _ = fs::remove_dir_all(&dir);
                continue;
            }
            match recover_frame(&dir) {
                Ok(frame) => {
                    tracing::info!(
                        frame = frame.id(),
                        samples = frame.info().samples,
                        "frame recovered"
                    );
                    frame.mark_durable(&frame.cut().seen, frame.version());
                    store.insert_restored(frame);
                    recovered += 1;
                }
                Err(e) => self.quarantine(&dir, e)?,
            }
        }
        metrics::gauge!("splatd_frames_quarantined").set(self.quarantined().len() as f64);
        Ok(recovered)
    }

    /// Moves a damaged frame's directory aside.
    fn quarantine(&self, dir: &Path, error: DurableError) -> Result<(), DurableError> {
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let aside = self.root.join(QUARANTINE_DIR);
        fs::create_dir_all(&aside).map_err(io_err("creating", &aside))?;
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let mut moved_to = aside.join(format!("{name}.{stamp}"));
        let mut n = 1;
        while moved_to.exists() {
            moved_to = aside.join(format!("{name}.{stamp}.{n}"));
            n += 1;
        }
        fs::rename(dir, &moved_to).map_err(io_err("moving a damaged frame aside", dir))?;
        sync_dir(&self.root.join("frames"))?;
        tracing::error!(
            frame = name,
            error = %error,
            moved_to = %moved_to.display(),
            "frame damaged: moved aside, not served"
        );
        self.quarantined
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(Quarantined {
                frame: name,
                reason: error.to_string(),
                moved_to,
            });
        Ok(())
    }

    /// Makes a new frame durable (its parameters; its cascades are empty).
    ///
    /// Creation, deletion and snapshots of one frame id take turns (one lock per id), so a
    /// snapshot of a deleted frame can never land in the directory of a new frame of the same
    /// id; and files a failed deletion left behind are removed first, so a new frame starts
    /// empty on disk as in memory.
    pub async fn frame_created(
        self: &Arc<Self>,
        frame: &Arc<ShardedFrame>,
    ) -> Result<(), DurableError> {
        let lock = self.lock_for(frame.id());
        let _turn = lock.lock().await;
        let this = self.clone();
        let frame = frame.clone();
        run_blocking(self.frame_dir(frame.id()), move || {
            let dir = this.frame_dir(frame.id());
            fs::create_dir_all(&dir).map_err(io_err("creating", &dir))?;
            for stale in [SNAPSHOT_FILE, SNAPSHOT_TMP, SNAPSHOT_MARKER] {
                let path = dir.join(stale);
                match fs::remove_file(&path) {
                    Ok(()) => sync_dir(&dir)?,
                    Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                    Err(e) => return Err(io_err("removing", &path)(e)),
                }
            }
            let json = serde_json::to_vec_pretty(&frame.spec().request).expect("serialisable");
            write_atomically(&dir, FRAME_FILE, "frame.json.tmp", |w| w.write_all(&json))
        })
        .await
    }

    /// Forgets a deleted frame: once this returns, the frame is not recovered at the next start.
    /// Call it after [`ShardedFrame::retire`], so no snapshot of the frame is written after.
    pub async fn frame_deleted(
        self: &Arc<Self>,
        frame: &Arc<ShardedFrame>,
    ) -> Result<(), DurableError> {
        let lock = self.lock_for(frame.id());
        let _turn = lock.lock().await;
        let dir = self.frame_dir(frame.id());
        run_blocking(dir.clone(), move || remove_frame_dir(&dir)).await?;
        self.failing_set().remove(frame.id());
        Ok(())
    }

    fn lock_for(&self, id: &str) -> Arc<tokio::sync::Mutex<()>> {
        let mut locks = self.locks.lock().unwrap_or_else(|e| e.into_inner());
        locks.entry(id.to_owned()).or_default().clone()
    }

    /// Writes a snapshot of `frame` if it changed since its last one; returns once everything
    /// applied to the frame before the call is on disk.
    pub async fn snapshot(self: &Arc<Self>, frame: &Arc<ShardedFrame>) -> Result<(), DurableError> {
        let lock = self.lock_for(frame.id());
        let _turn = lock.lock().await;
        if frame.is_retired() || frame.durable_version() == frame.version() {
            // A retired frame is deleted, or being deleted: writing it would bring it back.
            return Ok(());
        }
        let this = self.clone();
        let f = frame.clone();
        let written = async move {
            // The cut (no copy: writers copy a band the snapshot still holds before changing
            // it) waits for batches being applied, so it is taken off the request loop.
            let cutter = f.clone();
            let cut = tokio::task::spawn_blocking(move || cutter.cut()).await?;
            // The encoding and writing at low priority: on a saturated machine they take the
            // cores that ingest leaves idle, and durability lags instead of ingest slowing.
            crate::renders::on_low_priority_thread("splatd-snapshot", move || {
                this.write_snapshot(&f, &cut)
                    .map(|()| (cut.seen, cut.version))
            })
            .await
        }
        .await
        .map_err(|e| DurableError::Io {
            what: "snapshotting",
            path: self.frame_dir(frame.id()),
            source: io::Error::other(e.to_string()),
        })
        .and_then(|written| written);
        let (seen, version) = match written {
            Ok(cut) => cut,
            Err(e) => {
                self.note_failure(frame.id());
                return Err(e);
            }
        };
        {
            let mut failing = self.failing_set();
            failing.remove(frame.id());
            metrics::gauge!("splatd_frames_snapshot_failing").set(failing.len() as f64);
        }
        frame.mark_durable(&seen, version);
        metrics::counter!("splatd_snapshots_total").increment(1);
        Ok(())
    }

    fn write_snapshot(&self, frame: &ShardedFrame, cut: &FrameCut) -> Result<(), DurableError> {
        let dir = self.frame_dir(frame.id());
        let meta = SnapshotMeta {
            frame: frame.id().to_owned(),
            version: cut.version,
            counters: cut.counters,
            seen: cut.seen.clone(),
        };
        let meta = bincode::serde::encode_to_vec(&meta, bincode::config::legacy())
            .expect("snapshot metadata serialises");
        write_atomically(&dir, SNAPSHOT_FILE, SNAPSHOT_TMP, |w| {
            let mut w = CrcWriter::new(w);
            w.write_all(&SNAPSHOT_MAGIC)?;
            w.write_all(&SNAPSHOT_VERSION.to_le_bytes())?;
            w.write_all(&(meta.len() as u64).to_le_bytes())?;
            w.write_all(&meta)?;
            w.write_all(&(cut.bands.len() as u32).to_le_bytes())?;
            for band in &cut.bands {
                let aov_rows = cut.aovs.as_ref().map(|a| a.rows_copy(band.rows()));
                let aovs = aov_rows
                    .as_ref()
                    .map(|sums| (frame.spec().request.aovs.as_slice(), sums));
                // Length-prefixed, so a reader can bound each band before decoding it.
                w.write_all(&encoded_len(band, aovs, frame.id())?.to_le_bytes())?;
                splatd_formats::state::write(band, aovs, frame.id(), None, &mut w)?;
            }
            let crc = w.crc.clone().finalize();
            w.inner.write_all(&crc.to_le_bytes())
        })?;
        // From now on a missing snapshot is damage, not a frame that never had one. Marked only
        // after a snapshot exists: a first snapshot that failed (a full disk) leaves the frame
        // as it was, legitimately empty after a restart, not quarantined.
        let marker = dir.join(SNAPSHOT_MARKER);
        if !marker.exists() {
            File::create(&marker)
                .and_then(|f| f.sync_all())
                .map_err(io_err("creating", &marker))?;
            sync_dir(&dir)?;
        }
        Ok(())
    }

    /// Snapshots every changed frame until `stop` changes (spawned by the server). A round in
    /// progress is finished first, so no snapshot is abandoned half-written.
    ///
    /// Rounds are spaced by the configured interval, or by four times the last round's duration
    /// if that is longer: a 1080p frame holds 400 MB of cascades, which take over a second to
    /// write and sync, and snapshots must not take more than a fifth of the machine from ingest.
    /// Durability lags ingest by at most one spacing plus one round.
    pub async fn run(
        self: Arc<Self>,
        app: super::AppState,
        mut stop: tokio::sync::watch::Receiver<bool>,
    ) {
        let mut wait = self.interval;
        loop {
            tokio::select! {
                () = tokio::time::sleep(wait) => {}
                _ = stop.changed() => return,
            }
            let started = std::time::Instant::now();
            for frame in app.store.list() {
                // Each snapshot is a task of its own, so that nothing going wrong in one (an
                // error, or a panic) can end this loop: durability must not stop for good
                // because one write failed; the next round tries again.
                let this = self.clone();
                let id = frame.id().to_owned();
                let done = tokio::spawn(async move { this.snapshot(&frame).await }).await;
                let failure = match done {
                    Ok(Ok(())) => continue,
                    Ok(Err(e)) => e.to_string(),
                    Err(e) => {
                        self.note_failure(&id);
                        format!("the snapshot task failed: {e}")
                    }
                };
                tracing::error!(
                    frame = id,
                    error = failure,
                    "snapshot failed; retried next round"
                );
            }
            wait = self.interval.max(started.elapsed() * 4);
        }
    }
}

/// Makes a file-size limit (`ulimit -f`) a write error instead of death.
///
/// Past the limit the kernel sends SIGXFSZ, whose default action ends the process without a
/// log line, losing every frame's unsnapshotted samples. With a handler installed the write
/// fails with `EFBIG` instead, and the snapshot fails like any other write: reported, counted,
/// retried, while the server goes on. Call once, inside the runtime, before any snapshot.
#[cfg(unix)]
pub fn survive_file_size_limit() -> io::Result<()> {
    use tokio::signal::unix::{signal, SignalKind};
    const SIGXFSZ: i32 = 25; // the same on Linux, macOS and the BSDs
    let mut received = signal(SignalKind::from_raw(SIGXFSZ))?;
    tokio::spawn(async move {
        while received.recv().await.is_some() {
            tracing::error!("a write went past the file-size limit (SIGXFSZ); it fails as EFBIG");
        }
    });
    Ok(())
}

/// Reads one frame directory back.
fn recover_frame(dir: &Path) -> Result<ShardedFrame, DurableError> {
    let _ = fs::remove_file(dir.join(SNAPSHOT_TMP));
    let meta_path = dir.join(FRAME_FILE);
    let json = fs::read(&meta_path).map_err(io_err("reading", &meta_path))?;
    let request: CreateFrame =
        serde_json::from_slice(&json).map_err(|e| DurableError::Damaged {
            path: meta_path.clone(),
            reason: e.to_string(),
        })?;
    let spec = FrameSpec::new(request).map_err(|e| DurableError::Damaged {
        path: meta_path.clone(),
        reason: e.to_string(),
    })?;
    let snapshot = dir.join(SNAPSHOT_FILE);
    if snapshot.exists() {
        read_snapshot(&snapshot, spec)
    } else if dir.join(SNAPSHOT_MARKER).exists() {
        Err(DurableError::Damaged {
            path: snapshot,
            reason: "missing, although the frame was snapshotted before".into(),
        })
    } else {
        Ok(ShardedFrame::new(spec))
    }
}

/// Removes a frame's directory; the frame marker goes first (and durably), because a directory
/// without it is ignored, and cleaned, on recovery.
fn remove_frame_dir(dir: &Path) -> Result<(), DurableError> {
    let meta = dir.join(FRAME_FILE);
    match fs::remove_file(&meta) {
        Ok(()) => {}
        Err(e) if e.kind() == io::ErrorKind::NotFound => {}
        Err(e) => return Err(io_err("removing", &meta)(e)),
    }
    sync_dir(dir)?;
    let _ = fs::remove_dir_all(dir);
    Ok(())
}

/// Runs file work on the blocking pool; a panic there is reported as an I/O error on `path`.
async fn run_blocking(
    path: PathBuf,
    work: impl FnOnce() -> Result<(), DurableError> + Send + 'static,
) -> Result<(), DurableError> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| DurableError::Io {
            what: "writing",
            path,
            source: io::Error::other(e.to_string()),
        })?
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

/// Writes `dir/tmp`, fsyncs it, renames it to `dir/name` and fsyncs `dir`.
fn write_atomically(
    dir: &Path,
    name: &str,
    tmp: &str,
    write: impl FnOnce(&mut BufWriter<&File>) -> io::Result<()>,
) -> Result<(), DurableError> {
    let tmp_path = dir.join(tmp);
    let final_path = dir.join(name);
    let written = (|| {
        crate::failpoint::hit(&format!("{name}:before_write"))
            .map_err(io_err("writing", &tmp_path))?;
        let file = File::create(&tmp_path).map_err(io_err("creating", &tmp_path))?;
        let mut w = BufWriter::with_capacity(1 << 20, &file);
        write(&mut w).map_err(io_err("writing", &tmp_path))?;
        w.flush().map_err(io_err("writing", &tmp_path))?;
        drop(w);
        file.sync_all().map_err(io_err("syncing", &tmp_path))?;
        crate::failpoint::hit(&format!("{name}:before_rename"))
            .map_err(io_err("renaming", &tmp_path))?;
        fs::rename(&tmp_path, &final_path).map_err(io_err("renaming", &tmp_path))
    })();
    if written.is_err() {
        // A failed write (a full disk, a file-size limit) must not leave a partial file that
        // keeps the space: other frames' snapshots need it.
        let _ = fs::remove_file(&tmp_path);
    }
    written?;
    sync_dir(dir)
}

fn sync_dir(dir: &Path) -> Result<(), DurableError> {
    match File::open(dir) {
        Ok(d) => d.sync_all().map_err(io_err("syncing", dir)),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(io_err("opening", dir)(e)),
    }
}

/// Reads a snapshot back into a frame of `spec`.
fn read_snapshot(path: &Path, spec: FrameSpec) -> Result<ShardedFrame, DurableError> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::FrameSpec;
    use crate::Limits;
    use splatd_proto::{Batch, Record};

    fn open(dir: &Path) -> Arc<Durable> {
        Arc::new(Durable::open(dir, Duration::from_secs(3600)).unwrap())
    }

    fn frame(id: &str) -> Arc<ShardedFrame> {
        Arc::new(ShardedFrame::new(
            FrameSpec::new(CreateFrame::new(id, 8, 20)).unwrap(),
        ))
    }

    fn post(frame: &ShardedFrame, worker: u64, seq: u64) {
        let records = (0..20)
            .map(|y| Record::new(3, y, [1.0, 2.0, 3.0]))
            .collect();
        let batch = Batch::new(frame.id(), worker, seq, records).unwrap();
        assert!(!frame.ingest(&batch).unwrap().duplicate);
    }

    fn recover(dir: &Path) -> FrameStore {
        let store = FrameStore::new(Limits::default());
        open(dir).recover(&store).unwrap();
        store
    }

    /// The writer of a snapshot of a frame that is deleted, and re-created under the same id,
    /// while the snapshot is on its way must not put the old frame's samples and batch ids into
    /// the new frame's directory (they came back at the next start, and the new frame's first
    /// batch was answered "duplicate").
    #[tokio::test]
    async fn a_late_snapshot_of_a_deleted_frame_does_not_resurrect_it() {
        let dir = tempfile::tempdir().unwrap();
        let durable = open(dir.path());
        let old = frame("f");
        durable.frame_created(&old).await.unwrap();
        post(&old, 1, 0);
        // The snapshot task took `old` from the store, then the frame was deleted and created
        // again before the task got to write it.
        old.retire();
        durable.frame_deleted(&old).await.unwrap();
        let new = frame("f");
        durable.frame_created(&new).await.unwrap();
        durable.snapshot(&old).await.unwrap();

        let store = recover(dir.path());
        let back = store.get("f").unwrap();
        assert_eq!(back.info().samples, 0, "the new frame is empty");
        post(&back, 1, 0);
    }

    /// A create over files that a failed deletion left behind starts from an empty frame.
    #[tokio::test]
    async fn a_new_frame_ignores_a_stale_snapshot_in_its_directory() {
        let dir = tempfile::tempdir().unwrap();
        let durable = open(dir.path());
        let old = frame("f");
        durable.frame_created(&old).await.unwrap();
        post(&old, 1, 0);
        durable.snapshot(&old).await.unwrap();
        assert_eq!(recover(dir.path()).get("f").unwrap().info().samples, 20);
        durable.frame_created(&frame("f")).await.unwrap();
        assert_eq!(recover(dir.path()).get("f").unwrap().info().samples, 0);
    }

    /// Snapshots written before batches had digests are still read; their batches count as
    /// applied, and new batches get digests.
    #[tokio::test]
    async fn version_1_snapshots_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let durable = open(dir.path());
        let f = frame("f");
        durable.frame_created(&f).await.unwrap();
        post(&f, 4, 0);
        durable.snapshot(&f).await.unwrap();

        // Rewrite the snapshot as version 1 wrote it: metadata without digests.
        let path = dir.path().join("frames/f").join(SNAPSHOT_FILE);
        let (meta, _): (SnapshotMeta, usize) =
            bincode::serde::decode_from_slice(&snapshot_meta(&path), bincode::config::legacy())
                .unwrap();
        let v1 = SnapshotMetaV1 {
            frame: meta.frame,
            version: meta.version,
            counters: meta.counters,
            workers: meta.seen.workers,
            nodes: meta.seen.nodes,
        };
        let v1 = bincode::serde::encode_to_vec(&v1, bincode::config::legacy()).unwrap();
        // And its cells as state format version 1 held them.
        let whole = recover(dir.path()).get("f").unwrap().cut().whole();
        fs::write(&path, old_snapshot(1, &v1, &[v1_state(&whole, "f", None)])).unwrap();

        let store = recover(dir.path());
        let back = store.get("f").unwrap();
        assert_eq!(back.info().samples, 20);
        let retry = Batch::new("f", 4, 0, vec![Record::new(0, 0, [9.0; 3])]).unwrap();
        assert!(
            back.ingest(&retry).unwrap().duplicate,
            "old ids stay applied"
        );
        post(&back, 4, 1);
    }

    /// The body of `state` as state format version 1 wrote it: 2^-32 units (64 times finer,
    /// plus a remainder that rounds away), `4K` cells per pixel, no high word; pixel `saturate`
    /// gets a top-cascade sum saturated at `u64::MAX`.
    fn v1_state(state: &FrameState, id: &str, saturate: Option<usize>) -> Vec<u8> {
        let k = state.layout().cascades();
        let mut cells = Vec::new();
        for cell in state.cells().chunks_exact(splatd_estimator::cell_len(k)) {
            assert_eq!(cell[4 * k], 0, "no high word in an old state");
            for (i, &v) in cell[..4 * k].iter().enumerate() {
                cells.push(if i % 4 == 3 { v * 64 } else { v * 64 + 17 });
            }
        }
        if let Some(pixel) = saturate {
            cells[pixel * 4 * k + 4 * (k - 1)] = u64::MAX;
        }
        let mut dump = splatd_formats::state::dump(state, None, id, None, vec![]);
        dump.frac_bits = 32;
        dump.cells = cells;
        dump.encode_v1()
    }

    /// The metadata bytes of the snapshot file at `path` (after magic, version and their
    /// length), as [`old_snapshot`] takes them.
    fn snapshot_meta(path: &Path) -> Vec<u8> {
        let bytes = fs::read(path).unwrap();
        let meta_len = u64::from_le_bytes(bytes[6..14].try_into().unwrap()) as usize;
        bytes[14..14 + meta_len].to_vec()
    }

    /// A snapshot of `version` with metadata `meta` and `states` as its bands.
    fn old_snapshot(version: u16, meta: &[u8], states: &[Vec<u8>]) -> Vec<u8> {
        let mut old = Vec::new();
        old.extend_from_slice(&SNAPSHOT_MAGIC);
        old.extend_from_slice(&version.to_le_bytes());
        old.extend_from_slice(&(meta.len() as u64).to_le_bytes());
        old.extend_from_slice(meta);
        old.extend_from_slice(&(states.len() as u32).to_le_bytes());
        for state in states {
            old.extend_from_slice(&(state.len() as u64).to_le_bytes());
            old.extend_from_slice(state);
        }
        let crc = crc32fast::hash(&old);
        old.extend_from_slice(&crc.to_le_bytes());
        old
    }

    /// Snapshots of version 3 hold states of format version 2 (no AOV section): read as frames
    /// without AOV samples.
    #[tokio::test]
    async fn version_3_snapshots_with_version_2_states_are_read_without_aovs() {
        let dir = tempfile::tempdir().unwrap();
        let durable = open(dir.path());
        let f = frame("f");
        durable.frame_created(&f).await.unwrap();
        post(&f, 4, 0);
        durable.snapshot(&f).await.unwrap();
        let path = dir.path().join("frames/f").join(SNAPSHOT_FILE);
        // The snapshot a server of state format version 2 wrote: version 3, one band of a
        // version 2 state.
        let whole = f.cut().whole();
        let v2 = splatd_formats::state::dump(&whole, None, "f", None, vec![]).encode_v2();
        fs::write(&path, old_snapshot(3, &snapshot_meta(&path), &[v2])).unwrap();

        let back = recover(dir.path()).get("f").unwrap();
        assert_eq!(back.info().samples, 20);
        assert!(back.cut().whole() == whole);
        assert!(back.cut().aovs.is_none());
        post(&back, 4, 1);
    }

    /// A frame with AOVs keeps them through a snapshot and a restart, bit for bit.
    #[tokio::test]
    async fn aov_sums_survive_a_snapshot() {
        let dir = tempfile::tempdir().unwrap();
        let durable = open(dir.path());
        let request = CreateFrame {
            aovs: vec![splatd_proto::api::AovSpec::new("depth", &["Z"])],
            ..CreateFrame::new("f", 8, 20)
        };
        let f = Arc::new(ShardedFrame::new(FrameSpec::new(request).unwrap()));
        durable.frame_created(&f).await.unwrap();
        for seq in 0..3 {
            let records = (0..160)
                .map(|i| Record::new(i % 8, i / 8, [1.0, 2.0, 3.0]))
                .collect();
            let batch = Batch::new("f", 1, seq, records).unwrap();
            let depth: Vec<f32> = (0..160).map(|i| i as f32 * -0.37 + seq as f32).collect();
            f.ingest_with_aovs(&batch, Some(&depth)).unwrap();
        }
        durable.snapshot(&f).await.unwrap();
        let back = recover(dir.path()).get("f").unwrap();
        let (before, after) = (f.cut().aovs.unwrap(), back.cut().aovs.unwrap());
        assert_eq!(after.count(7, 19), 3);
        assert_eq!(before, after);
    }

    /// Snapshots of versions 1 and 2 hold states of format version 1 (32 fractional bits, `4K`
    /// cells per pixel): they are converted when read, and a saturated sum, which cannot be
    /// converted honestly, quarantines the frame, naming the pixel.
    #[tokio::test]
    async fn version_2_snapshots_with_old_states_are_converted() {
        let dir = tempfile::tempdir().unwrap();
        let durable = open(dir.path());
        for id in ["f", "sat"] {
            let f = frame(id);
            durable.frame_created(&f).await.unwrap();
            post(&f, 4, 0);
            let bright = vec![
                Record::new(5, 7, [1e5, 2.0, 3e4]),
                Record::new(0, 0, [0.3; 3]),
            ];
            let batch = Batch::new(id, 4, 1, bright).unwrap();
            f.ingest(&batch).unwrap();
            durable.snapshot(&f).await.unwrap();
        }
        let expected = recover(dir.path()).get("f").unwrap().cut().whole();

        for (id, saturate) in [("f", false), ("sat", true)] {
            let path = dir.path().join("frames").join(id).join(SNAPSHOT_FILE);
            let meta = snapshot_meta(&path);
            let state = v1_state(&expected, id, saturate.then_some(7 * 8 + 5));
            fs::write(&path, old_snapshot(2, &meta, &[state])).unwrap();
        }

        let store = FrameStore::new(Limits::default());
        let durable = open(dir.path());
        assert_eq!(durable.recover(&store).unwrap(), 1);
        let back = store.get("f").unwrap();
        assert_eq!(back.cut().whole(), expected, "converted exactly");
        assert_eq!(back.info().samples, 22);
        let q = durable.quarantined();
        assert_eq!(q.len(), 1);
        assert_eq!(q[0].frame, "sat");
        assert!(
            q[0].reason.contains("pixel (5, 7)") && q[0].reason.contains("saturated"),
            "{}",
            q[0].reason
        );
        // The next snapshot is written in the current versions and read back as it is.
        post(&back, 4, 2);
        durable.snapshot(&back).await.unwrap();
        let bytes = fs::read(dir.path().join("frames/f").join(SNAPSHOT_FILE)).unwrap();
        assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), SNAPSHOT_VERSION);
        assert_eq!(recover(dir.path()).get("f").unwrap().info().samples, 42);
    }

    /// A damaged or missing file never reads as an empty frame: the frame is moved aside and
    /// listed, and every other frame is served.
    #[tokio::test]
    async fn damaged_frames_are_quarantined_and_the_rest_recovered() {
        let dir = tempfile::tempdir().unwrap();
        let durable = open(dir.path());
        for id in ["good", "lost", "torn", "garbled"] {
            let f = frame(id);
            durable.frame_created(&f).await.unwrap();
            post(&f, 1, 0);
            durable.snapshot(&f).await.unwrap();
        }
        let frames = dir.path().join("frames");
        fs::remove_file(frames.join("lost").join(SNAPSHOT_FILE)).unwrap();
        let torn = frames.join("torn").join(SNAPSHOT_FILE);
        let len = fs::metadata(&torn).unwrap().len();
        File::options()
            .write(true)
            .open(&torn)
            .unwrap()
            .set_len(len / 2)
            .unwrap();
        fs::write(frames.join("garbled").join(FRAME_FILE), b"{not json").unwrap();

        let store = FrameStore::new(Limits::default());
        let durable = open(dir.path());
        assert_eq!(durable.recover(&store).unwrap(), 1);
        assert_eq!(store.get("good").unwrap().info().samples, 20);
        let mut q = durable.quarantined();
        q.sort_by(|a, b| a.frame.cmp(&b.frame));
        let names: Vec<&str> = q.iter().map(|q| q.frame.as_str()).collect();
        assert_eq!(names, ["garbled", "lost", "torn"]);
        assert!(q[1].reason.contains("missing"), "{}", q[1].reason);
        for entry in &q {
            assert!(entry.moved_to.join(FRAME_FILE).exists(), "{entry:?}");
            assert!(
                store.get(&entry.frame).is_err(),
                "{} is not served",
                entry.frame
            );
        }
        // The next start serves what is left, and the quarantined files stay put.
        let again = open(dir.path());
        assert_eq!(
            again.recover(&FrameStore::new(Limits::default())).unwrap(),
            1
        );
        assert!(again.quarantined().is_empty());
    }

    /// A frame created but never snapshotted is legitimately empty after a restart.
    #[tokio::test]
    async fn a_frame_never_snapshotted_recovers_empty() {
        let dir = tempfile::tempdir().unwrap();
        let durable = open(dir.path());
        durable.frame_created(&frame("f")).await.unwrap();
        let store = recover(dir.path());
        assert_eq!(store.get("f").unwrap().info().samples, 0);
    }

    /// A write that fails part way leaves no temporary file behind to hold the space.
    #[test]
    fn a_failed_write_removes_its_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let err = write_atomically(dir.path(), "out", "out.tmp", |w| {
            w.write_all(&[7u8; 4 << 20])?;
            Err(io::Error::new(
                io::ErrorKind::StorageFull,
                "no space left on device",
            ))
        })
        .unwrap_err();
        assert!(err.to_string().contains("no space left"), "{err}");
        assert!(!dir.path().join("out.tmp").exists());
        assert!(!dir.path().join("out").exists());
    }
}
