//! Passes end to end against `oiiotool`: the mean of N rendered passes, by posting them to a
//! real `splatd serve` and fetching the resolved `image.exr`, against averaging the same files
//! with OpenImageIO's `oiiotool`, measured in alternating pairs in one run.
//!
//! ```sh
//! bash tests/setup/oiio.sh      # oiiotool
//! bash tests/setup/oidn.sh      # optional: OIDN, for the denoise line (prints the library)
//! cargo build --release -p splatd --bin passbench --bin splatd
//! target/release/passbench [--passes 16] [--pairs 3] [--oidn-lib PATH]
//! ```
//!
//! It writes `--passes` 1920x1080 RGB 32-bit float ZIP-compressed EXRs (a smooth image times
//! exponential noise per pixel, with rare fireflies a thousand times brighter), starts
//! `splatd serve` (the binary beside this one) and times, in pairs whose order alternates:
//!
//! * splatd: `splatd post --create --frame F pass_*.exr` (the CLI, as an operator runs it) to a
//!   fresh frame, then `GET /v1/frames/F/image.exr` written to a file as it arrives (resolve +
//!   EXR encode + transfer);
//! * oiiotool: `oiiotool p0 p1 --add p2 --add ... --mulc 1/N -o avg.exr`.
//!
//! It prints each pair, the median ratio splatd / oiiotool beside its goal (<= 1.0), splatd's
//! split (post vs resolve + fetch), and CPU seconds of both sides (the server's from
//! `/proc/PID/stat`, the children's from this process's `cutime + cstime`), which a loaded
//! machine disturbs less than the wall clock. With `--oidn-lib` (or `SPLATD_OIDN_LIB`) the
//! server can denoise, and it also times `image.exr?denoise=oidn` of fresh frames against the
//! seconds OIDN itself spent on them (the server's `splatd_denoise_seconds` histogram): the
//! cost beyond OIDN, over OIDN's, beside its goal (<= 0.2).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Parser;
use splatd_harness::{sibling_binary, Options, ServerProcess};
use splatd_scenes::synth::SplitMix64;

#[path = "common/load.rs"]
mod load;

#[derive(Parser)]
#[command(about = "Posting passes and fetching the mean, against oiiotool averaging them")]
struct Args {
    /// Passes.
    #[arg(long, default_value_t = 16)]
    passes: usize,
    /// Frame width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Frame height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// Timed pairs (splatd, oiiotool); the median ratio is the figure.
    #[arg(long, default_value_t = 3)]
    pairs: usize,
    /// Folder for the passes and outputs (default: a fresh one under the temporary folder,
    /// removed at the end).
    #[arg(long)]
    dir: Option<PathBuf>,
    /// `libOpenImageDenoise.so.2` for the denoise line (`bash tests/setup/oidn.sh` prints it).
    #[arg(long, env = "SPLATD_OIDN_LIB")]
    oidn_lib: Option<PathBuf>,
    /// Denoised fetches timed (each of a fresh frame).
    #[arg(long, default_value_t = 2)]
    denoise_runs: usize,
    /// Skip the pairs (only the denoise line).
    #[arg(long)]
    no_pairs: bool,
}

/// splatd's end to end time / oiiotool's.
const GOAL: f64 = 1.0;
/// A denoised final's seconds beyond OIDN's own / OIDN's.
const DENOISE_GOAL: f64 = 0.2;

fn uptime() -> String {
    format!("load {}", load::load_averages())
}

/// Clock ticks per second (`getconf CLK_TCK`; 100 if that fails).
fn clock_tick() -> f64 {
    Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(100.0)
}

/// Fields after the comm of `/proc/{who}/stat`; index 0 is the state (field 3 of proc(5)).
fn stat_fields(who: &str) -> Result<Vec<u64>> {
    let stat = std::fs::read_to_string(format!("/proc/{who}/stat"))?;
    let after = &stat[stat.rfind(')').context("no comm in /proc stat")? + 2..];
    Ok(after
        .split_whitespace()
        .map(|f| f.parse().unwrap_or(0))
        .collect())
}

/// utime + stime of process `pid`, in seconds.
fn cpu_of(pid: u32, tick: f64) -> Result<f64> {
    let f = stat_fields(&pid.to_string())?;
    Ok((f[11] + f[12]) as f64 / tick)
}

