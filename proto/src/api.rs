//! JSON types of the HTTP API (everything except the sample batches).
//!
//! Requests are small and rare (creating a frame, asking for its state), so
//! they are JSON for readability and easy scripting with `curl`. Request
//! types use `deny_unknown_fields`: a typo such as `"kapa"` is an error
//! (HTTP 400) instead of a silently ignored setting. Response types accept
//! unknown fields, so a newer server can add fields without breaking older
//! workers.
//!
//! Every tunable default is the estimator's own (`splatd-estimator`, which chose them with the
//! quality benchmark); the `DEFAULT_*` constants below only name them for the wire.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};
use splatd_estimator as estimator;

/// Default ratio between the brightness ranges of adjacent cascades.
pub const DEFAULT_CASCADE_BASE: f64 = estimator::DEFAULT_CASCADE_BASE;
/// Default number of cascades.
pub const DEFAULT_CASCADE_COUNT: u32 = estimator::DEFAULT_CASCADE_COUNT;
/// Default scale `c0` of the lowest cascade (cascade `j` has scale `c0 * base^j`; samples with
/// luminance at or below `c0` go entirely to cascade 0).
pub const DEFAULT_LOWEST_SCALE: f64 = estimator::DEFAULT_LOWEST_SCALE;
/// Default luminance weights of linear RGB (Rec. 709).
pub const DEFAULT_LUMINANCE: [f64; 3] = estimator::REC709_LUMINANCE;
/// Default resolve variant.
pub const DEFAULT_VARIANT: Variant = Variant::from_estimator(estimator::DEFAULT_VARIANT);
/// Default `kappa`: a brightness band is fully trusted once about `kappa + kappa_min` samples
/// support it, and down-weighted in proportion below that.
pub const DEFAULT_KAPPA: f64 = estimator::DEFAULT_KAPPA;
/// Default `kappa_min`, subtracted from a band's support count before it is compared with `kappa`.
pub const DEFAULT_KAPPA_MIN: f64 = estimator::DEFAULT_KAPPA_MIN;
/// Default exponent of the sample-count adaptation of `kappa` (0 = fixed).
pub const DEFAULT_KAPPA_EXPONENT: f64 = estimator::DEFAULT_KAPPA_EXPONENT;
/// Default convergence threshold: a frame is converged once every pixel has samples and the
/// resolve removes at most this fraction of the mean's energy.
pub const DEFAULT_CONVERGED_BELOW: f64 = estimator::DEFAULT_CONVERGED_BELOW;
/// Default edge, in pixels, of the tiles of `GET /v1/frames/{id}/need`.
pub const DEFAULT_NEED_TILE: u32 = estimator::DEFAULT_NEED_TILE;

// serde's `default = "..."` wants functions; they only forward the constants.
fn default_cascade_base() -> f64 {
    DEFAULT_CASCADE_BASE
}
fn default_cascade_count() -> u32 {
    DEFAULT_CASCADE_COUNT
}
fn default_lowest_scale() -> f64 {
    DEFAULT_LOWEST_SCALE
}
fn default_luminance() -> [f64; 3] {
    DEFAULT_LUMINANCE
}
fn default_variant() -> Variant {
    DEFAULT_VARIANT
}
fn default_kappa() -> f64 {
    DEFAULT_KAPPA
}
fn default_kappa_min() -> f64 {
    DEFAULT_KAPPA_MIN
}
fn default_kappa_exponent() -> f64 {
    DEFAULT_KAPPA_EXPONENT
}
fn default_converged_below() -> f64 {
    DEFAULT_CONVERGED_BELOW
}

/// How samples are split into brightness cascades (fixed when a frame is created).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CascadeParams {
    /// Ratio between the luminance ranges of adjacent cascades.
    #[serde(default = "default_cascade_base")]
    pub base: f64,
    /// Number of cascades.
    #[serde(default = "default_cascade_count")]
    pub cascades: u32,
    /// Scale `c0` of the lowest cascade: cascade `j` has scale `c0 * base^j`. A sample whose
    /// luminance is at most `c0` goes entirely to cascade 0; one between `c_j` and `c_{j+1}` is
    /// split between cascades `j` and `j + 1`. `c0` is not an upper bound of cascade 0, which
    /// also takes shares of samples up to `c0 * base`.
    #[serde(default = "default_lowest_scale")]
    pub lowest_scale: f64,
    /// Weights turning linear RGB into the luminance that picks a cascade.
    #[serde(default = "default_luminance")]
    pub luminance: [f64; 3],
}

impl Default for CascadeParams {
    fn default() -> Self {
        CascadeParams {
            base: DEFAULT_CASCADE_BASE,
            cascades: DEFAULT_CASCADE_COUNT,
            lowest_scale: DEFAULT_LOWEST_SCALE,
            luminance: DEFAULT_LUMINANCE,
        }
    }
}

