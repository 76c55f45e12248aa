//! Running the server: the live page, health, metrics, and forcing a frame to disk.

use axum::extract::State;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use splatd_proto::api::SyncAck;

use crate::http::error::ApiError;
use crate::http::extract::{Frame, Json};
use crate::AppState;

/// `GET /`: the live page.
pub async fn index() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        include_str!("web/index.html"),
    )
}

/// `GET /healthz`: answers 200 while the server accepts requests. `status` is `degraded` when
/// acknowledged samples are not all becoming durable (a frame's last snapshot failed) or when
/// frames were found damaged at start and set aside; the body says which.
pub async fn healthz(State(app): State<AppState>) -> impl IntoResponse {
    let Some(durable) = &app.durable else {
        return Json(serde_json::json!({"status": "ok"}));
    };
    let failing = durable.failing();
    let quarantined: Vec<_> = durable.quarantined().into_iter().map(|q| q.frame).collect();
    let status = if failing.is_empty() && quarantined.is_empty() {
        "ok"
    } else {
        "degraded"
    };
    Json(serde_json::json!({
        "status": status,
        "snapshots_failing": failing,
        "frames_quarantined": quarantined,
    }))
}

/// `GET /metrics`: Prometheus text format; 404 `metrics_disabled` without a recorder.
pub async fn metrics(State(app): State<AppState>) -> Result<Response, ApiError> {
    let Some(handle) = &app.metrics else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "metrics_disabled",
            "this server was started without a metrics recorder",
        ));
    };
    Ok((
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/plain; version=0.0.4"),
        )],
        handle.render(),
    )
        .into_response())
}

/// `POST /v1/frames/{id}/sync`: returns once everything applied to the frame is on disk.
pub async fn sync(
    State(app): State<AppState>,
    Frame(frame): Frame,
) -> Result<Json<SyncAck>, ApiError> {
    app.sync(&frame).await?;
    Ok(Json(SyncAck {
        frame: frame.id().to_owned(),
        boot: app.boot,
        durable: app.durable.is_some(),
    }))
}
