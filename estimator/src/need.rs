//! Where a frame needs samples, and whether it needs any more: the need map and the convergence
//! figures, computed from a resolve and the state it came from.
//!
//! The frame is cut into square tiles of `tile` pixels (the last column and row of tiles may be
//! smaller). For every tile the map adds up, over its pixels `p` with `N_p` samples,
//!
//! * `mean` = `Σ_p L(mean_p)`, the luminance of the plain mean;
//! * `removed` = `Σ_p L(removed_p)`, the luminance the resolve took out as fireflies;
//! * `deficit` = `Σ_p Σ_j u_j(p) L(B_j(p)) / N_p`, the luminance of the bands that lack support,
//!   where `u_j = clamp(1 - (n_j - kappa_min) / kappa(N_p), 0, 1)` is how far band `j`'s own
//!   support `n_j = count_{j-1} + count_j + count_{j+1}` falls short of full weight from the
//!   count term (see docs/ALGORITHM.md). Unlike `removed`, it ignores the value term and the
//!   3x3 pool: it says which bands of this pixel are still thinly sampled, even where the resolve
//!   kept their energy because the pixel is bright enough;
//! * `samples`, `spp_min`, and `empty`, the pixels without any sample.
//!
//! and scores it:
//!
//! `need = (removed / mean + deficit / mean + empty / pixels) / (samples / pixels + 1)`
//!
//! (the fractions are 0 when `mean` is 0). The numerator is the share of the tile's energy in
//! doubt (removed or unsupported) plus the share of its pixels not seen at all, each in
//! `[0, 1]`; dividing by the tile's spp after one more pass makes it a gain per sample: a tile
//! with the same doubt and twice the samples needs them half as much. Tiles with the highest
//! need are where the next samples help most; [`NeedMap::plan`] spreads a sample budget over
//! tiles in proportion to its square root.
//!
//! The frame's convergence ([`Convergence`]) is the sum over tiles: the removed energy as a
//! fraction of the mean's, which falls toward 0 as samples accumulate (the estimator is
//! consistent), and the spp spread.

use crate::layout::{CascadeLayout, ParamError, COUNT_ONE, MAX_CASCADES};
use crate::resolve::{Rect, ResolveParams, Resolved, TilingError};
use crate::state::{cascade_units, cell_len, FrameState};

/// Default edge of a need-map tile, in pixels: 16x16 tiles give a 1080p frame 120x68 tiles,
/// coarse enough to ship as JSON every second and fine enough to steer crop windows.
pub const DEFAULT_NEED_TILE: u32 = 16;
/// Largest tile edge accepted.
pub const MAX_NEED_TILE: u32 = 4096;
/// Doubt a guided worker gives every tile beyond the map's score before it plans
/// ([`NeedMap::with_base_doubt`]).
pub const DEFAULT_BASE_DOUBT: f64 = 0.5;
/// Share of each guided round a worker renders as uniform passes (every pixel once per pass)
/// before it plans the rest of the round on the need map.
pub const DEFAULT_UNIFORM_SHARE: f64 = 0.25;
/// Default convergence threshold: a frame is converged once the resolve removes at most this
/// fraction of the mean's energy (1 %) and every pixel has samples.
pub const DEFAULT_CONVERGED_BELOW: f64 = 0.01;

/// Checks a need-map tile edge: `1..=MAX_NEED_TILE`.
pub fn check_tile(tile: u32) -> Result<u32, ParamError> {
    if (1..=MAX_NEED_TILE).contains(&tile) {
        Ok(tile)
    } else {
        Err(ParamError::new(
            "tile",
            format!("must be between 1 and {MAX_NEED_TILE} pixels, got {tile}"),
        ))
    }
}

/// Checks a convergence threshold: a fraction of the mean's energy in `(0, 1]`.
pub fn check_converged_below(threshold: f64) -> Result<f64, ParamError> {
    if threshold.is_finite() && threshold > 0.0 && threshold <= 1.0 {
        Ok(threshold)
    } else {
        Err(ParamError::new(
            "converged_below",
            format!(
                "must be a fraction of the mean's energy in (0, 1], got {threshold}; \
                 the default is {DEFAULT_CONVERGED_BELOW}"
            ),
        ))
    }
}

/// One tile of a [`NeedMap`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TileNeed {
    /// Left column of the tile.
    pub x: u32,
    /// Top row of the tile.
    pub y: u32,
    /// Width in pixels (the last column of tiles may be narrower).
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Samples in the tile.
    pub samples: u64,
    /// Fewest samples of a pixel of the tile.
    pub spp_min: u64,
    /// Most samples of a pixel of the tile.
    pub spp_max: u64,
    /// Pixels without samples.
    pub empty: u64,
    /// `Σ_p L(mean_p)`.
    pub mean: f64,
    /// `Σ_p L(removed_p)`; negative where the `spread` resolve gave the tile more energy from
    /// its neighbours than it removed.
    pub removed: f64,
    /// `Σ_p Σ_j u_j L(B_j) / N_p` (see the module docs).
    pub deficit: f64,
    /// The tile's need (see the module docs).
    pub need: f64,
}

