//! The resolve as it was before the row pass was vectorized (splatd's first `resolve_bands`),
//! kept unchanged (but for the bands' check, now the resolve's own) as the reference the fast
//! pass must match bit for bit: one pixel at a time, every cascade visited in order, support
//! counts pooled through a ring of three rows. Test-only.

use super::reference_spread::{spread, BAND_FLOATS};
use super::{support_samples, ResolveParams, Resolved, TilingError, Variant, SHADER_E_MIN_FLOOR};
use crate::layout::{CascadeLayout, COUNT_ONE, FRAC_BITS};
use crate::state::{cascade_units, cell_len, FrameState};

/// Resolves a frame held as bands that tile it top to bottom (in order, same layout and size).
///
/// `threads` row ranges are resolved in parallel (scoped threads; the core does no I/O and
/// chooses no thread count itself). The result is bit-identical for any `threads`: every pixel
/// is a pure function of its own cell and its neighbours'.
pub(super) fn resolve_bands(
    bands: &[&FrameState],
    params: &ResolveParams,
    threads: usize,
) -> Result<Resolved, TilingError> {
    // The bands' check is the resolve's own (not what this reference stands for).
    let (width, height, rows) = super::frame_rows(bands)?;
    let first = bands[0];
    let (w, h) = (width as usize, height as usize);
    let pixels = w * h;
    let mut out = Resolved {
        width,
        height,
        reweighted: vec![[0.0; 3]; pixels],
        mean: vec![[0.0; 3]; pixels],
        removed: vec![[0.0; 3]; pixels],
        spp: vec![0; pixels],
        scratch: Default::default(),
    };
    if pixels == 0 {
        return Ok(out);
    }
    let k = first.layout().cascades();
    let spreading = params.variant == Variant::Spread;
    // Band-major, so that the spread stage reads each band's plane contiguously.
    let mut bands_out: Vec<Vec<f32>> = if spreading {
        (0..k).map(|_| vec![0.0; pixels * BAND_FLOATS]).collect()
    } else {
        Vec::new()
    };
    let threads = threads.clamp(1, h);
    let chunk = h.div_ceil(threads) * w;
    let layout = first.layout();
    let rows = &rows;
    std::thread::scope(|scope| {
        let mut band_parts: Vec<_> = bands_out
            .iter_mut()
            .map(|b| b.chunks_mut(chunk * BAND_FLOATS))
            .collect();
        let parts = out
            .reweighted
            .chunks_mut(chunk)
            .zip(out.mean.chunks_mut(chunk))
            .zip(out.removed.chunks_mut(chunk))
            .zip(out.spp.chunks_mut(chunk))
            .enumerate();
        for (i, (((reweighted, mean), removed), spp)) in parts {
            let part = Part {
                y0: i * chunk / w,
                reweighted,
                mean,
                removed,
                spp,
                bands: band_parts
                    .iter_mut()
                    .map(|b| b.next().expect("one chunk per part"))
                    .collect(),
            };
            if i + 1 == threads.min(pixels.div_ceil(chunk)) {
                // The last part runs on this thread.
                Resolver::new(layout, w, params).run(rows, part);
            } else {
                scope.spawn(move || Resolver::new(layout, w, params).run(rows, part));
            }
        }
    });
    if spreading {
        spread(layout, &bands_out, params, &mut out);
    }
    Ok(out)
}

/// The rows `y0..` of the output that one resolver fills.
struct Part<'o> {
    y0: usize,
    reweighted: &'o mut [[f32; 3]],
    mean: &'o mut [[f32; 3]],
    removed: &'o mut [[f32; 3]],
    spp: &'o mut [u64],
    /// Per band, per pixel `[removed r, g, b, support]` for the spread stage, or empty.
    bands: Vec<&'o mut [f32]>,
}

