//! Incremental resolves: after a batch changed a few pixels' cells, only the pixels whose
//! output can change are resolved again, to the same bits as a resolve of the whole frame
//! (which stays the definition, and the tests' oracle).
//!
//! # How far a pixel's output reaches
//!
//! Distances are Chebyshev (`max(|dx|, |dy|)`), `m` is [`SpreadParams::max_radius`], neighbourhoods
//! are clamped to the frame.
//!
//! * **Paper and Shader** ([`Variant::Paper`], [`Variant::Shader`]): a pixel's weights use its own
//!   cell (its bands' sums, `N` and so `kappa(N)`, the value term's `F`) and the support counts
//!   and `N` of the 3x3 around it (the pooled support relative to `N`). Its four outputs depend
//!   on the cells within 1: `H = 1`.
//! * **Off** ([`Variant::Off`]): the plain mean, its own cell only: `H = 0`.
//! * **Spread** ([`Variant::Spread`]), the paper's outputs and then, per band `j`:
//!   1. a pixel's *support word* (its own support of band `j` with the neighbouring bands, and
//!      whether the band is solid there, from its own `kappa(N) + kappa_min` and `N`) reads its
//!      own cell only (not the 3x3 pool);
//!   2. a *source* `q` (where the paper removed energy of band `j`) and its removed energy depend
//!      on the cells within 1 of `q`;
//!   3. its *window*, the smallest radius `r <= m` whose box (clamped) holds `support`, stopped by
//!      a solid pixel in the box (the edge rule then reads `q`'s own word and `N`), reads the
//!      support words within `m` of `q`: so the window, and the event it adds, depend on the
//!      cells within `max(1, m) = m` of `q`, and the window covers pixels within `m` of `q`;
//!   4. the given-back energy of a pixel `p` is the tile-local prefix sum (`resolve_spread`'s
//!      `Grid`: tiles of [`GIVE_BACK_TILE`] pixels fixed to the frame, sums restarted at each
//!      tile, box sums of the supports exact) of the events whose windows meet `p`'s tile `t`,
//!      in source order (row by row, band by band within a row): those of the sources within
//!      `m` of `t`.
//!
//!   So the outputs of a tile `t` depend exactly on the cells within `2m` of `t` (a change at
//!   distance `2m` can decide a window of radius `m` that reaches `t`: the test
//!   `a_change_at_distance_two_max_radius_reaches_a_window` builds one), and a pixel's on the
//!   cells within `H = 2m + GIVE_BACK_TILE - 1` of it (its tile's far corner); without the
//!   tiles' rounding (in exact arithmetic) it would be `2m`. The order of a cell's additions
//!   is by the source's row, band and column, which a crop keeps (any two pixels of a crop are
//!   in the same row-major order as in the frame); nothing in the stage is frame-wide any more (box sums
//!   were `f64` sums from the frame's corner, and the give-back's prefix sums ran over the
//!   whole frame, both rounding by what lay far away: `resolve_spread`).
//!
//! # What is resolved again
//!
//! A changed rectangle `R` can change the outputs in `A = R ⊕ H` (Spread: the tiles meeting
//! `R ⊕ 2m`). `A` is resolved exactly by resolving the crop `C = A ⊕ H` (Spread: `A ⊕ 2m`;
//! clamped to the frame) as if it were a frame, with the give-back's tiles placed as in the
//! frame, and copying `A` back: within `C`, whatever reads past `C`'s cut edges (a 3x3 clamped
//! there, a window cut short, a source whose 3x3 is cut) lies within `H` (Spread: `2m`) of the
//! cut, and reaches no pixel of `A`; at the frame's own edges `C` clamps as the frame does.
//! The crop is read in place (each row's cells within `C`'s columns), not copied.

use super::{frame_rows, resolve_bands_with, resolve_rows, ResolveParams, Resolved, TilingError};
use super::{SpreadParams, Variant};
use crate::resolve_spread::GIVE_BACK_TILE;
use crate::state::{cell_len, FrameState, Kernel};

