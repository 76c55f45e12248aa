//! Recovery: every frame directory read back at start, and damaged ones moved aside.

use std::fs;
use std::path::Path;

use splatd_proto::api::CreateFrame;

use super::error::{io_err, DurableError};
use super::files::{
    sync_dir, FRAME_FILE, QUARANTINE_DIR, SNAPSHOT_FILE, SNAPSHOT_MARKER, SNAPSHOT_TMP,
};
use super::format::read_snapshot;
use super::{Durable, Quarantined};
use crate::frame::{FrameSpec, ShardedFrame};
use crate::store::FrameStore;

impl Durable {
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
        metrics::gauge!(crate::meters::FRAMES_QUARANTINED).set(self.quarantined().len() as f64);
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
