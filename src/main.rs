//! The `splatd` command line: the server, the offline tools and the demo.

mod demo;

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};

use splatd_estimator::{CascadeLayout, FrameState};
use splatd_formats::exr::{cascade_layers, encode_exr, Provenance};
use splatd_formats::state::SparseState;
use splatd_proto::batchfile::BatchReader;
use splatd_proto::{Applied, DecodeLimits};
use splatd_server::frame::core_resolve_params;
use splatd_server::frame::dedup::Seen;
use splatd_server::server::{shutdown_signal, Server};

#[derive(Parser)]
#[command(
    name = "splatd",
    version,
    about = "Firefly-reweighting sample accumulation service"
)]
struct Cli {
    /// Log filter (tracing's `EnvFilter` syntax, e.g. `info` or `splatd=debug`); `RUST_LOG`
    /// overrides it.
    #[arg(long, global = true, default_value = "info")]
    log_level: String,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Path-traces the built-in scene with render workers that stream samples over HTTP to an
    /// embedded server; writes reweighted.exr, mean.exr and side_by_side.png.
    Demo(DemoArgs),
    /// Runs the HTTP server.
    Serve(splatd_server::Config),
    /// Resolves batch files or state files into an EXR, offline.
    Resolve(ResolveArgs),
    /// Posts rendered passes (OpenEXR, one sample per pixel each) to a server.
    Post(PostArgs),
    /// Adds state files of one frame together into one state file, offline.
    Merge {
        /// State files (`GET /v1/frames/{id}/state` bodies).
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        /// Output state file.
        #[arg(short, long)]
        output: PathBuf,
    },
}

#[derive(Args)]
struct DemoArgs {
    /// Output folder.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    spp: u64,
    /// Concurrent render workers.
    #[arg(long, default_value_t = 2)]
    workers: usize,
    /// Address of the embedded server (port 0 picks a free port).
    #[arg(long, default_value = "127.0.0.1:0")]
    addr: String,
    /// Keep serving the live page after the demo, until Ctrl-C.
    #[arg(long)]
    serve: bool,
    /// Steer the workers by the server's need map: a quarter of the samples uniformly, the rest
    /// on the tiles that need them most (same total).
    #[arg(long)]
    guided: bool,
}

#[derive(Args)]
struct PostArgs {
    /// Server URL.
    #[arg(long, default_value = "http://127.0.0.1:7878")]
    url: String,
    /// Frame id.
    #[arg(long)]
    frame: String,
    /// Create the frame (default parameters, the size of the first pass) if it does not exist,
    /// with `PUT /v1/frames/{id}`: a `write` token is enough.
    #[arg(long)]
    create: bool,
    /// The layer holding the beauty (`ViewLayer.Combined`, `beauty` ...; an error lists a
    /// file's layers). Without it the server finds the beauty in the order PROTOCOL.md gives.
    #[arg(long)]
    layer: Option<String>,
    /// With `--create`: an AOV the frame keeps beside the beauty, as `LAYER=CHANNEL,CHANNEL...`
    /// (`ViewLayer.DiffCol=R,G,B`, `ViewLayer.Depth=Z`); repeat for several. Every pass must
    /// then carry all of them or none (PROTOCOL.md, "AOVs").
    #[arg(long = "aov", value_parser = parse_aov)]
    aovs: Vec<splatd_proto::api::AovSpec>,
    /// Worker id the passes are sent under. Each pass is numbered by a digest of its file, so
    /// posting a file again (a rerun, or from another machine) adds nothing twice, and new files
    /// are never mistaken for old ones; a different `--worker` makes the same files count again.
    #[arg(long)]
    worker: Option<u64>,
    /// Bearer token (also read from SPLATD_TOKEN).
    #[arg(long, env = "SPLATD_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Pass files, one sample per pixel each.
    #[arg(required = true)]
    passes: Vec<PathBuf>,
}

