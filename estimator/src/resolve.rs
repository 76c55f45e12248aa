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

use super::layout::ParamError;
use super::resolve_spread::{resolve_spread, Grid, Scratch, SpreadParams};
use super::state::{FrameState, Kernel};

#[cfg(test)]
mod matches_reference;
#[cfg(test)]
mod reference;
#[cfg(test)]
mod reference_spread;
mod region;
pub(crate) mod rows;

pub use region::{dependency_radius, reached_by, resolve_region_into, resolve_region_with, Rect};
use rows::{Consts, Layers, Part, Rows};

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
/// Sample counts whose `kappa(N)` the row pass and the need map look up rather than compute
/// ([`ResolveParams::kappa_table`]; a power of two: the row pass masks an index into it).
pub(crate) const KAPPA_TABLE: usize = 1024;
const _: () = assert!(KAPPA_TABLE.is_power_of_two());

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

    /// [`ResolveParams::kappa_at`] of `0 .. KAPPA_TABLE` samples, for the row pass and the need
    /// map to look up (computed per pixel, `N.powf` was most of the row pass's arithmetic and
    /// 40 % of the need map's time; the table holds the same values).
    pub(crate) fn kappa_table(&self) -> Vec<f64> {
        (0..KAPPA_TABLE).map(|n| self.kappa_at(n as f64)).collect()
    }

    /// The fewest samples from which the count term counts a pixel's own samples whatever its
    /// neighbourhood holds: the least `n` with `n >= (kappa(n) + kappa_min) / SPARSE_FULL_SHARE`
    /// (16 with the defaults). Below it the count term (`support_samples`) may count the pixel as
    /// having more samples than it has, from the share its neighbours' samples give each band, so
    /// the resolve judges a band by what the pixels around it agree on, not by the pixel's own
    /// samples (see [`crate::Convergence::converged`]).
    pub fn own_count_from(&self) -> u64 {
        let own = |n: u64| {
            let n = n as f64;
            support_samples(n, self.kappa_at(n) + self.kappa_min, f64::INFINITY) == n
        };
        // `n - (kappa n^e + kappa_min) / share` falls and then rises without bound (`e < 1`),
        // and is negative until it rises: so `own` is false below one `n` and true from it.
        // With a huge `kappa` and `e` near 1 that `n` is past any count (`u64::MAX`: never).
        let mut high = 1u64;
        while !own(high) {
            if high >= 1 << 62 {
                return u64::MAX;
            }
            high *= 2;
        }
        let mut low = high / 2;
        while high - low > 1 {
            let mid = low + (high - low) / 2;
            if own(mid) {
                high = mid;
            } else {
                low = mid;
            }
        }
        high
    }
}

/// The share of a sparse pixel's neighbourhood's samples that a band needs for full weight
/// with the paper's weights (see [`support_samples`]): a half. Chosen by the quality benchmark's
/// farm table against a whole neighbourhood (1) and the cap alone: at one and two passes a
/// whole neighbourhood left the caustic scene's 2x4-pixel light at half weight (the final 19-21 %
/// darker than OIDN(mean)), a half kept every row within 2 % of OIDN(mean)'s energy.
pub(crate) const SPARSE_FULL_SHARE: f64 = 0.5;

