//! Running the server: the live page, health, metrics, and forcing a frame to disk.

use std::time::Duration;

use axum::extract::State;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use splatd_proto::api::{Convergence, SyncAck};

use crate::http::error::ApiError;
use crate::http::extract::{Frame, Json};
use crate::render::figures::SCRAPE_WAIT;
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
pub async fn metrics(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let Some(handle) = &app.metrics else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "metrics_disabled",
            "this server was started without a metrics recorder",
        ));
    };
    let mut text = handle.render();
    // Every frame's figures at once, each waiting for a fresh render until one deadline.
    let deadline = tokio::time::Instant::now() + scrape_wait(&headers);
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

/// The header Prometheus sends with every scrape: how long it waits for the answer, in seconds.
pub const SCRAPE_TIMEOUT_HEADER: &str = "x-prometheus-scrape-timeout-seconds";

/// How long a scrape waits for fresh figures: half the timeout the scraper says it has
/// ([`SCRAPE_TIMEOUT_HEADER`]), and at most [`SCRAPE_WAIT`]. A Prometheus that scrapes every 5 s
/// gives each scrape 5 s (its timeout cannot exceed its interval), and a scrape that waited
/// [`SCRAPE_WAIT`] for a busy frame's render would time out: the target would read as down and
/// the dashboard lose its points. A header that is not a positive number of seconds is ignored.
fn scrape_wait(headers: &HeaderMap) -> Duration {
    headers
        .get(SCRAPE_TIMEOUT_HEADER)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<f64>().ok())
        .filter(|&seconds| seconds > 0.0)
        .and_then(|seconds| Duration::try_from_secs_f64(seconds / 2.0).ok())
        .map_or(SCRAPE_WAIT, |half| half.min(SCRAPE_WAIT))
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
            "Seconds since the render these figures come from (a scrape waits for a frame that \
             changed half its scrape timeout, 5 s at most).",
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
