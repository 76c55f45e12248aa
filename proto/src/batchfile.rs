//! Batch files: sample batches saved for offline use (`splatd resolve samples.splb`).
//!
//! A batch file is a sequence of length-prefixed batches: a `u64` little-endian byte count, then
//! that many bytes of one batch in the wire layout (`proto/PROTOCOL.md`). It is what a worker
//! would have posted, written to disk instead, so any worker can produce one by writing each body
//! after its length.

use std::io::{self, Read, Write};

use crate::{Batch, DecodeLimits, WireError};

/// Why a batch file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum BatchFileError {
    /// Reading failed.
    #[error("reading batch {index}: {source}")]
    Io {
        /// Index of the batch being read.
        index: u64,
        /// The I/O error.
        #[source]
        source: io::Error,
    },
    /// A length prefix promises more than a batch may hold.
    #[error("batch {index} claims {len} bytes; at most {max} are allowed")]
    TooLong {
        /// Index of the batch.
        index: u64,
        /// Its claimed length.
        len: u64,
        /// The largest batch allowed by the decode limits.
        max: u64,
    },
    /// A batch is malformed.
    #[error("batch {index}: {source}")]
    Wire {
        /// Index of the batch.
        index: u64,
        /// The decode error.
        #[source]
        source: WireError,
    },
}

/// Appends one batch to a batch file.
pub fn write_batch(out: &mut impl Write, batch: &Batch) -> io::Result<()> {
    let bytes = batch.encode();
    out.write_all(&(bytes.len() as u64).to_le_bytes())?;
    out.write_all(&bytes)
}

/// Reads batch files one batch at a time, so a file far larger than memory streams through.
#[derive(Debug)]
pub struct BatchReader<R> {
    input: R,
    limits: DecodeLimits,
    index: u64,
    buffer: Vec<u8>,
}

impl<R: Read> BatchReader<R> {
    /// A reader of `input` that decodes each batch under `limits`.
    pub fn new(input: R, limits: DecodeLimits) -> Self {
        BatchReader {
            input,
            limits,
            index: 0,
            buffer: Vec::new(),
        }
    }

    /// The next batch, `None` at a clean end of file.
    pub fn next_batch(&mut self) -> Result<Option<Batch>, BatchFileError> {
        let index = self.index;
        let io = |source| BatchFileError::Io { index, source };
        let mut len = [0u8; 8];
        let mut got = 0;
        while got < len.len() {
            match self.input.read(&mut len[got..]) {
                Ok(0) if got == 0 => return Ok(None),
                Ok(0) => return Err(io(io::ErrorKind::UnexpectedEof.into())),
                Ok(n) => got += n,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(io(e)),
            }
        }
        let len = u64::from_le_bytes(len);
        let max = self.limits.max_body_len() as u64;
        if len > max {
            return Err(BatchFileError::TooLong { index, len, max });
        }
        self.buffer.resize(len as usize, 0);
        self.input.read_exact(&mut self.buffer).map_err(io)?;
        let batch = Batch::decode(&self.buffer, &self.limits)
            .map_err(|source| BatchFileError::Wire { index, source })?;
        self.index += 1;
        Ok(Some(batch))
    }
}

impl<R: Read> Iterator for BatchReader<R> {
    type Item = Result<Batch, BatchFileError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_batch().transpose()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Record;

    #[test]
    fn batches_round_trip_through_a_file() {
        let batches: Vec<Batch> = (0..3)
            .map(|seq| {
                let records = (0..seq as u32 * 5)
                    .map(|i| Record::new(i, seq as u32, [i as f32, 1.0, 0.5]))
                    .collect();
                Batch::new("f", 7, seq, records).unwrap()
            })
            .collect();
        let mut file = Vec::new();
        for b in &batches {
            write_batch(&mut file, b).unwrap();
        }
        let back: Vec<Batch> = BatchReader::new(&file[..], DecodeLimits::default())
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(back, batches);
    }

    #[test]
    fn damage_is_reported_with_the_batch_index() {
        let mut file = Vec::new();
        write_batch(&mut file, &Batch::new("f", 1, 0, vec![]).unwrap()).unwrap();
        write_batch(&mut file, &Batch::new("f", 1, 1, vec![]).unwrap()).unwrap();
        let cut = &file[..file.len() - 3];
        let mut r = BatchReader::new(cut, DecodeLimits::default());
        assert!(r.next_batch().unwrap().is_some());
        let err = r.next_batch().unwrap_err();
        assert!(err.to_string().starts_with("reading batch 1"), "{err}");

        let mut huge = u64::MAX.to_le_bytes().to_vec();
        huge.extend_from_slice(b"SPLB");
        let err = BatchReader::new(&huge[..], DecodeLimits::default())
            .next_batch()
            .unwrap_err();
        assert!(
            matches!(err, BatchFileError::TooLong { index: 0, .. }),
            "{err}"
        );

        let mut bad = 4u64.to_le_bytes().to_vec();
        bad.extend_from_slice(b"JUNK");
        let err = BatchReader::new(&bad[..], DecodeLimits::default())
            .next_batch()
            .unwrap_err();
        assert!(err.to_string().contains("SPLB"), "{err}");
    }
}
