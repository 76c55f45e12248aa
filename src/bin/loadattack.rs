//! Load attacks against a real `splatd serve` process: what careless and hostile clients do to a
//! render head, one phase at a time, while a dashboard keeps asking `/healthz`.
//!
//! ```text
//! cargo build --release --bins && target/release/loadattack
//! ```
//!
//! Phases, on a 1920x1080 frame holding a few million samples:
//!
//! 1. 64 concurrent `image.exr` requests (half the same query, which share one resolve, half
//!    each with its own `kappa`, which cannot);
//! 2. 64 concurrent zstd bombs: 2.6 KB bodies inflating to maximum-size (80 MiB) batches;
//! 3. 64 slow readers: `image.exr` requested with a 4 KiB receive window and never read;
//! 4. 2,000 silent sockets: connected, never sending a byte;
//! 5. 2,000 active clients, each on its own connection, posting 5 small batches (retrying
//!    connection errors and 503 like the reference clients).
//!
//! For each phase it prints the answers by status (or by connection error), the server's peak
//! RSS (sampled from `/proc/PID/status` VmRSS every 20 ms, and VmHWM at the end), its peak
//! count of open descriptors (`/proc/PID/fd`), and the `/healthz` latency (max, and how many
//! probes failed), all measured in this one run. Linux only (it reads `/proc`).

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Parser;
use splatd_harness::{sibling_binary, Options, ServerProcess};
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Record, BATCH_CONTENT_TYPE};
use splatd_scenes::synth::SplitMix64;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[derive(Parser)]
#[command(
    about = "Hostile and careless clients against a real splatd, with RSS, descriptors and health latency"
)]
struct Args {
    /// `splatd serve` flags for the run, as one string.
    #[arg(
        long,
        allow_hyphen_values = true,
        default_value = "--work-memory-mib 1024 --work-wait-secs 10 --max-connections 1024 \
                         --head-timeout 3 --response-timeout 10"
    )]
    serve: String,
    /// Concurrent clients in the image, bomb and slow-reader phases.
    #[arg(long, default_value_t = 64)]
    concurrent: usize,
    /// Sockets in the silent phase and clients in the active phase.
    #[arg(long, default_value_t = 2000)]
    many: usize,
    /// Seconds the silent sockets are held (longer than the server's --head-timeout).
    #[arg(long, default_value_t = 6)]
    silent_secs: u64,
    /// Seconds the slow readers wait before reading (longer than --response-timeout).
    #[arg(long, default_value_t = 14)]
    slow_secs: u64,
}

const FRAME: &str = "big";
const WIDTH: u32 = 1920;
const HEIGHT: u32 = 1080;

/// What the sampler and the health prober saw during one phase.
#[derive(Debug, Default, Clone)]
struct Seen {
    rss_kib_max: u64,
    fds_max: usize,
    health_max: Duration,
    health_probes: u64,
    health_failures: u64,
}

type Answers = BTreeMap<String, u64>;

fn main() -> Result<()> {
    let args = Args::parse();
    // Thousands of sockets on this side too.
    splatd_server::transport::raise_descriptor_limit();
    let binary = sibling_binary().map_err(anyhow::Error::msg)?;
    let flags: Vec<&str> = args.serve.split_whitespace().collect();
    let server = ServerProcess::launch(&Options {
        log_level: "warn",
        ..Options::new(binary, &flags)
    })
    .map_err(anyhow::Error::msg)?;
    let pid = server.pid();
    println!("splatd serve {}", args.serve);
    println!("load average at start: {}", loadavg());

    let seen = Arc::new(Mutex::new(Seen::default()));
    let stop = Arc::new(AtomicBool::new(false));
    let sampler = {
        let (seen, stop) = (seen.clone(), stop.clone());
        std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                let rss = proc_status_kib(pid, "VmRSS:").unwrap_or(0);
                let fds = std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count());
                let mut s = seen.lock().unwrap();
                s.rss_kib_max = s.rss_kib_max.max(rss);
                s.fds_max = s.fds_max.max(fds);
                drop(s);
                std::thread::sleep(Duration::from_millis(20));
            }
        })
    };

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let result = runtime.block_on(async {
        let url = server.url.clone();
        let prober = tokio::spawn(probe_health(url.clone(), seen.clone(), stop.clone()));
        let http = reqwest::Client::new();
        let state_bytes = setup(&http, &url).await?;
        println!(
            "frame {FRAME}: {WIDTH}x{HEIGHT}, {:.0} MB of state; server RSS {} MB after setup",
            state_bytes as f64 / 1e6,
            proc_status_kib(pid, "VmRSS:").unwrap_or(0) / 1024
        );
        let n = args.concurrent;
        report("images", &seen, images(&http, &url, n)).await?;
        report("zstd bombs", &seen, bombs(&http, &url, n)).await?;
        report(
            "slow readers",
            &seen,
            slow_readers(&server.addr, n, Duration::from_secs(args.slow_secs)),
        )
        .await?;
        report(
            "silent sockets",
            &seen,
            silent(
                &server.addr,
                args.many,
                Duration::from_secs(args.silent_secs),
            ),
        )
        .await?;
        report("active clients", &seen, active(&url, args.many)).await?;
        stop.store(true, Ordering::Relaxed);
        prober.await?;
        anyhow::Ok(())
    });
    stop.store(true, Ordering::Relaxed);
    let _ = sampler.join();
    println!(
        "server peak RSS over the whole run (VmHWM): {} MB",
        proc_status_kib(pid, "VmHWM:").unwrap_or(0) / 1024
    );
    println!("load average at the end: {}", loadavg());
    result
}

