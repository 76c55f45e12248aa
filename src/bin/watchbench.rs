//! "Watching is free": what watchers cost the workers feeding a frame, measured in one run
//! against a real `splatd serve` over loopback.
//!
//! ```sh
//! cargo build --release -p splatd --bin watchbench --bin splatd
//! target/release/watchbench [--seconds 12] [--rounds 2] [--writers 4]
//! ```
//!
//! `--writers` tasks post batches of records (scan-line runs with a heavy-tailed brightness, as
//! `loadgen` makes them) to a 1920x1080 frame without pause, through phases of `--seconds`
//! each, alternated `none, watch, loop, kappa` for `--rounds` rounds (with a settling second
//! between phases, whose posts are not counted):
//!
//! * `none`: the writers alone;
//! * `watch`: plus a dashboard polling `GET /v1/frames/{id}` and `GET /metrics` once a second
//!   (the scrape with Prometheus' `X-Prometheus-Scrape-Timeout-Seconds: 1`, as a Prometheus
//!   scraping every second sends it: a scrape's timeout cannot exceed its interval), a
//!   live page (the server's own, emulated: every second `GET /v1/frames` and
//!   `GET /v1/frames/{id}?convergence=latest`, then both `preview.png` layers when the sample
//!   count moved and none are loading, as `server/src/http/web/index.html` polls; like
//!   `setInterval` it does not wait for the last refresh, up to 4 in flight) and an `image.exr`
//!   fetched every 5 s;
//! * `loop`: plus one client fetching `image.exr` back to back;
//! * `kappa`: instead, [`KAPPA_READERS`] clients each fetching `image.exr` back to back with a
//!   `kappa` of its own that changes every request, so that no two requests can share a
//!   resolve (as a lighting TD sweeping `kappa` would): every request a whole resolve, held to
//!   the frame's render pace like any other;
//!
//! then, on a second server (a frame's renders of every kind share its render pace, so a tev
//! phase after the others would find the frame held to their pace), `alone, tev`:
//!
//! * `alone`: the writers alone;
//! * `tev`: plus a tev viewer: the server runs with `--tev` pointed at a stand-in in this
//!   process that listens only during this phase and reads what it is sent (the server's feed
//!   pushes the changed frame about once a second, as its updates' pace allows); outside the
//!   phase the feed's connections are refused, which costs it nothing.
//!
//! It prints ingest samples/s and batch post latency (p50, p99, p99.9, max) per phase, the
//! server's CPU seconds per second of each phase (`/proc/PID/stat`), the renders and resolves
//! the server counted in `watch` (`splatd_renders_total` and `splatd_resolves_total` in the
//! dashboard's first and last scrape of each round), the bytes tev was sent, the ratios beside
//! their goals (ingest with watchers / without >= 0.9; post p99 with the image loop / without
//! <= 1.5; ingest with the `kappa` readers and with tev / without, which have no goal of their
//! own), and the server CPU
//! time of one `/metrics` scrape and of one round of `GET /v1/frames/{id}` over 20 frames, on a
//! second server holding 64 unchanged 512x512 frames, with the renders they caused (the
//! server's `splatd_renders_total` before and after; goal: none).
//! Every figure is under whatever else the machine runs: the load average is printed beside.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use bytes::Bytes;
use clap::Parser;
use splatd_harness::{sibling_binary, Options, ServerProcess};
use splatd_proto::api::CreateFrame;
use splatd_proto::{Client, BATCH_CONTENT_TYPE};

#[path = "common/load.rs"]
mod load;

#[derive(Parser)]
#[command(about = "Ingest with and without watchers (dashboard, live page, image fetches)")]
struct Args {
    /// Seconds of each phase.
    #[arg(long, default_value_t = 12.0)]
    seconds: f64,
    /// Rounds of the three phases.
    #[arg(long, default_value_t = 2)]
    rounds: usize,
    /// Writer tasks (connections) posting batches.
    #[arg(long, default_value_t = 4)]
    writers: usize,
    /// Records per batch.
    #[arg(long, default_value_t = 65536)]
    batch: usize,
    /// Frame width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Frame height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// Frames on the scrape-cost server.
    #[arg(long, default_value_t = 64)]
    scrape_frames: usize,
    /// Width and height of each of them.
    #[arg(long, default_value_t = 512)]
    scrape_size: u32,
    /// Frames whose info one round fetches.
    #[arg(long, default_value_t = 20)]
    info_frames: usize,
    /// Only the scrape-cost lines (no ingest phases), e.g. to profile them.
    #[arg(long)]
    scrape_only: bool,
    /// The server's `--render-share` (its default if not given).
    #[arg(long)]
    render_share: Option<f64>,
}

