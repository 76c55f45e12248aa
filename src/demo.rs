//! The demo: a render farm in one process, talking to a splatd server over real HTTP.
//!
//! [`run`] starts an embedded server on a loopback port, creates the frame [`FRAME_ID`], and lets
//! `workers` render workers path-trace the built-in scene ([`Tracer`]) pass after pass, each
//! streaming its samples through a [`BatchWriter`](splatd_proto::BatchWriter) exactly as a farm
//! worker would. Pass `p` is rendered by worker `p % workers`, a band of rows at a time on
//! tokio's blocking pool, and the next band is rendered while the previous one is being sent.
//! While it runs, the live page (`http://ADDR/#demo`) shows the frame converge.
//!
//! At the end the frame is fetched twice over HTTP, reweighted (the frame's default) and as the
//! plain mean (`variant=off`), and written as `reweighted.exr`, `mean.exr` and
//! `side_by_side.png`: mean | reweighted | removed energy, all tone-mapped with one exposure,
//! the reweighted image's (see [`splatd_formats::preview::auto_exposure`]), so that the panels compare
//! fairly.
//!
//! With `guided`, a quarter of the passes are rendered as above and the rest in rounds: each
//! round fetches the frame's need map (`GET /v1/frames/demo/need`) and renders the samples its
//! plan gives each tile, so the total is the same and lands where the reweighting still removes
//! energy or lacks support.
//!
//! Nothing in here is privileged: the demo uses the same endpoints, client and batch format as
//! any worker, so it doubles as an end-to-end check of the whole stack.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Client, Record, Variant};
use tokio::sync::oneshot;

use splatd_formats::exr::decode_exr_channels;
use splatd_formats::preview::{auto_exposure, encode_png, side_by_side, tonemap};
use splatd_scenes::tracer::Tracer;
use splatd_server::server::{shutdown_signal, Server};
use splatd_server::Config;

/// The id of the demo's frame.
pub const FRAME_ID: &str = "demo";

/// The tracer's stream seed: fixed, so every run of the demo renders the same samples.
pub const SEED: u64 = 2018;

/// Records per batch a worker sends (64 Ki, about 1 MiB on the wire).
pub const BATCH_RECORDS: usize = 64 * 1024;

/// Gap in pixels between the panels of `side_by_side.png`.
pub const PANEL_GAP: u32 = 8;

/// What the demo renders and where it puts the results.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DemoOptions {
    /// Output folder (created if missing).
    pub out: PathBuf,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Samples per pixel: one pass of the tracer is one sample of every pixel.
    pub spp: u64,
    /// Concurrent render workers (each one a tokio task rendering on the blocking pool).
    pub workers: usize,
    /// Address of the embedded server (port 0 picks a free port).
    pub addr: String,
    /// After writing the results, keep serving (for the live page) until Ctrl-C or SIGTERM.
    pub keep_serving: bool,
    /// Steer the workers by the need map: a quarter of the samples uniformly, the rest in
    /// [`GUIDED_ROUNDS`] rounds on the tiles `GET /v1/frames/demo/need` scores neediest.
    pub guided: bool,
}

/// Rounds of need-guided rendering after the uniform warm-up (see [`DemoOptions::guided`]).
pub const GUIDED_ROUNDS: u64 = 6;

impl Default for DemoOptions {
    /// 640x480 at 64 spp with two workers: 19.7 M samples, few enough per pixel that the plain
    /// mean still shows plenty of fireflies. The demo runs until every sample is rendered and
    /// ingested, however long that takes, and prints the wall time it took.
    fn default() -> Self {
        DemoOptions {
            out: PathBuf::from("out/demo"),
            width: 640,
            height: 480,
            spp: 64,
            workers: 2,
            addr: "127.0.0.1:0".to_owned(),
            keep_serving: false,
            guided: false,
        }
    }
}

/// What a demo run did.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoReport {
    /// Samples the server accepted (`width * height * spp`).
    pub samples: u64,
    /// Samples per pixel.
    pub spp: u64,
    /// Wall time from the first rendered band to the last image fetched, in seconds.
    pub seconds: f64,
    /// The files written: `reweighted.exr`, `mean.exr`, `side_by_side.png`.
    pub files: Vec<PathBuf>,
    /// The live page of the frame, `http://ADDR/#demo` (served only while the demo runs, or
    /// until Ctrl-C with `keep_serving`).
    pub url: String,
    /// Share of the mean's luminance the reweighting removed as fireflies.
    pub removed_fraction: f64,
}