/// Which resolve (cascade recombination) to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Variant {
    /// The reweighting of Zirr et al. 2018 as published.
    #[default]
    Paper,
    /// The weights of the authors' published shader (`rw/reweight.fs`).
    Shader,
    /// No firefly removal: the plain mean of all samples.
    Off,
    /// The paper's weights, then each brightness band's removed energy given back blurred over
    /// the smallest window (3x3 .. 17x17) where that band is supported.
    Spread,
}

impl Variant {
    /// The wire name of an estimator variant.
    pub const fn from_estimator(v: estimator::Variant) -> Variant {
        match v {
            estimator::Variant::Paper => Variant::Paper,
            estimator::Variant::Shader => Variant::Shader,
            estimator::Variant::Off => Variant::Off,
            estimator::Variant::Spread => Variant::Spread,
        }
    }

    /// The estimator variant this wire name stands for.
    pub const fn to_estimator(self) -> estimator::Variant {
        match self {
            Variant::Paper => estimator::Variant::Paper,
            Variant::Shader => estimator::Variant::Shader,
            Variant::Off => estimator::Variant::Off,
            Variant::Spread => estimator::Variant::Spread,
        }
    }

    /// All variants, in documentation order.
    pub const ALL: [Variant; 4] = [
        Variant::Paper,
        Variant::Shader,
        Variant::Off,
        Variant::Spread,
    ];

    /// The name used in JSON and query strings.
    pub fn as_str(self) -> &'static str {
        match self {
            Variant::Paper => "paper",
            Variant::Shader => "shader",
            Variant::Off => "off",
            Variant::Spread => "spread",
        }
    }
}

impl fmt::Display for Variant {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A string that names no [`Variant`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown resolve variant {0:?}; expected \"paper\", \"shader\", \"off\" or \"spread\"")]
pub struct UnknownVariant(pub String);

impl FromStr for Variant {
    type Err = UnknownVariant;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Variant::ALL
            .into_iter()
            .find(|v| v.as_str() == s)
            .ok_or_else(|| UnknownVariant(s.to_owned()))
    }
}

/// How a frame is resolved into an image (defaults stored with the frame,
/// overridable per image request).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResolveParams {
    /// Which recombination to run.
    #[serde(default = "default_variant")]
    pub variant: Variant,
    /// Support (in samples, beyond `kappa_min`) at which the count term
    /// `(support - kappa_min) / kappa` reaches 1, giving a brightness band full weight with
    /// `paper` (`shader` averages it with the value term). Bands with less support are
    /// down-weighted, not rejected.
    #[serde(default = "default_kappa")]
    pub kappa: f64,
    /// Support (in samples) that counts for nothing: it is subtracted from a band's support
    /// count before the count term divides by `kappa` (1: a band seen once gets no weight from
    /// the count term).
    #[serde(default = "default_kappa_min")]
    pub kappa_min: f64,
    /// Growth of `kappa` with the pixel's sample count `N`: the effective kappa is
    /// `kappa * N^kappa_exponent`, `0 <= kappa_exponent < 1` (0: fixed).
    #[serde(default = "default_kappa_exponent")]
    pub kappa_exponent: f64,
}

impl Default for ResolveParams {
    fn default() -> Self {
        ResolveParams {
            variant: DEFAULT_VARIANT,
            kappa: DEFAULT_KAPPA,
            kappa_min: DEFAULT_KAPPA_MIN,
            kappa_exponent: DEFAULT_KAPPA_EXPONENT,
        }
    }
}

/// Body of `POST /v1/frames`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateFrame {
    /// Frame id, see [`crate::validate_frame_id`].
    pub id: String,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Cascade layout; defaults when omitted.
    #[serde(default)]
    pub cascades: CascadeParams,
    /// Default resolve settings; defaults when omitted.
    #[serde(default)]
    pub resolve: ResolveParams,
    /// The frame counts as converged once every pixel has samples and the resolve removes at
    /// most this fraction of the mean's energy (in `(0, 1]`, default
    /// [`DEFAULT_CONVERGED_BELOW`]).
    #[serde(default = "default_converged_below")]
    pub converged_below: f64,
    /// AOVs accumulated beside the beauty from passes that carry them (none when omitted); see
    /// [`AovSpec`].
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub aovs: Vec<AovSpec>,
    /// The denoiser `image.exr` runs when its query does not say (`denoise=`); none when
    /// omitted.
    #[serde(default, skip_serializing_if = "Denoise::is_none")]
    pub denoise: Denoise,
    /// Which declared AOVs guide the denoiser; when omitted they are chosen by name (see
    /// [`DenoiseGuides`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub denoise_guides: Option<DenoiseGuides>,
}

/// A denoiser `image.exr` can run over the frame (`denoise=oidn`), adding the layer `denoised`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Denoise {
    /// No denoising (the default).
    #[default]
    None,
    /// Intel Open Image Denoise 2.x, its `RT` filter.
    Oidn,
}

impl Denoise {
    /// Whether this is [`Denoise::None`].
    pub fn is_none(&self) -> bool {
        *self == Denoise::None
    }