#[derive(Args)]
struct ResolveArgs {
    /// Batch files (length-prefixed batches) or state files; kinds cannot be mixed.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Output EXR.
    #[arg(short, long)]
    output: PathBuf,
    /// Frame width (batch files only; a state knows its size).
    #[arg(long)]
    width: Option<u32>,
    /// Frame height (batch files only).
    #[arg(long)]
    height: Option<u32>,
    /// Cascade base (batch files only).
    #[arg(long, default_value_t = splatd_proto::api::DEFAULT_CASCADE_BASE)]
    base: f64,
    /// Number of cascades (batch files only).
    #[arg(long, default_value_t = splatd_proto::api::DEFAULT_CASCADE_COUNT)]
    cascades: u32,
    /// Scale c0 of the lowest cascade; cascade j has c0 * base^j (batch files only).
    #[arg(long, default_value_t = splatd_proto::api::DEFAULT_LOWEST_SCALE)]
    lowest_scale: f64,
    /// Resolve variant: spread (the default), paper, shader or off.
    #[arg(long, default_value = splatd_proto::api::DEFAULT_VARIANT.as_str())]
    variant: splatd_proto::Variant,
    /// Support (samples, beyond kappa-min) at which a brightness band gets full weight; bands
    /// with less are down-weighted.
    #[arg(long, default_value_t = splatd_proto::api::DEFAULT_KAPPA)]
    kappa: f64,
    /// Support (samples) subtracted from a band's support count before dividing by kappa.
    #[arg(long, default_value_t = splatd_proto::api::DEFAULT_KAPPA_MIN)]
    kappa_min: f64,
    /// Growth of kappa with the pixel's sample count N: kappa * N^exponent, in [0, 1).
    #[arg(long, default_value_t = splatd_proto::api::DEFAULT_KAPPA_EXPONENT)]
    kappa_exponent: f64,
    /// Also write one raw layer per cascade.
    #[arg(long)]
    cascade_layers: bool,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    // The demo's progress bar is its output; the embedded server's routine logs would clutter it.
    let level = match (&cli.command, cli.log_level.as_str()) {
        (Command::Demo(_), "info") => "warn",
        (_, level) => level,
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .or_else(|_| tracing_subscriber::EnvFilter::try_new(level))
        .context("invalid --log-level")?;
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(|| LogSink)
        // Colour codes only for a person at a terminal, not in a log file or a pipe.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .log_internal_errors(false)
        .init();
    match cli.command {
        Command::Demo(a) => crate::demo::run(&crate::demo::DemoOptions {
            out: a.out,
            width: a.width,
            height: a.height,
            spp: a.spp,
            workers: a.workers,
            addr: a.addr,
            keep_serving: a.serve,
            guided: a.guided,
        })
        .map(|_| ()),
        Command::Serve(args) => run_server(args),
        Command::Resolve(args) => resolve(args),
        Command::Merge { inputs, output } => merge(&inputs, &output),
        Command::Post(args) => post(args),
    }
}

/// Where log lines go: stderr, but a line that cannot be written (stderr a closed pipe, a full
/// disk, a file past `ulimit -f`) is dropped and counted (`splatd_log_lines_dropped_total`),
/// never an error. tracing-subscriber reports a failed write with `eprintln!`, which panics when
/// stderr is broken: the request, snapshot or shutdown that logged would die with it, and did
/// (creates and deletes applied but never answered, the snapshot task gone for good).
struct LogSink;

impl std::io::Write for LogSink {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if std::io::stderr().write_all(buf).is_err() {
            metrics::counter!(splatd_server::meters::LOG_LINES_DROPPED).increment(1);
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        let _ = std::io::stderr().flush();
        Ok(())
    }
}

fn run_server(config: splatd_server::Config) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async move {
        let server = Server::bind(config).await?;
        // Handlers first: a SIGTERM right after the address is announced must stop us gently.
        let shutdown = shutdown_signal();
        // Scripts and tests wait for this line to learn the port. Nobody reading stdout is no
        // reason not to serve (println! would panic on a closed stdout).
        {
            use std::io::Write;
            let mut out = std::io::stdout().lock();
            let _ = writeln!(out, "splatd listening on http://{}", server.local_addr());
            let _ = out.flush();
        }
        server.run(shutdown).await
    })
}

