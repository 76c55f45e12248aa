//! Bodies that careless or hostile clients send, for the tests and the load benchmark: a zstd
//! frame written by hand (so no compression crate is needed), which turns long runs of one byte
//! into a few bytes each, and a *zstd bomb* built from it.

use splatd_proto::{Batch, Record};

/// Largest block a zstd frame may hold (RFC 8878, `Block_Maximum_Size`).
const ZSTD_BLOCK: usize = 128 * 1024;

/// Shortest run of one byte worth an RLE block of its own.
const MIN_RUN: usize = 64;

/// `data` as one zstd frame (RFC 8878): runs of one byte become RLE blocks (4 bytes per 128 KiB),
/// everything else is stored in raw blocks.
pub fn zstd_frame(data: &[u8]) -> Vec<u8> {
    let mut out = vec![0x28, 0xb5, 0x2f, 0xfd];
    // Frame header: single segment, 8-byte content size.
    out.push(0b1110_0000);
    out.extend_from_slice(&(data.len() as u64).to_le_bytes());
    // (block type, bytes): 0 raw, 1 RLE (the size is that of the regenerated block).
    let mut blocks: Vec<(u32, &[u8])> = Vec::new();
    let mut raw_from = 0;
    let mut i = 0;
    while i < data.len() {
        let run = data[i..].iter().take_while(|&&b| b == data[i]).count();
        if run >= MIN_RUN {
            for raw in data[raw_from..i].chunks(ZSTD_BLOCK) {
                blocks.push((0, raw));
            }
            for rle in data[i..i + run].chunks(ZSTD_BLOCK) {
                blocks.push((1, rle));
            }
            raw_from = i + run;
        }
        i += run;
    }
    for raw in data[raw_from..].chunks(ZSTD_BLOCK) {
        blocks.push((0, raw));
    }
    if blocks.is_empty() {
        out.extend_from_slice(&[1, 0, 0]);
    }
    let count = blocks.len();
    for (n, (kind, bytes)) in blocks.into_iter().enumerate() {
        let last = u32::from(n + 1 == count);
        let header = last | kind << 1 | (bytes.len() as u32) << 3;
        out.extend_from_slice(&header.to_le_bytes()[..3]);
        if kind == 1 {
            out.push(bytes[0]);
        } else {
            out.extend_from_slice(bytes);
        }
    }
    out
}

/// A valid batch of `records` black samples at pixel (0, 0) of `frame`, zstd-compressed: with
/// the default 4 Mi records, about 2.6 KB that inflate to an 80 MiB batch.
pub fn zstd_bomb(frame: &str, worker: u64, seq: u64, records: usize) -> Vec<u8> {
    let batch = Batch {
        frame: frame.to_owned(),
        worker,
        seq,
        records: vec![Record::new(0, 0, [0.0; 3]); records],
    };
    zstd_frame(&batch.encode())
}
