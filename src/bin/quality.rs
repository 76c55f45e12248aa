//! splatd's estimator quality benchmark; not part of the test suite.
//!
//! `quality [--data bench-data] [--scenes a,b] [--realizations R] [--time]
//!          [--denoised-only | --farm-only | --verdict-only]`
//! `quality --picture docs/quality.png [--picture-scene smalllight]`
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
//!
//! Then, in the same run, the DENOISED table (issue 22: studios ship the frame after Intel Open
//! Image Denoise): OIDN (`splatd-denoise`, `hdr`, default quality; the library from
//! `SPLATD_OIDN_LIB`, see `tests/setup/oidn.sh`) on every anchor a user could feed it instead,
//! each at its best per row (the plain mean, G-MoN with 8 or 16 sets, and every luminance clamp
//! that removes at most 5 % of the frame's energy), and on splatd's denoised final
//! ([`DenoisePlan`]: inputs, OIDN, combine) for every [`DenoiseDesign`], unguided and guided by
//! the means of the stream's albedo and normal AOVs (`albedo.f32`, `normal.f32`) where it has
//! them: relMSE, its ratio to the best denoised anchor (goal <= 0.8x at every spp), and the
//! energy relative to OIDN(mean)'s (goal within 2 % at 64 and 256 spp). `--denoised-only`
//! skips the raw table (for iterating on designs; the recorded tables come from one run of both).
//!
//! Last, the FARM table: frames as a render farm posts them, 1 to 8 passes of 16 or 64 spp
//! (each pass's pixel one sample of splatd's estimator, the mean of that many consecutive 1-spp
//! passes), so 1 to 8 samples a pixel. For each: the plain mean and splatd's raw default (not
//! denoised), OIDN(mean), and splatd's denoised final of every design, unguided and guided;
//! goals of the default design: relMSE <= OIDN(mean)'s and energy within 2 % of it on every
//! row; of the raw default: relMSE <= the plain mean's (splatd's frame never worse than the
//! one it replaces). `--farm-only` prints only that table (and the next).
//!
//! Last, the CONVERGENCE table: the verdict `GET /v1/frames/{id}` gives (`converged`, with
//! the removed and deficit fractions it comes from) on frames of farm passes and of 1-spp passes
//! up to 256 spp, beside their relMSE (see [`verdict_table`]). `--verdict-only` prints only it
//! (no OIDN needed; seconds).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use splatd_denoise::{DenoiseInput, Oidn, Quality};
use splatd_estimator::denoise::{DenoiseDesign, DenoisePlan, DEFAULT_DENOISE_DESIGN};
use splatd_estimator::{
    CascadeLayout, FrameState, ResolveParams, SpreadParams, Variant, DEFAULT_KAPPA,
    DEFAULT_KAPPA_EXPONENT, DEFAULT_KAPPA_MIN, DEFAULT_LOWEST_SCALE, DEFAULT_VARIANT,
    REC709_LUMINANCE,
};
use splatd_scenes::anchors::{clamped_mean, gmon, median_of_means};
use splatd_scenes::quality::{energy_bias, rel_mse};
use splatd_scenes::synth::FireflyScene;

const SPPS: [usize; 3] = [16, 64, 256];
const CLAMPS: [f64; 9] = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0];
/// Clamp levels fed to the denoiser: powers of 2 from 1/4 to 2^14, wide enough that some keep
/// directly seen lights (a clamp that removes more than [`SENSIBLE_CLAMP`] of the energy is
/// not an anchor of the denoised table).
const DENOISE_CLAMPS: std::ops::RangeInclusive<i32> = -2..=14;
/// The most energy a clamp fed to the denoiser may remove (issue 22's "sensible clamp").
const SENSIBLE_CLAMP: f64 = 0.05;
const C0S: [f64; 4] = [1.0, 0.25, 1.0 / 16.0, 1.0 / 64.0];
const KAPPAS: [f64; 6] = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0];
/// The paper's `kappa` when it was splatd's default (fixed, `kappa_exponent = 0`): the rows
/// `paper` and the ranking's `paper x` compare with it.
const PAPER_KAPPA: f64 = 4.0;

/// `spread`'s grid (each list can be replaced on the command line, e.g. `--kappas 3,4`):
/// first-stage `kappa` and its growth with `N`, then the spread stage's support, solid share
/// and widest radius.
const SPREAD_KAPPAS: &str = "2.5,3,4";
const SPREAD_EXPONENTS: &str = "0,0.3";
const SUPPORTS: &str = "32,64";
const SOLID_SHARES: &str = "0,0.1";
const MAX_RADII: &str = "8,16";
/// Energy cut next to a solid pixel: given back in place where the band holds this share of
/// the pixel's samples; -1: left removed.
const EDGES: &str = "-1,0.1";

