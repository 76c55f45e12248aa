//! Ingest benchmark: a load generator in its own process posting batches to a real `splatd serve`
//! over loopback, against the in-process splat rate of the same records, measured in one run.
//!
//! ```text
//! cargo build --release && target/release/loadgen [--batch 65536] [--connections 4]
//! # prints the in-process rate, then HTTP ingest in memory and with --data-dir (durable)
//! ```
//!
//! It starts the server itself (the `splatd` binary next to this one), once per configuration
//! (`--config` may be given several times, e.g. `--config memory --config "--data-dir {tmp}"`;
//! `memory` means no extra arguments and `{tmp}` a fresh temporary directory per run),
//! creates a 1920x1080 frame, and posts pre-encoded batches from several connections. Records
//! come in scan-line runs, as a worker rendering tiles or passes sends them, with a heavy-tailed
//! brightness so every cascade is used.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Result};
use bytes::Bytes;
use clap::Parser;
use splatd_estimator::{CascadeLayout, FrameState};
use splatd_harness::{sibling_binary, Options, ServerProcess};
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Record, BATCH_CONTENT_TYPE};
use splatd_scenes::synth::SplitMix64;

#[derive(Parser)]
#[command(about = "HTTP ingest throughput against in-process splatting, in one run")]
struct Args {
    /// Records per batch.
    #[arg(long, default_value_t = 65536)]
    batch: usize,
    /// Total records posted per configuration.
    /// (64 Mi records: about five seconds of ingest, so that durable runs reach the steady
    /// state of their snapshot schedule instead of measuring only the first snapshot.)
    #[arg(long, default_value_t = 64 << 20)]
    records: usize,
    /// Concurrent connections (workers).
    #[arg(long, default_value_t = 4)]
    connections: usize,
    /// Frame width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Frame height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// Extra `splatd serve` arguments of a configuration, as one string (repeatable); `memory`
    /// for none; `{tmp}` is replaced by a fresh temporary directory.
    #[arg(long = "config", allow_hyphen_values = true)]
    configs: Vec<String>,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let configs = if args.configs.is_empty() {
        vec!["memory".to_owned(), "--data-dir {tmp}".to_owned()]
    } else {
        args.configs.clone()
    };
    let batches = make_batches(&args);
    let n_records: usize = batches.iter().map(|b| b.records.len()).sum();
    let bodies: Vec<Bytes> = batches.iter().map(|b| Bytes::from(b.encode())).collect();
    let body_bytes: usize = bodies.iter().map(|b| b.len()).sum();
    println!(
        "{} records in {} batches of {} ({:.0} MB on the wire), {}x{} frame, {} connections",
        n_records,
        batches.len(),
        args.batch,
        body_bytes as f64 / 1e6,
        args.width,
        args.height,
        args.connections
    );

    // In-process: the same decoded records splatted into one state on one thread, the work the
    // server does per batch minus HTTP and decoding. Best of three.
    let mut in_process = f64::MAX;
    for _ in 0..3 {
        let mut state = FrameState::new(args.width, args.height, CascadeLayout::with_defaults());
        let t = Instant::now();
        for b in &batches {
            state.splat_all(b.records.iter().map(|r| (r.x, r.y, r.rgb)));
        }
        in_process = in_process.min(t.elapsed().as_secs_f64());
        std::hint::black_box(&state);
    }
    let in_rate = n_records as f64 / in_process;
    println!(
        "in-process splat: {:.1} M records/s ({in_process:.3} s)",
        in_rate / 1e6
    );

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    for config in &configs {
        let mut best = f64::MAX;
        for round in 0..2 {
            let tmp = std::env::temp_dir().join(format!("loadgen-{}-{round}", std::process::id()));
            let extra: Vec<String> = config
                .split_whitespace()
                .filter(|a| *a != "memory")
                .map(|a| a.replace("{tmp}", &tmp.display().to_string()))
                .collect();
            let server = start_server(&extra)?;
            let seconds = runtime.block_on(post_all(&server.url, &args, &bodies, round))?;
            best = best.min(seconds);
            drop(server);
            let _ = std::fs::remove_dir_all(&tmp);
        }
        let rate = n_records as f64 / best;
        println!(
            "HTTP ingest [{}]: {:.1} M records/s ({best:.3} s, {:.0} MB/s), ratio to in-process {:.2}",
            config,
            rate / 1e6,
            body_bytes as f64 / best / 1e6,
            rate / in_rate
        );
    }
    Ok(())
}

/// Batches of scan-line runs with heavy-tailed RGB.
fn make_batches(args: &Args) -> Vec<Batch> {
    let mut rng = SplitMix64::new(7);
    let pixels = args.width as usize * args.height as usize;
    let mut at = 0usize;
    let n_batches = args.records.div_ceil(args.batch);
    (0..n_batches)
        .map(|i| {
            let records = (0..args.batch)
                .map(|_| {
                    let p = at % pixels;
                    at += 1;
                    let z = (rng.next_f64().powf(-1.0 / 1.5) - 1.0) as f32;
                    Record::new(
                        (p % args.width as usize) as u32,
                        (p / args.width as usize) as u32,
                        [z * 0.8, z, z * 0.6],
                    )
                })
                .collect();
            Batch::new("bench", (i % args.connections) as u64, i as u64, records)
                .expect("valid frame id")
        })
        .collect()
}

/// Creates the frame and posts every body from `connections` tasks; returns the seconds taken.
async fn post_all(url: &str, args: &Args, bodies: &[Bytes], round: usize) -> Result<f64> {
    let client = splatd_proto::Client::new(url)?;
    client
        .create_frame(&CreateFrame::new("bench", args.width, args.height))
        .await?;
    let http = reqwest::Client::new();
    let next = Arc::new(AtomicUsize::new(0));
    let bodies = Arc::new(bodies.to_vec());
    let target = format!("{url}/v1/frames/bench/samples");
    let start = Instant::now();
    let mut tasks = Vec::new();
    for _ in 0..args.connections {
        let (http, next, bodies, target) =
            (http.clone(), next.clone(), bodies.clone(), target.clone());
        tasks.push(tokio::spawn(async move {
            loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(body) = bodies.get(i) else {
                    return Ok::<(), anyhow::Error>(());
                };
                let r = http
                    .post(&target)
                    .header("content-type", BATCH_CONTENT_TYPE)
                    .body(body.clone())
                    .send()
                    .await?;
                if !r.status().is_success() {
                    bail!("batch {i}: HTTP {}: {}", r.status(), r.text().await?);
                }
            }
        }));
    }
    for t in tasks {
        t.await??;
    }
    let seconds = start.elapsed().as_secs_f64();
    let info = client.frame_info("bench").await?;
    let expected: usize = bodies.iter().map(|b| (b.len() - 43) / 20).sum();
    if info.samples as usize != expected {
        bail!(
            "round {round}: server counted {} samples, {expected} were posted",
            info.samples
        );
    }
    Ok(seconds)
}

/// `splatd serve` (the one built beside this program) on a free port, with `extra` flags.
fn start_server(extra: &[String]) -> Result<ServerProcess> {
    let binary = sibling_binary().map_err(anyhow::Error::msg)?;
    let args: Vec<&str> = extra.iter().map(String::as_str).collect();
    ServerProcess::launch(&Options {
        log_level: "warn",
        ..Options::new(binary, &args)
    })
    .map_err(anyhow::Error::msg)
}