    /// The name used in JSON and queries: `none` or `oidn`.
    pub fn as_str(self) -> &'static str {
        match self {
            Denoise::None => "none",
            Denoise::Oidn => "oidn",
        }
    }
}

/// OIDN's quality mode for a denoised `image.exr` (`denoise_quality=`); `high` when omitted.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DenoiseQuality {
    /// OIDN's own default.
    Default,
    /// Balanced quality and speed.
    Balanced,
    /// OIDN's best, for final frames (the default here).
    #[default]
    High,
    /// Fastest, for previews.
    Fast,
}

impl DenoiseQuality {
    /// The name used in queries and the EXR header.
    pub fn as_str(self) -> &'static str {
        match self {
            DenoiseQuality::Default => "default",
            DenoiseQuality::Balanced => "balanced",
            DenoiseQuality::High => "high",
            DenoiseQuality::Fast => "fast",
        }
    }
}

/// The AOVs a denoiser is guided by: each the name of a declared AOV with exactly three
/// channels (albedo R, G, B in [0, 1]; normal X, Y, Z in [-1, 1]). A normal needs an albedo.
///
/// Given in [`CreateFrame::denoise_guides`], these are exactly the guides (`{}` denoises
/// unguided). Omitted, the server picks by the AOV name's last dot-separated component, case
/// ignored, among AOVs with three channels, the first declared winning: albedo `DiffCol`,
/// `Diffuse Color`, `albedo` or `Denoising Albedo`; normal `Normal`, `N` or `Denoising Normal`
/// (Blender's `ViewLayer.DiffCol` and `ViewLayer.Normal`). [`FrameInfo::denoise_guides`] shows
/// the guides in force.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DenoiseGuides {
    /// The albedo AOV's name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub albedo: Option<String>,
    /// The normal AOV's name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normal: Option<String>,
}

impl DenoiseGuides {
    /// Neither guide.
    pub fn is_empty(&self) -> bool {
        self.albedo.is_none() && self.normal.is_none()
    }
}

impl CreateFrame {
    /// A request for a `width`×`height` frame with default parameters.
    pub fn new(id: impl Into<String>, width: u32, height: u32) -> CreateFrame {
        CreateFrame {
            id: id.into(),
            width,
            height,
            cascades: CascadeParams::default(),
            resolve: ResolveParams::default(),
            converged_below: DEFAULT_CONVERGED_BELOW,
            aovs: Vec::new(),
            denoise: Denoise::None,
            denoise_guides: None,
        }
    }
}

/// One AOV of a frame: a layer of the passes other than the beauty, accumulated as a plain
/// per-pixel mean of each of its channels and served as the layer `name` of `image.exr`
/// (channels `name.R`, `name.G`, ...).
///
/// `name` is the layer's name in the passes, as `POST /v1/frames/{id}/passes` lists layers
/// (`albedo`, `ViewLayer.Denoising Albedo`, a part's name ...); `channels` are the channel names
/// after the layer's prefix (`R`, `G`, `B`; `X`, `Y`, `Z`; `Z`; `V` ...).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AovSpec {
    /// The layer's name.
    pub name: String,
    /// Its channels, in the order they are stored and served.
    pub channels: Vec<String>,
}

impl AovSpec {
    /// An AOV `name` with `channels`.
    pub fn new(name: impl Into<String>, channels: &[&str]) -> AovSpec {
        AovSpec {
            name: name.into(),
            channels: channels.iter().map(|c| c.to_string()).collect(),
        }
    }
}

/// Body of `PUT /v1/frames/{id}` (create-or-get, allowed to `write` tokens): the creation
/// parameters of [`CreateFrame`], the id coming from the path. An `id` in the body is
/// optional and must then equal the path's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PutFrame {
    /// Frame id; when given, it must be the path's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Cascade layout; defaults when omitted.
    #[serde(default)]
    pub cascades: CascadeParams,
    /// Default resolve settings; defaults when omitted.
    #[serde(default)]
    pub resolve: ResolveParams,
    /// Convergence threshold ([`CreateFrame::converged_below`]); default when omitted.
    #[serde(default = "default_converged_below")]
    pub converged_below: f64,
    /// AOVs accumulated beside the beauty from passes that carry them (none when omitted); see
    /// [`AovSpec`].
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub aovs: Vec<AovSpec>,
    /// [`CreateFrame::denoise`].
    #[serde(default, skip_serializing_if = "Denoise::is_none")]
    pub denoise: Denoise,
    /// [`CreateFrame::denoise_guides`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub denoise_guides: Option<DenoiseGuides>,
}

impl PutFrame {
    /// The create request this body makes for frame `id`.
    pub fn into_create(self, id: impl Into<String>) -> CreateFrame {
        CreateFrame {
            id: id.into(),
            width: self.width,
            height: self.height,
            cascades: self.cascades,
            resolve: self.resolve,
            converged_below: self.converged_below,
            aovs: self.aovs,
            denoise: self.denoise,
            denoise_guides: self.denoise_guides,
        }
    }
}