impl TileNeed {
    /// Pixels in the tile.
    pub fn pixels(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// Mean samples per pixel.
    pub fn spp_mean(&self) -> f64 {
        self.samples as f64 / self.pixels().max(1) as f64
    }

    /// `removed / mean` (0 for a black tile, and for a tile that received more energy than it
    /// removed: it is in no doubt, and a need must not go negative).
    pub fn removed_fraction(&self) -> f64 {
        fraction(self.removed.max(0.0), self.mean)
    }

    /// `deficit / mean` (0 for a black tile).
    pub fn deficit_fraction(&self) -> f64 {
        fraction(self.deficit, self.mean)
    }

    fn score(&self) -> f64 {
        let empty = self.empty as f64 / self.pixels().max(1) as f64;
        (self.removed_fraction() + self.deficit_fraction() + empty) / (self.spp_mean() + 1.0)
    }
}

fn fraction(part: f64, whole: f64) -> f64 {
    if whole > 0.0 {
        part / whole
    } else {
        0.0
    }
}

/// Whole-frame convergence figures (the sums of a [`NeedMap`]'s tiles).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Convergence {
    /// Samples in the frame.
    pub samples: u64,
    /// Fewest samples of any pixel.
    pub spp_min: u64,
    /// Mean samples per pixel.
    pub spp_mean: f64,
    /// Most samples of any pixel.
    pub spp_max: u64,
    /// Removed luminance as a fraction of the mean's (0 for a black frame).
    pub removed_fraction: f64,
    /// Luminance in bands lacking support, as a fraction of the mean's.
    pub deficit_fraction: f64,
    /// The fewest samples from which the resolve judges a pixel by its own samples alone
    /// ([`ResolveParams::own_count_from`] of the parameters the figures were made with).
    pub own_count_from: u64,
}

impl Convergence {
    /// Whether the frame has converged at `threshold`: every pixel has samples, the resolve
    /// removes at most `threshold` of the mean's energy, and, while some pixel has fewer than
    /// [`Convergence::own_count_from`] samples, the bands short of their own support hold at
    /// most `threshold` of it too (`deficit_fraction`).
    ///
    /// The last condition is why a farm's first passes never read converged. Below
    /// `own_count_from` samples the resolve counts a band by what the pixel's neighbours agree
    /// on ([`ResolveParams::own_count_from`]), so it removes little from a frame of one sample
    /// a pixel however noisy that frame is. Judged on the removed energy alone, the quality
    /// benchmark's scenes read converged after one or two passes of 64 spp: the small-light
    /// scene at 0.27 relMSE, 4x what four passes give. The deficit asks each pixel's own
    /// samples: it is 1 at one sample a pixel and falls as passes come. The quality benchmark's
    /// smooth scene now reads converged after eight passes, those with small lights after
    /// sixteen (docs/ALGORITHM.md, "Convergence").
    pub fn converged(&self, threshold: f64) -> bool {
        self.verdict(threshold) == Verdict::Converged
    }

    /// Whether the frame has converged at `threshold`, and if not, the first of the conditions
    /// of [`Convergence::converged`] it fails: what a farm is waiting on.
    pub fn verdict(&self, threshold: f64) -> Verdict {
        // A figure that is not a number is not within the threshold: it fails its condition.
        let within = |fraction: f64| fraction <= threshold;
        if self.spp_min == 0 {
            Verdict::PixelsWithoutSamples
        } else if !within(self.removed_fraction) {
            Verdict::RemovedEnergy
        } else if self.spp_min < self.own_count_from && !within(self.deficit_fraction) {
            Verdict::OwnSamples
        } else {
            Verdict::Converged
        }
    }
}

/// A frame's verdict at a threshold ([`Convergence::verdict`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Every condition holds.
    Converged,
    /// Some pixel has no samples.
    PixelsWithoutSamples,
    /// The resolve removes more than the threshold of the mean's energy.
    RemovedEnergy,
    /// The removed energy is below the threshold, but some pixel has fewer than
    /// [`Convergence::own_count_from`] samples and the bands short of their own support hold
    /// more than the threshold of the energy (`deficit_fraction`).
    OwnSamples,
}

/// Tiles of a frame scored by how much they would gain from more samples.
#[derive(Debug, Clone, PartialEq)]
pub struct NeedMap {
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Tile edge in pixels.
    pub tile: u32,
    /// Tiles per row.
    pub tiles_x: u32,
    /// Rows of tiles.
    pub tiles_y: u32,
    /// Row-major tiles.
    pub tiles: Vec<TileNeed>,
}

/// Fewest pixels to make again for which [`NeedMap::build_on`] starts threads.
const MIN_THREAD_PIXELS: u64 = 1 << 16;

impl NeedMap {
    /// The need map of a frame held as `bands` (as for [`crate::resolve_bands`]) whose resolve
    /// with `params` is `resolved`, in tiles of `tile` pixels.
    pub fn build(
        bands: &[&FrameState],
        resolved: &Resolved,
        params: &ResolveParams,
        tile: u32,
    ) -> Result<NeedMap, NeedError> {
        Self::build_on(bands, resolved, params, tile, 1)
    }

    /// [`NeedMap::build`] on `threads` threads, rows of tiles each: the same map for any number
    /// (each tile's sums are added by one thread, in the same order).
    pub fn build_on(
        bands: &[&FrameState],
        resolved: &Resolved,
        params: &ResolveParams,
        tile: u32,
        threads: usize,
    ) -> Result<NeedMap, NeedError> {
        let tile = check_tile(tile)?;
        let rows = rows_of(bands, resolved)?;
        let (width, height) = (resolved.width, resolved.height);
        let (tiles_x, tiles_y) = (width.div_ceil(tile), height.div_ceil(tile));
        let mut map = NeedMap {
            width,
            height,
            tile,
            tiles_x,
            tiles_y,
            tiles: vec![TileNeed::default(); (tiles_x * tiles_y) as usize],
        };
        let all = vec![true; map.tiles.len()];
        map.fill(&rows, bands[0].layout(), resolved, params, &all, threads);
        Ok(map)
    }