/// The sample count the paper's count term takes a pixel to have ([`Variant::Paper`], and
/// [`Variant::Spread`]'s first stage): `full /
/// SPARSE_FULL_SHARE` (`full` is `kappa(N) + kappa_min`, the support full weight needs), but
/// never more than `lone` (`kappa_min` times the samples of the pixel's 3x3 neighbourhood), and
/// never less than its own `n`.
///
/// A pixel's pooled support `n̄_j` is the share of its neighbourhood's samples that fall in band
/// `j`, times this count. With the pixel's own `n` the count term cannot reach full weight below
/// `N = kappa(N) + kappa_min`: at one sample a pixel (`kappa_min = 1`) nothing passes, so a
/// frame's first pass resolved to black, and the denoised final of two passes lost a quarter to
/// a half of its energy. Counted this way, a band that holds half the samples around the pixel
/// gets full weight at any `N`, while the cap at `lone` keeps a band seen by one sample of the
/// whole neighbourhood at `n̄_j <= kappa_min`: no weight, as in the paper. The count never falls
/// as samples arrive, and where `n >= full / SPARSE_FULL_SHARE` (every `N` past a few samples)
/// it is `n`, bit for bit.
///
/// `spread`'s first stage counts the same way. Kept to its own `n` (as first written), it
/// removed nearly everything at one sample a pixel and its second stage gave it back over
/// windows of up to 17x17 pixels: a farm's first passes came out blurred, worse than the plain
/// mean on 9 of the quality benchmark's 35 farm rows (3.7x the mean's relMSE on the slit scene
/// at one pass of 64 spp), and with the caustic scene's visible light (a band no window
/// supports) gone, 31-43 % of the frame's energy. Counted this way no row is worse than the
/// mean and the light stays; only the blur's gain on the noisiest rows is lost.
#[inline(always)]
pub(crate) fn support_samples(n: f64, full: f64, lone: f64) -> f64 {
    let wanted = full / SPARSE_FULL_SHARE;
    let floor = if wanted < lone { wanted } else { lone };
    if floor > n {
        floor
    } else {
        n
    }
}

/// What a resolve returns: per-pixel RGB layers (row-major, top row first) and sample counts.
/// (The default is the result of resolving no pixels, a buffer for [`resolve_bands_into`].)
#[derive(Debug, Clone, Default, PartialEq)]
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
    /// Working memory kept for the next resolve into these buffers (not part of the result:
    /// equal in every two results, empty in a clone).
    pub(crate) scratch: Scratch,
}

impl Resolved {
    /// Bytes of working memory kept for the next resolve into these buffers (see
    /// [`resolve_bands_into`]; 0 for a result of [`resolve_bands`]).
    pub fn working_bytes(&self) -> u64 {
        self.scratch.bytes()
    }
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
    let mut out = Resolved::default();
    resolve_bands_with(Kernel::detect(), bands, params, threads, &mut out)?;
    // A result on its own holds no working memory (but remembers what it was resolved with,
    // for `resolve_region_into`).
    let resolved_with = out.scratch.resolved_with;
    out.scratch = Scratch::default();
    out.scratch.resolved_with = resolved_with;
    Ok(out)
}

/// [`resolve_bands`] into the buffers of an earlier result of the same frame size, which are
/// overwritten (other sizes get new buffers). Resolving a large frame again and again into the
/// same buffers saves the page faults of new memory, whenever the allocator maps some for new
/// buffers (at 1080p up to a tenth of the resolve's time; `bench speed` measures both). The
/// resolve keeps nothing else of the frame's size (its stages stream down the frame); `out`
/// keeps the crops of [`resolve_region_into`] ([`Resolved::working_bytes`]). On error `out` is
/// left as it was.
pub fn resolve_bands_into(
    bands: &[&FrameState],
    params: &ResolveParams,
    threads: usize,
    out: &mut Resolved,
) -> Result<(), TilingError> {
    resolve_bands_with(Kernel::detect(), bands, params, threads, out)
}