fn post(args: PostArgs) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async move {
        let mut client = splatd_proto::Client::new(&args.url)?;
        if let Some(token) = &args.token {
            client = client.with_token(token.clone());
        }
        let worker = args.worker.unwrap_or(POST_WORKER);
        if !args.create && !args.aovs.is_empty() {
            bail!("--aov declares the AOVs of a frame being created: it needs --create");
        }
        if args.create {
            let first = std::fs::read(&args.passes[0])
                .with_context(|| format!("reading {}", args.passes[0].display()))?;
            let pass = splatd_formats::passes::decode_pass_with(
                &first,
                args.layer.as_deref(),
                splatd_formats::passes::MAX_PASS_PIXELS,
            )
            .with_context(|| format!("decoding {}", args.passes[0].display()))?;
            let request = splatd_proto::CreateFrame {
                aovs: args.aovs.clone(),
                ..splatd_proto::CreateFrame::new(&args.frame, pass.width, pass.height)
            };
            match client.create_or_get(&request).await {
                Ok(info) if info.batches > 0 => println!(
                    "frame {:?} exists with {} samples; adding to it",
                    args.frame, info.samples
                ),
                Ok(_) => {}
                // Made by someone else with other parameters (a lead's kappa, say): the passes
                // go to it as they are, and each is still refused if its size differs.
                Err(splatd_proto::ClientError::Rejected { status: 409, body })
                    if body.error == "frame_exists" =>
                {
                    println!("{}; adding to it", body.message);
                }
                Err(e) => return Err(e).context("creating the frame"),
            }
        }
        let bar = indicatif::ProgressBar::new(args.passes.len() as u64).with_style(
            indicatif::ProgressStyle::with_template(
                "{bar:40} {pos}/{len} passes, {msg} [{elapsed_precise}, eta {eta}]",
            )
            .expect("valid template"),
        );
        // The outbox keeps every pass (as its path) until the server has it on disk, and
        // resends what a server restart lost. `IN_FLIGHT` passes are sent at a time, so the
        // server decodes one while it adds the one before and the next file is read meanwhile;
        // their answers go to the outbox in the order the passes were started.
        let mut outbox = splatd_proto::Outbox::new(client.clone(), &args.frame, worker)?;
        let (mut samples, mut duplicates, mut posted) = (0u64, 0u64, 0usize);
        let mut flying = std::collections::VecDeque::new();
        let mut failed = None;
        let mut passes = args.passes.iter();
        loop {
            // A pass that fails stops the posting, but the passes already in flight are still
            // answered and counted: each was sent, and may be applied.
            let next = if failed.is_none() {
                passes.next()
            } else {
                None
            };
            if let Some(path) = next {
                let started = std::fs::read(path)
                    .with_context(|| format!("reading {}", path.display()))
                    .and_then(|bytes| {
                        let seq = pass_seq(&bytes);
                        outbox
                            .start_pass_file(seq, args.layer.as_deref(), path.clone(), bytes.into())
                            .with_context(|| format!("posting {}", path.display()))
                    });
                match started {
                    Ok(post) => flying.push_back((path, tokio::spawn(post.send()))),
                    Err(e) => failed = Some(e),
                }
                if flying.len() < IN_FLIGHT && failed.is_none() {
                    continue;
                }
            }
            let Some((path, sending)) = flying.pop_front() else {
                break;
            };
            let answer = match sending.await {
                Ok(sent) => outbox.received(sent).await.map_err(anyhow::Error::from),
                Err(e) => Err(anyhow::Error::from(e).context("the request's task")),
            };
            match answer.with_context(|| format!("posting {}", path.display())) {
                Ok(ack) => {
                    samples += ack.accepted;
                    duplicates += u64::from(ack.duplicate);
                    posted += 1;
                    bar.set_message(format!("{samples} samples"));
                    bar.inc(1);
                }
                Err(e) if failed.is_none() => failed = Some(e),
                Err(e) => eprintln!("also failed: {e:#}"),
            }
        }
        if let Some(e) = failed {
            bar.abandon();
            return Err(e.context(format!(
                "{posted} of {} passes were posted ({samples} samples) before it stopped",
                args.passes.len()
            )));
        }
        bar.finish();
        // On a server with a data directory, exit only once the passes are on disk, resending
        // those acknowledged by a server process that is gone.
        let synced = outbox
            .sync()
            .await
            .context("waiting for the passes to be on disk")?;
        if outbox.resent() > 0 {
            println!(
                "the server restarted while posting: {} pass(es) sent again",
                outbox.resent()
            );
        }
        // A worker's token may have `write` only: then the frame's totals are not its to read.
        let total = match client.frame_counts(&args.frame).await {
            Ok(info) => format!("; it now has {:.1} spp on average", info.spp_mean),
            Err(splatd_proto::ClientError::Rejected { status: 403, .. }) => String::new(),
            Err(e) => return Err(e).context("reading the frame's totals"),
        };
        println!(
            "posted {} passes ({samples} samples{}) to frame {:?} as worker {worker}{total}; {}",
            args.passes.len(),
            if duplicates > 0 {
                format!(", {duplicates} already there")
            } else {
                String::new()
            },
            args.frame,
            if synced.durable {
                "all on disk"
            } else {
                "the server keeps frames in memory only"
            },
        );
        Ok(())
    })
}

