//! The HTTP surface: the router, its layers, the handlers and the JSON errors they answer.
//!
//! Handlers are small and grouped by concept; each takes typed extractors ([`extract`]) and
//! answers [`error::ApiError`]s. The domain below them (`store`, `frame`, `durable`) knows
//! nothing of HTTP: its errors become statuses and codes in [`error`] alone.
//!
//! * [`frames`]: create, list, inspect, delete; [`ingest`]: samples and passes;
//!   [`images`]: EXR and PNG; [`states`]: export and import; [`operations`]: the page, health,
//!   metrics, sync;
//! * [`extract`]: request extractors with JSON refusals; [`error`]: the one error type;
//!   [`blocking`]: heavy work off the reactor;
//! * [`auth`]: bearer tokens and roles.

pub mod auth;
pub mod blocking;
pub mod error;
pub mod extract;
pub mod frames;
pub mod images;
pub mod ingest;
pub mod operations;
pub mod states;

use axum::extract::Request;
use axum::http::{header, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
use tower_http::compression::CompressionLayer;
use tower_http::decompression::RequestDecompressionLayer;
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;

use crate::AppState;
use error::ApiError;

/// The whole HTTP surface.
pub fn router(app: AppState) -> Router {
    let timeout = app.store.limits().request_timeout;
    let v1 = Router::new()
        .route("/frames", post(frames::create).get(frames::list))
        .route("/frames/{id}", get(frames::info).delete(frames::delete))
        .route("/frames/{id}/samples", post(ingest::post_samples))
        .route("/frames/{id}/image.exr", get(images::get_image))
        .route("/frames/{id}/sync", post(operations::sync))
        .route("/frames/{id}/passes", post(ingest::post_pass))
        .route("/frames/{id}/preview.png", get(images::get_preview))
        .route(
            "/frames/{id}/state",
            // States are mostly small integers and zeros: compress them for clients that ask.
            get(states::export)
                .layer(CompressionLayer::new().gzip(true).zstd(true))
                .post(states::import),
        );
    Router::new()
        .route("/", get(operations::index))
        .route("/healthz", get(operations::healthz))
        .route("/metrics", get(operations::metrics))
        .nest("/v1", v1)
        .fallback(unknown_route)
        .layer(RequestDecompressionLayer::new().gzip(true).zstd(true))
        // Outside decompression: a request without the right token is refused before its
        // body is read.
        .layer(axum::middleware::from_fn_with_state(
            app.clone(),
            auth::require_token,
        ))
        .layer(TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            timeout,
        ))
        .layer(axum::middleware::from_fn(json_errors))
        .layer(TraceLayer::new_for_http())
        .with_state(app)
}

async fn unknown_route(request: Request) -> ApiError {
    ApiError::new(
        StatusCode::NOT_FOUND,
        "unknown_route",
        format!("no endpoint {} {}", request.method(), request.uri().path()),
    )
}

/// Gives every error a JSON body, including the ones produced by layers and by axum itself (an
/// unsupported `Content-Encoding`, a wrong method), so clients can always parse an `ErrorBody`.
async fn json_errors(request: Request, next: Next) -> Response {
    let response = next.run(request).await;
    let status = response.status();
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let code = match status {
        StatusCode::METHOD_NOT_ALLOWED => "method_not_allowed",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_content_encoding",
        StatusCode::REQUEST_TIMEOUT => "request_timeout",
        StatusCode::PAYLOAD_TOO_LARGE => "body_too_large",
        _ => "http_error",
    };
    let reason = status.canonical_reason().unwrap_or("error");
    let message = match status {
        StatusCode::UNSUPPORTED_MEDIA_TYPE => {
            "unsupported Content-Encoding; use gzip, zstd or none".to_owned()
        }
        StatusCode::REQUEST_TIMEOUT => {
            "the request took longer than this server's request timeout".to_owned()
        }
        _ => reason.to_owned(),
    };
    let mut error = ApiError::new(status, code, message).into_response();
    for name in [header::ALLOW, header::RETRY_AFTER] {
        if let Some(v) = response.headers().get(&name) {
            error.headers_mut().insert(name, v.clone());
        }
    }
    error
}
