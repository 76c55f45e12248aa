//! splatd's estimator quality benchmark; not part of the test suite.
//!
//! `quality [--data bench-data] [--scenes a,b] [--realizations R] [--time]`
//!
//! For every scene (the synthetic stream with its exact mean, and every path-traced stream in
//! `--data` written by `benches/quality/render_streams.py`) at 16, 64 and 256 spp, averaged over
//! independent realizations (a path-traced stream of `P` passes gives `P / 256` of them, disjoint
//! runs of passes; the synthetic stream a new seed each), it prints relMSE
//! (`mean((x-gt)^2/(gt^2+0.01))`) and the energy bias of:
//! * the anchors, each tuned per row against the ground truth (an oracle no user has): the best
//!   luminance clamp, median of 4 means, G-MoN with 8 and 16 sets, and the paper's resolve with
//!   the best `c0` and `kappa` of a grid;
//! * splatd's resolve variants with their defaults, and `spread` over a grid of its support;
//!
//! with every row's ratio to the best anchor of its scene and spp. `--time` adds what `spread`'s
//! second stage costs, as the ratio of a 1080p resolve's time to `paper`'s.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use splatd_estimator::{
    CascadeLayout, FrameState, ResolveParams, Variant, DEFAULT_KAPPA, DEFAULT_KAPPA_EXPONENT,
    DEFAULT_KAPPA_MIN, DEFAULT_LOWEST_SCALE, DEFAULT_SPREAD_SUPPORT, DEFAULT_VARIANT,
    REC709_LUMINANCE,
};
use splatd_scenes::anchors::{clamped_mean, gmon, median_of_means};
use splatd_scenes::quality::{energy_bias, rel_mse};
use splatd_scenes::synth::FireflyScene;

const SPPS: [usize; 3] = [16, 64, 256];
const CLAMPS: [f64; 9] = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0];
const C0S: [f64; 4] = [1.0, 0.25, 1.0 / 16.0, 1.0 / 64.0];
const KAPPAS: [f64; 6] = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0];
const SUPPORTS: [f64; 5] = [2.0, 4.0, 8.0, 16.0, 32.0];

/// Independent realizations of one scene: runs of at least 256 one-sample passes, one truth.
struct Scene {
    name: String,
    width: u32,
    height: u32,
    runs: Vec<Vec<Vec<[f32; 3]>>>,
    gt: Vec<[f32; 3]>,
}

impl Scene {
    fn synthetic(size: u32, realizations: usize) -> Self {
        let runs = (0..realizations)
            .map(|r| {
                let scene = FireflyScene::new(size, size, 7 + r as u64);
                (0..SPPS[2] as u64)
                    .map(|p| scene.pass(p).map(|(_, _, rgb)| rgb).collect())
                    .collect()
            })
            .collect();
        let scene = FireflyScene::new(size, size, 7);
        Self {
            name: "synthetic".into(),
            width: size,
            height: size,
            runs,
            gt: (0..size)
                .flat_map(|y| (0..size).map(move |x| scene.mean(x, y).map(|v| v as f32)))
                .collect(),
        }
    }

