//! Resolve: accumulated cascades in, the reweighted image (plus the plain mean, the removed
//! energy and the sample counts) out.
//!
//! For every pixel the cascades are visited from dim to bright, building the estimate `F`; the
//! contribution `B_j` of cascade `j` is added with a weight `w_j in [0, 1]` that is below 1 only
//! where too few samples support the band (count term) and the band is much brighter than the
//! estimate built from the dimmer bands so far (value term). See docs/ALGORITHM.md.
//!
//! Decisions, each backed by the quality benchmark (`cargo run --release --bin bench -- quality`):
//! * Support counts are the explicit fixed-point counts kept per cascade (exact for samples
//!   outside the cascade range too, where the luminance-derived count is wrong).
//! * The 3x3 neighbourhood pools counts *relative to each pixel's own sample count*:
//!   `n̄_j = N_p * Σ_q n_j(q) / Σ_q N_q` over the clamped-to-edge neighbourhood. With even spp this
//!   is the plain 3x3 mean; with uneven or adaptive spp a pixel is not judged by its neighbours'
//!   sample budgets, and neighbours without samples carry no weight.
//! * `kappa` may grow with the pixel's sample count: `kappa(N) = kappa * N^kappa_exponent`, with
//!   `kappa_exponent in [0, 1)` so that every band with a fixed probability is eventually fully
//!   trusted (consistency: `(p N - kappa_min) / (kappa N^e) -> inf`).

use super::layout::{CascadeLayout, ParamError, COUNT_ONE, FRAC_BITS};
use super::resolve_spread::{spread, SpreadParams, BAND_FLOATS};
use super::state::{cascade_units, cell_len, FrameState};

/// Which weight formula to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Variant {
    /// The paper: `w = min(1, max(w_c, w_v))`, `w_c` from the 3x3-pooled support count.
    Paper,
    /// The authors' published shader (`rw/reweight.fs`): the count term from the 3x3 pool where
    /// it is negative and from the pixel itself otherwise, the value term with `E_min` floored at
    /// 0.05 and an energy factor, `w = clamp((w_c + w_v) / 2, 0, 1)`.
    Shader,
    /// All weights 1: the plain Monte Carlo mean.
    Off,
    /// The paper's weights, then each band's removed energy given back over the smallest window
    /// (3x3 .. 17x17) where the band is supported (see the `resolve_spread` module).
    Spread,
}

/// Resolve parameters; they may change from one resolve to the next without touching the state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResolveParams {
    variant: Variant,
    kappa: f64,
    kappa_min: f64,
    kappa_exponent: f64,
    spread: SpreadParams,
}

/// splatd's default resolve variant, chosen by the quality benchmark (docs/ALGORITHM.md).
pub const DEFAULT_VARIANT: Variant = Variant::Spread;
/// splatd's default `kappa`, chosen by the quality benchmark (with the default variant).
pub const DEFAULT_KAPPA: f64 = 3.0;
/// `kappa_min` as in the paper: a band seen once is not trusted at all.
pub const DEFAULT_KAPPA_MIN: f64 = 1.0;
/// splatd's default growth of `kappa` with `N`, chosen by the quality benchmark (with the
/// default variant): `kappa(N) = 3 N^0.3`, 7.6 at 16 spp, 10.4 at 64, 15.8 at 256.
pub const DEFAULT_KAPPA_EXPONENT: f64 = 0.3;
/// The shader's floor of `E_min`, in the sample's units.
pub const SHADER_E_MIN_FLOOR: f64 = 0.05;

impl ResolveParams {
    /// Validates and builds resolve parameters.
    ///
    /// * `kappa > 0`: samples below which a band is distrusted (finite, at most 1e6);
    /// * `kappa_min >= 0`: support that counts for nothing;
    /// * `kappa_exponent in [0, 1)`: growth of kappa with the pixel's sample count.
    pub fn new(
        variant: Variant,
        kappa: f64,
        kappa_min: f64,
        kappa_exponent: f64,
    ) -> Result<Self, ParamError> {
        if !(kappa.is_finite() && kappa > 0.0 && kappa <= 1e6) {
            return Err(ParamError::new(
                "kappa",
                format!("must be a number in (0, 1e6], got {kappa}"),
            ));
        }
        if !(kappa_min.is_finite() && (0.0..=1e6).contains(&kappa_min)) {
            return Err(ParamError::new(
                "kappa_min",
                format!("must be a number in [0, 1e6], got {kappa_min}"),
            ));
        }
        if !(kappa_exponent.is_finite() && (0.0..1.0).contains(&kappa_exponent)) {
            return Err(ParamError::new(
                "kappa_exponent",
                format!(
                    "must be in [0, 1) (at 1 and above rare bands are never trusted), \
                     got {kappa_exponent}"
                ),
            ));
        }
        Ok(Self {
            variant,
            kappa,
            kappa_min,
            kappa_exponent,
            spread: SpreadParams::with_defaults(),
        })
    }