/// cutime + cstime of this process (its reaped children), in seconds.
fn children_cpu(tick: f64) -> Result<f64> {
    let f = stat_fields("self")?;
    Ok((f[13] + f[14]) as f64 / tick)
}

/// A smooth image times exponential noise, with rare fireflies.
fn make_pass(w: usize, h: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut rng = SplitMix64::new(seed);
    (0..w * h)
        .map(|p| {
            let (x, y) = ((p % w) as f32 / w as f32, (p / w) as f32 / h as f32);
            let base = [
                0.2 + 0.6 * x,
                0.3 + 0.4 * (6.0 * x * y).sin().abs(),
                0.1 + 0.5 * y,
            ];
            let noise = -(1.0 - rng.next_f64()).ln() as f32;
            let firefly = if rng.next_f64() < 2e-5 { 1000.0 } else { 1.0 };
            base.map(|c| c * noise * firefly)
        })
        .collect()
}

fn write_passes(args: &Args, dir: &Path) -> Result<Vec<PathBuf>> {
    let (w, h) = (args.width as usize, args.height as usize);
    let mut files = Vec::new();
    let mut bytes = 0;
    let t = Instant::now();
    for i in 0..args.passes {
        let pass = make_pass(w, h, 1000 + i as u64);
        let exr = load::encode_pass(w, h, &pass, exr::compression::Compression::ZIP16)?;
        bytes += exr.len();
        let path = dir.join(format!("pass_{i:02}.exr"));
        std::fs::write(&path, exr)?;
        files.push(path);
    }
    eprintln!(
        "wrote {} passes of {w}x{h} (RGB f32, ZIP, {:.0} MB) in {:.1} s",
        args.passes,
        bytes as f64 / 1e6,
        t.elapsed().as_secs_f64()
    );
    Ok(files)
}

