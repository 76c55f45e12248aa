//! The API's documented defaults (in `splatd-proto`, which workers depend on without the core)
//! must be the estimator's defaults, which the quality benchmark chose.

use splatd::core::{self, CascadeLayout, ResolveParams};
use splatd_proto::api;

#[test]
fn api_defaults_are_the_estimators_defaults() {
    let layout = CascadeLayout::with_defaults();
    let cascades = api::CascadeParams::default();
    assert_eq!(cascades.base, layout.base());
    assert_eq!(cascades.cascades as usize, layout.cascades());
    assert_eq!(cascades.lowest_scale, layout.lowest_scale());
    assert_eq!(cascades.luminance, layout.luminance_weights());
    assert_eq!(cascades.luminance, core::REC709_LUMINANCE);

    let resolve = ResolveParams::with_defaults();
    let api_resolve = api::ResolveParams::default();
    assert_eq!(api_resolve.kappa, resolve.kappa());
    assert_eq!(api_resolve.kappa_min, resolve.kappa_min());
    assert_eq!(api_resolve.kappa_exponent, resolve.kappa_exponent());
    assert_eq!(api_resolve.variant, api::Variant::Paper);
    assert_eq!(resolve.variant(), core::Variant::Paper);
}