    /// The same parameters with other settings for [`Variant::Spread`]'s second stage.
    pub fn with_spread(self, spread: SpreadParams) -> Self {
        Self { spread, ..self }
    }

    /// The settings of [`Variant::Spread`]'s second stage.
    pub fn spread(&self) -> SpreadParams {
        self.spread
    }

    /// splatd's defaults: the `spread` variant with the benchmark's `kappa`, its growth and
    /// spread settings.
    pub fn with_defaults() -> Self {
        Self::new(
            DEFAULT_VARIANT,
            DEFAULT_KAPPA,
            DEFAULT_KAPPA_MIN,
            DEFAULT_KAPPA_EXPONENT,
        )
        .expect("defaults are valid")
    }

    /// The same parameters with another variant.
    pub fn with_variant(self, variant: Variant) -> Self {
        Self { variant, ..self }
    }

    /// The plain mean (all weights 1).
    pub fn off() -> Self {
        Self {
            variant: Variant::Off,
            ..Self::with_defaults()
        }
    }

    /// The variant.
    pub fn variant(&self) -> Variant {
        self.variant
    }

    /// `kappa` at `N = 1`.
    pub fn kappa(&self) -> f64 {
        self.kappa
    }

    /// `kappa_min`.
    pub fn kappa_min(&self) -> f64 {
        self.kappa_min
    }

    /// Growth exponent of kappa with `N`.
    pub fn kappa_exponent(&self) -> f64 {
        self.kappa_exponent
    }

    /// The effective kappa of a pixel with `n` samples.
    #[inline]
    pub fn kappa_at(&self, n: f64) -> f64 {
        if self.kappa_exponent == 0.0 {
            self.kappa
        } else {
            self.kappa * n.powf(self.kappa_exponent)
        }
    }
}

/// What a resolve returns: per-pixel RGB layers (row-major, top row first) and sample counts.
#[derive(Debug, Clone, PartialEq)]
pub struct Resolved {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// The reweighted estimate `F / N`.
    pub reweighted: Vec<[f32; 3]>,
    /// The plain Monte Carlo mean `Σ_j B_j / N`.
    pub mean: Vec<[f32; 3]>,
    /// Energy removed as fireflies, `Σ_j (1 - w_j) B_j / N`: never negative, except with
    /// [`Variant::Spread`], where a pixel may receive more removed energy from its neighbours
    /// than it lost itself (the frame's sum stays non-negative).
    pub removed: Vec<[f32; 3]>,
    /// Samples per pixel.
    pub spp: Vec<u64>,
}

/// Bands given to [`resolve_bands`] that do not tile one frame.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("bands do not tile a frame: {0}")]
pub struct TilingError(pub String);

impl FrameState {
    /// Resolves a state that holds the whole frame.
    ///
    /// # Panics
    /// If the state holds only a band (use [`resolve_bands`]).
    pub fn resolve(&self, params: &ResolveParams) -> Resolved {
        resolve_bands(&[self], params, 1).expect("a whole-frame state tiles its frame")
    }
}

