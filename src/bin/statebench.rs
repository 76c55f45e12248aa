//! How fast a frame state moves between nodes: export (`GET /v1/frames/{id}/state`), transfer
//! over loopback and import (`POST /v1/frames/{id}/state`) of a 1920x1080 state with 8
//! cascades (`--width`, `--height`, `--cascades`), against a plain memcpy of the same bytes
//! measured in the same run; the ratio is printed with its goal (<= 10), and against the floor of
//! moving the bytes twice over loopback TCP (goal <= 1.3), beside what one loopback
//! TCP transfer of the same bytes costs with no server at all (export + import make two; that
//! floor is about 5x memcpy each on a 2-core VM). Also the size of a push
//! delta (encoded as push mode encodes it) of the same frame after 1 % of its pixels took one
//! more sample, against the full state (goal <= 3 %).
//!
//! ```sh
//! cargo build --release --bins && cargo run --release --bin statebench
//! ```
//!
//! The server is the `splatd` binary next to this one, started as a child process on a free
//! loopback port. The source frame is filled with a few passes of the synthetic firefly scene
//! (imported as one state, which is faster than posting batches and gives the same cells).

use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Parser;
use splatd_estimator::{CascadeLayout, FrameState};
use splatd_harness::{sibling_binary, Options, ServerProcess};
use splatd_proto::api::{CascadeParams, CreateFrame};
use splatd_proto::Client;
use splatd_scenes::synth::FireflyScene;

/// The goal for export + import against memcpy of the same bytes.
const GOAL: f64 = 10.0;
/// The goal for export + import against the loopback floor: the state's bytes moved twice over
/// loopback TCP (once out of the server, once into it), measured in the same run.
const FLOOR_GOAL: f64 = 1.3;
/// The goal for a push delta of a frame in which 1 % of the pixels changed, against the full
/// state's bytes.
const DELTA_GOAL: f64 = 0.03;

#[derive(Parser)]
#[command(about = "State export/transfer/import over loopback, against memcpy")]
struct Args {
    /// Frame width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Frame height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// Cascades.
    #[arg(long, default_value_t = 8)]
    cascades: u32,
    /// Passes (samples per pixel) of the synthetic scene in the source frame.
    #[arg(long, default_value_t = 4)]
    spp: u64,
    /// Timed runs; the best is reported.
    #[arg(long, default_value_t = 3)]
    runs: u32,
}

/// `splatd serve` (the one built beside this program) on a free port, with room for two frames
/// of `state_bytes` and for the working memory of an export and an import of one (its encoding,
/// its body), which at 3840x2160 is more than the default `--work-memory-mib`.
fn start_server(state_bytes: u64) -> Result<ServerProcess> {
    let binary = sibling_binary().map_err(anyhow::Error::msg)?;
    let mib = (state_bytes >> 20) + 1;
    let frames = (2 * mib + 1024).max(16384).to_string();
    let work = (2 * mib + 256).max(2048).to_string();
    ServerProcess::launch(&Options {
        log_level: "warn",
        ..Options::new(
            binary,
            &[
                "--max-memory-mib",
                frames.as_str(),
                "--work-memory-mib",
                work.as_str(),
            ],
        )
    })
    .map_err(anyhow::Error::msg)
}

/// Best time of `runs` transfers of `src` over a loopback TCP connection (a fresh one per run,
/// as each request of the benchmark may use), written whole and read into a buffer already
/// faulted in: what one direction of a transfer costs with no server work at all.
fn loopback_best(src: &[u8], runs: u32) -> Result<Duration> {
    use std::io::{Read, Write};
    let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
    let addr = listener.local_addr()?;
    let mut dst = vec![1u8; src.len()];
    let mut best = Duration::MAX;
    for _ in 0..runs.max(3) {
        let t = std::thread::scope(|scope| -> Result<Duration> {
            let sender = scope.spawn(|| -> std::io::Result<()> {
                std::net::TcpStream::connect(addr)?.write_all(src)
            });
            let (mut conn, _) = listener.accept()?;
            let t = Instant::now();
            conn.read_exact(&mut dst)?;
            let elapsed = t.elapsed();
            sender.join().expect("the sender thread")?;
            Ok(elapsed)
        })?;
        best = best.min(t);
    }
    Ok(best)
}

/// Best time of `runs` memcpys of `src` into a buffer already faulted in.
fn memcpy_best(src: &[u8], runs: u32) -> Duration {
    let mut dst = vec![1u8; src.len()];
    let mut best = Duration::MAX;
    for _ in 0..runs.max(3) {
        let t = Instant::now();
        dst.copy_from_slice(std::hint::black_box(src));
        std::hint::black_box(&mut dst);
        best = best.min(t.elapsed());
    }
    best
}