/// [`resolve_bands_into`] with the row pass compiled for `kernel` (the same bits on every
/// kernel; for tests and benchmarks).
///
/// # Panics
/// If this CPU cannot run `kernel` ([`Kernel::available`]).
pub fn resolve_bands_with(
    kernel: Kernel,
    bands: &[&FrameState],
    params: &ResolveParams,
    threads: usize,
    out: &mut Resolved,
) -> Result<(), TilingError> {
    assert!(kernel.available(), "{kernel:?} kernel on a CPU without it");
    let (width, height, rows) = frame_rows(bands)?;
    let (w, h) = (width as usize, height as usize);
    let pixels = w * h;
    (out.width, out.height) = (width, height);
    // Buffers of another size are let go, so that the resolve writes into new ones of this
    // size (see `resolve_rows`), faulted in by the threads that fill them.
    let lens = [
        out.reweighted.len(),
        out.mean.len(),
        out.removed.len(),
        out.spp.len(),
    ];
    if lens != [pixels; 4] {
        out.reweighted = Vec::new();
        out.mean = Vec::new();
        out.removed = Vec::new();
        out.spp = Vec::new();
    }
    resolve_rows(
        kernel,
        bands[0].layout(),
        &rows,
        params,
        threads,
        (0, 0),
        out,
    );
    out.scratch.resolved_with = Some(*params);
    Ok(())
}

/// The rows of the frame that `bands` tile (checked: same size and layout, in order, every
/// row once), and the frame's size.
pub(crate) fn frame_rows<'s>(
    bands: &[&'s FrameState],
) -> Result<(u32, u32, Vec<&'s [u64]>), TilingError> {
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
    Ok((width, height, rows))
}

/// Resolves the pixels whose cells `rows` holds (each row the same number of cells) as if they
/// were a whole frame, into `out`'s layers, which it sizes to `out.width * out.height` pixels: a
/// frame, or a crop of one whose top-left pixel is the frame's `origin` (which places the spread
/// stage's tiles).
///
/// Every pixel is written and the layers' earlier contents are never read, so new buffers are
/// not zeroed first ([`Layers::room`]): zeroing a 1080p resolve's 91 MB of new layers (a
/// `memset`, where the allocator reused memory) took 6 % of a resolve into them, 0.149 s against
/// 0.136 s into reused ones (`bench speed`, one thread).
fn resolve_rows(
    kernel: Kernel,
    layout: &crate::layout::CascadeLayout,
    rows: &[&[u64]],
    params: &ResolveParams,
    threads: usize,
    origin: (usize, usize),
    out: &mut Resolved,
) {
    let (w, h) = (out.width as usize, out.height as usize);
    let pixels = w * h;
    debug_assert!(rows.len() == h);
    if pixels > 0 {
        let layers = Layers::room(out, pixels);
        let consts = &Consts::new(layout, params);
        if params.variant == Variant::Spread {
            let grid = Grid::at(origin);
            resolve_spread(kernel, consts, rows, params, threads, grid, (w, h), layers);
        } else {
            resolve_paper(kernel, consts, rows, threads, w, layers);
        }
    }
    // SAFETY: the resolve wrote every pixel of the room (the row pass writes each pixel of every
    // row it resolves, and both stages resolve every row); no room for no pixels.
    unsafe { Layers::written(out, pixels) }
}