    /// Brings the map up to date after the cells and the resolved pixels of the frame changed
    /// only within `areas` (what [`crate::reached_by`] gives for the changed cells): the tiles
    /// that meet them are made again, and the map is the one [`NeedMap::build_on`] gives,
    /// in every bit. Returns the number of tiles made again. A frame of another size is refused.
    pub fn update(
        &mut self,
        bands: &[&FrameState],
        resolved: &Resolved,
        params: &ResolveParams,
        areas: &[Rect],
        threads: usize,
    ) -> Result<usize, NeedError> {
        let rows = rows_of(bands, resolved)?;
        if (resolved.width, resolved.height) != (self.width, self.height) {
            return Err(TilingError(format!(
                "a {}x{} frame's map cannot be brought up to a {}x{} frame",
                self.width, self.height, resolved.width, resolved.height
            ))
            .into());
        }
        let mut stale = vec![false; self.tiles.len()];
        let tile = self.tile;
        for a in areas.iter().filter(|a| !a.is_empty()) {
            let (x1, y1) = (a.x1.min(self.width), a.y1.min(self.height));
            if a.x0 >= x1 || a.y0 >= y1 {
                continue;
            }
            for ty in a.y0 / tile..y1.div_ceil(tile) {
                for tx in a.x0 / tile..x1.div_ceil(tile) {
                    stale[(ty * self.tiles_x + tx) as usize] = true;
                }
            }
        }
        self.fill(&rows, bands[0].layout(), resolved, params, &stale, threads);
        Ok(stale.iter().filter(|&&s| s).count())
    }

    /// Computes the tiles marked in `which` again from the cells (`rows`, one per pixel row)
    /// and the resolved layers, rows of tiles split between up to `threads` threads.
    fn fill(
        &mut self,
        rows: &[&[u64]],
        layout: &CascadeLayout,
        resolved: &Resolved,
        params: &ResolveParams,
        which: &[bool],
        threads: usize,
    ) {
        let tiles_x = self.tiles_x as usize;
        let stale = which.iter().filter(|&&s| s).count();
        if stale == 0 {
            return;
        }
        let kappas = params.kappa_table();
        let geometry = Geometry {
            width: self.width,
            height: self.height,
            tile: self.tile,
            tiles_x: self.tiles_x,
        };
        let job = |first_row: usize, tiles: &mut [TileNeed], which: &[bool]| {
            for (i, (t, &stale)) in tiles.iter_mut().zip(which).enumerate() {
                if stale {
                    *t = geometry.empty(first_row * tiles_x + i);
                }
            }
            for (r, (tiles, which)) in tiles
                .chunks_mut(tiles_x)
                .zip(which.chunks(tiles_x))
                .enumerate()
            {
                let ty = (first_row + r) as u32;
                add_tile_row(
                    rows, layout, resolved, params, &kappas, &geometry, ty, tiles, which,
                );
            }
        };
        // Threads only for work worth one (a patch's few tiles are done here).
        let pixels = stale as u64 * u64::from(self.tile).pow(2);
        let threads = if pixels < MIN_THREAD_PIXELS {
            1
        } else {
            threads.max(1)
        };
        let per = (self.tiles_y as usize).div_ceil(threads).max(1);
        if threads == 1 {
            job(0, &mut self.tiles, which);
        } else {
            std::thread::scope(|scope| {
                for (c, (tiles, which)) in self
                    .tiles
                    .chunks_mut(per * tiles_x)
                    .zip(which.chunks(per * tiles_x))
                    .enumerate()
                {
                    let job = &job;
                    scope.spawn(move || job(c * per, tiles, which));
                }
            });
        }
        for (t, _) in self.tiles.iter_mut().zip(which).filter(|(_, &s)| s) {
            t.need = t.score();
        }
    }

    /// The whole frame's figures, for a map built with `params`.
    pub fn convergence(&self, params: &ResolveParams) -> Convergence {
        let (mut mean, mut removed, mut deficit) = (0.0, 0.0, 0.0);
        let mut c = Convergence {
            spp_min: u64::MAX,
            own_count_from: params.own_count_from(),
            ..Convergence::default()
        };
        for t in &self.tiles {
            c.samples += t.samples;
            c.spp_min = c.spp_min.min(t.spp_min);
            c.spp_max = c.spp_max.max(t.spp_max);
            mean += t.mean;
            removed += t.removed;
            deficit += t.deficit;
        }
        if self.tiles.is_empty() {
            c.spp_min = 0;
        }
        let pixels = u64::from(self.width) * u64::from(self.height);
        c.spp_mean = c.samples as f64 / pixels.max(1) as f64;
        c.removed_fraction = fraction(removed, mean);
        c.deficit_fraction = fraction(deficit, mean);
        c
    }

