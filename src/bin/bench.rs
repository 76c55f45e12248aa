//! splatd's estimator speed benchmark; not part of the test suite. (The quality benchmark is
//! its own binary, `src/bin/quality.rs`.)
//!
//! * `bench speed`: the core's speed goals as ratios measured in one run (splat vs a plain RGB +
//!   count accumulation, resolve vs one read of the state, merge vs memcpy) and the state size.

use std::hint::black_box;
use std::time::Instant;

use anyhow::{bail, Result};
use splatd_estimator::{
    cell_len, resolve_bands, CascadeLayout, FrameState, ResolveParams, DEFAULT_LOWEST_SCALE,
    REC709_LUMINANCE,
};
use splatd_scenes::synth::SplitMix64;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.first().map(String::as_str) {
        Some("speed") => speed(),
        Some("quality") => {
            bail!("the quality benchmark is its own binary: cargo run --release --bin quality")
        }
        _ => bail!("usage: bench speed"),
    }
}

// ---------------------------------------------------------------------------------------------
// Speed

/// Best of `runs` timings of `f`, in seconds (the minimum is the least disturbed by a noisy box).
fn best_of(runs: usize, mut f: impl FnMut()) -> f64 {
    (0..runs)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn speed() -> Result<()> {
    let (w, h) = (1920u32, 1080u32);
    let n_records = 8_000_000usize;
    let mut rng = SplitMix64::new(1);
    let records: Vec<(u32, u32, [f32; 3])> = (0..n_records)
        .map(|_| {
            let x = (rng.next_u64() % w as u64) as u32;
            let y = (rng.next_u64() % h as u64) as u32;
            let z = 0.2 * rng.next_f64().powf(-1.0 / 1.3);
            (x, y, [z as f32, (z * 0.8) as f32, (z * 0.5) as f32])
        })
        .collect();
    println!(
        "machine: {} cores",
        std::thread::available_parallelism()?.get()
    );

    // 1. Splat vs a plain RGB + count accumulation of the same records, in two orders: random
    //    pixels (the adversarial case: every record misses every cache) and scan order (what a
    //    worker sends when it posts whole passes or tiles).
    let layout6 = CascadeLayout::with_defaults();
    let mut state = FrameState::new(w, h, layout6.clone());
    let mut plain = vec![[0.0f32; 4]; (w * h) as usize];
    let mut scan = records.clone();
    scan.sort_by_key(|r| (r.1, r.0));
    let rate = |t: f64| n_records as f64 / t / 1e6;
    for (order, records) in [("random", &records), ("scan", &scan)] {
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
        let t_splat = best_of(3, || {
            let report = state.splat_all(records.iter().copied());
            assert_eq!(report.accepted, n_records as u64);
            black_box(&state);
        });
        println!(
            "splat {order:<6} {:>6.1} M samples/s; plain RGB+count {:>6.1} M/s; ratio {:.2} \
             (goal >= 0.5)",
            rate(t_splat),
            rate(t_plain),
            t_plain / t_splat
        );
    }

    // 2. Resolve 1080p, 8 cascades, vs one pass reading the same memory.
    let layout8 = CascadeLayout::new(8.0, 8, DEFAULT_LOWEST_SCALE, REC709_LUMINANCE)?;
    let mut state8 = FrameState::new(w, h, layout8);
    for &(x, y, rgb) in &records {
        state8.splat_checked(x, y, rgb);
    }
    let t_read = best_of(3, || {
        let sum = state8.cells().iter().fold(0u64, |a, &v| a.wrapping_add(v));
        black_box(sum);
    });
    let params = ResolveParams::with_defaults();
    for threads in [1, 2] {
        let t_resolve = best_of(3, || {
            black_box(resolve_bands(&[&state8], &params, threads).expect("whole frame"));
        });
        println!(
            "resolve    {:>7.3} s with {threads} thread(s); one read of the state {:.3} s; \
             ratio {:.2} (goal <= 3)",
            t_resolve,
            t_read,
            t_resolve / t_read
        );
    }

    // 3. Merge of two 1080p states vs a memcpy of one.
    let other = state8.clone();
    let mut target = state8.clone();
    let mut copy = vec![0u64; state8.cells().len()];
    let t_copy = best_of(3, || {
        copy.copy_from_slice(state8.cells());
        black_box(&copy);
    });
    let t_merge = best_of(3, || {
        target.merge(&other).expect("same frame");
        black_box(&target);
    });
    println!(
        "merge      {:>7.3} s; memcpy of the state {:.3} s; ratio {:.2} (goal <= 2)",
        t_merge,
        t_copy,
        t_merge / t_copy
    );

    // 4. State size.
    let per_pixel = state.memory_bytes() as f64 / (w * h) as f64;
    let k = layout6.cascades();
    println!(
        "state      {per_pixel} bytes/pixel with K={k} (goal <= 32K+8 = {}); 1080p: {:.0} MB \
         (goal < 420 MB); cell = {} u64",
        32 * k + 8,
        state.memory_bytes() as f64 / 1e6,
        cell_len(k)
    );
    Ok(())
}