/// Resolves a frame held as bands that tile it top to bottom (in order, same layout and size).
///
/// `threads` row ranges are resolved in parallel (scoped threads; the core does no I/O and
/// chooses no thread count itself). The result is bit-identical for any `threads`: every pixel
/// is a pure function of its own cell and its neighbours'.
pub fn resolve_bands(
    bands: &[&FrameState],
    params: &ResolveParams,
    threads: usize,
) -> Result<Resolved, TilingError> {
    let first = bands
        .first()
        .ok_or_else(|| TilingError("no bands".into()))?;
    let (width, height) = (first.width(), first.height());
    let mut rows: Vec<&[u64]> = Vec::with_capacity(height as usize);
    for band in bands {
        if (band.width(), band.height()) != (width, height) || band.layout() != first.layout() {
            return Err(TilingError(format!(
                "band {:?} has a different size or layout",
                band.rows()
            )));
        }
        if band.rows().start as usize != rows.len() {
            return Err(TilingError(format!(
                "band {:?} does not start at row {}",
                band.rows(),
                rows.len()
            )));
        }
        rows.extend(band.rows().map(|y| band.row(y)));
    }
    if rows.len() != height as usize {
        return Err(TilingError(format!(
            "bands cover {} of {height} rows",
            rows.len()
        )));
    }
    let (w, h) = (width as usize, height as usize);
    let pixels = w * h;
    let mut out = Resolved {
        width,
        height,
        reweighted: vec![[0.0; 3]; pixels],
        mean: vec![[0.0; 3]; pixels],
        removed: vec![[0.0; 3]; pixels],
        spp: vec![0; pixels],
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
    // Support relative to this pixel's own sample count (see the module docs).
    let pool_scale = if pooled[k] > 0.0 { n / pooled[k] } else { 0.0 };
    let kappa = params.kappa_at(n);
    let inv_kappa = 1.0 / kappa;
    let kmin = params.kappa_min;
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
                out[c] = ((1.0 - w) * b[c] / n) as f32;
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
    let inv = 1.0 / n;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::REC709_LUMINANCE;

    #[test]
    fn parameters_that_make_no_sense_are_refused_by_name() {
        let cases = [
            (ResolveParams::new(Variant::Paper, 0.0, 1.0, 0.0), "kappa"),
            (
                ResolveParams::new(Variant::Paper, f64::NAN, 1.0, 0.0),
                "kappa",
            ),
            (
                ResolveParams::new(Variant::Paper, 4.0, -1.0, 0.0),
                "kappa_min",
            ),
            (
                ResolveParams::new(Variant::Paper, 4.0, 1.0, 1.0),
                "kappa_exponent",
            ),
            (
                ResolveParams::new(Variant::Paper, 4.0, 1.0, -0.1),
                "kappa_exponent",
            ),
        ];
        for (result, name) in cases {
            assert_eq!(result.unwrap_err().name, name);
        }
    }

    #[test]
    fn a_lone_firefly_is_removed_and_its_energy_reported() {
        let layout = CascadeLayout::new(8.0, 6, 1.0, REC709_LUMINANCE).unwrap();
        let mut state = FrameState::new(3, 3, layout);
        for y in 0..3 {
            for x in 0..3 {
                for _ in 0..16 {
                    state.splat(x, y, [0.5, 0.5, 0.5]).unwrap();
                }
            }
        }
        state.splat(1, 1, [5000.0, 5000.0, 5000.0]).unwrap();
        // The paper's formula with a fixed kappa (the default variant adds a second stage, and
        // its kappa grows with N).
        let kappa = 4.0;
        let r = state
            .resolve(&ResolveParams::new(Variant::Paper, kappa, DEFAULT_KAPPA_MIN, 0.0).unwrap());
        let centre = 4;
        // By hand: L = 5000 splits between c4 = 4096 and c5 = 32768. Its support (one sample
        // pooled over 3x3) is far below kappa_min, so only the value term keeps anything:
        // w_4 = L(F)/(kappa c_4) with F = 16 * 0.5 from cascade 0, then w_5 likewise.
        let w_lo = (32768.0 / 5000.0 - 1.0) / 7.0;
        let mut f = 16.0 * 0.5;
        f += f / (kappa * 4096.0) * w_lo * 5000.0;
        f += f / (kappa * 32768.0) * (1.0 - w_lo) * 5000.0;
        assert!(
            (r.reweighted[centre][0] as f64 - f / 17.0).abs() < 1e-5,
            "firefly should be removed but for its value term: {:?} vs {}",
            r.reweighted[centre],
            f / 17.0
        );
        assert!(f / 17.0 < 0.6, "almost all of the firefly is gone");
        let expected_mean = (0.5 * 16.0 + 5000.0) / 17.0;
        assert!((r.mean[centre][0] - expected_mean).abs() < 1e-3);
        assert!((r.removed[centre][0] as f64 - (8.0 + 5000.0 - f) / 17.0).abs() < 1e-3);
        assert_eq!(r.spp[centre], 17);
        assert_eq!(r.reweighted[0], [0.5; 3], "neighbours untouched");
    }

    #[test]
    fn bands_must_tile_the_frame() {
        let layout = CascadeLayout::with_defaults();
        let bands = FrameState::bands(4, 6, 3, &layout);
        let p = ResolveParams::with_defaults();
        assert!(resolve_bands(&[&bands[0], &bands[2]], &p, 1).is_err());
        assert!(resolve_bands(&[&bands[1], &bands[0], &bands[2]], &p, 1).is_err());
        assert!(resolve_bands(&[], &p, 1).is_err());
        assert!(resolve_bands(&[&bands[0], &bands[1], &bands[2]], &p, 1).is_ok());
    }
}