/// Runs the demo (see the module docs). Blocks until done; with `opts.keep_serving`, until
/// Ctrl-C or SIGTERM after the results are written.
pub fn run(opts: &DemoOptions) -> Result<DemoReport> {
    ensure!(
        opts.width > 0 && opts.height > 0,
        "the image must have at least one pixel, got {}x{}",
        opts.width,
        opts.height
    );
    ensure!(opts.spp > 0, "spp must be at least 1");
    ensure!(opts.workers > 0, "at least one worker is needed");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;

    // The embedded server: the same `Server` as `splatd serve`, with the default configuration
    // on the demo's address. Dropping `stop` (on any return path) shuts it down.
    let config = Config {
        addr: opts.addr.clone(),
        ..Config::default()
    };
    let server = runtime.block_on(Server::bind(config))?;
    let local = server.local_addr();
    let (stop, stopped) = oneshot::channel::<()>();
    let server = runtime.spawn(server.run(async move {
        let _ = stopped.await;
    }));
    let base = format!("http://{local}");
    let url = format!("{base}/#{FRAME_ID}");
    println!(
        "splatd demo: {}x{} at {} spp, {} workers, path-traced built-in scene",
        opts.width, opts.height, opts.spp, opts.workers
    );
    println!("live page: {url}");

    let started = Instant::now();
    let (samples, reweighted_exr, mean_exr) = runtime.block_on(render(opts, &base))?;
    let seconds = started.elapsed().as_secs_f64();

    let (files, removed_fraction) = write_results(opts, &reweighted_exr, &mean_exr)?;
    println!(
        "{samples} samples in {seconds:.1} s ({:.2} M samples/s); reweighting removed {:.2} % \
         of the mean's energy",
        samples as f64 / seconds / 1e6,
        100.0 * removed_fraction
    );
    for file in &files {
        println!("wrote {}", file.display());
    }
    if opts.keep_serving {
        println!("serving the live page at {url}; press Ctrl-C to stop");
        runtime.block_on(shutdown_signal());
    }
    drop(stop);
    runtime
        .block_on(async { tokio::time::timeout(Duration::from_secs(10), server).await })
        .context("the embedded server did not stop within 10 s")?
        .context("the embedded server task failed")??;
    Ok(DemoReport {
        samples,
        spp: opts.spp,
        seconds,
        files,
        url,
        removed_fraction,
    })
}

/// Creates the frame, renders and sends every pass, and fetches the two images: returns the
/// server's sample count and the EXR bytes of the reweighted and the mean image.
async fn render(opts: &DemoOptions, base: &str) -> Result<(u64, bytes::Bytes, bytes::Bytes)> {
    let client = Client::new(base).context("client of the embedded server")?;
    client
        .create_frame(&CreateFrame::new(FRAME_ID, opts.width, opts.height))
        .await
        .context("creating the demo frame")?;

    let pixels = u64::from(opts.width) * u64::from(opts.height);
    let expected = pixels * opts.spp;
    let progress = progress_bar(expected);
    let tracer = Arc::new(Tracer::new(opts.width, opts.height));
    // Guided: a quarter of the passes uniformly, so the need map has something to judge by.
    let uniform_spp = if opts.guided {
        (opts.spp / 4).max(1)
    } else {
        opts.spp
    };
    // Bands of about one batch, so that rendering and sending interleave finely.
    let band = (BATCH_RECORDS as u32 / opts.width).clamp(1, opts.height);
    let mut workers = tokio::task::JoinSet::new();
    for worker in 0..opts.workers {
        let passes = (worker as u64..uniform_spp).step_by(opts.workers);
        let jobs: Vec<(u64, Range<u32>)> = passes
            .flat_map(|pass| {
                (0..opts.height)
                    .step_by(band as usize)
                    .map(move |y| (pass, y..(y + band).min(opts.height)))
            })
            .collect();
        workers.spawn(render_worker(
            client.clone(),
            tracer.clone(),
            worker as u64,
            jobs,
            progress.clone(),
            pixels,
        ));
    }
    while let Some(done) = workers.join_next().await {
        done.context("a render worker panicked")??;
    }
    if opts.guided {
        let counts = vec![uniform_spp; pixels as usize];
        let left = (opts.spp - uniform_spp) * pixels;
        guided_rounds(opts, &client, &tracer, counts, left, &progress).await?;
    }
    progress.finish_and_clear();

    let info = client.frame_counts(FRAME_ID).await?;
    if info.samples != expected || info.rejected_samples != 0 {
        bail!(
            "the server holds {} samples ({} rejected), expected {expected}",
            info.samples,
            info.rejected_samples
        );
    }
    let reweighted = client
        .image(FRAME_ID, &ImageQuery::default())
        .await
        .context("fetching the reweighted image")?;
    let off = ImageQuery {
        variant: Some(Variant::Off),
        ..ImageQuery::default()
    };
    let mean = client
        .image(FRAME_ID, &off)
        .await
        .context("fetching the mean image")?;
    Ok((info.samples, reweighted, mean))
}