/// Passes `splatd post` has in flight at once. Two keep both of a head's cores busy (one pass
/// decoded while the one before is added); more only queue in the server's memory.
const IN_FLIGHT: usize = 2;

/// The worker id `splatd post` sends passes under unless `--worker` is given.
// "SPLATPOS" in ASCII, cut to 53 bits so it stays exact in JSON numbers read as doubles.
const POST_WORKER: u64 = 0x5350_4C41_5450_4F53 >> 11;

/// A pass's sequence number: a digest of the file. The same file posted again, by a rerun or
/// from another machine, is the same batch and counts once; a different file never takes the
/// number of an earlier one (which, with numbers from file positions, a rerun on new files did,
/// and the server answered "duplicate" and dropped them).
fn pass_seq(bytes: &[u8]) -> u64 {
    xxhash_rust::xxh3::xxh3_64(bytes)
}

/// What an input file is, from its first bytes.
fn is_state_file(path: &Path) -> Result<bool> {
    use std::io::Read;
    let mut magic = [0u8; 4];
    let mut f = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let n = f.read(&mut magic)?;
    Ok(n == 4 && &magic == b"SPLS")
}

/// `--aov LAYER=C1,C2,...`.
fn parse_aov(s: &str) -> Result<splatd_proto::api::AovSpec, String> {
    let (name, channels) = s
        .rsplit_once('=')
        .ok_or_else(|| format!("expected LAYER=CHANNEL,CHANNEL..., got {s:?}"))?;
    Ok(splatd_proto::api::AovSpec {
        name: name.to_owned(),
        channels: channels.split(',').map(str::to_owned).collect(),
    })
}

/// A state file: its frame id, what it holds (only the pixels with samples: a small file may
/// declare a huge frame, and nothing here allocates by what it declares) and its batches.
fn read_state(path: &Path) -> Result<(String, SparseState, Vec<Applied>)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let mut state = SparseState::decode(&bytes)
        .with_context(|| format!("{} is not a valid state", path.display()))?;
    let batches = std::mem::take(&mut state.dump.batches);
    Ok((state.dump.frame.clone(), state, batches))
}

/// Adds state files together, checking they are of one frame and hold no batch twice. AOVs
/// add up like the cells; a state without AOVs adds none (its passes carried none), and two
/// states with different AOVs are refused. What it holds is as large as the files, whatever
/// frame size they declare.
fn merge_states(inputs: &[PathBuf]) -> Result<(String, SparseState, Seen)> {
    let (frame, mut total, batches) = read_state(&inputs[0])?;
    let mut seen = Seen::default();
    seen.insert_applied(&batches);
    for path in &inputs[1..] {
        let (other_frame, state, batches) = read_state(path)?;
        if other_frame != frame {
            bail!(
                "{} is a state of frame {other_frame:?}, but {} is of frame {frame:?}",
                path.display(),
                inputs[0].display()
            );
        }
        if let Some(o) = seen.overlap(&batches) {
            bail!(
                "{} holds {} batch(es) that the states before it hold too, the first (worker {}, \
                 seq {}); merging it would count them twice",
                path.display(),
                o.count,
                o.worker,
                o.seq
            );
        }
        total
            .merge(&state)
            .with_context(|| format!("merging {} into {}", path.display(), inputs[0].display()))?;
        seen.insert_applied(&batches);
    }
    Ok((frame, total, seen))
}

