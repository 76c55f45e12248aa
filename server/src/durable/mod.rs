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
//! never a torn one (and a CRC-32 at its end catches anything else). Snapshots are written
//! around the page cache (`O_DIRECT`) from a buffer the server keeps, where the file system
//! allows it: see `direct.rs` for why. Recovery reads every frame
//! directory, so restart costs one read of each frame's state: bounded by the state size, not by
//! how many samples arrived.

mod direct;
mod error;
mod files;
mod format;
mod recovery;
#[cfg(test)]
mod tests;

use std::collections::HashMap;
use std::fs::{self, File};
use std::io::{self, Write};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use super::frame::dedup::Seen;
use super::frame::{FrameCut, ShardedFrame};

use direct::DirectBuffer;
use error::io_err;
pub use error::{DurabilityError, DurableError};
#[cfg(unix)]
pub use files::survive_file_size_limit;
use files::{
    remove_frame_dir, run_blocking, sync_dir, write_atomically, FRAME_FILE, SNAPSHOT_FILE,
    SNAPSHOT_MARKER, SNAPSHOT_TMP,
};

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
    /// The buffer snapshots are written from, kept between them so its memory stays warm (a
    /// second snapshot written at the same time makes one of its own).
    buffer: std::sync::Mutex<Option<DirectBuffer>>,
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
            buffer: std::sync::Mutex::new(None),
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
        metrics::gauge!(crate::meters::FRAMES_SNAPSHOT_FAILING).set(failing.len() as f64);
        metrics::counter!(crate::meters::SNAPSHOT_FAILURES).increment(1);
    }

    fn failing_set(&self) -> std::sync::MutexGuard<'_, std::collections::BTreeSet<String>> {
        self.failing.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn frame_dir(&self, id: &str) -> PathBuf {
        // Frame ids are validated ([A-Za-z0-9._-], never "." or ".."), so they are safe names.
        self.root.join("frames").join(id)
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
            let mut buffer = DirectBuffer::new(json.len());
            write_atomically(&dir, FRAME_FILE, "frame.json.tmp", &mut buffer, |w| {
                w.write_all(&json)
            })
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
    ///
    /// Calls that wait for the same frame's turn share snapshots: one whose changes a snapshot
    /// written while it waited already holds returns without writing another, even if the frame
    /// changed since. So a farm's workers calling `sync` together as they finish, or nodes
    /// pushing to a head at once, cost one or two snapshots of the frame (hundreds of
    /// megabytes each), not one per call.
    pub async fn snapshot(self: &Arc<Self>, frame: &Arc<ShardedFrame>) -> Result<(), DurableError> {
        // Everything applied before this call is in this version (a change is in the bands
        // before its version is made), so any cut of this version or later holds it.
        let wanted = frame.version();
        let lock = self.lock_for(frame.id());
        let _turn = lock.lock().await;
        if frame.is_retired() || frame.durable_version() >= wanted {
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
            crate::priority::on_low_priority_thread("splatd-snapshot", move || {
                let version = cut.version;
                this.write_snapshot(&f, cut).map(|seen| (seen, version))
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
            metrics::gauge!(crate::meters::FRAMES_SNAPSHOT_FAILING).set(failing.len() as f64);
        }
        frame.mark_durable(&seen, version);
        metrics::counter!(crate::meters::SNAPSHOTS).increment(1);
        Ok(())
    }

    /// Writes the snapshot of `cut` and syncs it; returns the cut's applied set, now on disk.
    /// The cut's bands are let go of as they are written, before the sync ([`format::Snapshot`]).
    fn write_snapshot(&self, frame: &ShardedFrame, cut: FrameCut) -> Result<Seen, DurableError> {
        let dir = self.frame_dir(frame.id());
        let (snapshot, seen) = format::Snapshot::new(frame, cut);
        let kept = self.buffer.lock().unwrap_or_else(|e| e.into_inner()).take();
        let mut buffer = kept.unwrap_or_else(|| DirectBuffer::new(direct::BUFFER));
        let written = write_atomically(&dir, SNAPSHOT_FILE, SNAPSHOT_TMP, &mut buffer, |w| {
            snapshot.write_to(w)
        });
        *self.buffer.lock().unwrap_or_else(|e| e.into_inner()) = Some(buffer);
        written?;
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
        Ok(seen)
    }

    /// Snapshots every changed frame until `stop` changes (spawned by the server). A round in
    /// progress is finished first, so no snapshot is abandoned half-written.
    ///
    /// Rounds are spaced by the configured interval, or by four times the last round's duration
    /// if that is longer: a 1080p frame holds 400 MB of cascades, which take over a second to
    /// write and sync, and snapshots must not take more than a fifth of the machine from ingest.
    /// Durability lags ingest by at most one spacing plus one round.
    ///
    /// `frames` lists the frames to consider each round (the server's store): a lister rather
    /// than the server's state, so durability depends on the frames alone, not on the HTTP
    /// layer that holds them.
    pub async fn run(
        self: Arc<Self>,
        frames: impl Fn() -> Vec<Arc<ShardedFrame>>,
        mut stop: tokio::sync::watch::Receiver<bool>,
    ) {
        let mut wait = self.interval;
        loop {
            tokio::select! {
                () = tokio::time::sleep(wait) => {}
                _ = stop.changed() => return,
            }
            let started = std::time::Instant::now();
            for frame in frames() {
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