    /// Reads `<dir>/passes.f32` (P x H x W x 3), `gt.f32` (H x W x 3) and `meta.json`; replaces
    /// a renderer's invalid samples (NaN, negative) by 0 and says how many.
    fn load(dir: &Path, realizations: usize) -> Result<Self> {
        let meta: serde_json::Value = serde_json::from_slice(
            &std::fs::read(dir.join("meta.json")).with_context(|| format!("{}", dir.display()))?,
        )?;
        let get = |k: &str| {
            meta[k]
                .as_u64()
                .with_context(|| format!("meta.json lacks {k}"))
        };
        let (w, h, p) = (get("width")? as u32, get("height")? as u32, get("passes")?);
        let pixels = (w * h) as usize;
        let floats = |name: &str, n: usize| -> Result<Vec<[f32; 3]>> {
            let bytes = std::fs::read(dir.join(name))?;
            if bytes.len() != n * 12 {
                bail!("{name}: {} bytes, expected {}", bytes.len(), n * 12);
            }
            Ok(bytes
                .chunks_exact(12)
                .map(|c| {
                    let f = |i: usize| f32::from_le_bytes(c[i..i + 4].try_into().unwrap());
                    [f(0), f(4), f(8)]
                })
                .collect())
        };
        let name: String = dir.file_name().unwrap().to_string_lossy().into();
        let mut all = floats("passes.f32", pixels * p as usize)?;
        let bad = all
            .iter_mut()
            .filter(|s| s.iter().any(|v| !v.is_finite() || *v < 0.0))
            .map(|s| *s = [0.0; 3])
            .count();
        if bad > 0 {
            println!("{name}: {bad} invalid samples replaced by 0");
        }
        let passes: Vec<Vec<[f32; 3]>> = all.chunks(pixels).map(<[_]>::to_vec).collect();
        let runs: Vec<_> = passes
            .chunks_exact(SPPS[2])
            .take(realizations)
            .map(<[_]>::to_vec)
            .collect();
        if runs.is_empty() {
            bail!("{name}: {p} passes, at least {} needed", SPPS[2]);
        }
        Ok(Self {
            name,
            width: w,
            height: h,
            runs,
            gt: floats("gt.f32", pixels)?,
        })
    }
}

