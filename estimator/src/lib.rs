//! The estimator: cascaded firefly reweighting (Zirr, Hanika & Dachsbacher, "Re-weighting
//! Firefly Samples for Improved Finite-Sample Monte Carlo Estimates", CGF 37(6), 2018).
//!
//! Three verbs, as in a film of a renderer:
//! * **splat** ([`FrameState::splat`]): a sample is split by brightness between the two cascades
//!   around it ([`CascadeLayout::split`]) and counted in its pixel;
//! * **merge** ([`FrameState::merge`]): two partial states of the same frame add up exactly;
//! * **resolve** ([`FrameState::resolve`], [`resolve_bands`]): cascades in, the reweighted image,
//!   the plain mean and the removed energy out; after a batch changed a few pixels, an earlier
//!   resolve is brought up to date by resolving only around them ([`resolve_region_into`]), to
//!   the same bits;
//! * and from a resolve, **need** ([`NeedMap`]): which tiles would gain most from more samples,
//!   and how far the frame is from converged ([`Convergence`]).
//!
//! The core is pure: no I/O and no async; the only threads are the scoped ones
//! [`resolve_bands`] is asked for. All accumulated quantities are fixed-point integers (see
//! [`FRAC_BITS`]), so a state, and every image resolved from it, is bit-identical whatever the
//! order samples arrived in and however they were split across partial states.

mod aov;
pub mod denoise;
mod layout;
mod need;
mod resolve;
mod resolve_spread;
mod state;

pub use aov::{
    add_aov_pixel, aov_units, aov_values_accepted, aov_words, check_aov_pixel, check_aov_values,
    AovCellsError, AovSums, AovValueError, AOV_FRAC_BITS, AOV_MAX_ABS,
};
pub use layout::{
    component_bits_accepted, rec709_luminance, samples_accepted, CascadeLayout, ParamError, Split,
    COUNT_ONE, DEFAULT_CASCADE_BASE, DEFAULT_CASCADE_COUNT, DEFAULT_LOWEST_SCALE, FRAC_BITS,
    MAX_CASCADES, MAX_PIXEL_SAMPLES, MIN_LUMINANCE_WEIGHT, REC709_LUMINANCE, TOP_HEADROOM_BITS,
};
pub use need::{
    check_converged_below, check_tile, Convergence, NeedError, NeedMap, TileNeed, Verdict,
    DEFAULT_BASE_DOUBT, DEFAULT_CONVERGED_BELOW, DEFAULT_NEED_TILE, DEFAULT_UNIFORM_SHARE,
    MAX_NEED_TILE,
};
pub use resolve::{
    dependency_radius, reached_by, resolve_bands, resolve_bands_into, resolve_bands_with,
    resolve_region_into, resolve_region_with, Rect, ResolveParams, Resolved, TilingError, Variant,
    DEFAULT_KAPPA, DEFAULT_KAPPA_EXPONENT, DEFAULT_KAPPA_MIN, DEFAULT_VARIANT, SHADER_E_MIN_FLOOR,
};
pub use resolve_spread::{
    SpreadParams, DEFAULT_SPREAD_EDGE_SHARE, DEFAULT_SPREAD_MAX_RADIUS, DEFAULT_SPREAD_SOLID_SHARE,
    DEFAULT_SPREAD_SUPPORT, SPREAD_RADII,
};
pub use state::{
    add_cell, cascade_units, cell_len, cell_spp, check_pixels, check_sample, sub_cell, top_sum,
    CellsError, FrameState, Kernel, MergeError, SampleError, ShapeError, SplatReport,
    LOW_SHARE_MAX, TOP_SHARE_MAX,
};