/// Working memory of one resolve: per-pixel support counts of three rows, own and pooled
/// horizontally, in a ring indexed by row.
struct Resolver<'a> {
    layout: &'a CascadeLayout,
    params: &'a ResolveParams,
    width: usize,
    k: usize,
    ring: [RingRow; 3],
}

/// `[n_0 .. n_{K-1}, N]` of every pixel of one row, and their horizontal 3-pixel sums.
struct RingRow {
    y: usize,
    own: Vec<f64>,
    pooled: Vec<f64>,
}

impl<'a> Resolver<'a> {
    fn new(layout: &'a CascadeLayout, width: usize, params: &'a ResolveParams) -> Self {
        let k = layout.cascades();
        let row = || RingRow {
            y: usize::MAX,
            own: vec![0.0; width * (k + 1)],
            pooled: vec![0.0; width * (k + 1)],
        };
        Self {
            layout,
            params,
            width,
            k,
            ring: [row(), row(), row()],
        }
    }

    /// Support `n_j = count_{j-1} + count_j + count_{j+1}` of every pixel of a row, and `N`.
    fn support(k: usize, cells: &[u64], out: &mut [f64]) {
        let one = 1.0 / COUNT_ONE as f64;
        let mut counts = [0.0f64; crate::MAX_CASCADES as usize + 2];
        for (cell, out) in cells
            .chunks_exact(cell_len(k))
            .zip(out.chunks_exact_mut(k + 1))
        {
            let mut total = 0u64;
            for j in 0..k {
                let c = cell[4 * j + 3];
                // At most 2^58 per pixel (see the state module): exact.
                total += c;
                counts[j + 1] = c as f64 * one;
            }
            // counts[0] and counts[k + 1] stay 0: the missing neighbours at the ends.
            for j in 0..k {
                out[j] = counts[j] + counts[j + 1] + counts[j + 2];
            }
            out[k] = (total >> FRAC_BITS) as f64;
        }
    }

    /// Makes ring slot `y % 3` hold row `y`.
    fn load(&mut self, y: usize, rows: &[&[u64]]) {
        let (k, w) = (self.k, self.width);
        let row = &mut self.ring[y % 3];
        if row.y == y {
            return;
        }
        Self::support(k, rows[y], &mut row.own);
        let n = k + 1;
        let (own, pooled) = (&row.own, &mut row.pooled);
        for x in 0..w {
            let (l, r) = (x.saturating_sub(1) * n, (x + 1).min(w - 1) * n);
            let c = x * n;
            for i in 0..n {
                pooled[c + i] = own[l + i] + own[c + i] + own[r + i];
            }
        }
        row.y = y;
    }

    fn run(mut self, rows: &[&[u64]], mut part: Part<'_>) {
        let (w, h, k) = (self.width, rows.len(), self.k);
        let n = k + 1;
        let mut pooled = vec![0.0; n];
        let part_rows = part.spp.len() / w;
        for y in part.y0..part.y0 + part_rows {
            let (up, down) = (y.saturating_sub(1), (y + 1).min(h - 1));
            self.load(up, rows);
            self.load(y, rows);
            self.load(down, rows);
            let [a, b, c] = [&self.ring[up % 3], &self.ring[y % 3], &self.ring[down % 3]];
            for (x, cell) in rows[y].chunks_exact(cell_len(k)).enumerate() {
                let at = x * n;
                for (i, p) in pooled.iter_mut().enumerate() {
                    *p = a.pooled[at + i] + b.pooled[at + i] + c.pooled[at + i];
                }
                let own = &b.own[at..at + n];
                let i = (y - part.y0) * w + x;
                let bands = (!part.bands.is_empty()).then_some((&mut part.bands[..], i));
                let px = pixel(self.layout, self.params, cell, own, &pooled, bands);
                part.reweighted[i] = px.reweighted;
                part.mean[i] = px.mean;
                part.removed[i] = px.removed;
                part.spp[i] = own[k] as u64;
            }
        }
    }
}