impl From<&CreateFrame> for PutFrame {
    fn from(c: &CreateFrame) -> PutFrame {
        PutFrame {
            id: Some(c.id.clone()),
            width: c.width,
            height: c.height,
            cascades: c.cascades.clone(),
            resolve: c.resolve.clone(),
            converged_below: c.converged_below,
            aovs: c.aovs.clone(),
            denoise: c.denoise,
            denoise_guides: c.denoise_guides.clone(),
        }
    }
}

/// State of a frame: response of `POST /v1/frames`, `PUT /v1/frames/{id}` and
/// `GET /v1/frames/{id}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameInfo {
    /// Frame id.
    pub id: String,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Cascade layout.
    pub cascades: CascadeParams,
    /// Default resolve settings.
    pub resolve: ResolveParams,
    /// Accepted samples (records), duplicates not counted.
    pub samples: u64,
    /// Accepted batches, duplicates not counted.
    pub batches: u64,
    /// Fewest samples of any pixel.
    pub spp_min: u64,
    /// Mean samples per pixel.
    pub spp_mean: f64,
    /// Most samples of any pixel.
    pub spp_max: u64,
    /// Samples in rejected batches.
    pub rejected_samples: u64,
    /// Rejected batches.
    pub rejected_batches: u64,
    /// Memory the frame's accumulation buffers use.
    pub memory_bytes: u64,
    /// The AOV layers the frame was created with (served in `image.exr` as
    /// `<layer>.<channel>`); empty for a frame without AOVs.
    #[serde(default)]
    pub aovs: Vec<AovSpec>,
    /// The frame's default denoiser ([`CreateFrame::denoise`]; absent: none).
    #[serde(default, skip_serializing_if = "Denoise::is_none")]
    pub denoise: Denoise,
    /// The AOVs a denoised image is guided by, as given at creation or chosen by name (see
    /// [`DenoiseGuides`]); absent when there are none.
    #[serde(default, skip_serializing_if = "DenoiseGuides::is_empty")]
    pub denoise_guides: DenoiseGuides,
    /// How far the frame is from converged (`GET /v1/frames/{id}` only; absent in lists, and
    /// when the server's working memory was too busy to resolve the frame).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub convergence: Option<Convergence>,
}

/// A frame's convergence, from its latest resolve (see `GET /v1/frames/{id}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Convergence {
    /// Samples in the resolved state.
    pub samples: u64,
    /// Fewest samples of any pixel.
    pub spp_min: u64,
    /// Mean samples per pixel.
    pub spp_mean: f64,
    /// Most samples of any pixel.
    pub spp_max: u64,
    /// Luminance the resolve removed, as a fraction of the plain mean's; it falls toward 0 as
    /// samples accumulate.
    pub removed_fraction: f64,
    /// Luminance in brightness bands that lack support, as a fraction of the mean's.
    pub deficit_fraction: f64,
    /// Samples accepted per second lately (over the last second or more).
    pub samples_per_second: f64,
    /// The frame's threshold ([`CreateFrame::converged_below`]).
    pub converged_below: f64,
    /// The fewest samples a pixel needs to be judged by its own samples alone (16 with the
    /// default resolve); below it the resolve counts what the pixel's neighbours agree on.
    /// 0 from a server that does not say.
    #[serde(default)]
    pub own_count_from: u64,
    /// Every pixel has samples, `removed_fraction <= converged_below`, and, while `spp_min <
    /// own_count_from`, `deficit_fraction <= converged_below` too: a frame of a farm's first
    /// passes is judged by each pixel's own samples, not by its neighbours' agreement.
    pub converged: bool,
    /// While the frame has not converged, the first of those conditions it fails: what the
    /// farm is waiting on. `None` once it has converged, and from a server that does not say.
    #[serde(default)]
    pub waiting_on: Option<WaitingOn>,
    /// Earlier figures, oldest first: one point per resolved version of the frame, thinned to
    /// at most a few hundred points (every other one is dropped when the list is full).
    pub history: Vec<ConvergencePoint>,
}

/// What keeps a frame from converging ([`Convergence::waiting_on`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WaitingOn {
    /// Some pixel has no samples (`spp_min` is 0).
    PixelsWithoutSamples,
    /// The resolve removes more than `converged_below` of the mean's energy.
    RemovedEnergy,
    /// Some pixel has fewer than `own_count_from` samples, and the bands short of their own
    /// support hold more than `converged_below` of the energy (`deficit_fraction`).
    OwnSamples,
}

impl WaitingOn {
    /// What the estimator's verdict waits on (`None` for a converged frame).
    pub fn of(verdict: estimator::Verdict) -> Option<WaitingOn> {
        match verdict {
            estimator::Verdict::Converged => None,
            estimator::Verdict::PixelsWithoutSamples => Some(WaitingOn::PixelsWithoutSamples),
            estimator::Verdict::RemovedEnergy => Some(WaitingOn::RemovedEnergy),
            estimator::Verdict::OwnSamples => Some(WaitingOn::OwnSamples),
        }
    }
}

