//! Wire format of splatd, shared by the server and the render workers.
//!
//! Render workers stream Monte Carlo samples over HTTP to a splatd server,
//! which accumulates them per pixel in brightness cascades and resolves
//! OpenEXR frames with fireflies removed. This crate is the contract between
//! the two sides, in two formats:
//!
//! * **Sample batches** ([`Batch`], module [`batch`]): a compact binary body
//!   (`Content-Type: application/x-splatd-batch`, see [`BATCH_CONTENT_TYPE`])
//!   of 20-byte records, because the server ingests millions of samples per
//!   second. Magic and version, then bincode 2 with the legacy (fixed-width,
//!   little-endian) configuration.
//! * **Frame states** ([`StateDump`], module [`state`]): a frame's accumulated cascades,
//!   verbatim, for merging nodes (`Content-Type: application/x-splatd-state`).
//! * **Everything else** ([`api`]): small JSON documents: frame creation,
//!   frame state, batch acknowledgements and error bodies.
//!
//! With the default `client` feature the crate also has an async HTTP
//! client for workers (reqwest + tokio): [`Client`] (module `client`) sends
//! requests and retries transient failures with the same bytes, and
//! [`Outbox`] (module `outbox`) keeps every batch and pass a worker posted
//! until the server has it on disk, resending it after a restart, and
//! [`BatchWriter`] (module `writer`) numbers records into batches and posts
//! them through an outbox, so every sample counts exactly once.
//! `default-features = false` leaves the formats alone: serde, bincode, thiserror and xxhash
//! (the batch digests), with the estimator's types.
//!
//! `PROTOCOL.md` next to this crate's `Cargo.toml` documents the byte layout
//! and the HTTP endpoints for implementers in other languages;
//! `python/` holds a numpy implementation, the package `splatd-client`
//! (`pip install ./proto/python`).
//!
//! # Example
//!
//! ```
//! use splatd_proto::{Batch, DecodeLimits, Record};
//!
//! let batch = Batch::new(
//!     "shot010.beauty",
//!     42, // worker id
//!     0,  // sequence number of this worker's batch
//!     vec![Record::new(10, 20, [0.25, 0.5, 1.0])],
//! )?;
//! let bytes = batch.encode();
//! assert_eq!(&bytes[..4], b"SPLB");
//! assert_eq!(bytes.len(), 4 + 2 + 8 + 14 + 8 + 8 + 8 + 20);
//!
//! let decoded = Batch::decode(&bytes, &DecodeLimits::default())?;
//! assert_eq!(decoded, batch);
//! # Ok::<(), splatd_proto::WireError>(())
//! ```

#![warn(missing_docs)]

pub mod api;
pub mod batch;
pub mod batchfile;
#[cfg(feature = "client")]
pub mod client;
pub mod ids;
#[cfg(feature = "client")]
pub mod outbox;
pub mod state;
#[cfg(feature = "client")]
pub mod writer;

pub use api::{
    BatchAck, CascadeParams, CreateFrame, Denoise, DenoiseGuides, DenoiseQuality, ErrorBody,
    FrameInfo, FrameList, ImageQuery, ImportAck, PutFrame, ResolveParams, SyncAck, Variant,
};
pub use batch::{
    pass_digest, records_digest_of, validate_frame_id, Batch, DecodeLimits, Record, RecordsDigest,
    WireError, DECODE_RUN,
};
#[cfg(feature = "client")]
pub use client::{Client, ClientError, RetryPolicy};
#[cfg(feature = "client")]
pub use outbox::{Outbox, Post, Sent};
pub use state::{Applied, Origin, Runs, StateDump, StateError, StateWrite, STATE_CONTENT_TYPE};
#[cfg(feature = "client")]
pub use writer::BatchWriter;

/// `Content-Type` of a sample batch body.
pub const BATCH_CONTENT_TYPE: &str = "application/x-splatd-batch";