/// A rectangle of pixels: columns `x0..x1`, rows `y0..y1` (half-open; empty if either range
/// is).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub struct Rect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl Rect {
    /// Columns `x0..x1`, rows `y0..y1`.
    pub fn new(x0: u32, y0: u32, x1: u32, y1: u32) -> Self {
        Self { x0, y0, x1, y1 }
    }

    /// The one pixel `(x, y)`.
    pub fn pixel(x: u32, y: u32) -> Self {
        Self::new(x, y, x + 1, y + 1)
    }

    /// Whether it holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.x0 >= self.x1 || self.y0 >= self.y1
    }

    /// Its pixels.
    pub fn area(&self) -> u64 {
        if self.is_empty() {
            0
        } else {
            (self.x1 - self.x0) as u64 * (self.y1 - self.y0) as u64
        }
    }

    /// The smallest rectangle holding both (either may be empty).
    pub fn union(&self, other: &Rect) -> Rect {
        match (self.is_empty(), other.is_empty()) {
            (true, _) => *other,
            (_, true) => *self,
            _ => Rect::new(
                self.x0.min(other.x0),
                self.y0.min(other.y0),
                self.x1.max(other.x1),
                self.y1.max(other.y1),
            ),
        }
    }

    /// Grown by `r` pixels on every side and clamped to a `width` x `height` frame.
    pub fn dilate(&self, r: u32, width: u32, height: u32) -> Rect {
        if self.is_empty() {
            return Rect::default();
        }
        Rect::new(
            self.x0.saturating_sub(r).min(width),
            self.y0.saturating_sub(r).min(height),
            self.x1.saturating_add(r).min(width),
            self.y1.saturating_add(r).min(height),
        )
    }

    /// A cover of the pixels of `rects` by at most `max` (at least 1) rectangles, each a union
    /// of some of them: rectangles are merged while that costs no pixels (the union is no
    /// larger than the two apart, as for overlapping or adjacent ones), then, while there are
    /// more than `max`, the pair whose union adds the fewest pixels. Empty ones are dropped.
    /// (Many rectangles, beyond 256, are first merged in row-major runs, to bound the work.)
    pub fn merge(rects: &[Rect], max: usize) -> Vec<Rect> {
        let mut out: Vec<Rect> = rects.iter().copied().filter(|r| !r.is_empty()).collect();
        const PAIRWISE: usize = 256;
        if out.len() > PAIRWISE {
            out.sort_by_key(|r| (r.y0, r.x0));
            let run = out.len().div_ceil(PAIRWISE);
            out = out
                .chunks(run)
                .map(|c| c.iter().fold(Rect::default(), |a, r| a.union(r)))
                .collect();
        }
        let cost = |a: &Rect, b: &Rect| a.union(b).area() as i64 - (a.area() + b.area()) as i64;
        loop {
            let mut best: Option<(i64, usize, usize)> = None;
            for i in 0..out.len() {
                for j in i + 1..out.len() {
                    let c = cost(&out[i], &out[j]);
                    if best.is_none_or(|(b, _, _)| c < b) {
                        best = Some((c, i, j));
                    }
                }
            }
            match best {
                Some((c, i, j)) if c <= 0 || out.len() > max.max(1) => {
                    let merged = out[i].union(&out[j]);
                    out.swap_remove(j);
                    out[i] = merged;
                }
                _ => return out,
            }
        }
    }
}

/// At most this many crops per region resolve (more changed rectangles are merged).
const MAX_CROPS: usize = 16;

/// A region resolve that would resolve more than this share of the frame's pixels (counting
/// the crops' margins) resolves the whole frame instead.
const FULL_ABOVE: f64 = 0.5;

/// The radius `H` of a pixel's dependence: its outputs depend only on the cells within `H` of
/// it (Chebyshev; derivation in the module docs): 0 for [`Variant::Off`], 1 for the paper's
/// and the shader's weights, `2 max_radius + GIVE_BACK_TILE - 1` for [`Variant::Spread`].
pub fn dependency_radius(params: &ResolveParams) -> u32 {
    let (reach, tile) = reach(params);
    reach + tile - 1
}

/// How far a pixel's or tile's dependence reaches, and the tiles: `(H, 1)` for the per-pixel
/// variants, `(2 max_radius, GIVE_BACK_TILE)` for spread (the outputs of a tile depend on the
/// cells within `2 max_radius` of it).
fn reach(params: &ResolveParams) -> (u32, u32) {
    match params.variant() {
        Variant::Off => (0, 1),
        Variant::Paper | Variant::Shader => (1, 1),
        Variant::Spread => {
            let SpreadParams { max_radius, .. } = params.spread();
            (2 * max_radius as u32, GIVE_BACK_TILE as u32)
        }
    }
}

/// The pixels whose outputs a change in `changed` can reach: `changed` grown by the reach and
/// out to whole tiles.
fn affected(changed: &Rect, (reach, tile): (u32, u32), width: u32, height: u32) -> Rect {
    let r = changed.dilate(reach, width, height);
    if r.is_empty() {
        return r;
    }
    Rect::new(
        r.x0 / tile * tile,
        r.y0 / tile * tile,
        r.x1.div_ceil(tile).saturating_mul(tile).min(width),
        r.y1.div_ceil(tile).saturating_mul(tile).min(height),
    )
}

/// The pixels of a `width` x `height` frame whose outputs with `params` a change of the cells
/// in `changed` can reach (at most `MAX_CROPS` rectangles, each a union of some of the
/// areas): what [`resolve_region_into`] resolves again, and what anything made from the
/// resolved layers and the cells of single pixels (a need map's tiles: `NeedMap::update`) must
/// make again. Every output outside them is the same bits as before the change, however the
/// resolve after it was made.
pub fn reached_by(params: &ResolveParams, changed: &[Rect], width: u32, height: u32) -> Vec<Rect> {
    let reach = reach(params);
    let areas: Vec<Rect> = changed
        .iter()
        .map(|r| affected(r, reach, width, height))
        .collect();
    Rect::merge(&areas, MAX_CROPS)
}

