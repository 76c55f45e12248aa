//! splatd's estimator benchmarks; not part of the test suite. (The quality benchmark is its own
//! binary, `src/bin/quality.rs`.)
//!
//! * `bench speed [--size 3840x2160]`: the core's speed goals as ratios measured in one run, each
//!   printed with its goal: splat (random and scan order) and whole passes against the memory
//!   traffic they cannot avoid (a loop reading and writing the same cascade slots of the same
//!   cells in the same order, no arithmetic; plain RGB + count accumulation for reference),
//!   resolve against one read of the state (into new output buffers, as `resolve_bands` returns,
//!   and into buffers reused from the previous resolve), its first stage alone and, for scale,
//!   the same passes with every weight 1 (the plain mean), and its scaling with threads, an
//!   incremental resolve after a batch in 1 % of the pixels against a whole one, merge
//!   against memcpy, and the state size. Default size 1920x1080. The cells (and the baselines'
//!   buffers) ask for transparent huge pages, as the server's frames do; `--pages 4k` leaves
//!   them on 4 KiB pages to measure what the TLB costs. `--spp N` (default 4) sets the samples
//!   per pixel of every step: below about 16 a pixel is sparse, and the resolve's first stage
//!   trusts the bands that most of the samples around it share (docs/ALGORITHM.md, "Few samples
//!   a pixel"), which leaves its second stage less to give back than at 16 and more.
//! * `bench need`: need-guided against uniform sampling at the same total number of samples, on
//!   the synthetic scene (exact mean) and the demo's path-traced scene (against a reference of
//!   many more samples): relMSE of the reweighted image for both, and their ratio.

use std::hint::black_box;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use splatd_estimator::{
    cell_len, reached_by, resolve_bands, resolve_bands_into, resolve_region_into, CascadeLayout,
    FrameState, Kernel, NeedMap, Rect, ResolveParams, Resolved, Variant, DEFAULT_BASE_DOUBT,
    DEFAULT_LOWEST_SCALE, DEFAULT_NEED_TILE, DEFAULT_UNIFORM_SHARE, REC709_LUMINANCE,
};
use splatd_scenes::quality::rel_mse;
use splatd_scenes::synth::{FireflyScene, SplitMix64};
use splatd_scenes::tracer::Tracer;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let value = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1).cloned())
    };
    match args.first().map(String::as_str) {
        Some("quality") => {
            bail!("the quality benchmark is its own binary: cargo run --release --bin quality")
        }
        Some("speed") => speed(
            parse_size(value("--size").as_deref().unwrap_or("1920x1080"))?,
            match value("--pages").as_deref() {
                None | Some("huge") => true,
                Some("4k") => false,
                Some(other) => bail!("--pages {other:?}: use huge or 4k"),
            },
            match value("--spp") {
                None => 4,
                Some(n) => n
                    .parse()
                    .ok()
                    .filter(|&n| (1..=1024).contains(&n))
                    .with_context(|| format!("--spp {n:?}: a whole number in 1..=1024"))?,
            },
        ),
        Some("need") => need(),
        _ => bail!("usage: bench need | bench speed [--size WxH] [--pages huge|4k] [--spp N]"),
    }
}

/// `WIDTHxHEIGHT`, e.g. `3840x2160`.
fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s
        .split_once('x')
        .with_context(|| format!("size {s:?} is not WIDTHxHEIGHT"))?;
    let (w, h): (u32, u32) = (w.parse()?, h.parse()?);
    if w == 0 || h == 0 {
        bail!("size {s:?} has no pixels");
    }
    Ok((w, h))
}

// ---------------------------------------------------------------------------------------------
// Need-guided sampling

/// Edge of the need map's tiles in this benchmark (the images are multiples of it, so every
/// tile has the same number of pixels and a plan spends its budget exactly).
const NEED_TILE: u32 = 8;
/// Share of the budget rendered uniformly before the need map is first asked.
const WARM_UP_DIVISOR: u64 = 4;
/// How many times the need map is asked for the rest of the budget.
const ROUNDS: u64 = 6;

/// A scene that renders sample `k` of any pixel on demand, with a ground truth.
struct Source {
    name: String,
    width: u32,
    height: u32,
    sample: Box<dyn Fn(u32, u32, u64) -> [f32; 3] + Sync>,
    gt: Vec<[f32; 3]>,
}