    /// Spreads a budget of `samples` over the tiles in proportion to the square root of their
    /// need: the number of passes (one sample for every pixel of the tile) each tile should get,
    /// row-major.
    ///
    /// The square root, as in the classic allocation of samples to strata in proportion to
    /// their standard deviation, was chosen by `bench need`: in proportion to the need itself,
    /// the smooth tiles of the demo scene were starved and its relMSE at 64 spp came out 2 %
    /// worse than uniform sampling, with the square root 3 % better.
    ///
    /// Every tile gets `floor(share / pixels)` passes of its share
    /// `samples * sqrt(need) / Σ sqrt(need)`;
    /// what is left goes one pass at a time to the tiles with the largest remainders that still
    /// fit, so the plan never spends more than `samples`. Without any need (a black or
    /// converged frame) the budget is spread evenly.
    pub fn plan(&self, samples: u64) -> Vec<u64> {
        let total: f64 = self.tiles.iter().map(|t| t.need.sqrt()).sum();
        let weight = |t: &TileNeed| {
            if total > 0.0 {
                t.need.sqrt() / total
            } else {
                t.pixels() as f64 / (u64::from(self.width) * u64::from(self.height)) as f64
            }
        };
        let mut passes = Vec::with_capacity(self.tiles.len());
        let mut left = samples;
        let mut remainders = Vec::with_capacity(self.tiles.len());
        for (i, t) in self.tiles.iter().enumerate() {
            let share = samples as f64 * weight(t) / t.pixels() as f64;
            let whole = (share.floor() as u64).min(left / t.pixels());
            left -= whole * t.pixels();
            passes.push(whole);
            remainders.push((share - whole as f64, i));
        }
        remainders.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        for (_, i) in remainders {
            let pixels = self.tiles[i].pixels();
            if pixels <= left {
                passes[i] += 1;
                left -= pixels;
            }
        }
        passes
    }
}

/// The tiling of a need map.
struct Geometry {
    width: u32,
    height: u32,
    tile: u32,
    tiles_x: u32,
}

impl Geometry {
    /// Tile `i` (row-major) with nothing added yet.
    fn empty(&self, i: usize) -> TileNeed {
        let (tx, ty) = (i as u32 % self.tiles_x, i as u32 / self.tiles_x);
        let (x, y) = (tx * self.tile, ty * self.tile);
        TileNeed {
            x,
            y,
            width: self.tile.min(self.width - x),
            height: self.tile.min(self.height - y),
            spp_min: u64::MAX,
            ..TileNeed::default()
        }
    }
}

/// Every row of cells of the frame held as `bands`, checked to be the frame `resolved` is of.
fn rows_of<'s>(bands: &[&'s FrameState], resolved: &Resolved) -> Result<Vec<&'s [u64]>, NeedError> {
    let (width, height, rows) = crate::resolve::frame_rows(bands)?;
    let pixels = width as usize * height as usize;
    if (width, height) != (resolved.width, resolved.height)
        || [
            resolved.spp.len(),
            resolved.mean.len(),
            resolved.removed.len(),
        ] != [pixels; 3]
    {
        return Err(TilingError(format!(
            "bands of a {width}x{height} frame do not belong to the resolved {}x{} frame",
            resolved.width, resolved.height
        ))
        .into());
    }
    Ok(rows)
}

/// Adds the pixels of the tiles of tile row `ty` marked in `which` to `tiles` (that row's
/// tiles), each tile's pixels row by row, left to right.
#[allow(clippy::too_many_arguments)]
fn add_tile_row(
    rows: &[&[u64]],
    layout: &CascadeLayout,
    resolved: &Resolved,
    params: &ResolveParams,
    kappas: &[f64],
    g: &Geometry,
    ty: u32,
    tiles: &mut [TileNeed],
    which: &[bool],
) {
    let k = layout.cascades();
    let len = cell_len(k);
    let one = 1.0 / COUNT_ONE as f64;
    let mut counts = [0.0f64; MAX_CASCADES as usize + 2];
    let y_end = ((ty + 1) * g.tile).min(g.height);
    for y in ty * g.tile..y_end {
        let row = rows[y as usize];
        for (t, _) in tiles.iter_mut().zip(which).filter(|(_, &s)| s) {
            for x in t.x..t.x + t.width {
                let cell = &row[x as usize * len..][..len];
                let i = (y * g.width + x) as usize;
                let n = resolved.spp[i];
                t.samples += n;
                t.spp_min = t.spp_min.min(n);
                t.spp_max = t.spp_max.max(n);
                if n == 0 {
                    t.empty += 1;
                    continue;
                }
                t.mean += layout.luminance(resolved.mean[i].map(f64::from));
                t.removed += layout.luminance(resolved.removed[i].map(f64::from));
                for j in 0..k {
                    counts[j + 1] = cell[4 * j + 3] as f64 * one;
                }
                let nf = n as f64;
                let kappa = match kappas.get(n as usize) {
                    Some(&kappa) => kappa,
                    None => params.kappa_at(nf),
                };
                let mut deficit = 0.0;
                for j in 0..k {
                    let support = counts[j] + counts[j + 1] + counts[j + 2];
                    let u = (1.0 - (support - params.kappa_min()) / kappa).clamp(0.0, 1.0);
                    if u > 0.0 {
                        let b = [0, 1, 2].map(|c| cascade_units(cell, j, c));
                        deficit += u * layout.luminance(b) * layout.unit_value(j);
                    }
                }
                t.deficit += deficit / nf;
            }
        }
    }
}