/// Every setting of `spread`'s grid, the lists from `value(flag)` or the defaults above.
fn spread_grid(value: impl Fn(&str) -> Option<String>) -> Result<Vec<(String, ResolveParams)>> {
    let list = |flag: &str, default: &str| -> Result<Vec<f64>> {
        value(flag)
            .unwrap_or_else(|| default.into())
            .split(',')
            .map(|v| v.trim().parse().with_context(|| format!("{flag} {v}")))
            .collect()
    };
    let mut grid = Vec::new();
    for kappa in list("--kappas", SPREAD_KAPPAS)? {
        for exponent in list("--exponents", SPREAD_EXPONENTS)? {
            for support in list("--supports", SUPPORTS)? {
                for solid in list("--solids", SOLID_SHARES)? {
                    for radius in list("--radii", MAX_RADII)? {
                        for edge in list("--edges", EDGES)? {
                            let edge_share = (edge >= 0.0).then_some(edge);
                            let spread = SpreadParams::new(support, solid, radius as usize)?
                                .with_edge_share(edge_share)?;
                            let p = ResolveParams::new(
                                Variant::Spread,
                                kappa,
                                DEFAULT_KAPPA_MIN,
                                exponent,
                            )?
                            .with_spread(spread);
                            grid.push((
                                format!(
                                    "kappa={kappa} e={exponent} support={support} solid={solid} \
                                     r={radius} edge={edge}"
                                ),
                                p,
                            ));
                        }
                    }
                }
            }
        }
    }
    Ok(grid)
}

/// Independent realizations of one scene: runs of at least 256 one-sample passes, one truth.
struct Scene {
    name: String,
    width: u32,
    height: u32,
    runs: Vec<Vec<Vec<[f32; 3]>>>,
    gt: Vec<[f32; 3]>,
    /// Per run and per entry of [`SPPS`], the means of the albedo and normal AOVs over the
    /// run's first `spp` passes for every `spp` of [`GUIDE_SPPS`] (empty for a stream without
    /// AOVs).
    guides: Vec<Vec<Guides>>,
    /// The ground truth's own relMSE as render_streams.py estimated it (its chunks' spread):
    /// a floor under every relMSE of the scene.
    gt_noise: Option<f64>,
}

/// The pass counts whose AOV means are kept as guides: the 1-spp rows' and the farm rows'.
const GUIDE_SPPS: [usize; 5] = [16, 32, 64, 128, 256];

/// A denoiser's guides: the albedo and normal means of a run's first passes.
struct Guides {
    albedo: Vec<[f32; 3]>,
    normal: Vec<[f32; 3]>,
}

impl Scene {
    /// The guides of run `r` after its first `spp` 1-spp passes, if the stream has AOVs.
    fn guide(&self, r: usize, spp: usize) -> Option<&Guides> {
        let at = GUIDE_SPPS.iter().position(|&s| s == spp)?;
        self.guides.get(r).map(|g| &g[at])
    }

