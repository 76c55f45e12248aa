//! The data directory's files: their names, atomic replacement, directory fsyncs, and the
//! file-size limit.

use std::fs::{self, File};
use std::io;
use std::path::{Path, PathBuf};

use super::direct::{DirectBuffer, DirectWriter};
use super::error::{io_err, DurableError};

pub(super) const SNAPSHOT_FILE: &str = "snapshot.bin";
pub(super) const SNAPSHOT_TMP: &str = "snapshot.tmp";
pub(super) const FRAME_FILE: &str = "frame.json";
/// Written (durably) before a frame's first snapshot: from then on a missing `snapshot.bin`
/// means a lost file, not a frame that never had samples.
pub(super) const SNAPSHOT_MARKER: &str = "snapshotted";
/// Where damaged frames are moved at recovery, beside `frames/`.
pub(super) const QUARANTINE_DIR: &str = "quarantine";

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

/// Removes a frame's directory; the frame marker goes first (and durably), because a directory
/// without it is ignored, and cleaned, on recovery.
pub(super) fn remove_frame_dir(dir: &Path) -> Result<(), DurableError> {
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
pub(super) async fn run_blocking(
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

/// Writes `dir/tmp` through `buffer` (around the page cache where the file system lets it,
/// see [`super::direct`]), fsyncs it, renames it to `dir/name` and fsyncs `dir`.
pub(super) fn write_atomically(
    dir: &Path,
    name: &str,
    tmp: &str,
    buffer: &mut DirectBuffer,
    write: impl FnOnce(&mut DirectWriter<'_>) -> io::Result<()>,
) -> Result<(), DurableError> {
    let tmp_path = dir.join(tmp);
    let final_path = dir.join(name);
    let written = (|| {
        crate::failpoint::hit(&format!("{name}:before_write"))
            .map_err(io_err("writing", &tmp_path))?;
        let file = File::create(&tmp_path).map_err(io_err("creating", &tmp_path))?;
        let mut w = DirectWriter::new(&file, buffer);
        write(&mut w).map_err(io_err("writing", &tmp_path))?;
        w.finish().map_err(io_err("writing", &tmp_path))?;
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

pub(super) fn sync_dir(dir: &Path) -> Result<(), DurableError> {
    match File::open(dir) {
        Ok(d) => d.sync_all().map_err(io_err("syncing", dir)),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(io_err("opening", dir)(e)),
    }
}
