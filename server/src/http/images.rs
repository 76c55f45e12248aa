//! Images out: the resolved OpenEXR (`image.exr`) and the live page's PNG preview.

use std::time::Instant;

use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use serde::{Deserialize, Deserializer};
use splatd_proto::api::ImageQuery;

use bytes::Bytes;

use crate::frame::{core_resolve_params, ShardedFrame};
use crate::http::error::ApiError;
use crate::http::extract::{Frame, Query};
use crate::image::{cascade_layers, encode_exr, Provenance};
use crate::AppState;

/// `GET /v1/frames/{id}/image.exr`: resolves the frame as it is now.
pub async fn get_image(
    State(app): State<AppState>,
    Query(query): Query<ImageQuery>,
    Frame(frame): Frame,
) -> Result<impl IntoResponse, ApiError> {
    let params = core_resolve_params(&query.apply(&frame.spec().request.resolve))?;
    let threads = app.resolve_threads;
    let started = Instant::now();
    let extra_layers = if query.cascades {
        frame.spec().layout.cascades() as u64
    } else {
        0
    };
    // The copy of the state, three resolved layers and the EXR holding them (and the raw
    // cascades when asked for), at 12 bytes per pixel and layer.
    // AOV means: two copies (planes and channels) of 4 bytes per channel and pixel.
    let aov_bytes = pixels(&frame) * 8 * frame.spec().aov_channels() as u64;
    let cost =
        frame.spec().memory_bytes() + pixels(&frame) * 12 * (6 + 2 * extra_layers) + aov_bytes;
    let key = format!("exr {params:?} {query:?}");
    let exr = app
        .renders
        .get_or_render(&frame, key, cost, move |frame| {
            let cut = frame.cut();
            let resolved = cut.resolve(&params, threads);
            let extra = if query.cascades {
                cascade_layers(cut.cascade_means())
            } else {
                Vec::new()
            };
            let aovs = cut
                .aovs
                .as_ref()
                .map(|sums| crate::image::aov_planes(&frame.spec().request.aovs, sums))
                .unwrap_or_default();
            drop(cut);
            let provenance = Provenance {
                layout: &frame.spec().layout,
                params: &params,
            };
            encode_exr(&resolved, &extra, &aovs, &provenance)
                .map(Bytes::from)
                .map_err(|e| ApiError::internal("EXR encoding", e))
        })
        .await?;
    metrics::histogram!("splatd_resolve_seconds").record(started.elapsed().as_secs_f64());
    Ok(([(header::CONTENT_TYPE, "image/x-exr")], exr))
}

/// Pixels of a frame.
fn pixels(frame: &ShardedFrame) -> u64 {
    let r = &frame.spec().request;
    u64::from(r.width) * u64::from(r.height)
}

/// Which layer a preview shows.
#[derive(Debug, Clone, Copy, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PreviewLayer {
    /// The reweighted image.
    #[default]
    Reweighted,
    /// The plain mean.
    Mean,
    /// The energy removed as fireflies.
    Removed,
}

/// Query of `GET /v1/frames/{id}/preview.png`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreviewQuery {
    /// The layer (default reweighted).
    #[serde(default)]
    pub layer: PreviewLayer,
    /// Exposure multiplier; by default chosen from the reweighted image, so that every layer
    /// of a frame is shown with the same exposure and compares fairly. Must be positive.
    #[serde(default, deserialize_with = "positive_exposure")]
    pub exposure: Option<f32>,
    /// Stops added to the exposure (the given one or the automatic one): the live page's
    /// exposure slider. In `[-20, 20]`, default 0.
    #[serde(default, deserialize_with = "bounded_stops")]
    pub stops: f32,
    /// Ignored: lets pages defeat caches by naming the sample count they expect.
    pub samples: Option<u64>,
}

/// Refuses an exposure that would give a black or meaningless image, as part of parsing the
/// query, so that it is refused (400 `bad_query`) before the frame is even looked up.
fn positive_exposure<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f32>, D::Error> {
    let exposure = Option::<f32>::deserialize(d)?;
    match exposure {
        Some(e) if !(e.is_finite() && e > 0.0) => Err(serde::de::Error::custom(format!(
            "exposure must be a positive number, got {e}"
        ))),
        _ => Ok(exposure),
    }
}

/// Refuses exposure stops outside `[-20, 20]` (or not a number) while parsing the query.
fn bounded_stops<'de, D: Deserializer<'de>>(d: D) -> Result<f32, D::Error> {
    let stops = f32::deserialize(d)?;
    if (-20.0..=20.0).contains(&stops) {
        Ok(stops)
    } else {
        Err(serde::de::Error::custom(format!(
            "stops must be a number in [-20, 20], got {stops}"
        )))
    }
}

/// `GET /v1/frames/{id}/preview.png`: a tone-mapped 8-bit view of a layer, for the live page.
pub async fn get_preview(
    State(app): State<AppState>,
    Query(query): Query<PreviewQuery>,
    Frame(frame): Frame,
) -> Result<impl IntoResponse, ApiError> {
    let params = frame.spec().resolve;
    let threads = app.resolve_threads;
    // The copy of the state, three resolved layers, the tone-mapped bytes and the PNG.
    let cost = frame.spec().memory_bytes() + pixels(&frame) * (36 + 6);
    let key = format!("png {:?} {:?} {}", query.layer, query.exposure, query.stops);
    let png = app
        .renders
        .get_or_render(&frame, key, cost, move |frame| {
            let resolved = frame.cut().resolve(&params, threads);
            let exposure = query
                .exposure
                .unwrap_or_else(|| crate::preview::auto_exposure(&resolved.reweighted))
                * query.stops.exp2();
            let layer = match query.layer {
                PreviewLayer::Reweighted => &resolved.reweighted,
                PreviewLayer::Mean => &resolved.mean,
                PreviewLayer::Removed => &resolved.removed,
            };
            let pixels = crate::preview::tonemap(layer, exposure);
            crate::preview::encode_png(resolved.width, resolved.height, &pixels)
                .map(Bytes::from)
                .map_err(|e| ApiError::internal("PNG encoding", e))
        })
        .await?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        png,
    ))
}
