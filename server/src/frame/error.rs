//! What ingest and import report: a batch applied or recognised, and why one was refused.

use splatd_estimator::{MergeError, SampleError};
use splatd_formats::state::ImportError;

/// Why a batch was refused. Nothing of a refused batch is applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IngestError {
    /// A record is outside the frame or not a valid radiance value.
    #[error(
        "record {index} (pixel ({}, {}), RGB ({}, {}, {})): {error}",
        record.x, record.y, record.rgb[0], record.rgb[1], record.rgb[2]
    )]
    Sample {
        /// Index of the first bad record in the batch.
        index: usize,
        /// The record.
        record: splatd_proto::Record,
        /// What is wrong with it.
        error: SampleError,
    },
    /// The batch names another frame.
    #[error("batch is for frame {batch:?} but was posted to frame {url:?}")]
    WrongFrame {
        /// Frame id inside the batch.
        batch: String,
        /// Frame id of the URL.
        url: String,
    },
    /// A batch with this `(worker, seq)` but other records was applied before.
    #[error(
        "batch (worker {worker}, seq {seq}) was already applied with other records \
         (digest {applied:016x}, this one {digest:016x}); ids must not be reused for \
         different batches"
    )]
    IdReused {
        /// The worker id.
        worker: u64,
        /// The sequence number.
        seq: u64,
        /// Digest of the records applied under this id.
        applied: u64,
        /// Digest of the records of this batch.
        digest: u64,
    },
    /// A batch with this `(worker, seq)` came in an imported state that recorded no digest of
    /// its records: this one may be it or another batch under a reused id, and dropping it as a
    /// duplicate could lose it.
    #[error(
        "batch (worker {worker}, seq {seq}) is named by a state imported into this frame \
         without a digest of its records, so the server cannot tell whether this is the same \
         batch or another one under a reused id; it is neither applied nor dropped as a \
         duplicate: if the imported state holds it, nothing is missing, otherwise send its \
         samples under a new id"
    )]
    IdUnverified {
        /// The worker id.
        worker: u64,
        /// The sequence number.
        seq: u64,
    },
    /// The frame was deleted while the batch was on its way.
    #[error("frame {frame:?} was deleted")]
    Deleted {
        /// The frame.
        frame: String,
    },
    /// A pixel's AOVs hold 2^32 samples already.
    #[error("the AOVs of pixel ({x}, {y}) hold 2^32 samples already")]
    AovFull {
        /// Column.
        x: u32,
        /// Row.
        y: u32,
    },
}

/// What an applied (or recognised) batch did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ingested {
    /// Samples added (0 for a duplicate).
    pub accepted: u64,
    /// The batch had been applied before; nothing was added this time.
    pub duplicate: bool,
}

/// Why an imported state was refused. Nothing of it is applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ImportRefused {
    /// The state's cells cannot be used (found as they were being added: what was added of
    /// them has been taken back).
    #[error(transparent)]
    Invalid(ImportError),
    /// Size, rows or cascade layout differ from the frame's.
    #[error("state does not fit frame {frame:?}: {error}")]
    Mismatch {
        /// The frame.
        frame: String,
        /// What differs.
        error: MergeError,
    },
    /// The state names another frame.
    #[error("state is of frame {state:?} but was posted to frame {url:?}")]
    WrongFrame {
        /// Frame id inside the state.
        state: String,
        /// Frame id of the URL.
        url: String,
    },
    /// The frame was deleted while the state was on its way.
    #[error("frame {frame:?} was deleted")]
    Deleted {
        /// The frame.
        frame: String,
    },
    /// The state's AOVs are not the frame's, or cannot be added.
    #[error("state's AOVs do not fit frame {frame:?}: {reason}")]
    Aovs {
        /// The frame.
        frame: String,
        /// What differs.
        reason: String,
    },
    /// The state holds batches the frame has applied already: adding it would count them twice.
    #[error(
        "state holds {count} batch(es) that frame {frame:?} has applied already, the first \
         (worker {worker}, seq {seq}); adding it would count them twice (a worker resent them \
         to another node?)"
    )]
    Overlap {
        /// The frame.
        frame: String,
        /// The first such batch's worker.
        worker: u64,
        /// Its sequence number.
        seq: u64,
        /// How many batches of the state the frame has applied.
        count: u64,
    },
}
