//! A randomized fault soak of a durable `splatd serve` (not part of CI): many workers stream
//! batches while the server is SIGKILLed and restarted at random moments, some lives of it
//! cannot write snapshots (a full disk, injected with `SPLATD_FAILPOINTS`), some cannot write a
//! log line (stderr a closed pipe, logging at debug), one worker is the Python client's
//! `Outbox` (`tests/py/soak_worker.py`), a careless worker reuses batch ids for other samples, a
//! frame is deleted and created again, and a frame's state is imported into another frame, then
//! imported again.
//!
//! ```sh
//! cargo build --release --bins && cargo run --release --bin soak -- --seconds 120
//! ```
//!
//! At the end every frame is compared, cell by cell, with a reference that applied each batch the
//! workers produced exactly once, and the figures are printed: kills, batches, resends, samples
//! lost and doubled, and the refusals by kind. Exit status 1 if anything was lost, doubled or
//! came back.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use bytes::Bytes;
use clap::Parser;
use splatd_estimator::{CascadeLayout, FrameState};
use splatd_harness::{sibling_binary, Log, Options, ServerProcess};
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, BatchWriter, Client, ClientError, Record, RetryPolicy, StateDump};
use splatd_scenes::synth::SplitMix64;

#[derive(Parser)]
#[command(about = "Randomized fault soak of a durable splatd: kills, full disks, reused ids")]
struct Args {
    /// How long the workers stream.
    #[arg(long, default_value_t = 60)]
    seconds: u64,
    /// Workers, spread over the frames.
    #[arg(long, default_value_t = 8)]
    workers: u64,
    /// Frames the workers stream into.
    #[arg(long, default_value_t = 3)]
    frames: u64,
    /// Records per batch.
    #[arg(long, default_value_t = 512)]
    batch: usize,
    /// Mean time between two kills, in milliseconds.
    #[arg(long, default_value_t = 700)]
    kill_every_ms: u64,
    /// Seed of everything random.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

const SIZE: u32 = 64;

/// The server under test: one address, restarted in place after every kill.
struct Target {
    binary: PathBuf,
    dir: PathBuf,
    addr: String,
    process: Mutex<Option<ServerProcess>>,
}

impl Target {
    fn start(binary: PathBuf, dir: PathBuf) -> Result<Target> {
        let mut target = Target {
            binary,
            dir,
            addr: "127.0.0.1:0".into(),
            process: Mutex::new(None),
        };
        let first = target.launch(Life::default())?;
        target.addr = first.addr.clone();
        *target.process.lock().unwrap() = Some(first);
        Ok(target)
    }

    /// A server on `self.addr` over the data directory, living `life`.
    fn launch(&self, life: Life) -> Result<ServerProcess> {
        let dir = self.dir.display().to_string();
        let args = ["--data-dir", &dir, "--snapshot-interval-ms", "150"];
        let env: &[(&str, &str)] = if life.full_disk {
            &[("SPLATD_FAILPOINTS", "snapshot.bin:before_write=full")]
        } else {
            &[]
        };
        // The port was just released by the killed process; binding it again can fail for a
        // moment on a loaded machine, so a few tries.
        let mut last = String::new();
        for _ in 0..50 {
            let (log, log_level) = if life.closed_log {
                (Log::Closed, "debug")
            } else {
                (Log::Own, "off")
            };
            match ServerProcess::launch(&Options {
                addr: &self.addr,
                env,
                log,
                log_level,
                ..Options::new(&self.binary, &args)
            }) {
                Ok(p) => return Ok(p),
                Err(e) => {
                    last = e;
                    std::thread::sleep(Duration::from_millis(100));
                }
            }
        }
        bail!("restarting splatd failed: {last}")
    }

    /// SIGKILL, then start again to live `life`.
    fn kill_and_restart(&self, life: Life) -> Result<()> {
        let mut slot = self.process.lock().unwrap();
        if let Some(p) = slot.take() {
            p.kill();
        }
        *slot = Some(self.launch(life)?);
        Ok(())
    }