/// Ingest with watchers / without.
const INGEST_GOAL: f64 = 0.9;
/// Post p99 with an image fetched back to back / without.
const P99_GOAL: f64 = 1.5;
/// Renders a scrape or an info round of unchanged frames may cost (the server's
/// `splatd_renders_total` before and after).
const SCRAPE_GOAL_RENDERS: u64 = 0;

const PHASES: [&str; 6] = ["none", "watch", "loop", "kappa", "alone", "tev"];
const NONE: usize = 0;
const WATCH: usize = 1;
const LOOP: usize = 2;
const KAPPA: usize = 3;
const ALONE: usize = 4;
const TEV: usize = 5;
/// The phases on the first server, and on the second, which runs with `--tev`.
const WATCHERS: [usize; 4] = [NONE, WATCH, LOOP, KAPPA];
const TEV_PHASES: [usize; 2] = [ALONE, TEV];
/// Clients fetching `image.exr` with `kappa`s of their own in the `kappa` phase.
const KAPPA_READERS: usize = 4;
/// Between phases: nothing is counted.
const SETTLE: usize = usize::MAX;

const FRAME: &str = "watch";

/// How often an idle watcher, or one waiting for its phase to end, looks again.
const POLL: Duration = Duration::from_millis(20);

#[derive(Default)]
struct PhaseStats {
    samples: u64,
    posts: u64,
    post_ms: Vec<f64>,
    wall_s: f64,
    server_cpu_s: f64,
    /// (endpoint, milliseconds) of the watchers' requests.
    watcher_ms: Vec<(&'static str, f64)>,
    skipped_refreshes: u64,
    load: Vec<f64>,
    /// Renders and resolves the server counted between the dashboard's first and last
    /// `/metrics` of each stint of the phase, and the seconds between those scrapes.
    server_renders: (f64, f64, f64),
    /// Bytes the tev stand-in read.
    tev_bytes: u64,
}

struct Shared {
    phase: AtomicUsize,
    stop: AtomicBool,
    /// Watcher requests in flight (a phase ends only when they are done).
    in_flight: AtomicUsize,
    /// Watcher requests answered 503 `busy` (the working memory stayed spent): the live page
    /// and a dashboard keep what they showed and ask again, and so does this benchmark.
    busy: AtomicUsize,
    stats: Mutex<Vec<PhaseStats>>,
    http: reqwest::Client,
    url: String,
}

impl Shared {
    fn phase(&self) -> usize {
        self.phase.load(Ordering::SeqCst)
    }

    /// Whether `phase` is running; if it is not, after a moment's sleep ([`POLL`]): the idle
    /// step of a watcher that runs in one phase.
    async fn in_phase(&self, phase: usize) -> bool {
        if self.phase() == phase {
            return true;
        }
        tokio::time::sleep(POLL).await;
        false
    }

    fn record_watcher(&self, phase: usize, what: &'static str, ms: f64) {
        if phase != SETTLE {
            self.stats.lock().unwrap()[phase]
                .watcher_ms
                .push((what, ms));
        }
    }

    /// GETs `path` and reads the whole body; its milliseconds, recorded under `what`.
    async fn get(&self, phase: usize, what: &'static str, path: &str) -> Result<Bytes> {
        self.get_with(phase, what, path, &[]).await
    }

    /// [`Shared::get`] with extra request headers.
    async fn get_with(
        &self,
        phase: usize,
        what: &'static str,
        path: &str,
        headers: &[(&str, &str)],
    ) -> Result<Bytes> {
        self.in_flight.fetch_add(1, Ordering::SeqCst);
        let t = Instant::now();
        let result = async {
            let mut request = self.http.get(format!("{}{path}", self.url));
            for (name, value) in headers {
                request = request.header(*name, *value);
            }
            let r = request.send().await?;
            if r.status() == reqwest::StatusCode::SERVICE_UNAVAILABLE {
                self.busy.fetch_add(1, Ordering::SeqCst);
                return Ok(Bytes::new());
            }
            if !r.status().is_success() {
                bail!("GET {path}: HTTP {}", r.status());
            }
            Ok(r.bytes().await?)
        }
        .await;
        self.record_watcher(phase, what, t.elapsed().as_secs_f64() * 1e3);
        self.in_flight.fetch_sub(1, Ordering::SeqCst);
        result
    }
}

/// User plus system CPU seconds of process `pid` so far.
fn cpu_seconds(pid: u32, tick: f64) -> Result<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    let after = &stat[stat.rfind(')').context("no comm in /proc stat")? + 2..];
    let fields: Vec<&str> = after.split_whitespace().collect();
    // After the comm: state is field 3 of the man page, utime 14 and stime 15.
    let utime: f64 = fields[11].parse()?;
    let stime: f64 = fields[12].parse()?;
    Ok((utime + stime) / tick)
}