/// Bytes of the push delta of `state` after every 100th pixel took one more sample of the
/// scene: [`FrameState::delta_since`] encoded with an origin, as push mode sends it.
fn delta_len(state: &FrameState, scene: &FireflyScene, pass: u64) -> usize {
    let mut later = state.clone();
    let report = later.splat_all(scene.pass(pass).step_by(100));
    let delta = later.delta_since(state).expect("a later copy");
    let origin = splatd_proto::Origin {
        node: "bench".into(),
        seq: 1,
    };
    let len = splatd_formats::state::dump(&delta, None, "bench.src", Some(origin), vec![])
        .encode()
        .len();
    assert_eq!(report.accepted, delta.total_samples());
    len
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn main() -> Result<()> {
    let args = Args::parse();
    let (w, h, k) = (args.width, args.height, args.cascades);
    let cascades = CascadeParams {
        cascades: k,
        ..CascadeParams::default()
    };
    let layout = CascadeLayout::new(
        cascades.base,
        cascades.cascades,
        cascades.lowest_scale,
        cascades.luminance,
    )?;

    eprintln!(
        "filling a {w}x{h} state with {k} cascades, {} spp ...",
        args.spp
    );
    let scene = FireflyScene::new(w, h, 42);
    let mut fill = FrameState::new(w, h, layout);
    for pass in 0..args.spp {
        fill.splat_all(scene.pass(pass));
    }
    let fill_bytes = splatd_formats::state::dump(&fill, None, "bench.src", None, vec![]).encode();
    let delta_bytes = delta_len(&fill, &scene, args.spp);
    drop(fill);

    let server = start_server(fill_bytes.len() as u64)?;
    // Imports are posted from a multi-threaded runtime, as push mode posts them from the
    // server's own. Exports are read on one thread, as a pull reads them (curl, the Python
    // client) and as the floor's receiver reads. On a multi-threaded runtime reqwest reads the
    // socket in one task and hands each chunk to the task consuming the body, often on the
    // other thread: the 550 MB export then took 140-270 ms, against 120-170 ms read on one
    // thread, and the difference was the client's, not the server's.
    let poster = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let reader = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let (post, pull) = (Client::new(&server.url)?, Client::new(&server.url)?);
    poster.block_on(async {
        for id in ["bench.src", "bench.dst"] {
            let mut req = CreateFrame::new(id, w, h);
            req.cascades = cascades.clone();
            post.create_frame(&req).await?;
        }
        post.import_state("bench.src", fill_bytes.into())
            .await
            .context("filling the source frame")?;
        anyhow::Ok(())
    })?;
    let (mut export, mut import, mut total) = (Duration::MAX, Duration::MAX, Duration::MAX);
    // One receive buffer for every run, as a node pulling states repeatedly keeps one.
    let mut state = Vec::new();
    for run in 0..args.runs.max(1) {
        let t0 = Instant::now();
        reader.block_on(pull.export_state_into("bench.src", &mut state))?;
        let t1 = Instant::now();
        // The same bytes, posted to another frame of the same size.
        let mut dump = splatd_proto::StateDump::decode(&state, u64::MAX)?;
        dump.frame = "bench.dst".into();
        let body = bytes::Bytes::from(dump.encode());
        let t2 = Instant::now();
        // The client's copy of the body is freed after the clock stops: unmapping its 550 MB
        // took 70-140 ms after the server had answered (timestamps on both sides), a cost of
        // this program's allocation, which the floor below (a buffer kept across runs) does not
        // pay either.
        poster.block_on(post.import_state("bench.dst", body.clone()))?;
        let t3 = Instant::now();
        drop(body);
        eprintln!(
            "run {run}: export {:.0} ms, import {:.0} ms ({} bytes)",
            ms(t1 - t0),
            ms(t3 - t2),
            state.len()
        );
        export = export.min(t1 - t0);
        import = import.min(t3 - t2);
        total = total.min((t1 - t0) + (t3 - t2));
    }
    let bytes = state;
    let copy = memcpy_best(&bytes, args.runs);
    let wire = loopback_best(&bytes, args.runs)?;
    let mib = bytes.len() as f64 / (1 << 20) as f64;
    println!(
        "state {w}x{h}, {k} cascades: {mib:.1} MiB ({} bytes)",
        bytes.len()
    );
    println!(
        "export (GET state)   best of {}: {:>8.1} ms  {:>7.0} MiB/s",
        args.runs,
        ms(export),
        mib / export.as_secs_f64()
    );
    println!(
        "import (POST state)  best of {}: {:>8.1} ms  {:>7.0} MiB/s",
        args.runs,
        ms(import),
        mib / import.as_secs_f64()
    );
    println!(
        "export + import      best of {}: {:>8.1} ms  {:>7.0} MiB/s",
        args.runs,
        ms(total),
        mib / total.as_secs_f64()
    );
    println!(
        "memcpy of the bytes  best of {}: {:>8.1} ms  {:>7.0} MiB/s",
        args.runs.max(3),
        ms(copy),
        mib / copy.as_secs_f64()
    );
    println!(
        "loopback TCP of them best of {}: {:>8.1} ms  {:>7.0} MiB/s ({:.1}x memcpy; export + \
         import move the state twice)",
        args.runs.max(3),
        ms(wire),
        mib / wire.as_secs_f64(),
        wire.as_secs_f64() / copy.as_secs_f64()
    );
    let ratio = total.as_secs_f64() / copy.as_secs_f64();
    println!(
        "\ngoal at {w}x{h}:\n  export + import / memcpy: ratio {ratio:.1} (goal <= {GOAL}) {}",
        if ratio <= GOAL { "met" } else { "MISSED" }
    );
    let floor = 2.0 * wire.as_secs_f64();
    let over_floor = total.as_secs_f64() / floor;
    println!(
        "  export + import / loopback floor (2 x {:.1} ms): ratio {over_floor:.2} (goal <= \
         {FLOOR_GOAL}) {}",
        ms(wire),
        if over_floor <= FLOOR_GOAL {
            "met"
        } else {
            "MISSED"
        }
    );
    let share = delta_bytes as f64 / bytes.len() as f64;
    println!(
        "  push delta, 1 % of pixels changed / full state: {delta_bytes} / {} bytes = {:.2} % \
         (goal <= {:.0} %) {}",
        bytes.len(),
        100.0 * share,
        100.0 * DELTA_GOAL,
        if share <= DELTA_GOAL { "met" } else { "MISSED" }
    );
    drop(server);
    Ok(())
}