impl NeedMap {
    /// The map with `base / (spp + 1)` added to every tile's need, `spp` the tile's mean
    /// samples per pixel: the doubt every tile has that the score cannot see. The score counts
    /// energy removed as fireflies or in thinly supported bands, not plain Monte Carlo noise,
    /// which every tile has.
    ///
    /// Which is better depends on the scene. On the Mitsuba scenes of
    /// `benches/quality/guided.py` (a small light, caustics), planned on the score alone the
    /// light's tile kept its doubt and took nearly every sample, and guided sampling lost to
    /// uniform sampling everywhere; with [`DEFAULT_BASE_DOUBT`] and [`DEFAULT_UNIFORM_SHARE`]
    /// (the Mitsuba worker's defaults) it drew even. On the demo and synthetic scenes of
    /// `bench need`, whose doubt is spread over many tiles, the score alone does better
    /// (relMSE 0.92 to 0.97 of uniform against 0.94 to 1.03), so `splatd demo --guided` plans
    /// on the score alone.
    pub fn with_base_doubt(mut self, base: f64) -> NeedMap {
        for t in &mut self.tiles {
            t.need += base / (t.spp_mean() + 1.0);
        }
        self
    }

    /// The pixels a [`NeedMap::plan`] asks for, once per pass: for each tile in order, its
    /// pixels row by row, repeated `plan[i]` times. A worker renders one sample of each.
    pub fn planned_pixels(&self, plan: &[u64]) -> Vec<(u32, u32)> {
        let mut out = Vec::new();
        for (t, &passes) in self.tiles.iter().zip(plan) {
            for _ in 0..passes {
                for y in t.y..t.y + t.height {
                    out.extend((t.x..t.x + t.width).map(|x| (x, y)));
                }
            }
        }
        out
    }
}

