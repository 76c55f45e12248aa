//! The errors of the data directory.

use std::io;
use std::path::{Path, PathBuf};

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

pub(super) fn io_err<'a>(
    what: &'static str,
    path: &'a Path,
) -> impl FnOnce(io::Error) -> DurableError + 'a {
    move |source| DurableError::Io {
        what,
        path: path.to_owned(),
        source,
    }
}