    /// Whether OIDN is guided, for each row the tables print: unguided, and guided too where
    /// the stream has AOVs.
    fn guide_modes(&self) -> &'static [bool] {
        if self.guides.is_empty() {
            &[false]
        } else {
            &[false, true]
        }
    }

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
            guides: Vec::new(),
            gt_noise: Some(0.0),
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
        // The AOVs (streams rendered before they existed have none): only their means over
        // each run's first GUIDE_SPPS passes are kept.
        let mut guides = Vec::new();
        if dir.join("albedo.f32").exists() && dir.join("normal.f32").exists() {
            let means = |file: &str| -> Result<Vec<Vec<Vec<[f32; 3]>>>> {
                let all = floats(file, pixels * p as usize)?;
                Ok((0..runs.len())
                    .map(|r| {
                        GUIDE_SPPS
                            .iter()
                            .map(|&spp| {
                                let passes = &all[r * SPPS[2] * pixels..];
                                (0..pixels)
                                    .map(|i| {
                                        let mut sum = [0.0f64; 3];
                                        for pass in 0..spp {
                                            let v = passes[pass * pixels + i];
                                            for c in 0..3 {
                                                sum[c] += if v[c].is_finite() {
                                                    v[c] as f64
                                                } else {
                                                    0.0
                                                };
                                            }
                                        }
                                        sum.map(|s| (s / spp as f64) as f32)
                                    })
                                    .collect()
                            })
                            .collect()
                    })
                    .collect())
            };
            let (albedo, normal) = (means("albedo.f32")?, means("normal.f32")?);
            guides = albedo
                .into_iter()
                .zip(normal)
                .map(|(a, n)| {
                    a.into_iter()
                        .zip(n)
                        .map(|(albedo, normal)| Guides { albedo, normal })
                        .collect()
                })
                .collect();
        }
        Ok(Self {
            name,
            width: w,
            height: h,
            runs,
            gt: floats("gt.f32", pixels)?,
            guides,
            gt_noise: meta["relmse_gt_est_from_chunks"].as_f64(),
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
        let p = ResolveParams::with_defaults().with_variant(variant);
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

/// Summed luminance of an image.
fn energy(image: &[[f32; 3]]) -> f64 {
    let w = REC709_LUMINANCE;
    image
        .iter()
        .map(|p| w[0] * p[0] as f64 + w[1] * p[1] as f64 + w[2] * p[2] as f64)
        .sum()
}

/// `--picture PATH`: the first realization of one scene at 16, 64 and 256 spp, the plain mean
/// (top row) over splatd's default resolve (bottom row), all with one exposure (the ground
/// truth's), and beside them a plot of the share of the mean's energy removed at 1, 2, 4, ..
/// 256 spp: the default (orange) and `paper [kappa=4]` (blue), with a faint grid line every 5 %.
fn picture(scene: &Scene, path: &Path) -> Result<()> {
    use splatd_formats::preview::{auto_exposure, encode_png, tonemap};
    const SCALE: usize = 3;
    const GAP: usize = 6;
    const BACKGROUND: [u8; 3] = [24, 24, 24];
    let (w, h) = (scene.width as usize, scene.height as usize);
    let defaults = ResolveParams::with_defaults();
    let paper = ResolveParams::new(Variant::Paper, PAPER_KAPPA, DEFAULT_KAPPA_MIN, 0.0)?;
    let mut state = FrameState::new(scene.width, scene.height, CascadeLayout::with_defaults());
    let (mut curve, mut tiles) = (Vec::new(), Vec::new());
    for (i, pass) in scene.runs[0].iter().enumerate().take(SPPS[2]) {
        for (p, &rgb) in pass.iter().enumerate() {
            state.splat_checked((p % w) as u32, (p / w) as u32, rgb);
        }
        let spp = i + 1;
        if spp.is_power_of_two() {
            let r = state.resolve(&defaults);
            let removed = |r: &splatd_estimator::Resolved| energy(&r.removed) / energy(&r.mean);
            curve.push([removed(&r), removed(&state.resolve(&paper))]);
            if SPPS.contains(&spp) {
                tiles.push([r.mean, r.reweighted]);
            }
        }
    }
    // Half the ground truth's automatic exposure: the lit ceiling and walls of the rendered rooms
    // would clip at the full one.
    let exposure = 0.5 * auto_exposure(&scene.gt);
    let (tw, th) = (w * SCALE, h * SCALE);
    let grid_w = 3 * tw + 2 * GAP;
    let grid_h = 2 * th + GAP;
    let plot_w = 2 * tw;
    let width = grid_w + 3 * GAP + plot_w;
    let mut canvas = vec![BACKGROUND; width * grid_h];
    for (col, images) in tiles.iter().enumerate() {
        for (row, image) in images.iter().enumerate() {
            let (x0, y0) = (col * (tw + GAP), row * (th + GAP));
            let toned = tonemap(image, exposure);
            for y in 0..th {
                for x in 0..tw {
                    canvas[(y0 + y) * width + x0 + x] = toned[(y / SCALE) * w + x / SCALE];
                }
            }
        }
    }
    // The plot: x = log2(spp) from 0 to 8, y = removed share from 0 to the next 5 % above the
    // largest.
    let top = curve
        .iter()
        .flatten()
        .fold(0.05f64, |m, &v| m.max(v))
        .div_euclid(0.05)
        .mul_add(0.05, 0.05);
    let (px0, py0, pw, ph) = (grid_w + 3 * GAP + 12, 12, plot_w - 24, grid_h - 24);
    let mut put = |x: i64, y: i64, rgb: [u8; 3]| {
        if x >= 0 && y >= 0 && (x as usize) < width && (y as usize) < grid_h {
            canvas[y as usize * width + x as usize] = rgb;
        }
    };
    let to_xy = |i: usize, v: f64| {
        let x = px0 as f64 + pw as f64 * i as f64 / (curve.len() - 1) as f64;
        let y = (py0 + ph) as f64 - ph as f64 * v.max(0.0) / top;
        (x, y)
    };
    let mut level = 0.0;
    while level <= top + 1e-9 {
        let (_, y) = to_xy(0, level);
        let shade = if level == 0.0 { 200 } else { 70 };
        for x in px0..=px0 + pw {
            put(x as i64, y.round() as i64, [shade; 3]);
        }
        level += 0.05;
    }
    for i in 0..curve.len() {
        let (x, _) = to_xy(i, 0.0);
        for y in 0..6 {
            put(x.round() as i64, (py0 + ph + y) as i64, [200; 3]);
        }
    }
    for (series, colour) in [(1, [90, 150, 255]), (0, [255, 150, 40])] {
        for i in 0..curve.len() {
            let (x, y) = to_xy(i, curve[i][series]);
            for dy in -3..=3 {
                for dx in -3..=3 {
                    put(x.round() as i64 + dx, y.round() as i64 + dy, colour);
                }
            }
            if i + 1 < curve.len() {
                let (x1, y1) = to_xy(i + 1, curve[i + 1][series]);
                let steps = (x1 - x).abs().max((y1 - y).abs()).ceil() as usize;
                for s in 0..=steps {
                    let t = s as f64 / steps.max(1) as f64;
                    let (lx, ly) = (x + (x1 - x) * t, y + (y1 - y) * t);
                    for d in 0..2 {
                        put(lx.round() as i64 + d, ly.round() as i64, colour);
                        put(lx.round() as i64, ly.round() as i64 + d, colour);
                    }
                }
            }
        }
    }
    let png = encode_png(width as u32, grid_h as u32, &canvas)?;
    std::fs::write(path, png).with_context(|| format!("writing {}", path.display()))?;
    println!(
        "{}: {} ({width}x{grid_h}), spp 1..256 removed share:",
        path.display(),
        scene.name
    );
    for (i, [d, p]) in curve.iter().enumerate() {
        println!(
            "  {:>3} spp  default {:>6.2} %  paper {:>6.2} %",
            1 << i,
            100.0 * d,
            100.0 * p
        );
    }
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

/// One denoised estimator's relMSE and energy relative to OIDN(mean), per realization.
#[derive(Default)]
struct Denoised {
    rel_mse: Vec<f64>,
    energy: Vec<f64>,
}

impl Denoised {
    fn err(&self) -> f64 {
        Score::mean(&self.rel_mse)
    }
    fn energy(&self) -> f64 {
        Score::mean(&self.energy)
    }
}

/// How many rows of a table meet a goal, and which miss it.
#[derive(Default)]
struct Goal {
    met: usize,
    rows: usize,
    missed: Vec<String>,
}

impl Goal {
    fn check(&mut self, ok: bool, row: &str) -> &'static str {
        self.rows += 1;
        if ok {
            self.met += 1;
            "ok"
        } else {
            self.missed.push(row.to_owned());
            "MISS"
        }
    }
    fn report(&self, what: &str) {
        println!("  {what}: {}/{} rows", self.met, self.rows);
        if !self.missed.is_empty() {
            println!("    missed: {}", self.missed.join("; "));
        }
    }
}

/// OIDN (`hdr`, default quality, guides not marked clean) on one of `scene`'s images, guided by
/// `guides` if given.
fn oidn_on(
    oidn: &Oidn,
    scene: &Scene,
    color: &[[f32; 3]],
    guides: Option<&Guides>,
) -> Result<Vec<[f32; 3]>> {
    Ok(oidn.denoise(&DenoiseInput {
        width: scene.width as usize,
        height: scene.height as usize,
        color,
        albedo: guides.map(|g| &g.albedo[..]),
        normal: guides.map(|g| &g.normal[..]),
        hdr: true,
        quality: Quality::Default,
        clean_aux: false,
        max_memory_mib: None,
    })?)
}

/// Scores images against the ground truth and OIDN(mean) of the same realization.
struct VersusOidnMean<'g> {
    gt: &'g [[f32; 3]],
    /// OIDN(mean)'s energy, per realization.
    energy: Vec<f64>,
}

impl<'g> VersusOidnMean<'g> {
    /// From OIDN(mean) of every realization; with OIDN(mean)'s own row.
    fn new(gt: &'g [[f32; 3]], oidn_means: &[Vec<[f32; 3]>]) -> (Self, Denoised) {
        let mut row = Denoised::default();
        for d in oidn_means {
            row.rel_mse.push(rel_mse(d, gt));
            row.energy.push(0.0);
        }
        let energy = oidn_means.iter().map(|d| energy(d)).collect();
        (Self { gt, energy }, row)
    }

    /// relMSE and energy relative to OIDN(mean) of `image(r)` for every realization `r`.
    fn score(&self, image: impl Fn(usize) -> Result<Vec<[f32; 3]>>) -> Result<Denoised> {
        let mut s = Denoised::default();
        for (r, reference) in self.energy.iter().enumerate() {
            let d = image(r)?;
            s.rel_mse.push(rel_mse(&d, self.gt));
            s.energy.push(energy(&d) / reference - 1.0);
        }
        Ok(s)
    }
}

/// A design's row label: `splatd <name>`, with ` (default)` for [`DEFAULT_DENOISE_DESIGN`]
/// (the goals are checked on the row whose label ends so).
fn design_label(design: DenoiseDesign) -> String {
    let default = if design == DEFAULT_DENOISE_DESIGN {
        " (default)"
    } else {
        ""
    };
    format!("splatd {}{default}", design.name())
}

/// splatd's denoised final of `state` with `design` (the default resolve parameters), `denoise`
/// run on each of the plan's inputs.
fn design_final(
    state: &FrameState,
    design: DenoiseDesign,
    denoise: impl Fn(&[[f32; 3]]) -> Result<Vec<[f32; 3]>>,
) -> Result<Vec<[f32; 3]>> {
    let plan = DenoisePlan::with_design(&[state], &ResolveParams::with_defaults(), 2, design);
    let outputs = plan
        .inputs()
        .iter()
        .map(|input| denoise(input))
        .collect::<Result<Vec<_>>>()?;
    Ok(plan.combine(outputs))
}

/// The denoised table's rows of one scene: for every spp and guide (none, and the AOVs' means
/// where the stream has them), OIDN on every anchor and on every design's final.
fn denoised_rows(
    scene: &Scene,
    states: &[Vec<FrameState>],
    oidn: &Oidn,
    ratio_goal: &mut Goal,
    energy_goal: &mut Goal,
) -> Result<()> {
    let runs = scene.runs.len();
    let lum = |img: &[[f32; 3]]| energy(img);
    for (si, &spp) in SPPS.iter().enumerate() {
        for &guided in scene.guide_modes() {
            let denoise = |r: usize, color: &[[f32; 3]]| {
                let g = guided.then(|| scene.guide(r, spp).expect("guides"));
                oidn_on(oidn, scene, color, g)
            };
            let means: Vec<Vec<[f32; 3]>> = (0..runs)
                .map(|r| states[r][si].resolve(&ResolveParams::off()).reweighted)
                .collect();
            let oidn_means = (0..runs)
                .map(|r| denoise(r, &means[r]))
                .collect::<Result<Vec<_>>>()?;
            let (versus, mean_row) = VersusOidnMean::new(&scene.gt, &oidn_means);
            let score = |images: &dyn Fn(usize) -> Result<Vec<[f32; 3]>>| versus.score(images);
            let mut rows: Vec<(String, bool, Denoised)> = Vec::new();
            rows.push(("OIDN(mean)".into(), true, mean_row));
            // Clamps that remove at most 5 % of the mean's energy (averaged over realizations).
            let mut clamps = Vec::new();
            for k in DENOISE_CLAMPS {
                let c = 2f64.powi(k);
                let images: Vec<Vec<[f32; 3]>> = (0..runs)
                    .map(|r| per_pixel(&scene.runs[r], spp, |x| clamped_mean(x, c)))
                    .collect();
                let removed = (0..runs)
                    .map(|r| 1.0 - lum(&images[r]) / lum(&means[r]))
                    .sum::<f64>()
                    / runs as f64;
                if removed <= SENSIBLE_CLAMP {
                    let s = score(&|r| denoise(r, &images[r]))?;
                    clamps.push((
                        format!("L<={c}, removes {:.1} %", 100.0 * removed.max(0.0)),
                        s,
                    ));
                }
            }
            match clamps
                .into_iter()
                .min_by(|a, b| a.1.err().total_cmp(&b.1.err()))
            {
                Some((setting, s)) => {
                    rows.push((format!("OIDN(clamp <= 5 %) [{setting}]"), true, s))
                }
                None => println!(
                    "{} {spp} spp: no clamp of 2^{:?} removes at most 5 % of the energy",
                    scene.name, DENOISE_CLAMPS
                ),
            }
            let mut gmons = Vec::new();
            for m in [8, 16] {
                let s = score(&|r| denoise(r, &per_pixel(&scene.runs[r], spp, |x| gmon(x, m))))?;
                gmons.push((format!("M={m}"), s));
            }
            let (setting, s) = gmons
                .into_iter()
                .min_by(|a, b| a.1.err().total_cmp(&b.1.err()))
                .expect("two G-MoN settings");
            rows.push((format!("OIDN(G-MoN) [{setting}]"), true, s));
            for design in DenoiseDesign::ALL {
                let s = score(&|r| design_final(&states[r][si], design, |i| denoise(r, i)))?;
                rows.push((design_label(design), false, s));
            }
            let best = rows
                .iter()
                .filter(|r| r.1)
                .map(|r| r.2.err())
                .fold(f64::INFINITY, f64::min);
            let guide = if guided { "aovs" } else { "none" };
            for (label, anchor, s) in &rows {
                let ratio = s.err() / best;
                let mut goals = String::new();
                if label.ends_with("(default)") {
                    let row = format!("{} {spp} {guide}", scene.name);
                    goals = format!(
                        "ratio<=0.8: {}",
                        ratio_goal.check(ratio <= 0.8, &format!("{row} {ratio:.2}x"))
                    );
                    if spp >= 64 {
                        let e = s.energy();
                        goals += &format!(
                            "  |energy|<=2%: {}",
                            energy_goal
                                .check(e.abs() <= 0.02, &format!("{row} {:+.2} %", 100.0 * e))
                        );
                    }
                }
                println!(
                    "{:<10} {:>4} {:<5} {:<46} {:>9.5} {:>7.3} {:>+8.2}%  {goals}",
                    scene.name,
                    spp,
                    guide,
                    format!("{label}{}", if *anchor { " *" } else { "" }),
                    s.err(),
                    ratio,
                    100.0 * s.energy(),
                );
            }
        }
    }
    Ok(())
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
    let farm_only = args.iter().any(|a| a == "--farm-only");
    let denoised_only = farm_only || args.iter().any(|a| a == "--denoised-only");

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
    if let Some(path) = value("--picture") {
        let name = value("--picture-scene").unwrap_or_else(|| "smalllight".into());
        let scene = scenes
            .iter()
            .find(|s| s.name == name)
            .with_context(|| format!("--picture: no scene {name} in {}", data.display()))?;
        return picture(scene, Path::new(&path));
    }
    if scenes.iter().all(|s| s.name == "synthetic") {
        println!(
            "note: no path-traced streams in {} (python3 benches/quality/render_streams.py)",
            data.display()
        );
    }
    if args.iter().any(|a| a == "--verdict-only") {
        return verdict_table(&scenes);
    }
    let defaults = ResolveParams::with_defaults();
    println!(
        "defaults: variant={:?} c0={DEFAULT_LOWEST_SCALE} kappa={DEFAULT_KAPPA} \
         kappa_min={DEFAULT_KAPPA_MIN} kappa_exponent={DEFAULT_KAPPA_EXPONENT} spread={:?}",
        DEFAULT_VARIANT,
        defaults.spread()
    );
    let spread_settings = spread_grid(value)?;
    println!(
        "relMSE and energy bias are means over the realizations; ratio = relMSE / best anchor"
    );
    println!(
        "{:<10} {:>4} {:>3}  {:<36} {:>9} {:>7} {:>8}",
        "scene", "spp", "R", "estimator", "relMSE", "ratio", "bias"
    );
    // Every grid setting's relMSE over all scenes and spp, for the one-setting ranking.
    let mut grid: Vec<(String, Vec<f64>)> = Vec::new();
    // Per row, the best anchor's relMSE and `paper`'s with the defaults.
    let (mut best_anchor, mut paper_default) = (Vec::new(), Vec::new());
    let mut record = |setting: &str, err: f64| match grid.iter_mut().find(|g| g.0 == setting) {
        Some(g) => g.1.push(err),
        None => grid.push((setting.to_owned(), vec![err])),
    };
    let (mut raw_ratio_goal, mut raw_energy_goal) = (Goal::default(), Goal::default());
    for scene in scenes.iter().filter(|_| !denoised_only) {
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
            // The paper with its former defaults (`kappa = 4`, fixed), and splatd's defaults.
            let paper = resolve(
                &default_states,
                &ResolveParams::new(Variant::Paper, PAPER_KAPPA, DEFAULT_KAPPA_MIN, 0.0)?,
            );
            paper_default.push(paper.err());
            rows.push(Row {
                label: format!("paper [kappa={PAPER_KAPPA}]"),
                anchor: false,
                score: paper,
            });
            rows.push(Row {
                label: format!(
                    "splatd defaults ({})",
                    format!("{:?}", defaults.variant()).to_lowercase()
                ),
                anchor: false,
                score: resolve(&default_states, &defaults),
            });
            let mut tuned = Vec::new();
            for (setting, p) in &spread_settings {
                let score = resolve(&default_states, p);
                record(&format!("spread {setting}"), score.err());
                tuned.push((setting.clone(), score));
            }
            rows.push(best_of("spread (tuned)", false, tuned));
            let best = rows
                .iter()
                .filter(|r| r.anchor)
                .map(|r| r.score.err())
                .fold(f64::INFINITY, f64::min);
            best_anchor.push(best);
            for row in &rows {
                let ratio = row.score.err() / best;
                let mut goals = String::new();
                if row.label.starts_with("splatd defaults") {
                    let name = format!("{} {spp}", scene.name);
                    goals = format!(
                        "  ratio<=0.8: {}",
                        raw_ratio_goal.check(ratio <= 0.8, &format!("{name} {ratio:.2}x"))
                    );
                    let loss = -row.score.bias();
                    let allowed = match spp {
                        64 => Some(0.03),
                        256 => Some(0.015),
                        _ => None,
                    };
                    if let Some(allowed) = allowed {
                        goals += &format!(
                            "  loss<={:.1}%: {}",
                            100.0 * allowed,
                            raw_energy_goal
                                .check(loss <= allowed, &format!("{name} -{:.2} %", 100.0 * loss))
                        );
                    }
                }
                println!(
                    "{:<10} {:>4} {:>3}  {:<36} {:>9.5} {:>7.3} {:>+7.2}%{goals}",
                    scene.name,
                    spp,
                    runs,
                    format!("{}{}", row.label, if row.anchor { " *" } else { "" }),
                    row.score.err(),
                    ratio,
                    100.0 * row.score.bias()
                );
            }
        }
    }
    if !denoised_only {
        println!("* = anchor");
        println!("raw goals of splatd's default:");
        raw_ratio_goal.report("relMSE <= 0.8x the best raw anchor (every spp)");
        raw_energy_goal.report("energy loss <= 3 % at 64 spp, <= 1.5 % at 256 spp");
    }
    // One setting for every scene: the grid ranked by the geometric mean of relMSE over every
    // scene and spp (how a default is chosen without an oracle per row).
    let geo = |v: &[f64]| (v.iter().map(|e| e.ln()).sum::<f64>() / v.len() as f64).exp();
    grid.sort_by(|a, b| geo(&a.1).total_cmp(&geo(&b.1)));
    println!(
        "\nsingle settings, best first: geometric mean of relMSE over scenes x spp, worst and \
         geometric mean ratio to paper [kappa=4], worst ratio to the best anchor, rows <= 0.8x it"
    );
    for (setting, errs) in grid.iter().take(16) {
        let worst = |by: &[f64]| errs.iter().zip(by).map(|(e, b)| e / b).fold(0.0, f64::max);
        let ratios: Vec<f64> = errs
            .iter()
            .zip(&paper_default)
            .map(|(e, b)| e / b)
            .collect();
        let under = errs
            .iter()
            .zip(&best_anchor)
            .filter(|(e, b)| *e <= &(0.8 * *b))
            .count();
        println!(
            "  {:.5}  paper x{:.2} (geo x{:.2})  anchor x{:.2}  {under:>2}/{}  {setting}",
            geo(errs),
            worst(&paper_default),
            geo(&ratios),
            worst(&best_anchor),
            errs.len()
        );
        if args.iter().any(|a| a == "--rows") {
            let ratios: Vec<String> = errs
                .iter()
                .zip(&best_anchor)
                .map(|(e, b)| format!("{:.2}", e / b))
                .collect();
            println!(
                "           per row, ratio to the best anchor: {}",
                ratios.join(" ")
            );
        }
    }
    if args.iter().any(|a| a == "--time") {
        resolve_time()?;
    }
    if !farm_only {
        denoised_table(&scenes)?;
    }
    farm_table(&scenes)?;
    verdict_table(&scenes)
}

