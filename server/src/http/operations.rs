//! Running the server: the live page, health, metrics, and forcing a frame to disk.

use axum::extract::State;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use splatd_proto::api::{Convergence, SyncAck};

use crate::http::error::ApiError;
use crate::http::extract::{Frame, Json};
use crate::render::figures::FiguresError;
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

/// `GET /metrics`: Prometheus text format; 404 `metrics_disabled` without a recorder. After
/// the recorder's metrics come the convergence gauges of every frame there is now.
pub async fn metrics(State(app): State<AppState>) -> Result<Response, ApiError> {
    let Some(handle) = &app.metrics else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "metrics_disabled",
            "this server was started without a metrics recorder",
        ));
    };
    let mut text = handle.render();
    let mut frames = Vec::new();
    for frame in app.store.list() {
        match crate::render::figures::convergence(&app, &frame).await {
            Ok(c) => frames.push((frame.id().to_owned(), c)),
            // A frame deleted meanwhile has no figures; one that could not get working
            // memory is left out of this scrape, and the log says so.
            Err(FiguresError::Busy(busy)) => {
                tracing::warn!(frame = frame.id(), "no convergence metrics: {busy}")
            }
            Err(e) => return Err(e.into()),
        }
    }
    text.push_str(&convergence_metrics(&frames));
    Ok((
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/plain; version=0.0.4"),
        )],
        text,
    )
        .into_response())
}

/// The per-frame convergence gauges in the Prometheus text format.
pub fn convergence_metrics(frames: &[(String, Convergence)]) -> String {
    type Gauge = (&'static str, &'static str, fn(&Convergence) -> f64);
    const GAUGES: [Gauge; 7] = [
        (
            crate::meters::FRAME_REMOVED_FRACTION,
            "Luminance the resolve removes, as a fraction of the plain mean's.",
            |c| c.removed_fraction,
        ),
        (
            crate::meters::FRAME_SPP_MIN,
            "Fewest samples of any pixel.",
            |c| c.spp_min as f64,
        ),
        (
            crate::meters::FRAME_SPP_MEAN,
            "Mean samples per pixel.",
            |c| c.spp_mean,
        ),
        (
            crate::meters::FRAME_SPP_MAX,
            "Most samples of any pixel.",
            |c| c.spp_max as f64,
        ),
        (
            crate::meters::FRAME_SAMPLES_PER_SECOND,
            "Samples accepted per second lately.",
            |c| c.samples_per_second,
        ),
        (
            crate::meters::FRAME_CONVERGED,
            "1 when the frame is converged at its threshold, else 0.",
            |c| f64::from(u8::from(c.converged)),
        ),
        (
            crate::meters::FRAME_CONVERGED_BELOW,
            "The frame's convergence threshold.",
            |c| c.converged_below,
        ),
    ];
    let mut out = String::new();
    if frames.is_empty() {
        return out;
    }
    for (name, help, value) in GAUGES {
        out.push_str(&format!("# HELP {name} {help}\n# TYPE {name} gauge\n"));
        for (id, c) in frames {
            let id = id.replace('\\', "\\\\").replace('"', "\\\"");
            out.push_str(&format!("{name}{{frame=\"{id}\"}} {}\n", value(c)));
        }
    }
    out
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