/// Clock ticks per second (`getconf CLK_TCK`; 100 if that fails).
fn clock_tick() -> f64 {
    std::process::Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(100.0)
}

/// The 1-minute load average.
fn load1() -> f64 {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or(f64::NAN)
}

fn uptime() -> String {
    format!("load average {}", load::load_averages())
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i]
}

/// A `splatd serve` with `--render-share` if given, and with `--tev` if given.
fn start_server(render_share: Option<f64>, tev: Option<&str>) -> Result<ServerProcess> {
    let binary = sibling_binary().map_err(anyhow::Error::msg)?;
    let share = render_share.map(|s| s.to_string());
    let mut args: Vec<&str> = Vec::new();
    if let Some(s) = &share {
        args.extend(["--render-share", s]);
    }
    if let Some(addr) = tev {
        args.extend(["--tev", addr]);
    }
    ServerProcess::launch(&Options {
        log_level: "warn",
        ..Options::new(binary, &args)
    })
    .map_err(anyhow::Error::msg)
}

/// Where in an encoded batch the 8 little-endian bytes of `value` are (the worker or seq).
fn find_u64(body: &[u8], value: u64) -> Result<usize> {
    let needle = value.to_le_bytes();
    body.windows(8)
        .position(|w| w == needle)
        .context("marker not found in the encoded batch")
}

/// Encoded batches with the byte offsets of their worker and seq fields, to be patched per post.
struct Pool {
    bodies: Vec<Vec<u8>>,
    worker_at: usize,
    seq_at: usize,
    samples: u64,
}

fn make_pool(args: &Args) -> Result<Pool> {
    const WORKER_MARK: u64 = 0x5eed_a5a5_0000_0001;
    const SEQ_MARK: u64 = 0x5e90_5a5a_0000_0002;
    // 32 batches: 2 Mi records, one sample on every pixel of 1920x1080 and then some.
    let batches = load::make_batches(FRAME, args.width, args.height, args.batch, 32, 1, 7);
    let mut bodies = Vec::new();
    let (mut worker_at, mut seq_at) = (0, 0);
    for mut b in batches {
        b.worker = WORKER_MARK;
        b.seq = SEQ_MARK;
        let body = b.encode();
        worker_at = find_u64(&body, WORKER_MARK)?;
        seq_at = find_u64(&body, SEQ_MARK)?;
        bodies.push(body);
    }
    Ok(Pool {
        bodies,
        worker_at,
        seq_at,
        samples: args.batch as u64,
    })
}

/// Posts batches without pause until told to stop; counts those that start and end in the
/// same phase.
async fn writer(shared: Arc<Shared>, pool: Arc<Pool>, worker: u64) -> Result<()> {
    let target = format!("{}/v1/frames/{FRAME}/samples", shared.url);
    let mut seq = 0u64;
    while !shared.stop.load(Ordering::SeqCst) {
        let mut body =
            pool.bodies[(seq as usize + worker as usize * 7) % pool.bodies.len()].clone();
        body[pool.worker_at..pool.worker_at + 8].copy_from_slice(&worker.to_le_bytes());
        body[pool.seq_at..pool.seq_at + 8].copy_from_slice(&seq.to_le_bytes());
        seq += 1;
        let phase = shared.phase();
        let t = Instant::now();
        let r = shared
            .http
            .post(&target)
            .header("content-type", BATCH_CONTENT_TYPE)
            .body(body)
            .send()
            .await?;
        if !r.status().is_success() {
            bail!(
                "batch ({worker}, {seq}): HTTP {}: {}",
                r.status(),
                r.text().await?
            );
        }
        r.bytes().await?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        if phase != SETTLE && shared.phase() == phase {
            let mut stats = shared.stats.lock().unwrap();
            stats[phase].samples += pool.samples;
            stats[phase].posts += 1;
            stats[phase].post_ms.push(ms);
        }
    }
    Ok(())
}