/// One point of [`Convergence::history`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ConvergencePoint {
    /// Seconds since the server took the frame in (created or restored it).
    pub seconds: f64,
    /// Samples then.
    pub samples: u64,
    /// Mean samples per pixel then.
    pub spp_mean: f64,
    /// [`Convergence::removed_fraction`] then.
    pub removed_fraction: f64,
}

/// Response of `GET /v1/frames/{id}/need`: the frame in tiles, row-major, each scored by how
/// much it would gain from more samples (see `splatd_estimator::NeedMap`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NeedMap {
    /// The frame.
    pub frame: String,
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Tile edge in pixels; the last column and row of tiles may be smaller.
    pub tile: u32,
    /// Tiles per row.
    pub tiles_x: u32,
    /// Rows of tiles.
    pub tiles_y: u32,
    /// Samples in the resolved state.
    pub samples: u64,
    /// Need of each tile: `(removed + deficit) / mean + empty / pixels`, divided by the tile's
    /// spp plus one.
    pub need: Vec<f64>,
    /// Removed luminance of each tile as a fraction of its mean's.
    pub removed_fraction: Vec<f64>,
    /// Luminance in bands lacking support, as a fraction of the tile's mean's.
    pub deficit_fraction: Vec<f64>,
    /// Mean samples per pixel of each tile.
    pub spp_mean: Vec<f64>,
    /// Fewest samples of a pixel of each tile.
    pub spp_min: Vec<u64>,
}

impl NeedMap {
    /// The map as the estimator's type, to plan with ([`estimator::NeedMap::plan`]). The
    /// tiles' energies are not on the wire: they carry the need and the sample counts only.
    pub fn to_estimator(&self) -> Result<estimator::NeedMap, String> {
        let n = (self.tiles_x as usize) * (self.tiles_y as usize);
        if self.tile == 0
            || self.width.div_ceil(self.tile) != self.tiles_x
            || self.height.div_ceil(self.tile) != self.tiles_y
            || [self.need.len(), self.spp_mean.len(), self.spp_min.len()] != [n; 3]
        {
            return Err(format!(
                "need map of {}x{} in {} px tiles has {} tiles in {}x{} and {} scores",
                self.width,
                self.height,
                self.tile,
                n,
                self.tiles_x,
                self.tiles_y,
                self.need.len()
            ));
        }
        let tile = self.tile;
        let tiles = (0..n)
            .map(|i| {
                let (tx, ty) = (i as u32 % self.tiles_x, i as u32 / self.tiles_x);
                let (width, height) = (
                    tile.min(self.width - tx * tile),
                    tile.min(self.height - ty * tile),
                );
                estimator::TileNeed {
                    x: tx * tile,
                    y: ty * tile,
                    width,
                    height,
                    samples: (self.spp_mean[i] * f64::from(width * height)).round() as u64,
                    spp_min: self.spp_min[i],
                    need: self.need[i],
                    ..estimator::TileNeed::default()
                }
            })
            .collect();
        Ok(estimator::NeedMap {
            width: self.width,
            height: self.height,
            tile,
            tiles_x: self.tiles_x,
            tiles_y: self.tiles_y,
            tiles,
        })
    }
}

/// Query of `GET /v1/frames/{id}/need`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NeedQuery {
    /// Tile edge in pixels (default [`DEFAULT_NEED_TILE`], at most
    /// `splatd_estimator::MAX_NEED_TILE`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tile: Option<u32>,
    /// `json` (default) or `exr`: one pixel per tile, channels `need.Y`, `removed.Y`,
    /// `deficit.Y`, `spp.Y` (mean spp) and `spp_min.Y`.
    #[serde(default)]
    pub format: NeedFormat,
}

/// Encoding of a need map.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NeedFormat {
    /// JSON [`NeedMap`].
    #[default]
    Json,
    /// OpenEXR, one pixel per tile.
    Exr,
}

/// Response of `GET /v1/frames`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameList {
    /// All frames, in no particular order.
    pub frames: Vec<FrameInfo>,
    /// Frames whose files were found damaged or missing when the server started: not served,
    /// their files moved aside for an operator to look at. Empty on a healthy server.
    #[serde(default)]
    pub quarantined: Vec<QuarantinedFrame>,
}

/// A frame set aside at start because its files could not be read (see [`FrameList`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct QuarantinedFrame {
    /// The frame id.
    pub id: String,
    /// Why it could not be read.
    pub reason: String,
    /// Where its files are now, on the server.
    pub moved_to: String,
}

