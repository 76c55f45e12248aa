//! Measures batch decode throughput: the hand-written record loop of
//! `Batch::decode` against bincode's serde path in `Batch::decode_reference`.
//!
//! `cargo run --release -p splatd-proto --example decode_speed [records] [reps]`

use std::hint::black_box;
use std::time::{Duration, Instant};

use splatd_proto::{Batch, DecodeLimits, Record};

fn best_of(reps: u32, mut f: impl FnMut()) -> Duration {
    (0..reps)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed()
        })
        .min()
        .unwrap_or_default()
}

fn parse_arg(i: usize, default: u64) -> Result<u64, String> {
    match std::env::args().nth(i) {
        None => Ok(default),
        Some(s) => s.parse().map_err(|e| format!("argument {i} ({s:?}): {e}")),
    }
}

fn main() -> Result<(), String> {
    let n = parse_arg(1, 1 << 20)?;
    let reps = u32::try_from(parse_arg(2, 10)?).map_err(|e| e.to_string())?;
    let records: Vec<Record> = (0..n)
        .map(|i| {
            let v = i as f32;
            Record::new(i as u32 % 1920, i as u32 / 1920, [v * 0.25, v * 0.5, v])
        })
        .collect();
    let batch = Batch::new("bench", 1, 1, records).map_err(|e| e.to_string())?;
    let limits = DecodeLimits {
        max_records: usize::MAX,
        ..DecodeLimits::default()
    };
    let bytes = batch.encode();
    let check = |b: Batch| {
        if b != batch {
            panic!("decoder disagrees with the encoder");
        }
    };
    check(Batch::decode(&bytes, &limits).map_err(|e| e.to_string())?);
    check(Batch::decode_reference(&bytes, &limits).map_err(|e| e.to_string())?);

    let rate = |d: Duration| n as f64 / d.as_secs_f64() / 1e6;
    let enc = best_of(reps, || {
        black_box(black_box(&batch).encode());
    });
    let fast = best_of(reps, || {
        black_box(Batch::decode(black_box(&bytes), &limits).ok());
    });
    let slow = best_of(reps, || {
        black_box(Batch::decode_reference(black_box(&bytes), &limits).ok());
    });
    println!("{n} records ({} bytes), best of {reps}:", bytes.len());
    println!("  encode (bincode serde)    {:8.1} M records/s", rate(enc));
    println!("  decode (hand loop)        {:8.1} M records/s", rate(fast));
    println!("  decode (bincode serde)    {:8.1} M records/s", rate(slow));
    println!(
        "  speed-up                  {:8.1}x",
        slow.as_secs_f64() / fast.as_secs_f64()
    );
    Ok(())
}
