//! The spread stage as it was first written (dense per-band planes, one summed-area table of
//! the whole frame per band, one 2D difference array, all on one thread), kept as the
//! reference the sparse, threaded stage (`resolve_spread::spread`) must match bit for bit.
//! Test-only; the reference resolve (`reference.rs`) runs it after its paper stage.
//!
//! Changed three times since, with the stage. So that a part of the frame resolves on its own
//! to the same bits (`resolve_region_into`): the summed-area table sums supports in integers
//! (exact box sums), and the difference array's prefix sums restart at every tile of
//! `GIVE_BACK_TILE` pixels (each window cut into the tiles it covers). So that the stage can
//! give back a row as soon as the sources that reach it are known, without keeping every
//! band's windows of the whole frame: sources are taken row by row, and band by band within a
//! row (first band by band, each over the whole frame).

use crate::layout::CascadeLayout;
use crate::resolve::{ResolveParams, Resolved};
use crate::resolve_spread::{
    support_units, units_to_samples, SpreadParams, GIVE_BACK_TILE, SPREAD_RADII,
};

/// Per pixel and band, what the first (paper) stage leaves for the spread stage: the removed
/// energy in pixel-value units (RGB) and the band's support count.
pub(super) const BAND_FLOATS: usize = 4;

/// Gives removed energy back. `bands` holds, per band and pixel (row-major), `[r, g, b, n_j]`;
/// `out` holds the paper's images, updated in place.
pub(super) fn spread(
    layout: &CascadeLayout,
    bands: &[Vec<f32>],
    params: &ResolveParams,
    out: &mut Resolved,
) {
    let SpreadParams {
        support,
        solid_share,
        max_radius,
        edge_share,
    } = params.spread();
    let radii = SPREAD_RADII.iter().copied().filter(|&r| r <= max_radius);
    let (w, h) = (out.width as usize, out.height as usize);
    let pixels = w * h;
    debug_assert!(
        bands.len() == layout.cascades() && bands.iter().all(|b| b.len() == pixels * BAND_FLOATS)
    );
    let stride = w + 1;
    // Per pixel, the support from which a band is solid there (computed once for every band).
    let solid_from: Vec<f32> = out
        .spp
        .iter()
        .map(|&n| {
            let n = n as f64;
            if n == 0.0 {
                f32::INFINITY
            } else {
                (params.kappa_at(n) + params.kappa_min()).max(solid_share * n) as f32
            }
        })
        .collect();
    // Summed-area tables of each band's `[support, solid pixels]`, and one 2D difference array
    // of the give-back of every band (box sums are linear, so one set of prefix sums at the end
    // serves all bands).
    let busy: Vec<&Vec<f32>> = bands
        .iter()
        .filter(|plane| !plane.chunks_exact(BAND_FLOATS).all(|b| b[..3] == [0.0; 3]))
        .collect();
    let sats: Vec<Vec<[u128; 2]>> = busy
        .iter()
        .map(|plane| {
            let mut sat = vec![[0u128; 2]; stride * (h + 1)];
            for y in 0..h {
                let mut row = [0u128, 0];
                let (above, here) = sat[y * stride..(y + 2) * stride].split_at_mut(stride);
                let cells = &plane[y * w * BAND_FLOATS..(y + 1) * w * BAND_FLOATS];
                let solid = &solid_from[y * w..(y + 1) * w];
                for x in 0..w {
                    let n = cells[x * BAND_FLOATS + 3];
                    row[0] += support_units(n);
                    row[1] += (n >= solid[x]) as u128;
                    here[x + 1] = [above[x + 1][0] + row[0], above[x + 1][1] + row[1]];
                }
            }
            sat
        })
        .collect();
    let mut diff = vec![[0.0f64; 3]; stride * (h + 1)];
    // Sources in row-major order and, within a row, band by band: each cell of the difference
    // array gets its additions in this order.
    for y in 0..h {
        for (plane, sat) in busy.iter().zip(&sats) {
            let boxed = |x0: usize, x1: usize, y0: usize, y1: usize| {
                let [a, b, c, d] = [
                    sat[y1 * stride + x1],
                    sat[y0 * stride + x1],
                    sat[y1 * stride + x0],
                    sat[y0 * stride + x0],
                ];
                // (In this order an intermediate may be negative: wrapping, exact at the end.)
                let exact = |i: usize| {
                    a[i].wrapping_sub(b[i])
                        .wrapping_sub(c[i])
                        .wrapping_add(d[i])
                };
                [units_to_samples(exact(0)), exact(1) as f64]
            };
            for x in 0..w {
                let p = y * w + x;
                let band = &plane[p * BAND_FLOATS..(p + 1) * BAND_FLOATS];
                if band[..3] == [0.0; 3] {
                    continue;
                }
                let mut window = None;
                for (i, r) in radii.clone().enumerate() {
                    let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
                    let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
                    let [n, solid] = boxed(x0, x1, y0, y1);
                    if solid > 0.5 {
                        // The band is solid (fully trusted on its own, and a large share of the
                        // samples) in a pixel of the window: this energy was cut at the edge of
                        // a light or highlight, and blurring it would smear that edge. Right
                        // next to the solid pixel it is the pixel's partial cover of the light:
                        // given back in place (if the band holds `edge_share` of the pixel's
                        // samples); farther away it stays removed.
                        let own = band[3] as f64;
                        let spp = out.spp[p] as f64;
                        if i == 0 && edge_share.is_some_and(|share| own >= share * spp) {
                            window = Some((x, x + 1, y, y + 1));
                        }
                        break;
                    }
                    if n >= support {
                        window = Some((x0, x1, y0, y1));
                        break;
                    }
                }
                let Some((x0, x1, y0, y1)) = window else {
                    continue;
                };
                // Every pixel of the window (clamped to the frame) gets an equal share.
                let share = 1.0 / ((x1 - x0) * (y1 - y0)) as f64;
                // Its part in each tile it covers, as corners of a box of that tile's own
                // difference array (corners past the tile's right or bottom edge are not
                // needed).
                let t = GIVE_BACK_TILE;
                for ty in y0 / t..=(y1 - 1) / t {
                    for tx in x0 / t..=(x1 - 1) / t {
                        let (a0, a1) = (x0.max(tx * t), x1.min(tx * t + t));
                        let (b0, b1) = (y0.max(ty * t), y1.min(ty * t + t));
                        let (inner_x, inner_y) =
                            (a1 < (tx * t + t).min(w), b1 < (ty * t + t).min(h));
                        for c in 0..3 {
                            let v = band[c] as f64 * share;
                            diff[b0 * stride + a0][c] += v;
                            if inner_x {
                                diff[b0 * stride + a1][c] -= v;
                            }
                            if inner_y {
                                diff[b1 * stride + a0][c] -= v;
                            }
                            if inner_x && inner_y {
                                diff[b1 * stride + a1][c] += v;
                            }
                        }
                    }
                }
            }
        }
    }
    // Prefix sums turn the corners into boxes: along each row, then down each column (kept as
    // one running sum per column, so the frame is read in memory order), both from each tile's
    // top-left pixel.
    let mut col = vec![[0.0f64; 3]; w];
    for y in 0..h {
        if y % GIVE_BACK_TILE == 0 {
            col.fill([0.0; 3]);
        }
        let mut run = [0.0; 3];
        let row = y * w..(y + 1) * w;
        let pixels = out.reweighted[row.clone()]
            .iter_mut()
            .zip(&mut out.removed[row]);
        for ((x, (f, r)), col) in pixels.enumerate().zip(&mut col) {
            let d = &diff[y * stride + x];
            if x % GIVE_BACK_TILE == 0 {
                run = [0.0; 3];
            }
            for c in 0..3 {
                run[c] += d[c];
                col[c] += run[c];
                // Rounding of the running sums may leave a hair below 0 where nothing was
                // given; nothing is ever taken.
                let given = col[c].max(0.0);
                f[c] = (f[c] as f64 + given) as f32;
                r[c] = (r[c] as f64 - given) as f32;
            }
        }
    }
}