/// What `spread`'s second stage costs: a 1080p resolve (default layout, 8 M samples of the
/// synthetic stream's heavy tail, scattered) with `spread` vs `paper`, best of 3, as a ratio.
fn resolve_time() -> Result<()> {
    use splatd_scenes::synth::SplitMix64;
    let (w, h) = (1920u32, 1080u32);
    let mut state = FrameState::new(w, h, CascadeLayout::with_defaults());
    let mut rng = SplitMix64::new(1);
    for _ in 0..8_000_000 {
        let x = (rng.next_u64() % w as u64) as u32;
        let y = (rng.next_u64() % h as u64) as u32;
        let z = 0.2 * rng.next_f64().powf(-1.0 / 1.3);
        state.splat_checked(x, y, [z as f32, (z * 0.8) as f32, (z * 0.5) as f32]);
    }
    let time = |variant| -> Result<f64> {
        let p = ResolveParams::new(variant, DEFAULT_KAPPA, DEFAULT_KAPPA_MIN, 0.0)?;
        Ok((0..3)
            .map(|_| {
                let t = std::time::Instant::now();
                std::hint::black_box(state.resolve(&p));
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min))
    };
    let (paper, spread) = (time(Variant::Paper)?, time(Variant::Spread)?);
    println!(
        "\nresolve 1080p, 1 thread: paper {paper:.3} s, spread {spread:.3} s, ratio {:.2}",
        spread / paper
    );
    Ok(())
}

/// States of one run after 16, 64 and 256 passes.
fn states(scene: &Scene, run: &[Vec<[f32; 3]>], layout: &CascadeLayout) -> Vec<FrameState> {
    let mut state = FrameState::new(scene.width, scene.height, layout.clone());
    let mut out = Vec::new();
    let w = scene.width;
    for (i, pass) in run.iter().enumerate().take(SPPS[2]) {
        for (p, &rgb) in pass.iter().enumerate() {
            state.splat_checked(p as u32 % w, p as u32 / w, rgb);
        }
        if SPPS.contains(&(i + 1)) {
            out.push(state.clone());
        }
    }
    out
}

/// An image per pixel from that pixel's first `spp` samples of a run.
fn per_pixel(
    run: &[Vec<[f32; 3]>],
    spp: usize,
    f: impl Fn(&[[f32; 3]]) -> [f64; 3],
) -> Vec<[f32; 3]> {
    let mut samples = Vec::with_capacity(spp);
    (0..run[0].len())
        .map(|p| {
            samples.clear();
            samples.extend(run[..spp].iter().map(|pass| pass[p]));
            f(&samples).map(|v| v as f32)
        })
        .collect()
}

/// relMSE and energy bias of one estimator, summed over realizations.
#[derive(Default, Clone)]
struct Score {
    rel_mse: Vec<f64>,
    bias: Vec<f64>,
}

impl Score {
    fn add(&mut self, image: &[[f32; 3]], gt: &[[f32; 3]]) {
        self.rel_mse.push(rel_mse(image, gt));
        self.bias.push(energy_bias(image, gt, REC709_LUMINANCE));
    }
    fn mean(v: &[f64]) -> f64 {
        v.iter().sum::<f64>() / v.len() as f64
    }
    fn err(&self) -> f64 {
        Self::mean(&self.rel_mse)
    }
    fn bias(&self) -> f64 {
        Self::mean(&self.bias)
    }
}

/// A row of the table: its label, whether it is an anchor, its score.
struct Row {
    label: String,
    anchor: bool,
    score: Score,
}

/// Keeps the best-scoring entry of a tuned family under one label.
fn best_of(label: &str, anchor: bool, family: Vec<(String, Score)>) -> Row {
    let (setting, score) = family
        .into_iter()
        .min_by(|a, b| a.1.err().total_cmp(&b.1.err()))
        .expect("a non-empty family");
    Row {
        label: format!("{label} [{setting}]"),
        anchor,
        score,
    }
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let value = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1).cloned())
    };
    let data = PathBuf::from(value("--data").unwrap_or_else(|| "bench-data".into()));
    let realizations: usize = value("--realizations")
        .map(|v| v.parse())
        .transpose()
        .context("--realizations")?
        .unwrap_or(4);
    let only: Option<Vec<String>> =
        value("--scenes").map(|s| s.split(',').map(str::to_owned).collect());
    let wanted = |name: &str| only.as_ref().is_none_or(|o| o.iter().any(|n| n == name));

    let mut scenes = Vec::new();
    if wanted("synthetic") {
        scenes.push(Scene::synthetic(64, realizations));
    }
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&data)
        .map(|e| e.flatten().map(|e| e.path()).collect())
        .unwrap_or_default();
    dirs.sort();
    for dir in dirs.into_iter().filter(|d| d.join("meta.json").exists()) {
        if wanted(&dir.file_name().unwrap().to_string_lossy()) {
            scenes.push(Scene::load(&dir, realizations)?);
        }
    }
    if scenes.iter().all(|s| s.name == "synthetic") {
        println!(
            "note: no path-traced streams in {} (python3 benches/quality/render_streams.py)",
            data.display()
        );
    }
    let defaults = ResolveParams::with_defaults();
    println!(
        "defaults: variant={:?} c0={DEFAULT_LOWEST_SCALE} kappa={DEFAULT_KAPPA} \
         kappa_min={DEFAULT_KAPPA_MIN} kappa_exponent={DEFAULT_KAPPA_EXPONENT} \
         spread_support={DEFAULT_SPREAD_SUPPORT}",
        DEFAULT_VARIANT
    );
    println!(
        "relMSE and energy bias are means over the realizations; ratio = relMSE / best anchor"
    );
    println!(
        "{:<10} {:>4} {:>3}  {:<36} {:>9} {:>7} {:>8}",
        "scene", "spp", "R", "estimator", "relMSE", "ratio", "bias"
    );
    // Every grid setting's relMSE over all scenes and spp, for the one-setting ranking.
    let mut grid: Vec<(String, Vec<f64>)> = Vec::new();
    let mut record = |setting: &str, err: f64| match grid.iter_mut().find(|g| g.0 == setting) {
        Some(g) => g.1.push(err),
        None => grid.push((setting.to_owned(), vec![err])),
    };
    for scene in &scenes {
        let runs = scene.runs.len();
        let default_layout = CascadeLayout::with_defaults();
        let default_states: Vec<Vec<FrameState>> = scene
            .runs
            .iter()
            .map(|run| states(scene, run, &default_layout))
            .collect();
        let tuned_states: Vec<(f64, Vec<Vec<FrameState>>)> = C0S
            .iter()
            .map(|&c0| {
                let layout = CascadeLayout::new(8.0, 8, c0, REC709_LUMINANCE)?;
                Ok((
                    c0,
                    scene
                        .runs
                        .iter()
                        .map(|run| states(scene, run, &layout))
                        .collect(),
                ))
            })
            .collect::<Result<_>>()?;
        for (si, &spp) in SPPS.iter().enumerate() {
            let score_of = |image_of: &dyn Fn(usize) -> Vec<[f32; 3]>| {
                let mut s = Score::default();
                for r in 0..runs {
                    s.add(&image_of(r), &scene.gt);
                }
                s
            };
            let mut rows = Vec::new();
            let resolve = |states: &[Vec<FrameState>], p: &ResolveParams| {
                score_of(&|r| states[r][si].resolve(p).reweighted)
            };
            rows.push(Row {
                label: "mean".into(),
                anchor: false,
                score: resolve(&default_states, &ResolveParams::off()),
            });
            rows.push(best_of(
                "clamp (best)",
                true,
                CLAMPS
                    .iter()
                    .map(|&c| {
                        let s =
                            score_of(&|r| per_pixel(&scene.runs[r], spp, |x| clamped_mean(x, c)));
                        (format!("L<={c}"), s)
                    })
                    .collect(),
            ));
            rows.push(Row {
                label: "median of 4 means".into(),
                anchor: true,
                score: score_of(&|r| per_pixel(&scene.runs[r], spp, |x| median_of_means(x, 4))),
            });
            for m in [8, 16] {
                rows.push(Row {
                    label: format!("G-MoN M={m}"),
                    anchor: true,
                    score: score_of(&|r| per_pixel(&scene.runs[r], spp, |x| gmon(x, m))),
                });
            }
            let mut paper_grid = Vec::new();
            for (c0, states) in &tuned_states {
                for &kappa in &KAPPAS {
                    let p = ResolveParams::new(Variant::Paper, kappa, DEFAULT_KAPPA_MIN, 0.0)?;
                    let setting = format!("c0={c0} kappa={kappa}");
                    let score = resolve(states, &p);
                    record(&format!("paper {setting}"), score.err());
                    paper_grid.push((setting, score));
                }
            }
            rows.push(best_of("paper (tuned)", true, paper_grid));
            for variant in [Variant::Paper, Variant::Spread] {
                let p = ResolveParams::new(
                    variant,
                    DEFAULT_KAPPA,
                    DEFAULT_KAPPA_MIN,
                    DEFAULT_KAPPA_EXPONENT,
                )?;
                let tag = if variant == defaults.variant() {
                    " (default)"
                } else {
                    ""
                };
                rows.push(Row {
                    label: format!("{} defaults{tag}", format!("{variant:?}").to_lowercase()),
                    anchor: false,
                    score: resolve(&default_states, &p),
                });
            }
            let mut spread_grid = Vec::new();
            for &support in &SUPPORTS {
                let p = ResolveParams::new(
                    Variant::Spread,
                    DEFAULT_KAPPA,
                    DEFAULT_KAPPA_MIN,
                    DEFAULT_KAPPA_EXPONENT,
                )?
                .with_spread_support(support)?;
                let score = resolve(&default_states, &p);
                record(
                    &format!("spread c0={DEFAULT_LOWEST_SCALE} support={support}"),
                    score.err(),
                );
                spread_grid.push((format!("support={support}"), score));
            }
            rows.push(best_of("spread (tuned)", false, spread_grid));
            let best = rows
                .iter()
                .filter(|r| r.anchor)
                .map(|r| r.score.err())
                .fold(f64::INFINITY, f64::min);
            for row in &rows {
                println!(
                    "{:<10} {:>4} {:>3}  {:<36} {:>9.5} {:>7.3} {:>+7.2}%",
                    scene.name,
                    spp,
                    runs,
                    format!("{}{}", row.label, if row.anchor { " *" } else { "" }),
                    row.score.err(),
                    row.score.err() / best,
                    100.0 * row.score.bias()
                );
            }
        }
    }
    println!("* = anchor");
    // One setting for every scene: the grid ranked by the geometric mean of relMSE over every
    // scene and spp (how a default is chosen without an oracle per row).
    let geo = |v: &[f64]| (v.iter().map(|e| e.ln()).sum::<f64>() / v.len() as f64).exp();
    grid.sort_by(|a, b| geo(&a.1).total_cmp(&geo(&b.1)));
    println!("\nsingle settings, best first (geometric mean of relMSE over scenes x spp):");
    for (setting, errs) in grid.iter().take(12) {
        println!("  {:.5}  {setting}", geo(errs));
    }
    if args.iter().any(|a| a == "--time") {
        resolve_time()?;
    }
    Ok(())
}