/// Response of `POST /v1/frames/{id}/samples`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BatchAck {
    /// Frame id.
    pub frame: String,
    /// Worker id of the batch.
    pub worker: u64,
    /// Sequence number of the batch.
    pub seq: u64,
    /// Samples applied by this request (0 for a duplicate).
    pub accepted: u64,
    /// True when `(worker, seq)` had already been applied and this request
    /// changed nothing.
    pub duplicate: bool,
    /// Identifies the server process; it changes when the server restarts. A durable server
    /// loses what it applied after its last snapshot when it crashes: a worker that sees `boot`
    /// change resends every batch it has not yet seen covered by `durable_floor`.
    #[serde(default)]
    pub boot: u64,
    /// Durable servers only: every batch of this worker for this frame numbered below this is on
    /// disk and survives a crash; the worker may forget those. Absent when the server keeps
    /// frames only in memory.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub durable_floor: Option<u64>,
    /// Durable servers only, and only when true: the frame's last snapshot failed (a full disk,
    /// say), so `durable_floor` is not advancing; this batch is applied but will not be durable
    /// until the snapshots succeed again (`/healthz` names the frames).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub snapshots_failing: bool,
}

/// Response of `POST /v1/frames/{id}/sync`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SyncAck {
    /// The frame.
    pub frame: String,
    /// The server process (see [`BatchAck::boot`]).
    pub boot: u64,
    /// Whether the server is durable at all; when false nothing survives a restart.
    pub durable: bool,
}

/// Response of `POST /v1/frames/{id}/state` (importing a state or a pushed delta).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ImportAck {
    /// The frame.
    pub frame: String,
    /// Samples the state added (0 for a duplicate).
    pub samples: u64,
    /// The state was a delta this frame had applied before; nothing was added.
    pub duplicate: bool,
}

/// Body of every error response (4xx and 5xx).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ErrorBody {
    /// Machine-readable code, e.g. `"pixel_out_of_range"`.
    pub error: String,
    /// A sentence for humans naming the problem.
    pub message: String,
}

impl ErrorBody {
    /// An error body with code `error` and message `message`.
    pub fn new(error: impl Into<String>, message: impl Into<String>) -> ErrorBody {
        ErrorBody {
            error: error.into(),
            message: message.into(),
        }
    }
}

impl fmt::Display for ErrorBody {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.error, self.message)
    }
}

impl From<&crate::WireError> for ErrorBody {
    fn from(e: &crate::WireError) -> Self {
        ErrorBody::new(e.code(), e.to_string())
    }
}

/// Query of `GET /v1/frames/{id}`: which convergence figures the answer carries.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InfoQuery {
    /// `fresh` when omitted.
    #[serde(default)]
    pub convergence: InfoConvergence,
}

/// The convergence figures `GET /v1/frames/{id}` answers with (`convergence=`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InfoConvergence {
    /// Figures of a render of the frame as it is: rendered now if the frame changed since its
    /// latest figures, which on a frame that workers keep changing waits for its render pace.
    #[default]
    Fresh,
    /// The latest figures at once, never waiting for a render: if the frame changed since they
    /// were made, one render of its figures is started for later requests. `convergence.samples`
    /// (and the spp figures, which come from the same render) say what they saw; absent until a
    /// first render filed any. What the live page asks for every second; a `converged` verdict
    /// from them may be a render old.
    Latest,
    /// No figures: the counts alone (a count of the frame's cells), which never cost a render.
    None,
}

/// Query of `GET /v1/frames/{id}/image.exr`: overrides of the frame's
/// [`ResolveParams`], plus `cascades=1` to add the raw cascade layers.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageQuery {
    /// Overrides [`ResolveParams::variant`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub variant: Option<Variant>,
    /// Overrides [`ResolveParams::kappa`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kappa: Option<f64>,
    /// Overrides [`ResolveParams::kappa_min`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kappa_min: Option<f64>,
    /// Overrides [`ResolveParams::kappa_exponent`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kappa_exponent: Option<f64>,
    /// Add one layer per cascade to the EXR (`cascades=1`).
    #[serde(default, with = "flag")]
    pub cascades: bool,
    /// Run a denoiser and add its output as the layer `denoised` (`denoise=oidn`), or not
    /// (`denoise=none`); overrides [`CreateFrame::denoise`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub denoise: Option<Denoise>,
    /// OIDN's quality mode (`high` when omitted).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub denoise_quality: Option<DenoiseQuality>,
}

impl ImageQuery {
    /// `base` with this query's overrides applied.
    pub fn apply(&self, base: &ResolveParams) -> ResolveParams {
        ResolveParams {
            variant: self.variant.unwrap_or(base.variant),
            kappa: self.kappa.unwrap_or(base.kappa),
            kappa_min: self.kappa_min.unwrap_or(base.kappa_min),
            kappa_exponent: self.kappa_exponent.unwrap_or(base.kappa_exponent),
        }
    }
}

/// A boolean query flag written `1`/`0` (or `true`/`false`): query-string
/// deserialisers hand every value over as a string.
mod flag {
    use serde::de::{self, Visitor};
    use serde::{Deserializer, Serializer};
    use std::fmt;