/// The farm table's frames, as (passes, spp of each pass): a farm hands out a frame as a few
/// passes of many samples, each pixel of a pass one sample of splatd's estimator, so a frame
/// holds few samples a pixel (its first pass one) however many the renderer took.
const FARM: [(usize, usize); 7] = [
    (1, 16),
    (2, 16),
    (4, 16),
    (8, 16),
    (1, 64),
    (2, 64),
    (4, 64),
];

/// A frame of `passes` passes of a run, each pass the mean of `spp` consecutive 1-spp passes.
fn farm_state(scene: &Scene, run: &[Vec<[f32; 3]>], passes: usize, spp: usize) -> FrameState {
    let mut state = FrameState::new(scene.width, scene.height, CascadeLayout::with_defaults());
    let w = scene.width;
    for pass in run.chunks_exact(spp).take(passes) {
        for p in 0..pass[0].len() {
            let mut sum = [0.0f64; 3];
            for sample in pass {
                for c in 0..3 {
                    sum[c] += sample[p][c] as f64;
                }
            }
            let rgb = sum.map(|v| (v / spp as f64) as f32);
            state.splat_checked(p as u32 % w, p as u32 / w, rgb);
        }
    }
    state
}

/// The farm table's labels of the plain mean and of splatd's raw default (neither denoised).
const PLAIN_MEAN: &str = "mean (not denoised)";
const RAW_DEFAULT: &str = "splatd raw default (not denoised)";