/// A need map that cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NeedError {
    /// The tile size is out of range.
    #[error(transparent)]
    Param(#[from] ParamError),
    /// The bands do not tile the resolved frame.
    #[error(transparent)]
    Tiling(#[from] TilingError),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::{CascadeLayout, REC709_LUMINANCE};
    use crate::resolve::{reached_by, resolve_bands, resolve_bands_into, resolve_region_into};

    /// A 2x1 frame with `c0 = 1`, so grey 0.5 lies wholly in cascade 0 with one count per
    /// sample: pixel A has 8 samples, pixel B has 2.
    fn two_pixels() -> FrameState {
        let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
        let mut state = FrameState::new(2, 1, layout);
        for _ in 0..8 {
            state.splat(0, 0, [0.5; 3]).unwrap();
        }
        for _ in 0..2 {
            state.splat(1, 0, [0.5; 3]).unwrap();
        }
        state
    }

    /// The paper's resolve with a fixed kappa of 4, as the hand computations below assume.
    fn params() -> ResolveParams {
        ResolveParams::new(crate::Variant::Paper, 4.0, 1.0, 0.0).unwrap()
    }

    fn map(state: &FrameState, tile: u32) -> NeedMap {
        let resolved = resolve_bands(&[state], &params(), 1).unwrap();
        NeedMap::build(&[state], &resolved, &params(), tile).unwrap()
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-6
    }

    #[test]
    fn scores_match_a_hand_computation() {
        // By hand, with kappa = 4 and kappa_min = 1:
        // A: support n_0 = 8, u_0 = clamp(1 - 7/4) = 0; the resolve keeps everything.
        // B: own support 2, u_0 = 1 - 1/4 = 0.75, deficit 0.75 * L(B_0) / N = 0.75 * 0.5.
        //    Pooled over the clamped 3x3 (columns A, B, B), every sample of the neighbourhood is
        //    in band 0. B has fewer samples than full weight needs (kappa + kappa_min = 5); the
        //    resolve counts it as 10, twice that (`support_samples`; the cap, kappa_min
        //    times the 36 samples of the neighbourhood, is above): n̄ = 10 * 36 / 36 = 10 and
        //    w_0 = min(1, (10 - 1)/4) = 1, nothing removed. The deficit stays: B's own bands are short
        //    of samples, which is what the need map asks more of.
        let state = two_pixels();
        let per_pixel = map(&state, 1);
        assert_eq!((per_pixel.tiles_x, per_pixel.tiles_y), (2, 1));
        let [a, b] = [per_pixel.tiles[0], per_pixel.tiles[1]];
        assert!(close(a.mean, 0.5) && close(a.removed, 0.0) && close(a.deficit, 0.0));
        assert_eq!((a.samples, a.spp_min, a.empty), (8, 8, 0));
        assert!(close(a.need, 0.0), "{a:?}");
        assert!(close(b.mean, 0.5) && close(b.removed, 0.0) && close(b.deficit, 0.375));
        // (0/0.5 + 0.375/0.5 + 0) / (2 + 1)
        assert!(close(b.need, 0.25), "{b:?}");

        let whole = map(&state, 2);
        assert_eq!(whole.tiles.len(), 1);
        let t = whole.tiles[0];
        assert_eq!(
            (t.width, t.height, t.samples, t.spp_min, t.spp_max),
            (2, 1, 10, 2, 8)
        );
        // (0/1 + 0.375/1) / (10/2 + 1)
        assert!(close(t.need, 0.0625), "{t:?}");
        let c = whole.convergence(&params());
        assert_eq!((c.samples, c.spp_min, c.spp_max), (10, 2, 8));
        assert!(close(c.spp_mean, 5.0) && close(c.removed_fraction, 0.0));
        assert!(close(c.deficit_fraction, 0.375));
    }

    /// With `kappa` growing with `N`, a pixel's deficit uses its own `kappa(N)`, looked up or
    /// computed: two samples in a firefly's band, beside `N - 2` dim ones, for `N` on each side
    /// of the lookup table's end.
    #[test]
    fn deficits_use_each_pixels_kappa_of_n() {
        let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
        let params = ResolveParams::new(crate::Variant::Paper, 3.0, 1.0, 0.3).unwrap();
        let len = cell_len(6);
        for n in [40u64, 999, 1000, 1023, 1024, 1025, 1500] {
            let mut cell = vec![0u64; len];
            // `n - 2` samples in band 0, two in band 4 (its neighbours' bands empty).
            cell[0..4].copy_from_slice(&[n << 20, n << 20, n << 20, (n - 2) * COUNT_ONE]);
            cell[16..20].copy_from_slice(&[3 << 20, 3 << 20, 3 << 20, 2 * COUNT_ONE]);
            let state = FrameState::from_cells(1, 1, 0..1, layout.clone(), cell).unwrap();
            let resolved = resolve_bands(&[&state], &params, 1).unwrap();
            let map = NeedMap::build(&[&state], &resolved, &params, 1).unwrap();
            // By hand: band 4's support is its own 2 samples, `u = 1 - (2 - 1) / kappa(n)`.
            let nf = n as f64;
            let kappa = 3.0 * nf.powf(0.3);
            let u = (1.0 - 1.0 / kappa).clamp(0.0, 1.0);
            let b4 = layout.luminance([(3u64 << 20) as f64; 3]) * layout.unit_value(4);
            let expected = u * b4 / nf;
            let deficit = map.tiles[0].deficit;
            assert!(
                (deficit - expected).abs() <= 1e-12 * expected,
                "n {n}: deficit {deficit}, by hand {expected}"
            );
        }
    }

    /// A frame of `w` x `h` pixels, a firefly scene's `passes` passes, held as `bands` bands.
    fn firefly_bands(w: u32, h: u32, passes: u64, bands: u32) -> (FrameState, Vec<FrameState>) {
        let scene = splatd_scenes::synth::FireflyScene::new(w, h, 11);
        let mut state = FrameState::new(w, h, CascadeLayout::with_defaults());
        for pass in 0..passes {
            state.splat_all(scene.pass(pass));
        }
        let mut held = FrameState::bands(w, h, bands, state.layout());
        for band in &mut held {
            band.merge_overlap(&state).unwrap();
        }
        (state, held)
    }

    /// The map is the same, to the last bit, whatever the number of threads (the frame is
    /// large enough for threads to be used) and however the frame is split into bands.
    #[test]
    fn a_map_is_the_same_on_any_number_of_threads() {
        let (w, h) = (320, 240);
        assert!(
            w * h >= MIN_THREAD_PIXELS as u32,
            "large enough for threads"
        );
        let (state, bands) = firefly_bands(w, h, 2, 5);
        let bands: Vec<&FrameState> = bands.iter().collect();
        let params = ResolveParams::with_defaults();
        let resolved = resolve_bands(&[&state], &params, 1).unwrap();
        let one = NeedMap::build(&[&state], &resolved, &params, DEFAULT_NEED_TILE).unwrap();
        assert!(one.tiles.iter().any(|t| t.deficit > 0.0 && t.removed > 0.0));
        for threads in [2, 3, 7] {
            let many =
                NeedMap::build_on(&bands, &resolved, &params, DEFAULT_NEED_TILE, threads).unwrap();
            assert!(many == one, "{threads} threads");
            let odd = NeedMap::build_on(&bands, &resolved, &params, 7, threads).unwrap();
            assert!(odd == NeedMap::build(&[&state], &resolved, &params, 7).unwrap());
        }
    }

    /// After batches in a few places, the map brought up to date over the pixels the changes
    /// reach is the map built afresh, whether the resolve was patched or made whole, and only
    /// the tiles there were made again.
    #[test]
    fn an_updated_map_is_the_map_built_afresh() {
        let (w, h) = (320, 240);
        let (mut state, _) = firefly_bands(w, h, 2, 1);
        let params = ResolveParams::with_defaults();
        let mut resolved = resolve_bands(&[&state], &params, 1).unwrap();
        let mut map =
            NeedMap::build_on(&[&state], &resolved, &params, DEFAULT_NEED_TILE, 2).unwrap();
        let changes = [
            vec![Rect::pixel(5, 7)],
            vec![Rect::new(100, 50, 140, 60), Rect::pixel(319, 239)],
            vec![Rect::new(200, 0, 201, 240)],
            vec![Rect::new(300, 200, 400, 300)],
        ];
        for (round, rects) in changes.iter().enumerate() {
            for r in rects {
                for y in r.y0..r.y1.min(h) {
                    for x in r.x0..r.x1.min(w) {
                        let v = 0.1 + (x * 7 + y * 3 + round as u32) as f32 % 5.0;
                        state.splat(x, y, [v * 900.0, v, v]).unwrap();
                    }
                }
            }
            // Patched, or (every other round) resolved whole: outside what the change reaches
            // the outputs are the same bits either way.
            if round % 2 == 0 {
                resolve_region_into(&[&state], &params, 2, rects, &mut resolved).unwrap();
            } else {
                resolve_bands_into(&[&state], &params, 2, &mut resolved).unwrap();
            }
            let mut areas = reached_by(&params, rects, w, h);
            // More than the change reaches, past the frame's corner too: those tiles are made
            // again to the same figures.
            areas.push(Rect::new(w - 5, h - 5, w + 50, h + 50));
            let made = map
                .update(&[&state], &resolved, &params, &areas, 2)
                .unwrap();
            assert!(
                made > 0 && made < map.tiles.len() / 2,
                "round {round}: {made} tiles"
            );
            let fresh = NeedMap::build(&[&state], &resolved, &params, DEFAULT_NEED_TILE).unwrap();
            assert!(map == fresh, "round {round}");
            assert_eq!(map.convergence(&params), fresh.convergence(&params));
        }
        let other = FrameState::new(w, h + 1, state.layout().clone());
        let resolved_other = resolve_bands(&[&other], &params, 1).unwrap();
        assert!(matches!(
            map.update(&[&other], &resolved_other, &params, &[], 1),
            Err(NeedError::Tiling(_))
        ));
    }

    #[test]
    fn a_frame_is_converged_only_when_little_enough_energy_is_removed() {
        // The two pixels, and a firefly in A that no neighbour supports: the resolve removes
        // nearly all of it, and it is nearly all of the frame's energy.
        let mut state = two_pixels();
        state.splat(0, 0, [5000.0; 3]).unwrap();
        let c = map(&state, 2).convergence(&params());
        assert!(c.removed_fraction > 0.9, "{c:?}");
        assert!(!c.converged(0.5) && c.converged(1.0), "{c:?}");
    }

    /// The default parameters' figures of an 8x8 frame in which every pixel took `passes`
    /// samples: grey, but `bright` of them 256, three cascades up.
    fn farm_frame(passes: usize, bright: usize) -> Convergence {
        let params = ResolveParams::with_defaults();
        let mut state = FrameState::new(8, 8, CascadeLayout::with_defaults());
        for pass in 0..passes {
            let v = if pass < bright { 256.0 } else { 0.5 };
            state.splat_all((0..64).map(|i| (i % 8, i / 8, [v; 3])));
        }
        let resolved = resolve_bands(&[&state], &params, 1).unwrap();
        NeedMap::build(&[&state], &resolved, &params, 4)
            .unwrap()
            .convergence(&params)
    }

    #[test]
    fn a_farms_first_passes_are_converged_only_when_each_pixels_own_samples_agree() {
        assert_eq!(ResolveParams::with_defaults().own_count_from(), 16);
        // One pass: the resolve keeps everything, since every neighbour agrees, but one
        // sample a pixel supports nothing on its own.
        let one = farm_frame(1, 0);
        assert!(one.removed_fraction <= 0.01, "{one:?}");
        assert!(one.deficit_fraction > 0.99, "{one:?}");
        assert!(!one.converged(0.01), "{one:?}");
        // Eight passes of grey: eight samples in one band are full support on their own.
        let grey = farm_frame(8, 0);
        assert!(
            grey.deficit_fraction <= 0.01 && grey.converged(0.01),
            "{grey:?}"
        );
        // Eight passes, half of them bright: every neighbour holds the bright band as well, so
        // the resolve keeps it, but four samples are short of full support on their own.
        let split = farm_frame(8, 4);
        assert!(split.removed_fraction <= 0.01, "{split:?}");
        assert!(split.deficit_fraction > 0.1, "{split:?}");
        assert!(!split.converged(0.01), "{split:?}");
        // From `own_count_from` samples the resolve counts each pixel's own, and its removed
        // energy is the verdict (the deficit also ignores the value term and the pool).
        let own = Convergence {
            spp_min: 16,
            removed_fraction: 0.005,
            deficit_fraction: 0.3,
            own_count_from: 16,
            ..Convergence::default()
        };
        assert!(own.converged(0.01));
        assert!(!Convergence { spp_min: 15, ..own }.converged(0.01));
    }

    #[test]
    fn the_verdict_names_the_first_condition_a_frame_fails() {
        let done = Convergence {
            spp_min: 4,
            removed_fraction: 0.005,
            deficit_fraction: 0.005,
            own_count_from: 16,
            ..Convergence::default()
        };
        let at = |c: Convergence| c.verdict(0.01);
        assert_eq!(at(done), Verdict::Converged);
        // Each condition alone, then all at once: the first one named, in the order of
        // `converged`'s rule.
        assert_eq!(
            at(Convergence { spp_min: 0, ..done }),
            Verdict::PixelsWithoutSamples
        );
        assert_eq!(
            at(Convergence {
                removed_fraction: 0.02,
                ..done
            }),
            Verdict::RemovedEnergy
        );
        assert_eq!(
            at(Convergence {
                deficit_fraction: 0.02,
                ..done
            }),
            Verdict::OwnSamples
        );
        assert_eq!(
            at(Convergence {
                spp_min: 0,
                removed_fraction: 0.02,
                deficit_fraction: 0.02,
                ..done
            }),
            Verdict::PixelsWithoutSamples
        );
        assert_eq!(
            at(Convergence {
                removed_fraction: 0.02,
                deficit_fraction: 0.02,
                ..done
            }),
            Verdict::RemovedEnergy
        );
        // From `own_count_from` samples the deficit no longer counts; a figure that is not a
        // number fails its condition.
        let many = Convergence {
            spp_min: 16,
            deficit_fraction: 0.5,
            ..done
        };
        assert_eq!(at(many), Verdict::Converged);
        assert_eq!(
            at(Convergence {
                removed_fraction: f64::NAN,
                ..many
            }),
            Verdict::RemovedEnergy
        );
        assert_eq!(
            at(Convergence {
                deficit_fraction: f64::NAN,
                ..done
            }),
            Verdict::OwnSamples
        );
        for c in [done, many, Convergence { spp_min: 0, ..done }] {
            assert_eq!(c.converged(0.01), at(c) == Verdict::Converged, "{c:?}");
        }
    }

    #[test]
    fn base_doubt_adds_a_share_per_sample_to_every_tile() {
        // Per pixel: A has 8 samples and no need, B has 2 and a need of 0.25 (above).
        let doubted = map(&two_pixels(), 1).with_base_doubt(0.5);
        assert!(
            close(doubted.tiles[0].need, 0.5 / 9.0),
            "{:?}",
            doubted.tiles[0]
        );
        assert!(
            close(doubted.tiles[1].need, 0.25 + 0.5 / 3.0),
            "{:?}",
            doubted.tiles[1]
        );
        // A tile in no doubt gets nothing of a plan on the score alone; with the base it gets
        // its share: 4 samples over square roots 0.2357 and 0.6455 are 1.07 and 2.93, floored
        // to 1 and 2, and the one left goes to the larger remainder, B's.
        assert_eq!(map(&two_pixels(), 1).plan(4), vec![0, 4]);
        assert_eq!(doubted.plan(4), vec![1, 3]);
    }

    #[test]
    fn empty_pixels_and_ragged_edges() {
        let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
        let mut state = FrameState::new(5, 3, layout);
        for _ in 0..9 {
            state.splat(0, 0, [0.5; 3]).unwrap();
        }
        let m = map(&state, 4);
        assert_eq!((m.tiles_x, m.tiles_y), (2, 1));
        let (left, right) = (m.tiles[0], m.tiles[1]);
        assert_eq!(
            (left.width, left.height, right.width, right.height),
            (4, 3, 1, 3)
        );
        assert_eq!((left.empty, right.empty), (11, 3));
        // Left: 9 samples on 12 pixels, one pixel fully supported: (0 + 0 + 11/12) / (9/12 + 1).
        assert!(close(left.need, (11.0 / 12.0) / (0.75 + 1.0)), "{left:?}");
        // Right: nothing at all: (0 + 0 + 1) / (0 + 1).
        assert!(close(right.need, 1.0));
        let c = m.convergence(&params());
        assert_eq!((c.spp_min, c.spp_max, c.samples), (0, 9, 9));
        assert!(
            !c.converged(1.0),
            "pixels without samples are never converged"
        );
    }

    #[test]
    fn a_plan_spends_at_most_the_budget_in_proportion_to_need() {
        let m = NeedMap {
            width: 4,
            height: 2,
            tile: 2,
            tiles_x: 2,
            tiles_y: 1,
            tiles: vec![
                TileNeed {
                    width: 2,
                    height: 2,
                    need: 9.0,
                    ..TileNeed::default()
                },
                TileNeed {
                    x: 2,
                    width: 2,
                    height: 2,
                    need: 1.0,
                    ..TileNeed::default()
                },
            ],
        };
        // 40 samples: square roots 3 and 1, shares 30 and 10, i.e. 7.5 and 2.5 passes of 4
        // pixels; floors 7 and 2 spend 36, the 4 left go to the first tile (remainders tie; the
        // earlier tile wins).
        assert_eq!(m.plan(40), [8, 2]);
        assert_eq!(m.plan(3), [0, 0], "less than one pass of any tile");
        let flat = NeedMap {
            tiles: m
                .tiles
                .iter()
                .map(|t| TileNeed { need: 0.0, ..*t })
                .collect(),
            ..m.clone()
        };
        assert_eq!(flat.plan(16), [2, 2], "no need: spread evenly");
        let pixels = m.planned_pixels(&[1, 2]);
        assert_eq!(pixels.len(), 12);
        assert_eq!(&pixels[..4], [(0, 0), (1, 0), (0, 1), (1, 1)]);
        assert_eq!(&pixels[4..8], [(2, 0), (3, 0), (2, 1), (3, 1)]);
        assert_eq!(pixels[4..8], pixels[8..]);
    }

    #[test]
    fn bad_tiles_and_bands_are_refused() {
        let state = two_pixels();
        let params = ResolveParams::with_defaults();
        let resolved = state.resolve(&params);
        for tile in [0, MAX_NEED_TILE + 1] {
            let err = NeedMap::build(&[&state], &resolved, &params, tile).unwrap_err();
            assert!(
                matches!(err, NeedError::Param(ref p) if p.name == "tile"),
                "{err}"
            );
        }
        let other = FrameState::new(3, 1, state.layout().clone());
        assert!(matches!(
            NeedMap::build(&[&other], &resolved, &params, 1),
            Err(NeedError::Tiling(_))
        ));
        assert!(check_converged_below(0.0).is_err());
        assert!(check_converged_below(f64::NAN).is_err());
        assert!(check_converged_below(1.5).is_err());
        assert_eq!(check_converged_below(DEFAULT_CONVERGED_BELOW), Ok(0.01));
    }

    #[test]
    fn need_falls_as_samples_accumulate() {
        let scene = splatd_scenes::synth::FireflyScene::new(32, 32, 3);
        let mut state = FrameState::new(32, 32, CascadeLayout::with_defaults());
        let mut fractions = Vec::new();
        for pass in 0..256 {
            state.splat_all(scene.pass(pass));
            if [7, 63, 255].contains(&pass) {
                let m = map(&state, 8);
                let c = m.convergence(&params());
                let need: f64 = m.tiles.iter().map(|t| t.need).sum();
                fractions.push((c.removed_fraction, need));
            }
        }
        assert!(
            fractions
                .windows(2)
                .all(|w| w[1].0 < w[0].0 && w[1].1 < w[0].1),
            "removed fraction and need fall from 8 to 64 to 256 spp: {fractions:?}"
        );
    }
}