/// One pixel: `cell` its fixed-point state, `own` its support counts and `N`, `pooled` the 3x3
/// sums of support counts and `N`.
#[inline]
fn pixel(
    layout: &CascadeLayout,
    params: &ResolveParams,
    cell: &[u64],
    own: &[f64],
    pooled: &[f64],
    mut bands: Option<(&mut [&mut [f32]], usize)>,
) -> Pixel {
    let k = layout.cascades();
    let n = own[k];
    if n == 0.0 {
        return Pixel::default();
    }
    // Every layer and band of the pixel is scaled by `1 / N` (a multiplication, not a division
    // per band and channel), as the fast resolve scales them.
    let inv = 1.0 / n;
    // Support relative to this pixel's own sample count (see the module docs); with the paper's
    // weights, a pixel counted as having at least twice the samples full weight needs.
    let kappa = params.kappa_at(n);
    let inv_kappa = 1.0 / kappa;
    let kmin = params.kappa_min;
    let own_n = match params.variant {
        Variant::Paper | Variant::Spread => support_samples(n, kappa + kmin, kmin * pooled[k]),
        Variant::Shader | Variant::Off => n,
    };
    let pool_scale = if pooled[k] > 0.0 {
        own_n / pooled[k]
    } else {
        0.0
    };
    let mut f = [0.0f64; 3];
    let mut total = [0.0f64; 3];
    let mut removed = [0.0f64; 3];
    for j in 0..k {
        let units = &cell[4 * j..4 * j + 4];
        // The top cascade is empty only if its high word is too (a low word is 0 at 2^64).
        if units[0] | units[1] | units[2] == 0 && (j + 1 < k || cell[4 * k] == 0) {
            continue;
        }
        let u = layout.unit_value(j);
        let b = [
            cascade_units(cell, j, 0) * u,
            cascade_units(cell, j, 1) * u,
            cascade_units(cell, j, 2) * u,
        ];
        let inv_c = layout.inv_scale(j);
        let lf = layout.luminance(f);
        let w = match params.variant {
            Variant::Off => 1.0,
            Variant::Paper | Variant::Spread => {
                let w_c = (pooled[j] * pool_scale - kmin) * inv_kappa;
                let w_v = lf * inv_kappa * inv_c;
                w_c.max(w_v).clamp(0.0, 1.0)
            }
            Variant::Shader => {
                let mut w_c = (pooled[j] * pool_scale - kmin) * inv_kappa;
                if w_c >= 0.0 {
                    w_c = (own[j] - kmin) * inv_kappa;
                }
                let t = inv_kappa.min(1.0);
                let energy = (1.0 - t) * (0.4 + 0.6 * layout.base()) + t;
                let w_v = lf.max(SHADER_E_MIN_FLOOR * n) * inv_kappa * inv_c * energy;
                ((w_c + w_v) * 0.5).clamp(0.0, 1.0)
            }
        };
        for c in 0..3 {
            f[c] += w * b[c];
            total[c] += b[c];
            removed[c] += (1.0 - w) * b[c];
        }
        if let Some((bands, i)) = &mut bands {
            let out = &mut bands[j][*i * BAND_FLOATS..(*i + 1) * BAND_FLOATS];
            for c in 0..3 {
                out[c] = ((1.0 - w) * b[c] * inv) as f32;
            }
        }
    }
    if let Some((bands, i)) = bands {
        // The band's support, also where the band is empty in this pixel (its neighbours'
        // samples count in the windows around it).
        for j in 0..k {
            bands[j][i * BAND_FLOATS + 3] = own[j] as f32;
        }
    }
    Pixel {
        reweighted: f.map(|v| (v * inv) as f32),
        mean: total.map(|v| (v * inv) as f32),
        removed: removed.map(|v| (v * inv) as f32),
    }
}

#[derive(Default)]
struct Pixel {
    reweighted: [f32; 3],
    mean: [f32; 3],
    removed: [f32; 3],
}