/// Brings `out`, a resolve of the same frame with the same `params`, up to date after the
/// cells of the pixels in `changed` changed (rectangles in the frame's pixels; overlapping,
/// empty or past the frame's edge is fine; every pixel whose cell changed must be in one):
/// afterwards `out` is bit for bit what [`resolve_bands_into`](super::resolve_bands_into) of
/// `bands` gives, in every buffer, at a cost in proportion to the changed pixels and the
/// margin the resolve needs around them (module docs: up to `2 max_radius` plus a tile for the
/// default variant). `threads` resolve each crop; `out`'s working memory keeps the crops'
/// buffers for the next call.
///
/// The whole frame is resolved instead where that is cheaper (the crops would cover more than
/// half of it) or where `out` cannot be patched: another frame size, or not known to hold a
/// resolve with these `params` (a clone of a result does not; a result of [`resolve_bands`],
/// [`resolve_bands_into`] or this function does). The caller vouches that `out` holds a resolve
/// of this frame and that `changed` covers every change since.
///
/// [`resolve_bands`]: super::resolve_bands
/// [`resolve_bands_into`]: super::resolve_bands_into
pub fn resolve_region_into(
    bands: &[&FrameState],
    params: &ResolveParams,
    threads: usize,
    changed: &[Rect],
    out: &mut Resolved,
) -> Result<(), TilingError> {
    resolve_region_with(Kernel::detect(), bands, params, threads, changed, out)
}

/// [`resolve_region_into`] with the row pass compiled for `kernel` (for tests and benchmarks).
///
/// # Panics
/// If this CPU cannot run `kernel` ([`Kernel::available`]).
pub fn resolve_region_with(
    kernel: Kernel,
    bands: &[&FrameState],
    params: &ResolveParams,
    threads: usize,
    changed: &[Rect],
    out: &mut Resolved,
) -> Result<(), TilingError> {
    region(kernel, bands, params, threads, changed, out, FULL_ABOVE)
}

/// [`resolve_region_with`], resolving the whole frame where the crops would cover more than
/// `full_above` of it (tests resolve small frames in crops with `INFINITY`).
fn region(
    kernel: Kernel,
    bands: &[&FrameState],
    params: &ResolveParams,
    threads: usize,
    changed: &[Rect],
    out: &mut Resolved,
    full_above: f64,
) -> Result<(), TilingError> {
    assert!(kernel.available(), "{kernel:?} kernel on a CPU without it");
    let (width, height, rows) = frame_rows(bands)?;
    let pixels = width as usize * height as usize;
    let patchable = (out.width, out.height) == (width, height)
        && [
            out.reweighted.len(),
            out.mean.len(),
            out.removed.len(),
            out.spp.len(),
        ] == [pixels; 4]
        && out.scratch.resolved_with == Some(*params);
    if !patchable {
        return resolve_bands_with(kernel, bands, params, threads, out);
    }
    // The crop around an affected region: what its outputs read.
    let margin = reach(params).0;
    let areas = reached_by(params, changed, width, height);
    let cost: u64 = areas
        .iter()
        .map(|a| a.dilate(margin, width, height).area())
        .sum();
    if cost as f64 > full_above * pixels as f64 {
        return resolve_bands_with(kernel, bands, params, threads, out);
    }
    let layout = bands[0].layout();
    let len = cell_len(layout.cascades());
    let mut crop = out.scratch.crop.take().unwrap_or_default();
    let w = width as usize;
    for a in &areas {
        let c = a.dilate(margin, width, height);
        let (cx0, cx1) = (c.x0 as usize, c.x1 as usize);
        let crop_rows: Vec<&[u64]> = rows[c.y0 as usize..c.y1 as usize]
            .iter()
            .map(|row| &row[cx0 * len..cx1 * len])
            .collect();
        let (cw, ch) = (cx1 - cx0, (c.y1 - c.y0) as usize);
        // The resolve sizes the crop's buffers, in the memory they have where it is enough.
        (crop.width, crop.height) = (cw as u32, ch as u32);
        resolve_rows(
            kernel,
            layout,
            &crop_rows,
            params,
            threads,
            (cx0, c.y0 as usize),
            &mut crop,
        );
        // Copy the affected pixels back.
        let (ax0, ax1) = (a.x0 as usize, a.x1 as usize);
        for y in a.y0 as usize..a.y1 as usize {
            let from = (y - c.y0 as usize) * cw + (ax0 - cx0);
            let to = y * w + ax0;
            let n = ax1 - ax0;
            out.reweighted[to..to + n].copy_from_slice(&crop.reweighted[from..from + n]);
            out.mean[to..to + n].copy_from_slice(&crop.mean[from..from + n]);
            out.removed[to..to + n].copy_from_slice(&crop.removed[from..from + n]);
            out.spp[to..to + n].copy_from_slice(&crop.spp[from..from + n]);
        }
    }
    out.scratch.crop = Some(crop);
    Ok(())
}

#[cfg(test)]
mod tests;