    pub fn serialize<S: Serializer>(v: &bool, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_u8(u8::from(*v))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<bool, D::Error> {
        struct Flag;
        impl Visitor<'_> for Flag {
            type Value = bool;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("1, 0, true or false")
            }
            fn visit_bool<E: de::Error>(self, v: bool) -> Result<bool, E> {
                Ok(v)
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<bool, E> {
                match v {
                    0 => Ok(false),
                    1 => Ok(true),
                    _ => Err(E::invalid_value(de::Unexpected::Unsigned(v), &self)),
                }
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<bool, E> {
                match v {
                    0 => Ok(false),
                    1 => Ok(true),
                    _ => Err(E::invalid_value(de::Unexpected::Signed(v), &self)),
                }
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<bool, E> {
                match v {
                    "1" | "true" => Ok(true),
                    "0" | "false" => Ok(false),
                    _ => Err(E::invalid_value(de::Unexpected::Str(v), &self)),
                }
            }
        }
        d.deserialize_any(Flag)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn create_frame_defaults() {
        let c: CreateFrame =
            serde_json::from_value(json!({"id": "f", "width": 4, "height": 2})).expect("valid");
        assert_eq!(c, CreateFrame::new("f", 4, 2));
        assert_eq!(c.cascades.base, 8.0);
        assert_eq!(c.cascades.cascades, 6);
        assert_eq!(c.cascades.lowest_scale, 0.125);
        assert_eq!(c.cascades.luminance, [0.2126, 0.7152, 0.0722]);
        assert_eq!(c.resolve.variant, Variant::Spread);
        assert_eq!(c.resolve.kappa, 3.0);
        assert_eq!(c.resolve.kappa_min, 1.0);
        assert_eq!(c.resolve.kappa_exponent, 0.3);
        assert_eq!(c.converged_below, 0.01);
    }

    /// The denoise fields: omitted means none and by name, and they round-trip through
    /// `PutFrame`; an old frame's JSON (without them) writes back unchanged.
    #[test]
    fn denoise_fields_default_to_none_and_round_trip() {
        let c: CreateFrame = serde_json::from_value(json!({
            "id": "f", "width": 4, "height": 2, "denoise": "oidn",
            "denoise_guides": {"albedo": "ViewLayer.DiffCol"}
        }))
        .expect("valid");
        assert_eq!(c.denoise, Denoise::Oidn);
        let guides = c.denoise_guides.clone().unwrap();
        assert_eq!(
            (guides.albedo.as_deref(), guides.normal),
            (Some("ViewLayer.DiffCol"), None)
        );
        assert_eq!(PutFrame::from(&c).into_create("f"), c);
        let plain = json!({"id": "f", "width": 4, "height": 2});
        let old: CreateFrame = serde_json::from_value(plain.clone()).unwrap();
        assert_eq!(
            (old.denoise, old.denoise_guides.clone()),
            (Denoise::None, None)
        );
        let back = serde_json::to_value(&old).unwrap();
        assert!(back.get("denoise").is_none() && back.get("denoise_guides").is_none());
        for bad in [
            json!({"id": "f", "width": 4, "height": 2, "denoise": "bm3d"}),
            json!({"id": "f", "width": 4, "height": 2, "denoise_guides": {"albedo": "a", "depth": "z"}}),
        ] {
            assert!(serde_json::from_value::<CreateFrame>(bad).is_err());
        }
    }

    #[test]
    fn partial_params_fill_in_per_field() {
        let c: CreateFrame = serde_json::from_value(json!({
            "id": "f", "width": 4, "height": 2,
            "cascades": {"base": 4.0},
            "resolve": {"variant": "shader", "kappa": 2.5}
        }))
        .expect("valid");
        assert_eq!(c.cascades.base, 4.0);
        assert_eq!(c.cascades.cascades, DEFAULT_CASCADE_COUNT);
        assert_eq!(c.resolve.variant, Variant::Shader);
        assert_eq!(c.resolve.kappa, 2.5);
        assert_eq!(c.resolve.kappa_min, DEFAULT_KAPPA_MIN);
    }

    #[test]
    fn unknown_fields_are_refused_in_requests() {
        for bad in [
            json!({"id": "f", "width": 4, "height": 2, "widht": 3}),
            json!({"id": "f", "width": 4, "height": 2, "resolve": {"kapa": 1.0}}),
            json!({"id": "f", "width": 4, "height": 2, "cascades": {"count": 3}}),
        ] {
            let err = serde_json::from_value::<CreateFrame>(bad).unwrap_err();
            assert!(err.to_string().contains("unknown field"), "{err}");
        }
    }

    #[test]
    fn variant_names() {
        assert_eq!(json!(Variant::Paper), json!("paper"));
        assert_eq!(json!(Variant::Shader), json!("shader"));
        assert_eq!(json!(Variant::Off), json!("off"));
        for v in Variant::ALL {
            assert_eq!(v.as_str().parse::<Variant>(), Ok(v));
            assert_eq!(
                serde_json::from_value::<Variant>(json!(v.as_str())).ok(),
                Some(v)
            );
        }
        assert!("Paper".parse::<Variant>().is_err());
        assert!(serde_json::from_value::<Variant>(json!("median")).is_err());
    }

    #[test]
    fn responses_round_trip_and_tolerate_new_fields() {
        let info = FrameInfo {
            id: "f".into(),
            width: 4,
            height: 2,
            cascades: CascadeParams::default(),
            resolve: ResolveParams::default(),
            samples: 10,
            batches: 2,
            spp_min: 1,
            spp_mean: 1.25,
            spp_max: 2,
            rejected_samples: 3,
            rejected_batches: 1,
            memory_bytes: 4096,
            aovs: vec![AovSpec::new("albedo", &["R", "G", "B"])],
            denoise: Denoise::Oidn,
            denoise_guides: DenoiseGuides {
                albedo: Some("albedo".into()),
                normal: None,
            },
            convergence: None,
        };
        let mut v = serde_json::to_value(&info).expect("serialises");
        assert_eq!(
            serde_json::from_value::<FrameInfo>(v.clone()).ok(),
            Some(info.clone())
        );
        v["added_later"] = json!(1);
        assert_eq!(
            serde_json::from_value::<FrameInfo>(v.clone()).ok(),
            Some(info)
        );
        // A server from before AOVs were listed: no `aovs` field, read as none.
        v.as_object_mut().unwrap().remove("aovs");
        v.as_object_mut().unwrap().remove("denoise");
        v.as_object_mut().unwrap().remove("denoise_guides");
        let old = serde_json::from_value::<FrameInfo>(v).expect("an older server's answer");
        assert!(old.aovs.is_empty());
        assert_eq!(
            (old.denoise, old.denoise_guides),
            (Denoise::None, DenoiseGuides::default())
        );

        let ack = BatchAck {
            frame: "f".into(),
            worker: 1,
            seq: 2,
            accepted: 3,
            duplicate: false,
            boot: 9,
            durable_floor: None,
            snapshots_failing: false,
        };
        let v = serde_json::to_value(&ack).expect("serialises");
        assert_eq!(
            v,
            json!({"frame": "f", "worker": 1, "seq": 2, "accepted": 3, "duplicate": false,
                   "boot": 9})
        );
        // An older server without the durability fields still parses.
        let old = json!({"frame": "f", "worker": 1, "seq": 2, "accepted": 3, "duplicate": false});
        assert_eq!(
            serde_json::from_value::<BatchAck>(old).ok(),
            Some(BatchAck { boot: 0, ..ack })
        );
    }

    #[test]
    fn error_body_from_wire_error() {
        let e = crate::WireError::TrailingBytes { count: 3 };
        let body = ErrorBody::from(&e);
        assert_eq!(body.error, "trailing_bytes");
        assert_eq!(
            serde_json::to_value(&body).expect("serialises"),
            json!({"error": "trailing_bytes", "message": e.to_string()})
        );
    }

    #[test]
    fn need_queries_and_maps() {
        let q: NeedQuery =
            serde_json::from_value(json!({"tile": 8, "format": "exr"})).expect("valid");
        assert_eq!((q.tile, q.format), (Some(8), NeedFormat::Exr));
        let q: NeedQuery = serde_json::from_value(json!({})).expect("valid");
        assert_eq!((q.tile, q.format), (None, NeedFormat::Json));
        assert!(serde_json::from_value::<NeedQuery>(json!({"format": "png"})).is_err());
        assert!(serde_json::from_value::<NeedQuery>(json!({"tiles": 8})).is_err());

        // A 5x3 frame in 4 px tiles: a 4x3 tile and a 1x3 one.
        let map = NeedMap {
            frame: "f".into(),
            width: 5,
            height: 3,
            tile: 4,
            tiles_x: 2,
            tiles_y: 1,
            samples: 30,
            need: vec![0.5, 0.25],
            removed_fraction: vec![0.1, 0.2],
            deficit_fraction: vec![0.0, 0.3],
            spp_mean: vec![2.0, 2.0],
            spp_min: vec![1, 2],
        };
        let m = map.to_estimator().expect("consistent");
        let geometry: Vec<_> = m
            .tiles
            .iter()
            .map(|t| (t.x, t.y, t.width, t.height, t.samples, t.need))
            .collect();
        assert_eq!(geometry, [(0, 0, 4, 3, 24, 0.5), (4, 0, 1, 3, 6, 0.25)]);
        let short = NeedMap {
            need: vec![0.5],
            ..map
        };
        assert!(short.to_estimator().is_err());
    }

    #[test]
    fn image_query() {
        let q: ImageQuery =
            serde_json::from_value(json!({"variant": "off", "cascades": "1"})).expect("valid");
        assert_eq!(q.variant, Some(Variant::Off));
        assert!(q.cascades);
        let r = q.apply(&ResolveParams::default());
        assert_eq!(r.variant, Variant::Off);
        assert_eq!(r.kappa, DEFAULT_KAPPA);
        let q: ImageQuery = serde_json::from_value(json!({"cascades": 0})).expect("valid");
        assert!(!q.cascades);
        assert!(serde_json::from_value::<ImageQuery>(json!({"cascades": "yes"})).is_err());
        assert!(serde_json::from_value::<ImageQuery>(json!({"kapa": 1})).is_err());
    }
}