/// Renders `left` more samples in [`GUIDED_ROUNDS`] rounds, each spread over the tiles by the
/// server's need map ([`splatd_estimator::NeedMap::plan`]); `counts` are the samples of every
/// pixel so far, so that each new sample of a pixel is the next pass of its stream. What a
/// round's plan cannot spend (tiles at the frame's edge are smaller) carries over; the last
/// round's remainder goes to the pixels of the neediest tiles, one each.
async fn guided_rounds(
    opts: &DemoOptions,
    client: &Client,
    tracer: &Arc<Tracer>,
    mut counts: Vec<u64>,
    mut left: u64,
    progress: &ProgressBar,
) -> Result<()> {
    let pixels = counts.len() as u64;
    let per_round = left / GUIDED_ROUNDS;
    for round in 0..GUIDED_ROUNDS {
        let last = round + 1 == GUIDED_ROUNDS;
        let budget = if last { left } else { per_round.min(left) };
        let map = client
            .need(FRAME_ID, None)
            .await
            .context("fetching the need map")?
            .to_estimator()
            .map_err(anyhow::Error::msg)?;
        let mut planned = map.planned_pixels(&map.plan(budget));
        if last {
            let mut tiles: Vec<_> = map.tiles.iter().collect();
            tiles.sort_by(|a, b| b.need.total_cmp(&a.need));
            let extra = tiles.iter().flat_map(|t| {
                (t.y..t.y + t.height).flat_map(move |y| (t.x..t.x + t.width).map(move |x| (x, y)))
            });
            let short = (budget - planned.len() as u64) as usize;
            planned.extend(extra.take(short));
        }
        left -= planned.len() as u64;
        // Every planned sample with its pass: the pixel's count so far.
        let jobs: Vec<(u32, u32, u64)> = planned
            .into_iter()
            .map(|(x, y)| {
                let i = (y * opts.width + x) as usize;
                counts[i] += 1;
                (x, y, counts[i] - 1)
            })
            .collect();
        let share = jobs.len().div_ceil(opts.workers).max(1);
        let mut workers = tokio::task::JoinSet::new();
        for (w, chunk) in jobs.chunks(share).enumerate() {
            // A fresh worker id per round and worker: each numbers its batches from 0.
            let worker = (opts.workers as u64) * (round + 1) + w as u64;
            let mut writer = client.batch_writer(FRAME_ID, worker, 0, BATCH_RECORDS)?;
            let (tracer, chunk, progress) = (tracer.clone(), chunk.to_vec(), progress.clone());
            workers.spawn(async move {
                for part in chunk.chunks(BATCH_RECORDS) {
                    let (tracer, part) = (tracer.clone(), part.to_vec());
                    let records = tokio::task::spawn_blocking(move || {
                        part.iter()
                            .map(|&(x, y, pass)| Record::new(x, y, tracer.sample(x, y, pass, SEED)))
                            .collect::<Vec<Record>>()
                    })
                    .await
                    .context("a render task panicked")?;
                    let acks = writer.extend(records).await?;
                    advance(&progress, acks.iter().map(|a| a.accepted).sum(), pixels);
                }
                let acks = writer.flush().await?;
                advance(&progress, acks.iter().map(|a| a.accepted).sum(), pixels);
                anyhow::Ok(())
            });
        }
        while let Some(done) = workers.join_next().await {
            done.context("a guided render worker panicked")??;
        }
    }
    ensure!(
        left == 0,
        "{left} samples of the guided rounds were not planned"
    );
    Ok(())
}

/// One render worker: renders its `(pass, rows)` jobs in order, each while the previous one is
/// being sent, and streams the records to the server.
async fn render_worker(
    client: Client,
    tracer: Arc<Tracer>,
    worker: u64,
    jobs: Vec<(u64, Range<u32>)>,
    progress: ProgressBar,
    pixels: u64,
) -> Result<()> {
    let mut writer = client.batch_writer(FRAME_ID, worker, 0, BATCH_RECORDS)?;
    let render = |(pass, rows): (u64, Range<u32>)| {
        let tracer = tracer.clone();
        tokio::task::spawn_blocking(move || {
            let mut records: Vec<Record> = Vec::new();
            tracer.render_rows(rows, pass, SEED, &mut records);
            records
        })
    };
    let mut jobs = jobs.into_iter();
    let mut next = jobs.next().map(render);
    while let Some(band) = next {
        let records = band.await.context("a render task panicked")?;
        next = jobs.next().map(render);
        let acks = writer
            .extend(records)
            .await
            .with_context(|| format!("worker {worker} sending samples"))?;
        advance(&progress, acks.iter().map(|a| a.accepted).sum(), pixels);
    }
    let acks = writer
        .flush()
        .await
        .with_context(|| format!("worker {worker} sending its last samples"))?;
    advance(&progress, acks.iter().map(|a| a.accepted).sum(), pixels);
    Ok(())
}