/// The FARM table (`--farm`, or after the denoised table): frames of 1 to 8 passes of 16 or
/// 64 spp, as a farm posts them. For each, relMSE and the energy relative to OIDN(mean)'s of
/// the plain mean, splatd's raw default, OIDN(mean) (what a farm ships without splatd) and
/// splatd's denoised final of every design, unguided and guided by the passes' AOV means.
/// Goals of the default design: relMSE <= OIDN(mean)'s and energy within 2 % of it, every row;
/// of the raw default: relMSE <= the plain mean's.
fn farm_table(scenes: &[Scene]) -> Result<()> {
    let oidn = match Oidn::load() {
        Ok(oidn) => oidn,
        Err(e) => {
            println!("\nFARM: skipped, OIDN not loaded ({e})");
            return Ok(());
        }
    };
    println!(
        "\nFARM PASSES: frames of P passes of S spp (each pass one sample a pixel); OIDN {} as \
         above; relMSE and energy (vs OIDN(mean) of the same realization and guide) are means \
         over the realizations; ratio = relMSE / OIDN(mean)'s",
        oidn.version()
    );
    println!(
        "{:<10} {:>6} {:>2} {:<5} {:<38} {:>9} {:>7} {:>9}  goals of the default",
        "scene", "PxS", "R", "guide", "estimator", "relMSE", "ratio", "energy"
    );
    let (mut ratio_goal, mut energy_goal) = (Goal::default(), Goal::default());
    let mut raw_goal = Goal::default();
    let defaults = ResolveParams::with_defaults();
    for scene in scenes {
        for (passes, spp) in FARM {
            let runs: Vec<usize> = (0..scene.runs.len())
                .filter(|&r| scene.runs[r].len() >= passes * spp)
                .collect();
            let states: Vec<FrameState> = runs
                .iter()
                .map(|&r| farm_state(scene, &scene.runs[r], passes, spp))
                .collect();
            let means: Vec<Vec<[f32; 3]>> = states
                .iter()
                .map(|state| state.resolve(&ResolveParams::off()).reweighted)
                .collect();
            for &guided in scene.guide_modes() {
                let denoise = |i: usize, color: &[[f32; 3]]| {
                    let g = guided.then(|| scene.guide(runs[i], passes * spp).expect("guides"));
                    oidn_on(&oidn, scene, color, g)
                };
                let oidn_means = (0..states.len())
                    .map(|i| denoise(i, &means[i]))
                    .collect::<Result<Vec<_>>>()?;
                let (versus, mean_row) = VersusOidnMean::new(&scene.gt, &oidn_means);
                let mut rows: Vec<(String, Denoised)> = Vec::new();
                if !guided {
                    let mean = versus.score(|i| Ok(means[i].clone()))?;
                    rows.push((PLAIN_MEAN.into(), mean));
                    let raw = versus.score(|i| Ok(states[i].resolve(&defaults).reweighted))?;
                    rows.push((RAW_DEFAULT.into(), raw));
                }
                let oidn_mean_err = mean_row.err();
                rows.push(("OIDN(mean)".into(), mean_row));
                for design in DenoiseDesign::ALL {
                    let s =
                        versus.score(|i| design_final(&states[i], design, |x| denoise(i, x)))?;
                    rows.push((design_label(design), s));
                }
                let guide = if guided { "aovs" } else { "none" };
                let row = format!("{} {passes}x{spp} {guide}", scene.name);
                for (label, s) in &rows {
                    let ratio = s.err() / oidn_mean_err;
                    let mut goals = String::new();
                    if label == RAW_DEFAULT {
                        let mean = rows
                            .iter()
                            .find(|(l, _)| l == PLAIN_MEAN)
                            .expect("a mean row");
                        let r = s.err() / mean.1.err();
                        goals = format!(
                            "relMSE<=mean's: {}",
                            raw_goal.check(r <= 1.0, &format!("{row} {r:.2}x the mean's"))
                        );
                    }
                    if label.ends_with("(default)") {
                        let e = s.energy();
                        goals = format!(
                            "ratio<=1: {}  |energy|<=2%: {}",
                            ratio_goal.check(ratio <= 1.0, &format!("{row} {ratio:.2}x")),
                            energy_goal
                                .check(e.abs() <= 0.02, &format!("{row} {:+.2} %", 100.0 * e))
                        );
                    }
                    println!(
                        "{:<10} {:>6} {:>2} {:<5} {:<38} {:>9.5} {:>7.3} {:>+8.2}%  {goals}",
                        scene.name,
                        format!("{passes}x{spp}"),
                        runs.len(),
                        guide,
                        label,
                        s.err(),
                        ratio,
                        100.0 * s.energy(),
                    );
                }
            }
        }
    }
    println!("goals of splatd's default design on farm passes:");
    ratio_goal.report("relMSE <= OIDN(mean)'s");
    energy_goal.report("energy within 2 % of OIDN(mean)'s");
    println!("goal of splatd's raw default on farm passes:");
    raw_goal.report("relMSE <= the plain mean's (not denoised)");
    Ok(())
}