/// Renders `(x, y)` once more: its next sample index is its count so far.
fn render_one(source: &Source, state: &mut FrameState, counts: &mut [u64], x: u32, y: u32) {
    let i = (y * source.width + x) as usize;
    state.splat_checked(x, y, (source.sample)(x, y, counts[i]));
    counts[i] += 1;
}

/// `spp` passes of every pixel.
fn uniform(source: &Source, spp: u64) -> FrameState {
    let mut state = FrameState::new(source.width, source.height, CascadeLayout::with_defaults());
    let mut counts = vec![0u64; source.gt.len()];
    for _ in 0..spp {
        for y in 0..source.height {
            for x in 0..source.width {
                render_one(source, &mut state, &mut counts, x, y);
            }
        }
    }
    state
}

/// How a guided round spends its budget: `uniform_share` of it as uniform passes, the rest
/// planned on the need map with `base_doubt` added ([`NeedMap::with_base_doubt`]).
#[derive(Clone, Copy)]
struct Policy {
    uniform_share: f64,
    base_doubt: f64,
}

/// The same total as `uniform(source, spp)`: a uniform warm-up of `spp / WARM_UP_DIVISOR`
/// passes, then the rest in `ROUNDS` rounds, each spent by `policy` on the need map of the
/// state so far, as a worker using `GET /v1/frames/{id}/need` would.
fn guided(source: &Source, spp: u64, params: &ResolveParams, policy: Policy) -> Result<FrameState> {
    let warm = spp / WARM_UP_DIVISOR;
    let mut state = uniform(source, warm);
    let mut counts = vec![warm; source.gt.len()];
    let pixels = source.gt.len() as u64;
    let per_round = (spp - warm) / ROUNDS;
    let mut left = (spp - warm) * pixels;
    for round in 0..ROUNDS {
        let budget = if round + 1 == ROUNDS {
            left
        } else {
            per_round * pixels
        };
        let passes = (policy.uniform_share * budget as f64) as u64 / pixels;
        for _ in 0..passes {
            for y in 0..source.height {
                for x in 0..source.width {
                    render_one(source, &mut state, &mut counts, x, y);
                }
            }
        }
        let resolved = state.resolve(params);
        let map = NeedMap::build(&[&state], &resolved, params, NEED_TILE)?
            .with_base_doubt(policy.base_doubt);
        let plan = map.plan(budget - passes * pixels);
        let planned = map.planned_pixels(&plan);
        for &(x, y) in &planned {
            render_one(source, &mut state, &mut counts, x, y);
        }
        left -= passes * pixels + planned.len() as u64;
    }
    let total: u64 = counts.iter().sum();
    if total != spp * pixels || left != 0 {
        bail!(
            "{}: need-guided sampling took {total} samples, uniform {}",
            source.name,
            spp * pixels
        );
    }
    Ok(state)
}