/// A progress bar of samples accepted by the server, drawn on stderr when it is a terminal.
fn progress_bar(total: u64) -> ProgressBar {
    let bar = ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr());
    let style = ProgressStyle::with_template(
        "{bar:32.cyan/blue} {human_pos}/{human_len} samples, {msg}, ETA {eta}",
    )
    .expect("valid progress template")
    .progress_chars("=> ");
    bar.set_style(style);
    bar.set_message("0.0 spp");
    bar
}

fn advance(progress: &ProgressBar, accepted: u64, pixels: u64) {
    if accepted == 0 {
        return;
    }
    progress.inc(accepted);
    let done = progress.position();
    let seconds = progress.elapsed().as_secs_f64().max(1e-3);
    progress.set_message(format!(
        "{:.1} spp, {:.2} M samples/s",
        done as f64 / pixels as f64,
        done as f64 / seconds / 1e6
    ));
}

/// Writes the two EXRs and the side-by-side PNG; returns their paths and the share of the
/// mean's luminance that was removed.
fn write_results(
    opts: &DemoOptions,
    reweighted_exr: &[u8],
    mean_exr: &[u8],
) -> Result<(Vec<PathBuf>, f64)> {
    let out = &opts.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let reweighted_path = out.join("reweighted.exr");
    let mean_path = out.join("mean.exr");
    let png_path = out.join("side_by_side.png");
    write(&reweighted_path, reweighted_exr)?;
    write(&mean_path, mean_exr)?;

    let pixels = opts.width as usize * opts.height as usize;
    let channels = decode_exr_channels(reweighted_exr).context("decoding the reweighted EXR")?;
    let reweighted = rgb_layer(&channels, "", pixels)?;
    let removed = rgb_layer(&channels, "removed.", pixels)?;
    let channels = decode_exr_channels(mean_exr).context("decoding the mean EXR")?;
    let mean = rgb_layer(&channels, "", pixels)?;

    // One exposure for all panels, so that brightness differences are real.
    let exposure = auto_exposure(&reweighted);
    let panels = [&mean, &reweighted, &removed].map(|layer| tonemap(layer, exposure));
    let panels: Vec<&[[u8; 3]]> = panels.iter().map(Vec::as_slice).collect();
    let (w, h, pixels_out) = side_by_side(opts.width, opts.height, &panels, PANEL_GAP);
    let png = encode_png(w, h, &pixels_out).context("encoding the side-by-side PNG")?;
    write(&png_path, &png)?;

    let luminance = |layer: &[[f32; 3]]| -> f64 {
        layer
            .iter()
            .map(|p| splatd_estimator::rec709_luminance(p.map(f64::from)))
            .sum()
    };
    let total = luminance(&mean);
    let removed_fraction = if total > 0.0 {
        luminance(&removed) / total
    } else {
        0.0
    };
    Ok((vec![reweighted_path, mean_path, png_path], removed_fraction))
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// The RGB layer `prefix` (`""` for the main image, `"mean."`, `"removed."`) of decoded EXR
/// channels.
fn rgb_layer(
    channels: &[(String, Vec<f32>)],
    prefix: &str,
    pixels: usize,
) -> Result<Vec<[f32; 3]>> {
    let channel = |c: &str| -> Result<&[f32]> {
        let name = format!("{prefix}{c}");
        let (_, values) = channels
            .iter()
            .find(|(n, _)| *n == name)
            .with_context(|| format!("the EXR has no channel {name:?}"))?;
        ensure!(
            values.len() == pixels,
            "channel {name:?} has {} values, expected {pixels}",
            values.len()
        );
        Ok(values)
    };
    let (r, g, b) = (channel("R")?, channel("G")?, channel("B")?);
    Ok((0..pixels).map(|i| [r[i], g[i], b[i]]).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_small_demo_writes_decodable_exrs_and_a_three_panel_png() {
        let dir = tempfile::tempdir().expect("temp dir");
        let opts = DemoOptions {
            out: dir.path().join("out"),
            width: 48,
            height: 36,
            spp: 4,
            workers: 3,
            ..DemoOptions::default()
        };
        let report = run(&opts).expect("the demo runs");
        assert_eq!(report.samples, 48 * 36 * 4, "samples the server accepted");
        assert_eq!(report.spp, 4);
        assert!(
            report.url.starts_with("http://127.0.0.1:") && report.url.ends_with("/#demo"),
            "live page URL {}",
            report.url
        );
        let names: Vec<_> = report
            .files
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["reweighted.exr", "mean.exr", "side_by_side.png"]);
        for file in &report.files {
            assert!(
                file.starts_with(&opts.out),
                "{} is outside out/",
                file.display()
            );
        }

        let read = |name: &str| std::fs::read(opts.out.join(name)).expect("file written");
        for name in ["reweighted.exr", "mean.exr"] {
            let channels = decode_exr_channels(&read(name)).expect("EXR decodes");
            let spp = channels
                .iter()
                .find(|(n, _)| n == "spp.Y")
                .unwrap_or_else(|| panic!("{name} has no spp.Y layer"));
            assert!(
                spp.1.iter().all(|&n| n == 4.0),
                "{name}: every pixel has 4 samples"
            );
            for layer in ["", "mean."] {
                let rgb = rgb_layer(&channels, layer, 48 * 36).expect("layer present");
                assert!(
                    rgb.iter().flatten().all(|v| v.is_finite() && *v >= 0.0),
                    "{name}: layer {layer:?} has a negative or non-finite value"
                );
            }
            // The default `spread` may give a pixel more energy from its neighbours than it
            // removed (a negative `removed` there); over the frame nothing is ever added.
            let removed = rgb_layer(&channels, "removed.", 48 * 36).expect("layer present");
            assert!(removed.iter().flatten().all(|v| v.is_finite()), "{name}");
            let mean = rgb_layer(&channels, "mean.", 48 * 36).expect("layer present");
            let sum = |rgb: &[[f32; 3]]| rgb.iter().flatten().map(|&v| v as f64).sum::<f64>();
            assert!(
                sum(&removed) >= -1e-6 * sum(&mean),
                "{name}: the frame gained energy"
            );
        }
        // variant=off removes nothing; the default variant may.
        let mean = decode_exr_channels(&read("mean.exr")).unwrap();
        let removed = rgb_layer(&mean, "removed.", 48 * 36).unwrap();
        assert!(removed.iter().flatten().all(|&v| v == 0.0));
        assert!((0.0..1.0).contains(&report.removed_fraction));

        let png = read("side_by_side.png");
        let decoder = png::Decoder::new(png.as_slice());
        let mut reader = decoder.read_info().expect("PNG header decodes");
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).expect("PNG decodes");
        assert_eq!(
            (info.width, info.height),
            (3 * 48 + 2 * PANEL_GAP, 36),
            "three panels with two gaps"
        );
    }

    #[test]
    fn a_guided_demo_renders_the_same_total_unevenly_where_the_need_map_says() {
        let dir = tempfile::tempdir().expect("temp dir");
        let opts = DemoOptions {
            out: dir.path().join("out"),
            width: 48,
            height: 32,
            spp: 16,
            workers: 2,
            guided: true,
            ..DemoOptions::default()
        };
        let report = run(&opts).expect("the guided demo runs");
        assert_eq!(
            report.samples,
            48 * 32 * 16,
            "the same total as a uniform run"
        );
        let exr = std::fs::read(opts.out.join("reweighted.exr")).expect("written");
        let channels = decode_exr_channels(&exr).expect("EXR decodes");
        let spp = &channels.iter().find(|(n, _)| n == "spp.Y").expect("spp").1;
        let (min, max) = spp
            .iter()
            .fold((f32::MAX, 0.0f32), |(a, b), &n| (a.min(n), b.max(n)));
        assert!(
            min >= 4.0,
            "every pixel has at least the uniform quarter: min {min}"
        );
        assert!(
            min < 16.0 && max > 16.0,
            "some tiles got more than a uniform share, others less: {min} to {max}"
        );
        assert_eq!(spp.iter().sum::<f32>(), (48 * 32 * 16) as f32);
    }

    #[test]
    fn bad_options_are_refused_before_anything_starts() {
        for opts in [
            DemoOptions {
                width: 0,
                ..DemoOptions::default()
            },
            DemoOptions {
                spp: 0,
                ..DemoOptions::default()
            },
            DemoOptions {
                workers: 0,
                ..DemoOptions::default()
            },
        ] {
            assert!(run(&opts).is_err(), "{opts:?} was accepted");
        }
    }
}