fn merge(inputs: &[PathBuf], output: &Path) -> Result<()> {
    let (frame, total, seen) = merge_states(inputs)?;
    let bytes = total.encode(seen.applied());
    std::fs::write(output, bytes).with_context(|| format!("writing {}", output.display()))?;
    println!(
        "merged {} states of frame {frame:?} ({} samples) into {}",
        inputs.len(),
        total.samples(),
        output.display()
    );
    Ok(())
}

fn resolve(args: ResolveArgs) -> Result<()> {
    let states = args
        .inputs
        .iter()
        .map(|p| is_state_file(p))
        .collect::<Result<Vec<bool>>>()?;
    let mut aovs = None;
    let state = if states.iter().all(|&s| s) {
        let (_, merged, _) = merge_states(&args.inputs)?;
        let (state, merged_aovs) = merged.into_dense().context("resolving the merged states")?;
        aovs = merged_aovs;
        state
    } else if states.iter().all(|&s| !s) {
        let (Some(width), Some(height)) = (args.width, args.height) else {
            bail!("batch files do not carry the frame size: give --width and --height");
        };
        let layout = CascadeLayout::new(
            args.base,
            args.cascades,
            args.lowest_scale,
            splatd_proto::api::DEFAULT_LUMINANCE,
        )?;
        let mut state = FrameState::new(width, height, layout);
        let mut frame_id: Option<String> = None;
        for path in &args.inputs {
            let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
            let limits = DecodeLimits {
                max_records: splatd_proto::batch::HARD_MAX_RECORDS,
                ..DecodeLimits::default()
            };
            for batch in BatchReader::new(BufReader::new(file), limits) {
                let batch = batch.with_context(|| format!("in {}", path.display()))?;
                match &frame_id {
                    None => frame_id = Some(batch.frame.clone()),
                    Some(f) if *f != batch.frame => bail!(
                        "{} holds batches of frames {f:?} and {:?}; resolve one frame at a time",
                        path.display(),
                        batch.frame
                    ),
                    Some(_) => {}
                }
                let report =
                    state.splat_records_from(batch.records.iter().map(|r| (r.x, r.y, r.rgb)));
                if report.rejected() > 0 {
                    bail!(
                        "{}: batch (worker {}, seq {}) has invalid samples: {report:?}",
                        path.display(),
                        batch.worker,
                        batch.seq
                    );
                }
            }
        }
        state
    } else {
        bail!("inputs mix state files and batch files");
    };
    let params = core_resolve_params(&splatd_proto::ResolveParams {
        variant: args.variant,
        kappa: args.kappa,
        kappa_min: args.kappa_min,
        kappa_exponent: args.kappa_exponent,
    })?;
    let resolved = state.resolve(&params);
    let extra = if args.cascade_layers {
        cascade_layers(state.cascade_means())
    } else {
        Vec::new()
    };
    let provenance = Provenance {
        layout: state.layout(),
        params: &params,
    };
    let aov_planes = aovs
        .as_ref()
        .map(|(specs, sums)| splatd_formats::exr::aov_planes(specs, sums))
        .unwrap_or_default();
    let bytes = encode_exr(&resolved, &extra, &aov_planes, &provenance)?;
    std::fs::write(&args.output, bytes)
        .with_context(|| format!("writing {}", args.output.display()))?;
    println!(
        "resolved {} samples ({}x{}) into {}",
        state.total_samples(),
        state.width(),
        state.height(),
        args.output.display()
    );
    Ok(())
}