/// The row pass alone (every variant but [`Variant::Spread`]) over the rows of `out`.
fn resolve_paper(
    kernel: Kernel,
    consts: &Consts,
    rows: &[&[u64]],
    threads: usize,
    w: usize,
    out: Layers<'_>,
) {
    let h = rows.len();
    let part_rows = h.div_ceil(threads.clamp(1, h));
    std::thread::scope(|scope| {
        let mut rest = out;
        for y0 in (0..h).step_by(part_rows) {
            let ys = y0..(y0 + part_rows).min(h);
            let (layers, after) = rest.split_at(ys.len() * w);
            rest = after;
            let mut part = Part {
                y0,
                out: layers,
                support: Vec::new(),
                support_rows: 0,
                sources: Vec::new(),
                column: 0,
            };
            let run = move || Rows::new(kernel, consts, w).run(rows, &mut part, ys);
            if y0 + part_rows >= h {
                // The last part runs on this thread.
                run();
            } else {
                scope.spawn(run);
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::{CascadeLayout, REC709_LUMINANCE};

    #[test]
    fn own_count_from_is_where_the_count_term_stops_borrowing() {
        // A scan of every count against the rule itself, for a few parameter sets.
        for (kappa, kappa_min, e) in [
            (3.0, 1.0, 0.3),
            (4.0, 1.0, 0.0),
            (1.0, 0.0, 0.0),
            (20.0, 2.0, 0.5),
        ] {
            let p = ResolveParams::new(Variant::Paper, kappa, kappa_min, e).unwrap();
            let first = (1..100_000u64)
                .find(|&n| n as f64 >= (p.kappa_at(n as f64) + kappa_min) / SPARSE_FULL_SHARE)
                .unwrap();
            assert_eq!(
                p.own_count_from(),
                first,
                "kappa {kappa}, kappa_min {kappa_min}, e {e}"
            );
        }
        assert_eq!(ResolveParams::with_defaults().own_count_from(), 16);
        let never = ResolveParams::new(Variant::Paper, 1e6, 1e6, 0.9999).unwrap();
        assert_eq!(never.own_count_from(), u64::MAX);
    }

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
    fn a_band_holding_every_sample_around_it_is_kept_at_any_sample_count() {
        // Fewer samples than full weight needs (kappa + kappa_min: 3 with kappa 2, 4 with the
        // default at N = 1): before `support_samples`, a first pass resolved to black.
        let params = [
            ResolveParams::new(Variant::Paper, 2.0, 1.0, 0.0).unwrap(),
            // Full weight needs 9 samples: the whole neighbourhood at N = 1.
            ResolveParams::new(Variant::Paper, 8.0, 1.0, 0.3).unwrap(),
            ResolveParams::with_defaults().with_variant(Variant::Paper),
        ];
        for spp in 1..=3 {
            let state = FrameState::flat(6, 5, spp, [1.0, 0.5, 0.25]);
            for p in &params {
                let r = state.resolve(p);
                // Up to the rounding of `n̄ - kappa_min` against `kappa`.
                for (i, (rw, removed)) in r.reweighted.iter().zip(&r.removed).enumerate() {
                    for c in 0..3 {
                        let mean = r.mean[i][c];
                        assert!(
                            (rw[c] - mean).abs() <= 1e-6 * mean,
                            "{spp} spp, {p:?}: {rw:?}"
                        );
                        assert!(removed[c] <= 1e-6 * mean, "{spp} spp, {p:?}: {removed:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn at_one_sample_a_band_holding_half_the_samples_around_it_is_kept() {
        // One sample a pixel: grey on the centre's cross, bright on its diagonals, so the grey
        // band holds 5 of the 9 samples around the centre (more than SPARSE_FULL_SHARE).
        let mut state = FrameState::new(5, 5, CascadeLayout::with_defaults());
        for y in 0..5u32 {
            for x in 0..5u32 {
                let diagonal = x.abs_diff(2) == 1 && y.abs_diff(2) == 1;
                state
                    .splat(x, y, if diagonal { [5000.0; 3] } else { [0.5; 3] })
                    .unwrap();
            }
        }
        let r = state.resolve(&ResolveParams::new(Variant::Paper, 2.0, 1.0, 0.0).unwrap());
        assert_eq!(r.reweighted[12], [0.5; 3], "the centre keeps its grey");
        // A diagonal pixel's bright band holds 1 of the 9 samples around it: removed.
        assert_eq!(r.reweighted[6], [0.0; 3]);
    }

    #[test]
    fn a_small_light_keeps_more_as_samples_arrive_never_less() {
        // A 2x4-pixel light on grey (like the quality benchmark's caustic scene): at most 6 of
        // the 9 samples around each of its pixels are in its band. What `paper` keeps of it
        // must not fall when a sample arrives (the count once stepped down from 2 T to N at
        // N = T, so the light dimmed at the third pass).
        let mut state = FrameState::new(8, 6, CascadeLayout::with_defaults());
        let params = ResolveParams::new(Variant::Paper, 2.0, 1.0, 0.0).unwrap();
        let mut kept = Vec::new();
        for _ in 0..8 {
            for y in 0..6u32 {
                for x in 0..8u32 {
                    let light = (2..4).contains(&y) && (2..6).contains(&x);
                    state
                        .splat(x, y, if light { [5000.0; 3] } else { [0.5; 3] })
                        .unwrap();
                }
            }
            let r = state.resolve(&params);
            let sum = |layer: &[[f32; 3]]| layer.iter().map(|p| f64::from(p[1])).sum::<f64>();
            kept.push(sum(&r.reweighted) / sum(&r.mean));
        }
        assert!(kept.windows(2).all(|w| w[1] >= w[0]), "{kept:?}");
        assert!(kept[0] > 0.9, "{kept:?}");
    }

    #[test]
    fn the_default_keeps_a_small_light_in_a_farms_first_passes_and_removes_a_firefly() {
        // A farm's pass is one sample a pixel. A 2x4-pixel light on grey is supported by no
        // window of the spread stage (8 samples of its band, far below 64): with the pixel's own
        // count the first stage removed it all and it stayed removed, 31-43 % of the caustic
        // scene's energy at one to four passes. A firefly, one sample in its band among the
        // nine around it, is still removed at every pass.
        let params = ResolveParams::with_defaults();
        let (w, h) = (24u32, 20u32);
        let mut light = FrameState::new(w, h, CascadeLayout::with_defaults());
        let mut firefly = FrameState::new(w, h, CascadeLayout::with_defaults());
        for pass in 0..4u32 {
            for y in 0..h {
                for x in 0..w {
                    let lit = (9..11).contains(&y) && (10..14).contains(&x);
                    let rgb = if lit { [5000.0; 3] } else { [0.5; 3] };
                    light.splat(x, y, rgb).unwrap();
                    let hot = (x, y) == (12, 10) && pass == 0;
                    firefly
                        .splat(x, y, if hot { [5000.0; 3] } else { [0.5; 3] })
                        .unwrap();
                }
            }
            let sum = |layer: &[[f32; 3]]| layer.iter().map(|p| f64::from(p[1])).sum::<f64>();
            let r = light.resolve(&params);
            let kept = sum(&r.reweighted) / sum(&r.mean);
            assert!(kept > 0.9, "{} passes: kept {kept}", pass + 1);
            let r = firefly.resolve(&params);
            let (mean, kept) = (sum(&r.mean), sum(&r.reweighted));
            let hot = (5000.0 - 0.5) / f64::from(pass + 1);
            assert!(
                mean - kept > 0.99 * hot && kept > 0.99 * (mean - hot),
                "{} passes: kept {kept} of {mean}, the firefly's share {hot}",
                pass + 1
            );
        }
    }

    #[test]
    fn at_one_sample_a_band_seen_once_around_it_is_still_removed() {
        // One sample a pixel, grey but for a firefly in the middle: its band holds one sample of
        // the nine around it, which counts for nothing (kappa_min), whatever kappa is.
        let mut firefly = FrameState::new(5, 5, CascadeLayout::with_defaults());
        for y in 0..5 {
            for x in 0..5 {
                let rgb = if (x, y) == (2, 2) {
                    [5000.0; 3]
                } else {
                    [0.5; 3]
                };
                firefly.splat(x, y, rgb).unwrap();
            }
        }
        for kappa in [2.0, 8.0, 32.0] {
            let r = firefly.resolve(&ResolveParams::new(Variant::Paper, kappa, 1.0, 0.0).unwrap());
            assert_eq!(r.reweighted[12], [0.0; 3], "kappa {kappa}");
            assert!(
                (r.removed[12][0] - 5000.0).abs() < 1e-2,
                "{:?}",
                r.removed[12]
            );
            // A corner, whose neighbourhood does not reach the firefly, keeps everything where
            // its nine samples are the support full weight needs, and (9 - 1) / 32 of it with
            // kappa 32.
            let kept = if kappa > 8.0 { 0.125 } else { 0.5 };
            assert_eq!(r.reweighted[0], [kept; 3], "kappa {kappa}");
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