/// The DENOISED table (see the module docs), after the raw one in the same run.
fn denoised_table(scenes: &[Scene]) -> Result<()> {
    let oidn = match Oidn::load() {
        Ok(oidn) => oidn,
        Err(e) => {
            println!(
                "\nDENOISED: skipped, OIDN not loaded ({e}); SPLATD_OIDN_LIB=$(bash tests/setup/oidn.sh)"
            );
            return Ok(());
        }
    };
    println!(
        "\nDENOISED: OIDN {} (hdr, quality default, guides not clean), {}; relMSE and energy \
         (vs OIDN(mean) of the same realization and guide) are means over the realizations; \
         ratio = relMSE / best denoised anchor (*); default design {}",
        oidn.version(),
        oidn.path().display(),
        DEFAULT_DENOISE_DESIGN.name()
    );
    for scene in scenes {
        if let Some(noise) = scene.gt_noise {
            println!(
                "  {}: the ground truth's own relMSE is about {noise:.5} (a floor under every row)",
                scene.name
            );
        }
    }
    println!(
        "{:<10} {:>4} {:<5} {:<46} {:>9} {:>7} {:>9}  goals of the default",
        "scene", "spp", "guide", "estimator", "relMSE", "ratio", "energy"
    );
    let (mut ratio_goal, mut energy_goal) = (Goal::default(), Goal::default());
    let layout = CascadeLayout::with_defaults();
    for scene in scenes {
        let states: Vec<Vec<FrameState>> = scene
            .runs
            .iter()
            .map(|run| states(scene, run, &layout))
            .collect();
        denoised_rows(scene, &states, &oidn, &mut ratio_goal, &mut energy_goal)?;
    }
    println!("* = anchor; denoised goals of splatd's default design:");
    ratio_goal.report("relMSE <= 0.8x the best denoised anchor (every spp and guide)");
    energy_goal.report("energy within 2 % of OIDN(mean)'s at 64 and 256 spp");
    Ok(())
}