/// Runs one phase and prints what it got and what the server went through meanwhile.
async fn report(
    name: &str,
    seen: &Mutex<Seen>,
    phase: impl std::future::Future<Output = Result<Answers>>,
) -> Result<()> {
    *seen.lock().unwrap() = Seen::default();
    let started = Instant::now();
    let answers = phase.await.with_context(|| name.to_owned())?;
    let s = seen.lock().unwrap().clone();
    println!(
        "{name}: {answers:?} in {:.1} s; server RSS peak {} MB, open descriptors peak {}; \
         /healthz max {:.1} ms over {} probes, {} failed",
        started.elapsed().as_secs_f64(),
        s.rss_kib_max / 1024,
        s.fds_max,
        s.health_max.as_secs_f64() * 1e3,
        s.health_probes,
        s.health_failures
    );
    Ok(())
}

/// A dashboard: `/healthz` every 50 ms on a keep-alive connection, each probe allowed 10 s.
async fn probe_health(url: String, seen: Arc<Mutex<Seen>>, stop: Arc<AtomicBool>) {
    let http = reqwest::Client::builder()
        .timeout(Duration::from_secs(10))
        .build()
        .expect("a client");
    let target = format!("{url}/healthz");
    while !stop.load(Ordering::Relaxed) {
        let t = Instant::now();
        let ok = match http.get(&target).send().await {
            Ok(r) => r.status().is_success() && r.bytes().await.is_ok(),
            Err(_) => false,
        };
        let took = t.elapsed();
        {
            let mut s = seen.lock().unwrap();
            s.health_probes += 1;
            s.health_max = s.health_max.max(took);
            s.health_failures += u64::from(!ok);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Creates the frame and posts 2 Mi heavy-tailed samples into it; the frame's state size.
async fn setup(http: &reqwest::Client, url: &str) -> Result<u64> {
    let client = splatd_proto::Client::new(url)?;
    let info = client
        .create_frame(&CreateFrame::new(FRAME, WIDTH, HEIGHT))
        .await?;
    let mut rng = SplitMix64::new(12);
    for seq in 0..32u64 {
        let records = (0..64 * 1024)
            .map(|_| {
                let x = (rng.next_u64() % u64::from(WIDTH)) as u32;
                let y = (rng.next_u64() % u64::from(HEIGHT)) as u32;
                let z = (rng.next_f64().powf(-1.0 / 1.5) - 1.0) as f32;
                Record::new(x, y, [z * 0.8, z, z * 0.6])
            })
            .collect();
        let body = Batch::new(FRAME, 1, seq, records)?.encode();
        let r = post_batch(http, url, body, None).await?;
        if r.status() != 200 {
            bail!("setup batch {seq}: HTTP {}", r.status());
        }
    }
    Ok(info.memory_bytes)
}

async fn post_batch(
    http: &reqwest::Client,
    url: &str,
    body: Vec<u8>,
    encoding: Option<&str>,
) -> reqwest::Result<reqwest::Response> {
    let mut request = http
        .post(format!("{url}/v1/frames/{FRAME}/samples"))
        .header("content-type", BATCH_CONTENT_TYPE);
    if let Some(e) = encoding {
        request = request.header("content-encoding", e);
    }
    request.body(body).send().await
}

fn count(answers: &Mutex<Answers>, key: String) {
    *answers.lock().unwrap().entry(key).or_default() += 1;
}

fn outcome(result: &reqwest::Result<reqwest::StatusCode>) -> String {
    match result {
        Ok(s) => s.as_u16().to_string(),
        Err(e) if e.is_connect() => "connect error".into(),
        Err(e) if e.is_timeout() => "timeout".into(),
        Err(_) => "connection error".into(),
    }
}

/// Concurrent `image.exr`s, read whole: even ones share a query, odd ones each have their own.
async fn images(http: &reqwest::Client, url: &str, n: usize) -> Result<Answers> {
    let answers = Arc::new(Mutex::new(Answers::new()));
    let mut tasks = Vec::new();
    for i in 0..n {
        let (http, answers) = (http.clone(), answers.clone());
        let target = if i % 2 == 0 {
            format!("{url}/v1/frames/{FRAME}/image.exr")
        } else {
            format!(
                "{url}/v1/frames/{FRAME}/image.exr?kappa={}",
                4.0 + i as f64 / 100.0
            )
        };
        tasks.push(tokio::spawn(async move {
            let result = async {
                let r = http.get(&target).send().await?;
                let status = r.status();
                r.bytes().await?;
                Ok(status)
            }
            .await;
            count(&answers, outcome(&result));
        }));
    }
    for t in tasks {
        t.await?;
    }
    Ok(Arc::try_unwrap(answers).unwrap().into_inner().unwrap())
}

/// Concurrent zstd bombs, each a valid maximum-size batch of its own worker.
async fn bombs(http: &reqwest::Client, url: &str, n: usize) -> Result<Answers> {
    let max_records = splatd_proto::batch::DEFAULT_MAX_RECORDS;
    let bodies: Vec<Vec<u8>> = (0..n)
        .map(|i| splatd_scenes::hostile::zstd_bomb(FRAME, 1000 + i as u64, 0, max_records))
        .collect();
    println!(
        "  (each bomb: {} bytes on the wire, {} bytes inflated)",
        bodies[0].len(),
        Batch {
            frame: FRAME.into(),
            worker: 0,
            seq: 0,
            records: Vec::new()
        }
        .encoded_len()
            + 20 * max_records
    );
    let answers = Arc::new(Mutex::new(Answers::new()));
    let mut tasks = Vec::new();
    for body in bodies {
        let (http, answers, url) = (http.clone(), answers.clone(), url.to_owned());
        tasks.push(tokio::spawn(async move {
            let result = async {
                let r = post_batch(&http, &url, body, Some("zstd")).await?;
                let status = r.status();
                r.bytes().await?;
                Ok(status)
            }
            .await;
            count(&answers, outcome(&result));
        }));
    }
    for t in tasks {
        t.await?;
    }
    Ok(Arc::try_unwrap(answers).unwrap().into_inner().unwrap())
}

/// Clients that ask for `image.exr` with a tiny receive window and do not read for `hold`;
/// then they read what they can: a response cut off by the server, or whole.
async fn slow_readers(addr: &str, n: usize, hold: Duration) -> Result<Answers> {
    let addr: std::net::SocketAddr = addr.parse()?;
    let mut sockets = Vec::new();
    for _ in 0..n {
        let socket = tokio::net::TcpSocket::new_v4()?;
        socket.set_recv_buffer_size(4096)?;
        let mut s = socket.connect(addr).await?;
        s.write_all(
            format!("GET /v1/frames/{FRAME}/image.exr HTTP/1.1\r\nhost: x\r\n\r\n").as_bytes(),
        )
        .await?;
        sockets.push(s);
    }
    tokio::time::sleep(hold).await;
    let mut answers = Answers::new();
    for mut s in sockets {
        let mut got = Vec::new();
        let read = tokio::time::timeout(Duration::from_secs(60), s.read_to_end(&mut got)).await;
        let declared = content_length(&got);
        let key = match (read, declared) {
            (Err(_), _) => "still open after 60 s".to_owned(),
            (Ok(_), Some((head, len))) if got.len() - head < len => {
                format!("{} cut off", status_of(&got))
            }
            (Ok(_), Some(_)) => format!("{} whole", status_of(&got)),
            (Ok(_), None) => "closed before a response head".to_owned(),
        };
        *answers.entry(key).or_default() += 1;
    }
    Ok(answers)
}

fn status_of(response: &[u8]) -> String {
    String::from_utf8_lossy(&response[..response.len().min(12)])
        .split(' ')
        .nth(1)
        .unwrap_or("?")
        .to_owned()
}

/// The head's length and the declared body length of a raw response.
fn content_length(response: &[u8]) -> Option<(usize, usize)> {
    let end = response.windows(4).position(|w| w == b"\r\n\r\n")? + 4;
    let head = String::from_utf8_lossy(&response[..end]).to_ascii_lowercase();
    let len = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))?
        .trim()
        .parse()
        .ok()?;
    Some((end, len))
}

/// Sockets that connect and say nothing for `hold`; then: which did the server close?
async fn silent(addr: &str, n: usize, hold: Duration) -> Result<Answers> {
    let mut sockets = Vec::new();
    let mut answers = Answers::new();
    for _ in 0..n {
        match tokio::net::TcpStream::connect(addr).await {
            Ok(s) => sockets.push(s),
            Err(_) => *answers.entry("connect error".into()).or_default() += 1,
        }
    }
    tokio::time::sleep(hold).await;
    for mut s in sockets {
        let mut byte = [0u8; 1];
        let key = match tokio::time::timeout(Duration::from_millis(1), s.read(&mut byte)).await {
            Ok(Ok(0)) | Ok(Err(_)) => "closed by the server",
            Ok(Ok(_)) => "answered",
            Err(_) => "still open",
        };
        *answers.entry(key.into()).or_default() += 1;
    }
    Ok(answers)
}

/// `n` clients, each with its own connection, posting 5 batches of 64 samples; connection
/// errors and 503 are retried (up to 10 attempts, 100 ms apart). Checks that the frame gained
/// exactly the samples acknowledged.
async fn active(url: &str, n: usize) -> Result<Answers> {
    let client = splatd_proto::Client::new(url)?;
    let before = client.frame_counts(FRAME).await?.samples;
    let answers = Arc::new(Mutex::new(Answers::new()));
    // Batches answered 200 (applied now, or recognised as applied by an earlier attempt whose
    // answer was lost): each is in the frame exactly once.
    let acknowledged = Arc::new(Mutex::new(0u64));
    let mut tasks = Vec::new();
    for i in 0..n {
        let (answers, acknowledged, url) = (answers.clone(), acknowledged.clone(), url.to_owned());
        tasks.push(tokio::spawn(async move {
            let http = reqwest::Client::builder()
                .timeout(Duration::from_secs(60))
                .pool_max_idle_per_host(1)
                .build()
                .expect("a client");
            for seq in 0..5u64 {
                let records = (0..64)
                    .map(|k| Record::new((i as u32 * 7 + k) % WIDTH, seq as u32, [0.5; 3]))
                    .collect();
                let body = Batch::new(FRAME, 100_000 + i as u64, seq, records)
                    .expect("valid")
                    .encode();
                for attempt in 0..10 {
                    let result = async {
                        let r = post_batch(&http, &url, body.clone(), None).await?;
                        let status = r.status();
                        r.bytes().await?;
                        Ok((status, ()))
                    }
                    .await;
                    let retry = match &result {
                        Ok((status, _)) if status.is_success() => {
                            *acknowledged.lock().unwrap() += 1;
                            false
                        }
                        Ok((status, _)) => status.as_u16() == 503,
                        Err(_) => true,
                    };
                    let key = outcome(&result.map(|(s, _)| s));
                    count(
                        &answers,
                        if attempt == 0 {
                            key
                        } else {
                            format!("{key} (retry)")
                        },
                    );
                    if !retry {
                        break;
                    }
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }));
    }
    for t in tasks {
        t.await?;
    }
    let after = client.frame_counts(FRAME).await?.samples;
    let acked = 64 * *acknowledged.lock().unwrap();
    println!(
        "  (frame gained {} samples; {} were acknowledged, {} posted)",
        after - before,
        acked,
        64 * 5 * n
    );
    if after - before != acked {
        bail!(
            "the frame gained {} samples but {acked} were acknowledged",
            after - before
        );
    }
    Ok(Arc::try_unwrap(answers).unwrap().into_inner().unwrap())
}

fn proc_status_kib(pid: u32, field: &str) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix(field))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}
