//! Running the server: the live page, health, metrics, and forcing a frame to disk.

use axum::extract::State;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use splatd_proto::api::{Convergence, SyncAck};

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
    // Every frame's figures at once, each waiting for a fresh render until one deadline.
    let deadline = tokio::time::Instant::now() + crate::render::figures::SCRAPE_WAIT;
    let waits: Vec<_> = app
        .store
        .list()
        .into_iter()
        .map(|frame| {
            let app = app.clone();
            tokio::spawn(async move {
                let figures = crate::render::figures::latest_convergence(&app, &frame, deadline);
                (frame.id().to_owned(), figures.await)
            })
        })
        .collect();
    let mut frames = Vec::new();
    for wait in waits {
        // A frame whose figures never rendered (no working memory: its render logged why) is
        // left out of this scrape.
        if let (id, Some((c, age))) = wait.await.expect("a scrape's wait does not panic") {
            frames.push(FrameFigures { id, c, age });
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

/// A frame's figures in a scrape.
#[derive(Debug)]
pub struct FrameFigures {
    /// The frame.
    pub id: String,
    /// Its latest figures.
    pub c: Convergence,
    /// Seconds since the render they come from.
    pub age: f64,
}

/// The per-frame convergence gauges in the Prometheus text format.
pub fn convergence_metrics(frames: &[FrameFigures]) -> String {
    type Gauge = (&'static str, &'static str, fn(&FrameFigures) -> f64);
    const GAUGES: [Gauge; 8] = [
        (
            crate::meters::FRAME_REMOVED_FRACTION,
            "Luminance the resolve removes, as a fraction of the plain mean's.",
            |f| f.c.removed_fraction,
        ),
        (
            crate::meters::FRAME_SPP_MIN,
            "Fewest samples of any pixel.",
            |f| f.c.spp_min as f64,
        ),
        (
            crate::meters::FRAME_SPP_MEAN,
            "Mean samples per pixel.",
            |f| f.c.spp_mean,
        ),
        (
            crate::meters::FRAME_SPP_MAX,
            "Most samples of any pixel.",
            |f| f.c.spp_max as f64,
        ),
        (
            crate::meters::FRAME_SAMPLES_PER_SECOND,
            "Samples accepted per second lately.",
            |f| f.c.samples_per_second,
        ),
        (
            crate::meters::FRAME_CONVERGED,
            "1 when the frame is converged at its threshold, else 0.",
            |f| f64::from(u8::from(f.c.converged)),
        ),
        (
            crate::meters::FRAME_CONVERGED_BELOW,
            "The frame's convergence threshold.",
            |f| f.c.converged_below,
        ),
        (
            crate::meters::FRAME_FIGURES_AGE,
            "Seconds since the render these figures come from (a scrape waits 5 s at most for \
             a frame that changed).",
            |f| f.age,
        ),
    ];
    let mut out = String::new();
    if frames.is_empty() {
        return out;
    }
    for (name, help, value) in GAUGES {
        out.push_str(&format!("# HELP {name} {help}\n# TYPE {name} gauge\n"));
        for f in frames {
            let id = f.id.replace('\\', "\\\\").replace('"', "\\\"");
            out.push_str(&format!("{name}{{frame=\"{id}\"}} {}\n", value(f)));
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