/// The CONVERGENCE table's frames, as (passes, spp of each pass): farm passes of 64 and 16
/// spp, and 1-spp passes as a streaming renderer sends them, up to the 256 spp of a run.
fn verdict_rows() -> Vec<(usize, usize)> {
    let mut rows = Vec::new();
    for spp in [64, 16, 1] {
        rows.extend(
            std::iter::successors(Some(1), |p| Some(p * 2))
                .take_while(|p| p * spp <= SPPS[2])
                .map(|p| (p, spp)),
        );
    }
    rows
}

/// The CONVERGENCE table (`--verdict-only`, or last): what `GET /v1/frames/{id}` would say of
/// each frame of the verdict rows ([`verdict_rows`]), with the default resolve and threshold
/// (`removed_fraction`, `deficit_fraction`, `converged` in how many realizations), beside the
/// relMSE of the plain mean and of the raw default, and that relMSE over the raw default's at
/// 256 spp of the same kind of pass (how much the rest of a 256-spp budget would still give).
/// A verdict is `--until-converged`'s stop: the frame a farm ships. No goal is printed: the
/// table shows where the verdict falls; the unit tests of `need.rs` hold its rule.
fn verdict_table(scenes: &[Scene]) -> Result<()> {
    use splatd_estimator::{NeedMap, DEFAULT_CONVERGED_BELOW, DEFAULT_NEED_TILE};
    let defaults = ResolveParams::with_defaults();
    println!(
        "\nCONVERGENCE: the verdict of GET /v1/frames/{{id}} (default resolve, converged_below \
         {DEFAULT_CONVERGED_BELOW}, own_count_from {}) on frames of P passes of S spp; means \
         over the realizations",
        defaults.own_count_from()
    );
    println!(
        "{:<10} {:>6} {:>9} {:>9} {:>9} {:>9} {:>9} {:>11}",
        "scene", "PxS", "removed", "deficit", "converged", "mean", "raw", "raw/at 256"
    );
    for scene in scenes {
        let n = scene.runs.len();
        let mut rows = Vec::new();
        for (passes, spp) in verdict_rows() {
            let (mut removed, mut deficit, mut converged) = (0.0, 0.0, 0);
            let (mut mean, mut raw) = (0.0, 0.0);
            for run in &scene.runs {
                let state = farm_state(scene, run, passes, spp);
                let resolved = state.resolve(&defaults);
                let c = NeedMap::build(&[&state], &resolved, &defaults, DEFAULT_NEED_TILE)?
                    .convergence(&defaults);
                removed += c.removed_fraction / n as f64;
                deficit += c.deficit_fraction / n as f64;
                converged += usize::from(c.converged(DEFAULT_CONVERGED_BELOW));
                mean += rel_mse(&resolved.mean, &scene.gt) / n as f64;
                raw += rel_mse(&resolved.reweighted, &scene.gt) / n as f64;
            }
            rows.push((passes, spp, removed, deficit, converged, mean, raw));
        }
        for &(passes, spp, removed, deficit, converged, mean, raw) in &rows {
            let full = rows
                .iter()
                .find(|r| r.1 == spp && r.0 * r.1 == SPPS[2])
                .map_or(f64::NAN, |r| r.6);
            println!(
                "{:<10} {:>6} {:>8.2}% {:>8.2}% {:>7}/{n} {:>9.5} {:>9.5} {:>10.2}x",
                scene.name,
                format!("{passes}x{spp}"),
                100.0 * removed,
                100.0 * deficit,
                converged,
                mean,
                raw,
                raw / full
            );
        }
    }
    Ok(())
}
