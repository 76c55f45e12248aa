//! Where a frame needs samples: `GET /v1/frames/{id}/need`, the need map as JSON or OpenEXR.
//! The map is computed by the estimator from a shared render ([`crate::render::figures`]).

use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use exr::prelude::{AnyChannel, FlatSamples, LayerAttributes, Text};
use splatd_proto::api::{self, NeedFormat, NeedQuery, DEFAULT_NEED_TILE};

use crate::http::blocking::blocking;
use crate::http::error::ApiError;
use crate::http::extract::{Frame, Query};
use crate::render::figures::need_map;
use crate::AppState;

/// `GET /v1/frames/{id}/need?tile=T&format=json|exr`.
pub async fn get_need(
    State(app): State<AppState>,
    Query(query): Query<NeedQuery>,
    Frame(frame): Frame,
) -> Result<Response, ApiError> {
    let tile = query.tile.unwrap_or(DEFAULT_NEED_TILE);
    let json = need_map(&app, &frame, tile).await?;
    Ok(match query.format {
        NeedFormat::Json => (
            [
                (header::CONTENT_TYPE, "application/json"),
                (header::CACHE_CONTROL, "no-store"),
            ],
            json,
        )
            .into_response(),
        NeedFormat::Exr => {
            let exr = blocking("need map EXR", move || {
                let map: api::NeedMap = serde_json::from_slice(&json)
                    .map_err(|e| ApiError::internal("need map JSON", e))?;
                encode_need_exr(&map)
                    .map(Bytes::from)
                    .map_err(|e| ApiError::internal("need map EXR", e))
            })
            .await?;
            ([(header::CONTENT_TYPE, "image/x-exr")], exr).into_response()
        }
    })
}

/// A need map as a one-part EXR of `tiles_x` x `tiles_y` pixels, one per tile, with the
/// single-channel layers `need.Y`, `removed.Y`, `deficit.Y`, `spp.Y` (mean) and `spp_min.Y`.
pub fn encode_need_exr(map: &api::NeedMap) -> exr::error::Result<Vec<u8>> {
    let f32s = |v: &[f64]| FlatSamples::F32(v.iter().map(|&x| x as f32).collect());
    let channels = vec![
        AnyChannel::new("need.Y", f32s(&map.need)),
        AnyChannel::new("removed.Y", f32s(&map.removed_fraction)),
        AnyChannel::new("deficit.Y", f32s(&map.deficit_fraction)),
        AnyChannel::new("spp.Y", f32s(&map.spp_mean)),
        AnyChannel::new(
            "spp_min.Y",
            FlatSamples::F32(map.spp_min.iter().map(|&n| n as f32).collect()),
        ),
    ];
    let attributes = LayerAttributes {
        software_name: Some(Text::from("splatd need map")),
        ..LayerAttributes::default()
    };
    splatd_formats::exr::write_one_part(
        (map.tiles_x as usize, map.tiles_y as usize),
        attributes,
        channels,
    )
}