fn need() -> Result<()> {
    let synth = FireflyScene::new(128, 128, 7);
    let (tw, th, reference_spp) = (128u32, 96u32, 8192u64);
    let tracer = Tracer::new(tw, th);
    let started = Instant::now();
    // The reference uses another seed than the benchmarked renders, so its own noise is
    // independent of theirs (it adds the same amount to both columns' relMSE).
    let reference = {
        let tracer = &tracer;
        let rows: Vec<Vec<[f32; 3]>> = std::thread::scope(|scope| {
            let threads = std::thread::available_parallelism().map_or(1, |n| n.get()) as u32;
            let handles: Vec<_> = (0..threads)
                .map(|t| {
                    scope.spawn(move || {
                        (t..th)
                            .step_by(threads as usize)
                            .map(|y| {
                                (0..tw)
                                    .map(|x| {
                                        let mut acc = [0.0f64; 3];
                                        for k in 0..reference_spp {
                                            let s = tracer.sample(x, y, k, 1);
                                            for c in 0..3 {
                                                acc[c] += f64::from(s[c]);
                                            }
                                        }
                                        acc.map(|v| (v / reference_spp as f64) as f32)
                                    })
                                    .collect::<Vec<_>>()
                            })
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            let parts: Vec<Vec<Vec<[f32; 3]>>> =
                handles.into_iter().map(|h| h.join().unwrap()).collect();
            (0..th)
                .map(|y| parts[(y % threads) as usize][(y / threads) as usize].clone())
                .collect()
        });
        rows.concat()
    };
    println!(
        "demo scene reference: {tw}x{th} at {reference_spp} spp in {:.1} s",
        started.elapsed().as_secs_f64()
    );
    let sources = [
        Source {
            name: "synthetic".into(),
            width: synth.width,
            height: synth.height,
            sample: Box::new(move |x, y, k| synth.sample(k, x, y)),
            gt: (0..synth.height)
                .flat_map(|y| (0..synth.width).map(move |x| synth.mean(x, y).map(|v| v as f32)))
                .collect(),
        },
        Source {
            name: "demo".into(),
            width: tw,
            height: th,
            sample: Box::new(move |x, y, k| tracer.sample(x, y, k, 2018)),
            gt: reference,
        },
    ];
    let params = ResolveParams::with_defaults();
    println!(
        "need-guided: {} of the budget uniform, then {ROUNDS} rounds planned by the need map ({NEED_TILE}x{NEED_TILE} tiles); same total samples as uniform",
        format_args!("1/{WARM_UP_DIVISOR}")
    );
    println!(
        "  map alone: every round planned on the map's score; default: {DEFAULT_UNIFORM_SHARE} \
         of every round uniform, the rest planned with a base doubt of {DEFAULT_BASE_DOUBT}"
    );
    println!(
        "{:<10} {:>4}  {:>12} {:>10} {:>10} {:>6} {:>10} {:>6}",
        "scene", "spp", "uniform mean", "uniform", "map alone", "ratio", "default", "ratio"
    );
    let alone = Policy {
        uniform_share: 0.0,
        base_doubt: 0.0,
    };
    let default = Policy {
        uniform_share: DEFAULT_UNIFORM_SHARE,
        base_doubt: DEFAULT_BASE_DOUBT,
    };
    for source in &sources {
        for spp in [16u64, 64] {
            let uniform = uniform(source, spp);
            let e_mean = rel_mse(
                &uniform.resolve(&ResolveParams::off()).reweighted,
                &source.gt,
            );
            let e_uniform = rel_mse(&uniform.resolve(&params).reweighted, &source.gt);
            let e_alone = rel_mse(
                &guided(source, spp, &params, alone)?
                    .resolve(&params)
                    .reweighted,
                &source.gt,
            );
            let e_default = rel_mse(
                &guided(source, spp, &params, default)?
                    .resolve(&params)
                    .reweighted,
                &source.gt,
            );
            println!(
                "{:<10} {:>4}  {:>12.4} {:>10.4} {:>10.4} {:>6.3} {:>10.4} {:>6.3}",
                source.name,
                spp,
                e_mean,
                e_uniform,
                e_alone,
                e_alone / e_uniform,
                e_default,
                e_default / e_uniform
            );
        }
    }
    println!("(relMSE of the reweighted image; ratio = need-guided / uniform, below 1 is better)");
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Speed

/// Seconds this thread has spent on a CPU (`CLOCK_THREAD_CPUTIME_ID`), if known.
///
/// The benchmark machines are shared: with other jobs running, wall-clock time counts the time
/// this thread waited for a core, which says nothing about the code. Single-threaded timings use
/// this clock where it exists (it still counts the memory bandwidth others take). It is read
/// from the kernel's running total brought up to now; Linux's `/proc/thread-self/schedstat`
/// (used before) is only brought up to date at the scheduler's tick, so on a kernel of 250 Hz
/// every figure was a multiple of 4 ms: one read of a 1080p state (about 30 ms) measured 28,
/// 32 or 36 ms for the same code, and the resolve's ratio to it moved between 9.3x and 11.7x.
fn thread_cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        let mut t = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `t` is a valid timespec for the call to write.
        let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
        (rc == 0).then_some(t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9)
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// Best of `runs` timings of `f`, in seconds of this thread's CPU time where known, else of
/// wall-clock time (the minimum is the least disturbed by a noisy box).
fn best_of(runs: usize, mut f: impl FnMut()) -> f64 {
    (0..runs)
        .map(|_| {
            let (t, cpu) = (Instant::now(), thread_cpu_seconds());
            f();
            match (cpu, thread_cpu_seconds()) {
                (Some(a), Some(b)) => b - a,
                _ => t.elapsed().as_secs_f64(),
            }
        })
        .fold(f64::INFINITY, f64::min)
}

/// Best of `runs` wall-clock timings of `f`, for work spread over several threads.
fn best_wall_of(runs: usize, mut f: impl FnMut()) -> f64 {
    (0..runs)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// A record stream in one order, with what the memory-traffic baseline touches for it.
struct Order<'a> {
    name: &'static str,
    records: &'a [(u32, u32, [f32; 3])],
}

/// Where each record's two cascades start in the cells (`pixel * cell_len + 4 * lo`): the
/// slots the splat reads and writes, computed once, outside the timing.
fn slots(layout: &CascadeLayout, w: u32, records: &[(u32, u32, [f32; 3])]) -> Vec<usize> {
    let stride = cell_len(layout.cascades());
    records
        .iter()
        .map(|&(x, y, rgb)| {
            let lo = layout.split(layout.luminance(rgb.map(f64::from))).lo;
            (y as usize * w as usize + x as usize) * stride + 4 * lo
        })
        .collect()
}

/// The memory-traffic baseline: reads and writes the 8 words of every slot, in order, with no
/// arithmetic beyond the add that makes each a write.
fn touch(cells: &mut [u64], slots: &[usize]) {
    for &at in slots {
        for v in &mut cells[at..at + 8] {
            *v = v.wrapping_add(1);
        }
    }
    black_box(cells);
}

fn ratio_line(what: &str, ratio: f64, goal: &str, met: bool) -> String {
    // Three decimals: with two, a ratio of 0.598 read "ratio 0.60 (goal >= 0.6) MISSED".
    format!(
        "{what}: ratio {ratio:.3} (goal {goal}) {}",
        if met { "met" } else { "MISSED" }
    )
}

/// Asks for huge pages for `buf` if `huge`, saying so when the kernel refuses.
fn advise<T>(buf: &[T], huge: bool) {
    if huge {
        if let Err(e) = splatd_server::memory::advise_huge_pages(buf) {
            eprintln!(
                "warning: no huge pages for a buffer of {} bytes: {e}",
                size_of_val(buf)
            );
        }
    }
}

/// A zeroed buffer of `len` values, on huge pages if `huge` (asked before anything touches it).
fn buffer<T: Clone + Default>(len: usize, huge: bool) -> Vec<T> {
    let buf = vec![T::default(); len];
    advise(&buf, huge);
    buf
}

fn speed(size: (u32, u32), huge: bool, spp: usize) -> Result<()> {
    let (w, h) = size;
    let pixels = w as usize * h as usize;
    // Four samples per pixel by default: the state is far larger than any cache at either size.
    let n_records = spp * pixels;
    let mut rng = SplitMix64::new(1);
    let mut value = || {
        let z = 0.2 * rng.next_f64().powf(-1.0 / 1.3);
        [z as f32, (z * 0.8) as f32, (z * 0.5) as f32]
    };
    // Scan order: `spp` passes, each one sample per pixel row by row, as a worker posting whole
    // passes or tiles sends them. Random order: the same records shuffled, the adversarial case
    // in which every record misses every cache.
    let passes: Vec<Vec<[f32; 3]>> = (0..spp)
        .map(|_| (0..pixels).map(|_| value()).collect())
        .collect();
    let scan: Vec<(u32, u32, [f32; 3])> = passes
        .iter()
        .flat_map(|pass| {
            pass.iter()
                .enumerate()
                .map(|(p, &rgb)| ((p % w as usize) as u32, (p / w as usize) as u32, rgb))
        })
        .collect();
    let mut random = scan.clone();
    for i in (1..random.len()).rev() {
        random.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
    }
    println!(
        "machine: {} cores; frame {w}x{h}, {n_records} records ({spp} per pixel); {} pages; times \
         are {}",
        std::thread::available_parallelism()?.get(),
        if huge { "huge (2 MiB)" } else { "4 KiB" },
        if thread_cpu_seconds().is_some() {
            "this thread's CPU time (best of 3), resolve on several threads by the wall clock"
        } else {
            "wall-clock time (best of 3)"
        }
    );

    // 1. Splat against the memory traffic it cannot avoid: a loop reading and writing the same
    //    cascade slots of the same cells in the same order. Plain RGB + count accumulation is
    //    printed for reference (it touches 16 bytes per pixel, not two 32-byte cascades).
    let layout6 = CascadeLayout::with_defaults();
    let mut state = FrameState::new(w, h, layout6.clone());
    advise(state.cells(), huge);
    let mut baseline: Vec<u64> = buffer(state.cells().len(), huge);
    baseline.fill(1);
    let mut plain: Vec<[f32; 4]> = buffer(pixels, huge);
    let rate = |n: usize, t: f64| n as f64 / t / 1e6;
    let mut report = Vec::new();
    for order in [
        Order {
            name: "random",
            records: &random,
        },
        Order {
            name: "scan",
            records: &scan,
        },
    ] {
        let records = order.records;
        let slots = slots(&layout6, w, records);
        let t_plain = best_of(3, || {
            for &(x, y, rgb) in records.iter() {
                let p = &mut plain[(y * w + x) as usize];
                p[0] += rgb[0];
                p[1] += rgb[1];
                p[2] += rgb[2];
                p[3] += 1.0;
            }
            black_box(&plain);
        });
        let t_base = best_of(3, || touch(&mut baseline, &slots));
        let t_splat = best_of(3, || {
            let report = state.splat_records(records);
            assert_eq!(report.accepted, records.len() as u64);
            black_box(&state);
        });
        println!(
            "splat {:<6} {:>6.1} M samples/s; memory baseline {:>6.1} M/s; plain RGB+count \
             {:>6.1} M/s (splat/plain {:.2})",
            order.name,
            rate(n_records, t_splat),
            rate(n_records, t_base),
            rate(n_records, t_plain),
            t_plain / t_splat
        );
        let r = t_base / t_splat;
        report.push(ratio_line(
            &format!("splat {} / memory baseline", order.name),
            r,
            ">= 0.6",
            r >= 0.6,
        ));
    }

    // 2. Whole passes, row by row (what the passes route does), on each kernel this CPU has.
    let pass_slots: Vec<usize> = slots(&layout6, w, &scan);
    let t_base = best_of(3, || touch(&mut baseline, &pass_slots));
    for kernel in [Kernel::Portable, Kernel::Avx2, Kernel::Avx512] {
        if !kernel.available() {
            println!("pass kernel {kernel:?}: not available on this CPU");
            continue;
        }
        let t_pass = best_of(3, || {
            for pass in &passes {
                for (y, row) in pass.chunks_exact(w as usize).enumerate() {
                    state.splat_row_with(kernel, 0, y as u32, row);
                }
            }
            black_box(&state);
        });
        println!(
            "passes {kernel:?} {:>6.1} M samples/s; memory baseline {:>6.1} M/s",
            rate(n_records, t_pass),
            rate(n_records, t_base)
        );
        if kernel == Kernel::detect() {
            let r = t_base / t_pass;
            report.push(ratio_line(
                &format!("whole passes ({kernel:?}) / memory baseline"),
                r,
                ">= 0.6",
                r >= 0.6,
            ));
        }
    }
    drop((baseline, plain));

    // 3. Resolve, 8 cascades, vs one pass reading the same memory; and how it scales. Fresh
    //    output (what `resolve_bands` returns: new buffers, faulted in by the resolve) and
    //    output buffers reused from the resolve before (`resolve_bands_into`).
    let layout8 = CascadeLayout::new(8.0, 8, DEFAULT_LOWEST_SCALE, REC709_LUMINANCE)?;
    let mut state8 = FrameState::new(w, h, layout8);
    advise(state8.cells(), huge);
    state8.splat_records(&random);
    let t_read = best_of(3, || {
        let sum = state8.cells().iter().fold(0u64, |a, &v| a.wrapping_add(v));
        black_box(sum);
    });
    let params = ResolveParams::with_defaults();
    let cores = std::thread::available_parallelism()?.get();
    let mut t_one_wall = 0.0;
    let mut counts = vec![1, 2];
    if cores > 2 {
        counts.push(cores);
    }
    let mut reused = Resolved::default();
    let mut paper_out = Resolved::default();
    for threads in counts {
        // One thread on this thread's CPU clock, like the read; several by the wall clock (the
        // scaling figure is only meaningful on an otherwise idle machine).
        let resolve = || {
            black_box(resolve_bands(&[&state8], &params, threads).expect("whole frame"));
        };
        let (t_resolve, t_wall) = if threads == 1 {
            (best_of(3, resolve), best_wall_of(3, resolve))
        } else {
            let t = best_wall_of(3, resolve);
            (t, t)
        };
        // Into buffers reused from the resolve before, timed as above.
        let time_into = |params: &ResolveParams, out: &mut Resolved| {
            let mut into = || {
                resolve_bands_into(&[&state8], params, threads, out).expect("whole frame");
                black_box(&*out);
            };
            if threads == 1 {
                best_of(3, &mut into)
            } else {
                best_wall_of(3, &mut into)
            }
        };
        let t_into = time_into(&params, &mut reused);
        // The paper's resolve alone (the default's first stage): the difference to the default
        // is the spread's second stage.
        let t_paper = time_into(&params.with_variant(Variant::Paper), &mut paper_out);
        // The same row pass with every weight 1 (`off`, the plain mean): what reading the
        // cells, converting their sums and writing the layers cost before any weight.
        let t_off = time_into(&ResolveParams::off(), &mut paper_out);
        if threads == 1 {
            t_one_wall = t_wall;
        }
        println!(
            "resolve    {:>7.3} s with {threads} thread(s) ({:.3} s into reused buffers); one \
             read of the state {:.3} s; {:.2}x the read ({:.2}x reused), {:.2}x faster than 1 \
             thread (wall clock: {:.3} s)",
            t_resolve,
            t_into,
            t_read,
            t_resolve / t_read,
            t_into / t_read,
            t_one_wall / t_wall,
            t_wall
        );
        println!(
            "  of which {:?} (first stage) {:.3} s into reused buffers ({:.2}x the read), {:?}'s \
             second stage {:.3} s; working memory kept in the reused buffers {:.1} bytes/pixel",
            Variant::Paper,
            t_paper,
            t_paper / t_read,
            params.variant(),
            t_into - t_paper,
            reused.working_bytes() as f64 / pixels as f64
        );
        println!(
            "  for scale, {:?} (the same passes with every weight 1: the plain mean) {:.3} s \
             ({:.2}x the read)",
            Variant::Off,
            t_off,
            t_off / t_read
        );
        if threads == 1 {
            let r = t_resolve / t_read;
            report.push(ratio_line(
                "resolve, 1 thread / one read",
                r,
                "<= 3",
                r <= 3.0,
            ));
            let r = t_into / t_read;
            report.push(ratio_line(
                "resolve into reused buffers, 1 thread / one read",
                r,
                "<= 3",
                r <= 3.0,
            ));
        }
    }

    // 3b. An incremental resolve after a batch touched 1 % of the pixels (one contiguous square
    //     in the middle of the frame) into the buffers of the resolve before it, against a
    //     resolve of the whole frame into them; one thread, this thread's CPU time. The patched
    //     result is checked against a whole resolve, bit for bit.
    let side = ((pixels as f64 * 0.01).sqrt().round() as u32).clamp(1, w.min(h));
    let (x0, y0) = ((w - side) / 2, (h - side) / 2);
    let tile = Rect::new(x0, y0, x0 + side, y0 + side);
    let mut patched = Resolved::default();
    let t_whole = best_of(3, || {
        resolve_bands_into(&[&state8], &params, 1, &mut patched).expect("whole frame");
        black_box(&patched);
    });
    // The figures of a render (a dashboard's, `/metrics`'): the resolve and its need map.
    let mut need = NeedMap::build_on(&[&state8], &patched, &params, DEFAULT_NEED_TILE, 1)
        .expect("whole frame");
    let t_whole_need = best_of(3, || {
        black_box(
            NeedMap::build_on(&[&state8], &patched, &params, DEFAULT_NEED_TILE, 1)
                .expect("whole frame"),
        );
    });
    let mut batch_rng = SplitMix64::new(2);
    let (mut t_region, mut t_region_need) = (f64::INFINITY, f64::INFINITY);
    for _ in 0..3 {
        // The batch (not timed): one sample in every pixel of the square.
        for y in tile.y0..tile.y1 {
            let row: Vec<[f32; 3]> = (tile.x0..tile.x1)
                .map(|_| {
                    let z = 0.2 * batch_rng.next_f64().powf(-1.0 / 1.3);
                    [z as f32, (z * 0.8) as f32, (z * 0.5) as f32]
                })
                .collect();
            state8.splat_row(tile.x0, y, &row);
        }
        let t_patch = best_of(1, || {
            resolve_region_into(&[&state8], &params, 1, &[tile], &mut patched)
                .expect("whole frame");
            black_box(&patched);
        });
        t_region = t_region.min(t_patch);
        let areas = reached_by(&params, &[tile], w, h);
        let t_need = best_of(1, || {
            need.update(&[&state8], &patched, &params, &areas, 1)
                .expect("whole frame");
        });
        t_region_need = t_region_need.min(t_patch + t_need);
    }
    let whole = resolve_bands(&[&state8], &params, 1).expect("whole frame");
    let bits = |r: &Resolved| -> Vec<u32> {
        [&r.reweighted, &r.mean, &r.removed]
            .iter()
            .flat_map(|layer| layer.iter().flatten().map(|v| v.to_bits()))
            .collect()
    };
    assert!(
        bits(&patched) == bits(&whole) && patched.spp == whole.spp,
        "the incremental resolve is the whole resolve, bit for bit"
    );
    assert!(
        need == NeedMap::build(&[&state8], &whole, &params, DEFAULT_NEED_TILE).expect("whole"),
        "the need map brought up to date is the one built afresh, bit for bit"
    );
    println!(
        "incremental resolve {t_region:.4} s after a batch in {side}x{side} pixels ({:.2} % of \
         the frame); whole resolve into the same buffers {t_whole:.3} s; same bits",
        100.0 * tile.area() as f64 / pixels as f64
    );
    let r = t_region / t_whole;
    report.push(ratio_line(
        "incremental resolve after 1 % of pixels changed (one contiguous tile of 1 %) / full \
         resolve, 1 thread",
        r,
        "<= 0.05",
        r <= 0.05,
    ));
    println!(
        "incremental figures {t_region_need:.4} s (the resolve, then the need map's tiles the \
         batch reaches); whole: resolve {t_whole:.3} s + need map {t_whole_need:.3} s; same bits"
    );
    let r = t_region_need / (t_whole + t_whole_need);
    report.push(ratio_line(
        "incremental figures render (resolve + need map) after the same batch / full, 1 thread",
        r,
        "<= 0.05",
        r <= 0.05,
    ));

    // 4. Merge of two states vs a memcpy of one.
    let other = state8.clone();
    let mut target = state8.clone();
    let mut copy: Vec<u64> = buffer(state8.cells().len(), huge);
    let t_copy = best_of(3, || {
        copy.copy_from_slice(state8.cells());
        black_box(&copy);
    });
    drop(copy);
    let t_merge = best_of(3, || {
        target.merge(&other).expect("same frame");
        black_box(&target);
    });
    println!("merge      {t_merge:>7.3} s; memcpy of the state {t_copy:.3} s");
    let r = t_merge / t_copy;
    report.push(ratio_line("merge / memcpy", r, "<= 2", r <= 2.0));

    // 5. State size.
    let per_pixel = state.memory_bytes() as f64 / pixels as f64;
    let k = layout6.cascades();
    println!(
        "state      {per_pixel} bytes/pixel with K={k}; {:.0} MB at {w}x{h}; cell = {} u64",
        state.memory_bytes() as f64 / 1e6,
        cell_len(k)
    );
    report.push(ratio_line(
        &format!("state bytes/pixel / (32K+8 = {})", 32 * k + 8),
        per_pixel / (32 * k + 8) as f64,
        "<= 1",
        per_pixel <= (32 * k + 8) as f64,
    ));
    println!("\ngoals at {w}x{h}:");
    for line in report {
        println!("  {line}");
    }
    Ok(())
}