/// The sum of every series of counter `name` in a Prometheus text body (0 before the server
/// counted any).
fn counter(text: &str, name: &str) -> f64 {
    text.lines()
        .filter(|l| {
            l.strip_prefix(name)
                .is_some_and(|rest| rest.starts_with([' ', '{']))
        })
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

/// Every second in `watch`: frame info, then a Prometheus scrape. The scrapes' render and
/// resolve counters, first and last of each stint of the phase, go to the phase's figures.
async fn dashboard(shared: Arc<Shared>) -> Result<()> {
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // (when, renders, resolves) of this stint's first scrape and of its latest.
    let mut stint: Option<[(Instant, f64, f64); 2]> = None;
    while !shared.stop.load(Ordering::SeqCst) {
        tick.tick().await;
        let phase = shared.phase();
        if phase != WATCH {
            if let Some([(t0, renders0, resolves0), (t1, renders1, resolves1)]) = stint.take() {
                let counted = &mut shared.stats.lock().unwrap()[WATCH].server_renders;
                counted.0 += renders1 - renders0;
                counted.1 += resolves1 - resolves0;
                counted.2 += (t1 - t0).as_secs_f64();
            }
            continue;
        }
        shared
            .get(phase, "dashboard info", &format!("/v1/frames/{FRAME}"))
            .await?;
        // Prometheus tells a target how long it will wait (its scrape timeout, at most its
        // interval): the server waits for paced renders at most half of that.
        let timeout = [(splatd_server::http::operations::SCRAPE_TIMEOUT_HEADER, "1")];
        let text = shared
            .get_with(phase, "dashboard /metrics", "/metrics", &timeout)
            .await?;
        let text = String::from_utf8_lossy(&text);
        let now = (
            Instant::now(),
            counter(&text, splatd_server::meters::RENDERS),
            counter(&text, splatd_server::meters::RESOLVES),
        );
        stint = Some(stint.map_or([now, now], |[first, _]| [first, now]));
    }
    Ok(())
}

/// What the emulated live page keeps between refreshes (index.html's `view`).
#[derive(Default)]
struct Page {
    /// The sample count the images were last asked for at.
    last: Mutex<i64>,
    /// Both previews are being fetched (one set at a time, as the page does).
    loading: AtomicBool,
    /// The first error of a refresh or a preview fetch.
    failed: Mutex<Option<anyhow::Error>>,
}

/// One refresh of the live page (index.html's `refresh`: the list, then the frame's latest
/// figures, then both previews when the sample count moved and none are loading, without
/// waiting for them, as `refreshImages` runs).
async fn live_refresh(shared: Arc<Shared>, page: Arc<Page>, phase: usize) -> Result<()> {
    shared.get(phase, "live /v1/frames", "/v1/frames").await?;
    let info = shared
        .get(
            phase,
            "live info",
            &format!("/v1/frames/{FRAME}?convergence=latest"),
        )
        .await?;
    let info: serde_json::Value = serde_json::from_slice(&info)?;
    let samples = info["samples"].as_i64().unwrap_or(-1);
    let changed = *page.last.lock().unwrap() != samples;
    if changed && !page.loading.swap(true, Ordering::SeqCst) {
        *page.last.lock().unwrap() = samples;
        tokio::spawn(async move {
            let base = format!("/v1/frames/{FRAME}/preview.png");
            let q = format!("&stops=0&samples={samples}");
            let mean = format!("{base}?layer=mean{q}");
            let reweighted = format!("{base}?layer=reweighted{q}");
            let (a, b) = tokio::join!(
                shared.get(phase, "live preview.png mean", &mean),
                shared.get(phase, "live preview.png reweighted", &reweighted)
            );
            if let Err(e) = a.and(b) {
                page.failed.lock().unwrap().get_or_insert(e);
            }
            page.loading.store(false, Ordering::SeqCst);
        });
    }
    Ok(())
}

/// The live page: a refresh started every second (as `setInterval`), up to 4 in flight.
async fn live_page(shared: Arc<Shared>) -> Result<()> {
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let page = Arc::new(Page {
        last: Mutex::new(-1),
        ..Page::default()
    });
    let running = Arc::new(AtomicUsize::new(0));
    while !shared.stop.load(Ordering::SeqCst) {
        tick.tick().await;
        if let Some(e) = page.failed.lock().unwrap().take() {
            return Err(e);
        }
        let phase = shared.phase();
        if phase != WATCH {
            continue;
        }
        if running.load(Ordering::SeqCst) >= 4 {
            shared.stats.lock().unwrap()[phase].skipped_refreshes += 1;
            continue;
        }
        running.fetch_add(1, Ordering::SeqCst);
        let (shared, page, running) = (shared.clone(), page.clone(), running.clone());
        tokio::spawn(async move {
            if let Err(e) = live_refresh(shared, page.clone(), phase).await {
                page.failed.lock().unwrap().get_or_insert(e);
            }
            running.fetch_sub(1, Ordering::SeqCst);
        });
    }
    Ok(())
}

/// `image.exr` every 5 s in `watch`, back to back in `loop`.
async fn images(shared: Arc<Shared>) -> Result<()> {
    let path = format!("/v1/frames/{FRAME}/image.exr");
    let mut last_watch: Option<Instant> = None;
    while !shared.stop.load(Ordering::SeqCst) {
        let phase = shared.phase();
        match phase {
            LOOP => {
                shared.get(phase, "loop image.exr", &path).await?;
            }
            WATCH if last_watch.is_none_or(|t| t.elapsed() >= Duration::from_secs(5)) => {
                last_watch = Some(Instant::now());
                shared.get(phase, "watch image.exr", &path).await?;
            }
            _ => {
                if phase != WATCH {
                    last_watch = None;
                }
                tokio::time::sleep(POLL).await;
            }
        }
    }
    Ok(())
}

/// In `kappa`: `image.exr` back to back, each request with a `kappa` no other request of the
/// phase asks for (reader `reader` of [`KAPPA_READERS`]: 2.0, 2.0 + 1/64, ... interleaved with
/// the other readers'), so no resolve is shared.
async fn kappa_reader(shared: Arc<Shared>, reader: usize) -> Result<()> {
    let path = format!("/v1/frames/{FRAME}/image.exr");
    let mut request = 0;
    while !shared.stop.load(Ordering::SeqCst) {
        if !shared.in_phase(KAPPA).await {
            continue;
        }
        let kappa = 2.0 + (request * KAPPA_READERS + reader) as f64 / 64.0;
        request += 1;
        shared
            .get(KAPPA, "kappa image.exr", &format!("{path}?kappa={kappa}"))
            .await?;
    }
    Ok(())
}

/// In `tev`: a tev viewer at `addr` that reads and counts what it is sent; it listens only
/// during the phase and closes its connections when the phase ends.
async fn tev_viewer(shared: Arc<Shared>, addr: String) -> Result<()> {
    while !shared.stop.load(Ordering::SeqCst) {
        if !shared.in_phase(TEV).await {
            continue;
        }
        let listener = tokio::net::TcpListener::bind(&addr)
            .await
            .with_context(|| format!("the tev stand-in binding {addr}"))?;
        while shared.phase() == TEV {
            let accepted = tokio::time::timeout(POLL, listener.accept());
            if let Ok(accepted) = accepted.await {
                let (stream, _) = accepted?;
                tokio::spawn(tev_connection(shared.clone(), stream));
            }
        }
    }
    Ok(())
}

/// Reads a connection to the tev stand-in until the server closes it or the phase ends.
async fn tev_connection(shared: Arc<Shared>, mut stream: tokio::net::TcpStream) {
    use tokio::io::AsyncReadExt;
    let mut buf = vec![0u8; 1 << 20];
    while shared.phase() == TEV {
        let read = tokio::time::timeout(POLL, stream.read(&mut buf));
        match read.await {
            Ok(Ok(0) | Err(_)) => return,
            Ok(Ok(n)) => shared.stats.lock().unwrap()[TEV].tev_bytes += n as u64,
            Err(_) => {}
        }
    }
}

/// Runs `which` phases in turn, `--rounds` times, after a warm-up.
async fn phases(
    args: &Args,
    shared: &Arc<Shared>,
    pid: u32,
    tick: f64,
    which: &[usize],
) -> Result<()> {
    let settle = || async {
        shared.phase.store(SETTLE, Ordering::SeqCst);
        let t = Instant::now();
        tokio::time::sleep(Duration::from_secs(1)).await;
        while shared.in_flight.load(Ordering::SeqCst) > 0 && t.elapsed() < Duration::from_secs(60) {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    };
    // A warm-up, so that the frame's memory is faulted in before anything is counted.
    settle().await;
    tokio::time::sleep(Duration::from_secs_f64(args.seconds.min(3.0))).await;
    for round in 0..args.rounds {
        for &phase in which {
            settle().await;
            let cpu0 = cpu_seconds(pid, tick)?;
            let t0 = Instant::now();
            shared.phase.store(phase, Ordering::SeqCst);
            tokio::time::sleep(Duration::from_secs_f64(args.seconds)).await;
            shared.phase.store(SETTLE, Ordering::SeqCst);
            let wall = t0.elapsed().as_secs_f64();
            let cpu = cpu_seconds(pid, tick)? - cpu0;
            let mut stats = shared.stats.lock().unwrap();
            let s = &mut stats[phase];
            s.wall_s += wall;
            s.server_cpu_s += cpu;
            s.load.push(load1());
            eprintln!(
                "round {round} {:<5}: {:.1} M samples/s so far, server CPU {:.2} s/s, load {:.2}",
                PHASES[phase],
                s.samples as f64 / s.wall_s / 1e6,
                cpu / wall,
                load1()
            );
        }
    }
    settle().await;
    Ok(())
}

/// Server CPU seconds of `f`, one call of which is `reps` repetitions of the measured thing.
async fn cpu_of<F, Fut>(pid: u32, tick: f64, reps: usize, mut f: F) -> Result<f64>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<()>>,
{
    let c0 = cpu_seconds(pid, tick)?;
    for _ in 0..reps {
        f().await?;
    }
    Ok((cpu_seconds(pid, tick)? - c0) / reps as f64)
}

/// Waits (bounded) until the server spends no CPU over half a second.
async fn wait_idle(pid: u32, tick: f64) -> Result<f64> {
    let t = Instant::now();
    let mut last = cpu_seconds(pid, tick)?;
    loop {
        tokio::time::sleep(Duration::from_millis(500)).await;
        let now = cpu_seconds(pid, tick)?;
        if now - last < 1.5 / tick || t.elapsed() > Duration::from_secs(30) {
            return Ok(now - last);
        }
        last = now;
    }
}

/// The scrape-cost lines: a fresh server with `scrape_frames` unchanged frames.
async fn scrape_cost(args: &Args, tick: f64) -> Result<Vec<String>> {
    let server = start_server(args.render_share, None)?;
    let pid = server.pid();
    let client = Client::new(&server.url)?;
    let http = reqwest::Client::new();
    let s = args.scrape_size;
    let per_frame = (s as usize * s as usize).div_ceil(args.batch);
    eprintln!(
        "scrape cost: loading {} frames of {s}x{s}, 1 spp each ...",
        args.scrape_frames
    );
    for f in 0..args.scrape_frames {
        let id = format!("scrape{f:02}");
        client.create_frame(&CreateFrame::new(&id, s, s)).await?;
        for b in load::make_batches(&id, s, s, args.batch, per_frame, 1, f as u64) {
            client.post_batch(&b).await?;
        }
    }
    let get = |path: String| {
        let (http, url) = (http.clone(), server.url.clone());
        async move {
            let r = http.get(format!("{url}{path}")).send().await?;
            if !r.status().is_success() {
                bail!("GET {path}: HTTP {}", r.status());
            }
            r.bytes().await?;
            Ok(())
        }
    };
    let info_round = || async {
        for f in 0..args.info_frames.min(args.scrape_frames) {
            get(format!("/v1/frames/scrape{f:02}")).await?;
        }
        Ok(())
    };
    // The server's count of renders run, from a scrape of its own.
    let renders = || {
        let (http, url) = (http.clone(), server.url.clone());
        async move {
            let text = http
                .get(format!("{url}/metrics"))
                .send()
                .await?
                .text()
                .await?;
            Ok::<u64, anyhow::Error>(counter(&text, splatd_server::meters::RENDERS) as u64)
        }
    };
    let idle = wait_idle(pid, tick).await?;
    // The first scrape and info round after the samples arrived may resolve (the frames
    // changed since nothing looked at them); printed, but not the goal.
    // Nothing rendered while the frames loaded: the first scrape is the first request to look.
    let first_scrape = cpu_of(pid, tick, 1, || get("/metrics".into())).await?;
    let first_round = cpu_of(pid, tick, 1, info_round).await?;
    let first_renders = renders().await?;
    wait_idle(pid, tick).await?;
    // Enough repetitions that a clock tick is a small part of the figure.
    let reps = 100;
    let before = renders().await?;
    let t = Instant::now();
    let scrape = cpu_of(pid, tick, reps, || get("/metrics".into())).await?;
    let scrape_wall = t.elapsed().as_secs_f64() / reps as f64;
    let between = renders().await?;
    let t = Instant::now();
    let round = cpu_of(pid, tick, reps, info_round).await?;
    let round_wall = t.elapsed().as_secs_f64() / reps as f64;
    let after = renders().await?;
    let (scrape_renders, round_renders) = (between - before, after - between);
    // For scale: one image.exr of one of these frames (changed frame, so a resolve).
    let image = cpu_of(pid, tick, 3, || get("/v1/frames/scrape00/image.exr".into())).await?;
    drop(server);
    let n = args.info_frames.min(args.scrape_frames);
    println!(
        "\nscrape cost, {} unchanged {s}x{s} frames (server CPU; clock tick {:.0} ms; idle before: \
         {idle:.3} s per 0.5 s; {}):",
        args.scrape_frames,
        1e3 / tick,
        uptime()
    );
    println!(
        "  first /metrics after loading {first_scrape:.3} s, first info round {first_round:.3} s \
         ({first_renders} renders: the frames changed since loading)"
    );
    println!(
        "  /metrics: {scrape:.5} s CPU per scrape (mean of {reps}; {:.1} ms wall); renders in \
         the {reps} scrapes: {scrape_renders}",
        scrape_wall * 1e3
    );
    println!(
        "  GET /v1/frames/{{id}} over {n} frames: {round:.5} s CPU per round (mean of {reps}; \
         {:.1} ms wall); renders in the {reps} rounds: {round_renders}",
        round_wall * 1e3
    );
    println!("  for scale, image.exr of one {s}x{s} frame: {image:.4} s CPU");
    let met = |renders: u64| {
        if renders == SCRAPE_GOAL_RENDERS {
            "met"
        } else {
            "MISSED"
        }
    };
    Ok(vec![
        format!(
            "/metrics scrape, {} unchanged frames: {scrape_renders} renders in {reps} scrapes \
             (goal no resolve: {SCRAPE_GOAL_RENDERS}), {scrape:.5} s server CPU each {}",
            args.scrape_frames,
            met(scrape_renders)
        ),
        format!(
            "frame info round over {n} unchanged frames: {round_renders} renders in {reps} \
             rounds (goal no resolve: {SCRAPE_GOAL_RENDERS}), {round:.5} s server CPU each {}",
            met(round_renders)
        ),
    ])
}

fn main() -> Result<()> {
    let args = Args::parse();
    if args.seconds.is_nan() || args.seconds <= 0.0 || args.rounds == 0 || args.writers == 0 {
        bail!("--seconds, --rounds and --writers must be positive");
    }
    let tick = clock_tick();
    println!("watchbench: {} at start", uptime());
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    if args.scrape_only {
        let scrape = runtime.block_on(scrape_cost(&args, tick))?;
        println!("\ngoals ({} at the end):", uptime());
        for line in scrape {
            println!("  {line}");
        }
        return Ok(());
    }
    let pool = Arc::new(make_pool(&args)?);
    let stats = PHASES.iter().map(|_| PhaseStats::default()).collect();
    let (stats, busy) = runtime.block_on(watch_server(&args, &pool, tick, None, stats))?;
    // The tev stand-in's address: a port taken and given back, on which nothing listens
    // outside the `tev` phase.
    let tev = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .to_string();
    let (mut stats, more_busy) =
        runtime.block_on(watch_server(&args, &pool, tick, Some(tev), stats))?;
    let goals = report(&mut stats, busy + more_busy, &args)?;
    let scrape = runtime.block_on(scrape_cost(&args, tick))?;
    println!("\ngoals ({} at the end):", uptime());
    for line in goals.iter().chain(&scrape) {
        println!("  {line}");
    }
    Ok(())
}

/// Starts a server (with `--tev` at `tev` if given, then running the phases [`TEV_PHASES`],
/// else [`WATCHERS`]), creates the frame, and runs the writers and watchers through the
/// phases; returns `stats` with the figures added, and the watcher requests answered busy.
async fn watch_server(
    args: &Args,
    pool: &Arc<Pool>,
    tick: f64,
    tev: Option<String>,
    stats: Vec<PhaseStats>,
) -> Result<(Vec<PhaseStats>, usize)> {
    let server = start_server(args.render_share, tev.as_deref())?;
    let which: &[usize] = if tev.is_some() {
        &TEV_PHASES
    } else {
        &WATCHERS
    };
    let pid = server.pid();
    let url = server.url.clone();
    let shared = Arc::new(Shared {
        phase: AtomicUsize::new(SETTLE),
        stop: AtomicBool::new(false),
        in_flight: AtomicUsize::new(0),
        busy: AtomicUsize::new(0),
        stats: Mutex::new(stats),
        http: reqwest::Client::new(),
        url: url.clone(),
    });
    let names: Vec<&str> = which.iter().map(|&p| PHASES[p]).collect();
    println!(
        "{}x{} frame, {} writers posting batches of {} records; phases of {} s, {} rounds of \
         {}; server log {}",
        args.width,
        args.height,
        args.writers,
        args.batch,
        args.seconds,
        args.rounds,
        names.join("/"),
        server
            .log_path()
            .map_or("-".into(), |p| p.display().to_string())
    );
    Client::new(&url)?
        .create_frame(&CreateFrame::new(FRAME, args.width, args.height))
        .await?;
    let mut tasks = Vec::new();
    for w in 0..args.writers {
        tasks.push(tokio::spawn(writer(
            shared.clone(),
            pool.clone(),
            w as u64 + 1,
        )));
    }
    match tev {
        Some(tev) => tasks.push(tokio::spawn(tev_viewer(shared.clone(), tev))),
        None => {
            tasks.push(tokio::spawn(dashboard(shared.clone())));
            tasks.push(tokio::spawn(live_page(shared.clone())));
            tasks.push(tokio::spawn(images(shared.clone())));
            for reader in 0..KAPPA_READERS {
                tasks.push(tokio::spawn(kappa_reader(shared.clone(), reader)));
            }
        }
    }
    let result = phases(args, &shared, pid, tick, which).await;
    shared.stop.store(true, Ordering::SeqCst);
    for t in tasks {
        t.await??;
    }
    result?;
    drop(server);
    let busy = shared.busy.load(Ordering::SeqCst);
    let stats = std::mem::take(&mut *shared.stats.lock().unwrap());
    Ok((stats, busy))
}

/// Prints the per-phase figures; the goal lines.
fn report(stats: &mut [PhaseStats], busy: usize, args: &Args) -> Result<Vec<String>> {
    let mut rate = [0.0; PHASES.len()];
    let mut p99 = [0.0; PHASES.len()];
    println!();
    for (phase, s) in stats.iter_mut().enumerate() {
        s.post_ms.sort_by(f64::total_cmp);
        rate[phase] = s.samples as f64 / s.wall_s;
        p99[phase] = percentile(&s.post_ms, 0.99);
        let loads: Vec<String> = s.load.iter().map(|l| format!("{l:.2}")).collect();
        println!(
            "{:<5}: {:>6.1} M samples/s ({} posts in {:.1} s); post latency p50 {:.1} ms, p99 \
             {:.1} ms, p99.9 {:.1} ms, max {:.1} ms; server CPU {:.2} s/s; load at phase ends {}",
            PHASES[phase],
            rate[phase] / 1e6,
            s.posts,
            s.wall_s,
            percentile(&s.post_ms, 0.5),
            p99[phase],
            percentile(&s.post_ms, 0.999),
            s.post_ms.last().copied().unwrap_or(f64::NAN),
            s.server_cpu_s / s.wall_s,
            loads.join(" ")
        );
        let mut whats: Vec<&'static str> = s.watcher_ms.iter().map(|(w, _)| *w).collect();
        whats.sort();
        whats.dedup();
        for what in whats {
            let mut ms: Vec<f64> = s
                .watcher_ms
                .iter()
                .filter(|(w, _)| *w == what)
                .map(|(_, ms)| *ms)
                .collect();
            ms.sort_by(f64::total_cmp);
            println!(
                "         {what:<28} {:>4} requests, p50 {:.1} ms, max {:.1} ms",
                ms.len(),
                percentile(&ms, 0.5),
                ms.last().copied().unwrap_or(f64::NAN)
            );
        }
        if s.skipped_refreshes > 0 {
            println!(
                "         live page refreshes skipped (4 in flight): {}",
                s.skipped_refreshes
            );
        }
        if s.tev_bytes > 0 {
            // An update sends 9 floats a pixel (3 layers), besides the packets' headers.
            let update = 36.0 * f64::from(args.width) * f64::from(args.height);
            println!(
                "         tev was sent {:.0} MB (about {:.1} updates of the whole frame)",
                s.tev_bytes as f64 / 1e6,
                s.tev_bytes as f64 / update
            );
        }
        let (renders, resolves, seconds) = s.server_renders;
        if seconds > 0.0 {
            println!(
                "         the server's renders {renders}, resolves {resolves} in {seconds:.1} s \
                 (its /metrics, the dashboard's first and last scrape of each round)"
            );
        }
    }
    println!("watcher requests answered 503 busy (shown again later): {busy}");
    if stats.iter().any(|s| s.posts == 0) {
        bail!("a phase counted no posts: lengthen --seconds");
    }
    let ingest = rate[WATCH] / rate[NONE];
    let lat = p99[LOOP] / p99[NONE];
    let verdict = |met: bool| if met { "met" } else { "MISSED" };
    Ok(vec![
        format!(
            "ingest with watchers / without: ratio {ingest:.2} (goal >= {INGEST_GOAL}) {}",
            verdict(ingest >= INGEST_GOAL)
        ),
        format!(
            "batch post p99 with image loop / without: ratio {lat:.2} ({:.1} / {:.1} ms) (goal \
             <= {P99_GOAL}) {}",
            p99[LOOP],
            p99[NONE],
            verdict(lat <= P99_GOAL)
        ),
        format!(
            "ingest with image loop / without: ratio {:.2} (no goal; for reference)",
            rate[LOOP] / rate[NONE]
        ),
        format!(
            "ingest with {KAPPA_READERS} readers varying kappa / without: ratio {:.2} (no goal; \
             bounded by --render-share, for reference)",
            rate[KAPPA] / rate[NONE]
        ),
        format!(
            "ingest with tev watching / without (the second server's phases): ratio {:.2} (no \
             goal; for reference)",
            rate[TEV] / rate[ALONE]
        ),
    ])
}