fn run(cmd: &mut Command) -> Result<()> {
    let out = cmd
        .output()
        .with_context(|| format!("starting {:?}", cmd.get_program()))?;
    if !out.status.success() {
        bail!(
            "{:?} failed ({}): {}{}",
            cmd.get_program(),
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(())
}

/// One timed splatd run: (post s, resolve + fetch s, server CPU s, CLI CPU s, image bytes).
struct SplatdRun {
    post: f64,
    fetch: f64,
    server_cpu: f64,
    cli_cpu: f64,
    bytes: usize,
}

struct Bench<'a> {
    splatd: PathBuf,
    server: &'a ServerProcess,
    http: reqwest::Client,
    runtime: tokio::runtime::Runtime,
    tick: f64,
    files: &'a [PathBuf],
}

impl Bench<'_> {
    fn post(&self, frame: &str) -> Result<()> {
        run(Command::new(&self.splatd)
            .args([
                "post",
                "--url",
                &self.server.url,
                "--frame",
                frame,
                "--create",
            ])
            .args(self.files))
    }

    /// The response to `method path`, an error unless it succeeded.
    async fn send(&self, method: reqwest::Method, path: &str) -> Result<reqwest::Response> {
        let r = self
            .http
            .request(method.clone(), format!("{}{path}", self.server.url))
            .send()
            .await?;
        if !r.status().is_success() {
            bail!("{method} {path}: HTTP {}: {}", r.status(), r.text().await?);
        }
        Ok(r)
    }

    /// The response to `GET path`, an error unless it succeeded.
    async fn fetch(&self, path: &str) -> Result<reqwest::Response> {
        self.send(reqwest::Method::GET, path).await
    }

    fn get(&self, path: &str) -> Result<Vec<u8>> {
        self.runtime
            .block_on(async { Ok(self.fetch(path).await?.bytes().await?.to_vec()) })
    }

    /// `GET path` written to `out` as its chunks arrive, as `curl -o` does (the whole body
    /// collected in memory and copied first took 0.4 s more than the resolve and the encoding on
    /// a VM whose fresh memory faults in slowly); returns its bytes.
    fn download(&self, path: &str, out: &Path) -> Result<usize> {
        use std::io::Write;
        self.runtime.block_on(async {
            let mut r = self.fetch(path).await?;
            let mut file = std::fs::File::create(out)?;
            let mut bytes = 0;
            while let Some(chunk) = r.chunk().await? {
                file.write_all(&chunk)?;
                bytes += chunk.len();
            }
            Ok(bytes)
        })
    }

    fn delete(&self, frame: &str) -> Result<()> {
        self.runtime.block_on(async {
            self.send(reqwest::Method::DELETE, &format!("/v1/frames/{frame}"))
                .await?;
            Ok(())
        })
    }

    fn splatd_run(&self, frame: &str, out: &Path) -> Result<SplatdRun> {
        let pid = self.server.pid();
        let (s0, c0) = (cpu_of(pid, self.tick)?, children_cpu(self.tick)?);
        let t0 = Instant::now();
        self.post(frame)?;
        let t1 = Instant::now();
        let bytes = self.download(&format!("/v1/frames/{frame}/image.exr"), out)?;
        let t2 = Instant::now();
        let run = SplatdRun {
            post: (t1 - t0).as_secs_f64(),
            fetch: (t2 - t1).as_secs_f64(),
            server_cpu: cpu_of(pid, self.tick)? - s0,
            cli_cpu: children_cpu(self.tick)? - c0,
            bytes,
        };
        self.delete(frame)?;
        Ok(run)
    }

    /// (seconds, CPU seconds) of oiiotool averaging the passes into `out`.
    fn oiiotool_run(&self, out: &Path) -> Result<(f64, f64)> {
        let mut cmd = Command::new("oiiotool");
        let (first, rest) = self.files.split_first().context("no passes")?;
        cmd.arg(first);
        // The first --add sums p0 and p1; each later one adds the next file to the sum.
        for f in rest {
            cmd.arg(f).arg("--add");
        }
        cmd.arg("--mulc")
            .arg(format!("{}", 1.0 / self.files.len() as f64))
            .arg("-o")
            .arg(out);
        let c0 = children_cpu(self.tick)?;
        let t = Instant::now();
        run(&mut cmd)?;
        Ok((t.elapsed().as_secs_f64(), children_cpu(self.tick)? - c0))
    }

    /// `splatd_denoise_seconds` sum from `/metrics`.
    fn denoise_seconds(&self) -> Result<f64> {
        let text = String::from_utf8(self.get("/metrics")?)?;
        Ok(text
            .lines()
            .filter(|l| l.starts_with("splatd_denoise_seconds_sum"))
            .filter_map(|l| l.split_whitespace().last()?.parse::<f64>().ok())
            .sum())
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

fn main() -> Result<()> {
    let args = Args::parse();
    if args.passes < 2 {
        bail!("--passes must be at least 2");
    }
    let tick = clock_tick();
    let (dir, remove) = match &args.dir {
        Some(d) => (d.clone(), false),
        None => (
            std::env::temp_dir().join(format!("passbench-{}", std::process::id())),
            true,
        ),
    };
    std::fs::create_dir_all(&dir)?;
    let result = bench(&args, &dir, tick);
    if remove {
        let _ = std::fs::remove_dir_all(&dir);
    }
    result
}

fn bench(args: &Args, dir: &Path, tick: f64) -> Result<()> {
    println!("passbench: {} at start", uptime());
    let files = write_passes(args, dir)?;
    let splatd = sibling_binary().map_err(anyhow::Error::msg)?;
    let lib = args.oidn_lib.as_ref().map(|p| p.display().to_string());
    let mut extra: Vec<&str> = Vec::new();
    if let Some(lib) = &lib {
        extra.extend(["--oidn-lib", lib.as_str()]);
    }
    let server = ServerProcess::launch(&Options {
        log_level: "warn",
        ..Options::new(&splatd, &extra)
    })
    .map_err(anyhow::Error::msg)?;
    let bench = Bench {
        splatd,
        server: &server,
        // No idle connections: between requests the runtime does not run, so a connection the
        // server closed meanwhile would only be noticed by the next request, which would fail.
        http: reqwest::Client::builder()
            .pool_max_idle_per_host(0)
            .build()?,
        runtime: tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?,
        tick,
        files: &files,
    };
    // A warm-up of each side (page cache, the server's first frame), not counted.
    bench.splatd_run("warmup", &dir.join("warmup.exr"))?;
    bench.oiiotool_run(&dir.join("warmup_oiio.exr"))?;

    let mut goals = Vec::new();
    if !args.no_pairs {
        let mut ratios = Vec::new();
        let (mut posts, mut fetches, mut cpu_ratios) = (Vec::new(), Vec::new(), Vec::new());
        for pair in 0..args.pairs {
            let mut a = None;
            let mut b = None;
            // Alternate the order within pairs: A B, B A, A B ...
            for side in if pair % 2 == 0 { [0, 1] } else { [1, 0] } {
                if side == 0 {
                    a = Some(bench.splatd_run(
                        &format!("pair{pair}"),
                        &dir.join(format!("splatd_{pair}.exr")),
                    )?);
                } else {
                    b = Some(bench.oiiotool_run(&dir.join(format!("oiio_{pair}.exr")))?);
                }
            }
            let (a, (b, b_cpu)) = (a.expect("ran"), b.expect("ran"));
            let total = a.post + a.fetch;
            let oiio_bytes = std::fs::metadata(dir.join(format!("oiio_{pair}.exr")))?.len();
            println!(
                "pair {pair}: splatd {total:.2} s (post {:.2} s + resolve & fetch {:.2} s; CPU: \
                 server {:.2} s, post CLI {:.2} s; image {:.1} MB) | oiiotool {b:.2} s (CPU \
                 {b_cpu:.2} s; {:.1} MB) | ratio {:.2} | {}",
                a.post,
                a.fetch,
                a.server_cpu,
                a.cli_cpu,
                a.bytes as f64 / 1e6,
                oiio_bytes as f64 / 1e6,
                total / b,
                uptime()
            );
            ratios.push(total / b);
            cpu_ratios.push((a.server_cpu + a.cli_cpu) / b_cpu);
            posts.push(a.post);
            fetches.push(a.fetch);
        }
        let ratio = median(ratios);
        println!(
            "splatd split (medians): post {:.2} s, resolve + fetch {:.2} s",
            median(posts),
            median(fetches)
        );
        println!(
            "CPU seconds, splatd (server + post CLI) / oiiotool: median {:.2} (no goal; what \
             the load disturbs less)",
            median(cpu_ratios)
        );
        goals.push(format!(
            "{} passes {}x{} posted + image.exr fetched / oiiotool --add ... --mulc: median \
             ratio of {} pairs {ratio:.2} (goal <= {GOAL}) {}",
            args.passes,
            args.width,
            args.height,
            args.pairs,
            if ratio <= GOAL { "met" } else { "MISSED" }
        ));
    }

    if lib.is_some() {
        let mut ratios = Vec::new();
        for run in 0..args.denoise_runs {
            let frame = format!("denoise{run}");
            bench.post(&frame)?;
            let before = bench.denoise_seconds()?;
            let t = Instant::now();
            let bytes = bench.download(
                &format!("/v1/frames/{frame}/image.exr?denoise=oidn"),
                &dir.join(format!("denoised_{run}.exr")),
            )?;
            let total = t.elapsed().as_secs_f64();
            let oidn = bench.denoise_seconds()? - before;
            let t = Instant::now();
            bench.download(
                &format!("/v1/frames/{frame}/image.exr"),
                &dir.join(format!("plain_{run}.exr")),
            )?;
            let plain = t.elapsed().as_secs_f64();
            bench.delete(&frame)?;
            if oidn <= 0.0 {
                bail!("the server reported no denoise seconds: was OIDN loaded?");
            }
            let beyond = total - oidn;
            println!(
                "denoise run {run}: image.exr?denoise=oidn {total:.2} s, of which OIDN {oidn:.2} \
                 s, beyond OIDN {beyond:.2} s ({:.2} of OIDN's; {:.1} MB); the plain image.exr \
                 of the same frame after it {plain:.2} s | {}",
                beyond / oidn,
                bytes as f64 / 1e6,
                uptime()
            );
            ratios.push(beyond / oidn);
        }
        if !ratios.is_empty() {
            let r = median(ratios);
            goals.push(format!(
                "denoised final's cost beyond OIDN / OIDN's: median ratio of {} runs {r:.2} \
                 (goal <= {DENOISE_GOAL}) {}",
                args.denoise_runs,
                if r <= DENOISE_GOAL { "met" } else { "MISSED" }
            ));
        }
    } else {
        println!("(no --oidn-lib: no denoise line; bash tests/setup/oidn.sh prints the library)");
    }
    drop(server);
    println!("\ngoals ({} at the end):", uptime());
    for g in goals {
        println!("  {g}");
    }
    Ok(())
}
