//! [`BatchWriter`]: the worker's side of the exactly-once and durability
//! contract (feature `client`; `PROTOCOL.md`, "Exactly-once and durability").
//!
//! A writer turns a stream of records into numbered batches and keeps a batch
//! that could not be delivered, so that the next call resends it under its
//! original sequence number. It posts through an [`Outbox`], which keeps every
//! acknowledged batch until the server has it on disk and resends it when the
//! server restarted. Requests and their retries are [`Client`]'s job.

use bytes::Bytes;

use crate::api::BatchAck;
use crate::batch::{Batch, Record, DEFAULT_MAX_RECORDS};
use crate::client::{Client, ClientError};
use crate::outbox::Outbox;

/// A batch that has a sequence number and its final bytes but is not yet
/// acknowledged.
#[derive(Debug)]
struct Pending {
    seq: u64,
    body: Bytes,
}

/// Buffers the records of one `(frame, worker)` and sends them in batches of
/// `batch_size` with sequence numbers `first_seq`, `first_seq + 1`, ...
///
/// Once a batch has been given a sequence number its bytes never change: if
/// sending fails (even after all retries), the batch stays pending and the
/// next [`push`](BatchWriter::push) or [`flush`](BatchWriter::flush) resends
/// it before anything else, so the server sees each sequence number with one
/// content only. Call `flush` at the end: records still buffered when the
/// writer is dropped are lost.
///
/// Against a durable server (one whose acknowledgements carry
/// `durable_floor`), acknowledged batches are kept until the server reports
/// them on disk, and all kept batches are resent when the server's `boot`
/// changes (it restarted and lost what its last snapshot did not hold; the
/// ones it did hold come back as duplicates). Call [`BatchWriter::sync`]
/// instead of `flush` before exiting to be sure every sample is durable.
/// Number batches from 0 for a new worker id: the server's durable floor
/// advances over contiguous sequence numbers only.
#[derive(Debug)]
pub struct BatchWriter {
    outbox: Outbox,
    next_seq: u64,
    batch_size: usize,
    buffer: Vec<Record>,
    pending: Option<Pending>,
}

impl BatchWriter {
    /// A writer for `frame` as `worker`, numbering batches from `first_seq`.
    /// `batch_size` must be in `1..=DEFAULT_MAX_RECORDS` (4 Mi), the default
    /// server limit.
    pub fn new(
        client: Client,
        frame: impl Into<String>,
        worker: u64,
        first_seq: u64,
        batch_size: usize,
    ) -> Result<BatchWriter, ClientError> {
        let outbox = Outbox::new(client, frame, worker)?;
        if !(1..=DEFAULT_MAX_RECORDS).contains(&batch_size) {
            return Err(ClientError::InvalidArgument(format!(
                "batch size {batch_size} is outside 1..={DEFAULT_MAX_RECORDS}"
            )));
        }
        Ok(BatchWriter {
            outbox,
            next_seq: first_seq,
            batch_size,
            buffer: Vec::with_capacity(batch_size),
            pending: None,
        })
    }

    /// Adds one record; sends a batch when `batch_size` records are buffered
    /// and returns the acknowledgements of the batches sent by this call.
    pub async fn push(&mut self, record: Record) -> Result<Vec<BatchAck>, ClientError> {
        self.buffer.push(record);
        self.send_full().await
    }

    /// Adds many records, sending full batches as they fill up.
    pub async fn extend(
        &mut self,
        records: impl IntoIterator<Item = Record>,
    ) -> Result<Vec<BatchAck>, ClientError> {
        let mut acks = Vec::new();
        for record in records {
            self.buffer.push(record);
            acks.extend(self.send_full().await?);
        }
        Ok(acks)
    }

    /// Sends the pending batch, if any, and everything buffered (the last
    /// batch may be short). Returns the acknowledgements.
    pub async fn flush(&mut self) -> Result<Vec<BatchAck>, ClientError> {
        let mut acks = Vec::new();
        if let Some(ack) = self.send_pending().await? {
            acks.push(ack);
        }
        while !self.buffer.is_empty() {
            self.seal()?;
            if let Some(ack) = self.send_pending().await? {
                acks.push(ack);
            }
        }
        Ok(acks)
    }

    /// The sequence number the next sealed batch gets (persist it to resume
    /// a worker without reusing numbers).
    pub fn next_seq(&self) -> u64 {
        self.next_seq
    }

    /// Records buffered and not yet part of a batch.
    pub fn buffered(&self) -> usize {
        self.buffer.len()
    }

    /// Sequence number of the batch that failed to send and will be resent
    /// first, if any.
    pub fn pending_seq(&self) -> Option<u64> {
        self.pending.as_ref().map(|p| p.seq)
    }

    /// Gives up on the pending batch (e.g. after [`ClientError::Rejected`],
    /// which resending cannot fix); returns its sequence number. Its number
    /// is not reused.
    pub fn discard_pending(&mut self) -> Option<u64> {
        self.pending.take().map(|p| p.seq)
    }

    /// Sends the pending batch and then every full batch in the buffer.
    async fn send_full(&mut self) -> Result<Vec<BatchAck>, ClientError> {
        let mut acks = Vec::new();
        if self.buffer.len() < self.batch_size {
            return Ok(acks);
        }
        if let Some(ack) = self.send_pending().await? {
            acks.push(ack);
        }
        while self.buffer.len() >= self.batch_size {
            self.seal()?;
            if let Some(ack) = self.send_pending().await? {
                acks.push(ack);
            }
        }
        Ok(acks)
    }

    /// Turns up to `batch_size` buffered records into the pending batch.
    fn seal(&mut self) -> Result<(), ClientError> {
        debug_assert!(
            self.pending.is_none(),
            "seal only after the pending batch is sent"
        );
        let n = self.buffer.len().min(self.batch_size);
        let batch = Batch {
            frame: self.outbox.frame().to_owned(),
            worker: self.outbox.worker(),
            seq: self.next_seq,
            records: self.buffer.drain(..n).collect(),
        };
        self.next_seq = self.next_seq.checked_add(1).ok_or_else(|| {
            ClientError::InvalidArgument("sequence numbers exhausted (u64::MAX reached)".into())
        })?;
        self.pending = Some(Pending {
            seq: batch.seq,
            body: Bytes::from(batch.encode()),
        });
        Ok(())
    }

    /// Sends the pending batch; it stays pending if sending fails.
    async fn send_pending(&mut self) -> Result<Option<BatchAck>, ClientError> {
        let Some(pending) = &self.pending else {
            return Ok(None);
        };
        let ack = self
            .outbox
            .post_batch(pending.seq, pending.body.clone())
            .await?;
        self.pending = None;
        Ok(Some(ack))
    }

    /// Flushes, then waits until the server has every batch of this writer on
    /// disk (`POST /v1/frames/{frame}/sync`), resending what a restart lost.
    /// Against a server without durability this is `flush`.
    pub async fn sync(&mut self) -> Result<(), ClientError> {
        self.flush().await?;
        self.outbox.sync().await?;
        Ok(())
    }

    /// Batches acknowledged as applied but not yet reported durable.
    pub fn unconfirmed(&self) -> usize {
        self.outbox.kept()
    }

    /// Batches resent because the server restarted.
    pub fn resent(&self) -> u64 {
        self.outbox.resent()
    }
}