    fn url(&self) -> String {
        format!("http://{}", self.addr)
    }
}

/// What goes wrong in one life of the server besides its end by SIGKILL.
#[derive(Debug, Clone, Copy, Default)]
struct Life {
    /// Every snapshot write fails as on a full disk.
    full_disk: bool,
    /// Stderr is a closed pipe: every log line fails to be written.
    closed_log: bool,
}

#[derive(Default)]
struct Figures {
    kills: AtomicU64,
    full_disk_lives: AtomicU64,
    closed_log_lives: AtomicU64,
    batches: AtomicU64,
    resent: AtomicU64,
    reused_refused: AtomicU64,
    reused_applied: AtomicU64,
    recreated: AtomicU64,
    came_back: AtomicU64,
    overlap_refused: AtomicU64,
    overlap_applied: AtomicU64,
}

/// The records of batch `seq` of `worker`: uniform samples with a few fireflies.
fn records(seed: u64, worker: u64, seq: u64, n: usize) -> Vec<Record> {
    let mut rng = SplitMix64::new(seed ^ worker.wrapping_mul(0x9E37_79B9) ^ seq << 20);
    (0..n)
        .map(|_| {
            let x = (rng.next_u64() % SIZE as u64) as u32;
            let y = (rng.next_u64() % SIZE as u64) as u32;
            let v = if rng.next_u64().is_multiple_of(64) {
                2e4 * rng.next_f64() as f32
            } else {
                rng.next_f64() as f32
            };
            Record {
                x,
                y,
                rgb: [v, 0.5 * v, 0.25 * v],
            }
        })
        .collect()
}

fn splat(reference: &Mutex<FrameState>, records: &[Record]) {
    let report = reference
        .lock()
        .unwrap()
        .splat_all(records.iter().map(|r| (r.x, r.y, r.rgb)));
    assert_eq!(report.rejected(), 0);
}

fn client(url: &str) -> Result<Client> {
    // Patient: a restart may take a while on a loaded machine.
    Ok(Client::new(url)?.with_retry_policy(RetryPolicy {
        max_attempts: 60,
        initial_backoff: Duration::from_millis(20),
        max_backoff: Duration::from_millis(500),
    }))
}

/// Retries `op` while it fails transiently (the server is being restarted).
async fn patiently<T, F, Fut>(mut op: F) -> Result<T>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<T, ClientError>>,
{
    for _ in 0..100 {
        match op().await {
            Ok(v) => return Ok(v),
            Err(ClientError::Rejected { status, body }) if status != 507 => {
                bail!("refused: {status} {body:?}")
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
    bail!("the server never came back")
}

/// Gives `records` to `writer` and keeps resending its pending batch (same sequence number, same
/// bytes) until the server takes it.
async fn deliver(writer: &mut BatchWriter, records: Vec<Record>) -> Result<()> {
    let mut result = writer.extend(records).await;
    for _ in 0..200 {
        match result {
            Ok(_) => return Ok(()),
            Err(ClientError::Rejected { status, body }) if status != 507 => {
                bail!("refused: {status} {body:?}")
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
        }
        result = writer.flush().await;
    }
    bail!("the server never took the batch")
}

/// One worker: batches of random records into `frame` until `stop`, then a sync.
async fn worker(
    url: String,
    frame: String,
    id: u64,
    args: Arc<Args>,
    stop: Arc<AtomicBool>,
    reference: Arc<Mutex<FrameState>>,
    figures: Arc<Figures>,
) -> Result<()> {
    let client = client(&url)?;
    let mut writer = client.batch_writer(&frame, id, 0, args.batch)?;
    let mut seq = 0;
    while !stop.load(Ordering::Relaxed) {
        let recs = records(args.seed, id, seq, args.batch);
        // The writer numbers this batch `seq`: every record given to it is in exactly one batch.
        splat(&reference, &recs);
        deliver(&mut writer, recs)
            .await
            .with_context(|| format!("worker {id}"))?;
        seq += 1;
        figures.batches.fetch_add(1, Ordering::Relaxed);
    }
    for _ in 0..100 {
        match writer.sync().await {
            Ok(()) => break,
            Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    }
    if writer.unconfirmed() > 0 {
        bail!(
            "worker {id}: {} batches never became durable",
            writer.unconfirmed()
        );
    }
    figures.resent.fetch_add(writer.resent(), Ordering::Relaxed);
    Ok(())
}

/// The worker written with the Python client (`tests/py/soak_worker.py`), running as its own
/// process until the soak stops it.
struct PythonWorker {
    child: std::process::Child,
    stop: PathBuf,
    sent: PathBuf,
}

fn python_worker(
    url: &str,
    frame: &str,
    args: &Args,
    dir: &std::path::Path,
) -> Result<PythonWorker> {
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/soak_worker.py");
    let stop = dir.join("python-worker.stop");
    let sent = dir.join("python-worker.records");
    let child = std::process::Command::new("python3")
        .arg(&script)
        .args([url, frame, "1000"])
        .arg(args.seed.to_string())
        .arg(args.batch.to_string())
        .arg(SIZE.to_string())
        .arg(&stop)
        .arg(&sent)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .with_context(|| format!("python3 {} (pip install numpy)", script.display()))?;
    Ok(PythonWorker { child, stop, sent })
}

impl PythonWorker {
    /// Stops the worker, waits for its sync, and adds every record it sent to `reference`;
    /// returns its batches.
    fn finish(self, reference: &Mutex<FrameState>) -> Result<u64> {
        std::fs::write(&self.stop, b"")?;
        let out = self.child.wait_with_output()?;
        if !out.status.success() {
            bail!("the Python worker failed ({})", out.status);
        }
        let report: serde_json::Value =
            serde_json::from_slice(&out.stdout).context("the Python worker's report")?;
        if report["kept"] != 0 {
            bail!("the Python worker ended with batches not durable: {report}");
        }
        let bytes = std::fs::read(&self.sent)?;
        let records: Vec<Record> = bytes
            .chunks_exact(20)
            .map(|c| {
                let u = |i: usize| u32::from_le_bytes(c[i..i + 4].try_into().unwrap());
                let f = |i: usize| f32::from_le_bytes(c[i..i + 4].try_into().unwrap());
                Record::new(u(0), u(4), [f(8), f(12), f(16)])
            })
            .collect();
        splat(reference, &records);
        Ok(report["batches"].as_u64().unwrap_or(0))
    }
}

/// A careless worker: sends a batch, makes it durable, then sends other records under the same
/// id, which must be refused (409 `batch_id_reused`), never applied nor dropped silently.
async fn careless(
    url: String,
    frame: String,
    args: Arc<Args>,
    stop: Arc<AtomicBool>,
    reference: Arc<Mutex<FrameState>>,
    figures: Arc<Figures>,
) -> Result<()> {
    let client = client(&url)?;
    let mut n = 0u64;
    while !stop.load(Ordering::Relaxed) {
        let id = 1_000_000 + n;
        let first = records(args.seed, id, 0, 64);
        splat(&reference, &first);
        let mut writer = client.batch_writer(&frame, id, 0, 64)?;
        deliver(&mut writer, first).await?;
        for _ in 0..100 {
            if writer.sync().await.is_ok() && writer.unconfirmed() == 0 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        let other = Batch {
            frame: frame.clone(),
            worker: id,
            seq: 0,
            records: records(args.seed, id, 1, 64),
        };
        loop {
            match client.post_batch(&other).await {
                Err(ClientError::Rejected { status: 409, body })
                    if body.error == "batch_id_reused" =>
                {
                    figures.reused_refused.fetch_add(1, Ordering::Relaxed);
                    break;
                }
                Ok(ack) => {
                    eprintln!("a reused id was answered {ack:?}");
                    figures.reused_applied.fetch_add(1, Ordering::Relaxed);
                    break;
                }
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        }
        n += 1;
    }
    Ok(())
}

/// Deletes a frame holding samples and creates it again, over and over; the new frame must be
/// empty, whatever restarts come between.
async fn recreate(url: String, stop: Arc<AtomicBool>, figures: Arc<Figures>) -> Result<()> {
    let client = client(&url)?;
    let create = CreateFrame::new("scratch", SIZE, SIZE);
    let mut round = 0u64;
    while !stop.load(Ordering::Relaxed) {
        match client.create_frame(&create).await {
            Ok(_) => {}
            Err(ClientError::Rejected { status: 409, .. }) => {} // exists (a retried create)
            Err(_) => {
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        }
        let info = patiently(|| client.frame_counts("scratch")).await?;
        if info.spp_max != 0 && round > 0 {
            eprintln!("a deleted frame came back: {info:?}");
            figures.came_back.fetch_add(1, Ordering::Relaxed);
        }
        let mut writer = client.batch_writer("scratch", 1, 0, 256)?;
        deliver(&mut writer, records(7, 1, round, 256)).await?;
        for _ in 0..100 {
            if writer.sync().await.is_ok() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        loop {
            match client.delete_frame("scratch").await {
                Ok(()) | Err(ClientError::Rejected { status: 404, .. }) => break,
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        }
        figures.recreated.fetch_add(1, Ordering::Relaxed);
        round += 1;
    }
    Ok(())
}

/// Samples lost and doubled in `frame` against `reference`, pixel by pixel; exact cells compared
/// too.
async fn compare(client: &Client, frame: &str, reference: &FrameState) -> Result<(u64, u64, bool)> {
    let bytes = patiently(|| client.export_state(frame)).await?;
    let dump = StateDump::decode(&bytes, u64::MAX)?;
    let state = splatd_formats::state::load(dump)?;
    let (mut lost, mut doubled) = (0, 0);
    for y in 0..SIZE {
        for x in 0..SIZE {
            let (got, want) = (state.spp(x, y), reference.spp(x, y));
            lost += want.saturating_sub(got);
            doubled += got.saturating_sub(want);
        }
    }
    Ok((lost, doubled, state.cells() == reference.cells()))
}

#[tokio::main]
async fn main() -> Result<()> {
    let args = Arc::new(Args::parse());
    let binary = sibling_binary().map_err(anyhow::Error::msg)?;
    let dir =
        std::env::temp_dir().join(format!("splatd-soak-{:x}", splatd_proto::ids::random_u64()));
    std::fs::create_dir_all(&dir)?;
    let target = Arc::new(Target::start(binary, dir.clone())?);
    let url = target.url();
    let admin = client(&url)?;
    let figures = Arc::new(Figures::default());
    let layout = CascadeLayout::with_defaults();
    let frames: Vec<String> = (0..args.frames).map(|f| format!("soak-{f}")).collect();
    let mut references = Vec::new();
    for f in &frames {
        admin
            .create_frame(&CreateFrame::new(f.clone(), SIZE, SIZE))
            .await?;
        references.push(Arc::new(Mutex::new(FrameState::new(
            SIZE,
            SIZE,
            layout.clone(),
        ))));
    }

    let stop = Arc::new(AtomicBool::new(false));
    let mut tasks = Vec::new();
    for w in 0..args.workers {
        let f = (w % args.frames) as usize;
        tasks.push(tokio::spawn(worker(
            url.clone(),
            frames[f].clone(),
            w + 1,
            args.clone(),
            stop.clone(),
            references[f].clone(),
            figures.clone(),
        )));
    }
    let python = python_worker(&url, &frames[1 % frames.len()], &args, &dir)?;
    tasks.push(tokio::spawn(careless(
        url.clone(),
        frames[0].clone(),
        args.clone(),
        stop.clone(),
        references[0].clone(),
        figures.clone(),
    )));
    tasks.push(tokio::spawn(recreate(
        url.clone(),
        stop.clone(),
        figures.clone(),
    )));

    // Chaos: kills at random moments; one life in four cannot write snapshots.
    let chaos = {
        let (target, figures, args) = (target.clone(), figures.clone(), args.clone());
        tokio::task::spawn_blocking(move || -> Result<()> {
            let mut rng = SplitMix64::new(args.seed);
            let end = Instant::now() + Duration::from_secs(args.seconds);
            while Instant::now() < end {
                let wait = rng.next_u64() % (2 * args.kill_every_ms + 1);
                std::thread::sleep(Duration::from_millis(wait));
                let life = Life {
                    full_disk: rng.next_u64().is_multiple_of(4),
                    closed_log: rng.next_u64().is_multiple_of(4),
                };
                target.kill_and_restart(life)?;
                figures.kills.fetch_add(1, Ordering::Relaxed);
                if life.full_disk {
                    figures.full_disk_lives.fetch_add(1, Ordering::Relaxed);
                }
                if life.closed_log {
                    figures.closed_log_lives.fetch_add(1, Ordering::Relaxed);
                }
            }
            // The last life has a working disk (and a broken log), so every batch can become
            // durable, and the end of the soak runs without a log.
            target.kill_and_restart(Life {
                full_disk: false,
                closed_log: true,
            })?;
            figures.kills.fetch_add(1, Ordering::Relaxed);
            Ok(())
        })
    };
    chaos.await??;
    stop.store(true, Ordering::Relaxed);
    for t in tasks {
        t.await??;
    }
    let python_batches = python.finish(&references[1 % frames.len()])?;

    // The first frame's state imported into a second (durable) server, then again, also after
    // that server restarted, and into the first server itself: applied once, refused after.
    let head_dir = dir.join("head");
    std::fs::create_dir_all(&head_dir)?;
    let head = Target::start(target.binary.clone(), head_dir)?;
    let head_client = client(&head.url())?;
    head_client
        .create_frame(&CreateFrame::new(frames[0].clone(), SIZE, SIZE))
        .await?;
    let state = Bytes::from(patiently(|| admin.export_state(&frames[0])).await?.to_vec());
    patiently(|| head_client.import_state(&frames[0], state.clone())).await?;
    for round in 0..3 {
        if round == 1 {
            head.kill_and_restart(Life::default())?;
            figures.kills.fetch_add(1, Ordering::Relaxed);
        }
        let into = if round == 2 { &admin } else { &head_client };
        match into.import_state(&frames[0], state.clone()).await {
            Err(ClientError::Rejected { status: 409, body }) if body.error == "batches_overlap" => {
                figures.overlap_refused.fetch_add(1, Ordering::Relaxed);
            }
            Err(e) => return Err(e).context("importing a state twice"),
            Ok(ack) => {
                eprintln!("a state imported twice was answered {ack:?}");
                figures.overlap_applied.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    let (mut lost, mut doubled, mut exact) = (0, 0, true);
    for (f, reference) in frames.iter().zip(&references) {
        let reference = reference.lock().unwrap().clone();
        let (l, d, e) = compare(&admin, f, &reference).await?;
        println!(
            "frame {f}: {} samples, lost {l}, doubled {d}, cells exact: {e}",
            reference.total_samples()
        );
        lost += l;
        doubled += d;
        exact &= e;
        if f == &frames[0] {
            let (l, d, e) = compare(&head_client, f, &reference).await?;
            println!(
                "frame {f} imported into a second server: lost {l}, doubled {d}, cells exact: {e}"
            );
            lost += l;
            doubled += d;
            exact &= e;
        }
    }
    let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
    println!(
        "kills {} (full-disk lives {}, lives without a log {}), batches {} ({python_batches} of \
         them from the Python worker), resent after restarts {}, \
         reused ids refused {} (applied {}), frames deleted and re-created {} (came back {}), \
         double imports refused {} (applied {}); samples lost {lost}, doubled {doubled}, \
         every frame exact: {exact}",
        g(&figures.kills),
        g(&figures.full_disk_lives),
        g(&figures.closed_log_lives),
        g(&figures.batches) + python_batches,
        g(&figures.resent),
        g(&figures.reused_refused),
        g(&figures.reused_applied),
        g(&figures.recreated),
        g(&figures.came_back),
        g(&figures.overlap_refused),
        g(&figures.overlap_applied),
    );
    drop(target);
    let _ = std::fs::remove_dir_all(&dir);
    let failed = lost
        + doubled
        + g(&figures.came_back)
        + g(&figures.reused_applied)
        + g(&figures.overlap_applied)
        > 0
        || !exact;
    if failed {
        std::process::exit(1);
    }
    Ok(())
}
