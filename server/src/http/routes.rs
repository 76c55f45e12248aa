//! The HTTP surface, one small handler per endpoint: parse, call the frame, answer.
//!
//! Anything heavier than a lookup (decoding a batch, splatting it, resolving, encoding an EXR)
//! runs on tokio's blocking pool, so a 4-million-record batch never stalls the reactor.

use std::sync::Arc;
use std::time::Instant;

use axum::body::{Body, Bytes};
use axum::extract::{Path, RawQuery, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::de::DeserializeOwned;
use splatd_proto::api::{
    BatchAck, CreateFrame, FrameInfo, FrameList, ImageQuery, ImportAck, SyncAck,
};
use splatd_proto::{Batch, StateDump, BATCH_CONTENT_TYPE, STATE_CONTENT_TYPE};

use crate::frame::{core_resolve_params, ShardedFrame};
use crate::http::error::ApiError;
use crate::image::{cascade_layers, encode_exr};
use crate::store::Created;
use crate::AppState;

/// Largest JSON request body (a `CreateFrame` is a few hundred bytes).
const MAX_JSON_BODY: usize = 64 * 1024;

/// `GET /`: the live page.
pub async fn index() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        include_str!("web/index.html"),
    )
}

/// `GET /healthz`.
pub async fn healthz() -> impl IntoResponse {
    Json(serde_json::json!({"status": "ok"}))
}

/// `POST /v1/frames`.
pub async fn create_frame(
    State(app): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let request: CreateFrame = read_json(&headers, body).await?;
    let spec = app.store.check(request)?;
    let created = app.store.create(spec)?;
    let (status, frame) = match created {
        Created::New(frame) => {
            if let Err(e) = app.on_created(&frame).await {
                // Not durable: take it back, so the client's retry creates it properly.
                let _ = app.store.remove(frame.id());
                return Err(e.into());
            }
            tracing::info!(frame = frame.id(), "frame created");
            (StatusCode::CREATED, frame)
        }
        Created::Existing(frame) => (StatusCode::OK, frame),
    };
    metrics::gauge!("splatd_frames").set(app.store.list().len() as f64);
    Ok((status, Json(frame.info())).into_response())
}

/// `GET /v1/frames`.
pub async fn list_frames(State(app): State<AppState>) -> Json<FrameList> {
    let frames = app.store.list();
    let frames = tokio::task::spawn_blocking(move || frames.iter().map(|f| f.info()).collect())
        .await
        .unwrap_or_default();
    Json(FrameList { frames })
}

/// `GET /v1/frames/{id}`.
pub async fn frame_info(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<FrameInfo>, ApiError> {
    let frame = app.store.get(&id)?;
    blocking("frame info", move || Ok(frame.info()))
        .await
        .map(Json)
}

/// `DELETE /v1/frames/{id}`.
pub async fn delete_frame(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    let frame = app.store.get(&id)?;
    app.delete_frame(&frame).await?;
    metrics::gauge!("splatd_frames").set(app.store.list().len() as f64);
    tracing::info!(frame = id, "frame deleted");
    Ok(StatusCode::NO_CONTENT)
}

/// `POST /v1/frames/{id}/samples`: one batch, applied whole or not at all.
pub async fn post_samples(
    State(app): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<BatchAck>, ApiError> {
    check_content_type(&headers, BATCH_CONTENT_TYPE)?;
    let frame = app.store.get(&id)?;
    let bytes = read_body(body, app.decode_limits.max_body_len()).await;
    let bytes = bytes.inspect_err(|_| reject(&frame, 0, "body"))?;
    metrics::counter!("splatd_ingest_bytes_total").increment(bytes.len() as u64);
    let limits = app.decode_limits;
    ingest(&app, frame, move |frame| {
        Batch::decode(&bytes, &limits).map_err(|e| {
            reject(frame, 0, e.code());
            ApiError::from(&e)
        })
    })
    .await
}

/// Query of `POST /v1/frames/{id}/passes`: the pass's identity, for exactly-once.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PassQuery {
    /// The worker that rendered the pass.
    pub worker: u64,
    /// The worker's number for this pass (a retry resends the same number).
    pub seq: u64,
}

/// `POST /v1/frames/{id}/passes?worker=W&seq=S`: one rendered pass as an EXR; each pixel is one
/// sample. Applied whole or not at all, and once per `(worker, seq)`, like a batch.
pub async fn post_pass(
    State(app): State<AppState>,
    Path(id): Path<String>,
    RawQuery(query): RawQuery,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<BatchAck>, ApiError> {
    let query: PassQuery = parse_query(query.as_deref())?;
    check_content_type(&headers, EXR_CONTENT_TYPE)?;
    let frame = app.store.get(&id)?;
    let spec = &frame.spec().request;
    let (width, height) = (spec.width, spec.height);
    let pixels = width as u64 * height as u64;
    // An EXR of the frame's size: its floats, plus generous room for headers and poor compression.
    let limit = (pixels as usize)
        .saturating_mul(4 * 16)
        .saturating_add(1 << 20);
    let bytes = read_body(body, limit).await;
    let bytes = bytes.inspect_err(|_| reject(&frame, 0, "body"))?;
    metrics::counter!("splatd_ingest_bytes_total").increment(bytes.len() as u64);
    ingest(&app, frame, move |frame| {
        let refuse = |e: crate::passes::PassError| {
            reject(frame, 0, "pass");
            ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                "invalid_pass",
                format!("pass for frame {:?}: {e}", frame.id()),
            )
        };
        let pass = crate::passes::decode_pass_with_limit(&bytes, pixels).map_err(refuse)?;
        pass.check(width, height).map_err(refuse)?;
        Ok(Batch {
            frame: frame.id().to_owned(),
            worker: query.worker,
            seq: query.seq,
            records: pass.records().collect(),
        })
    })
    .await
}

/// Content type of EXR bodies.
pub const EXR_CONTENT_TYPE: &str = "image/x-exr";

/// Builds a batch (decoding it on the blocking pool), applies it and acknowledges it.
async fn ingest(
    app: &AppState,
    frame: Arc<ShardedFrame>,
    make_batch: impl FnOnce(&ShardedFrame) -> Result<Batch, ApiError> + Send + 'static,
) -> Result<Json<BatchAck>, ApiError> {
    // Held until the acknowledgement is ready, so a deletion is answered after it.
    let _lease = frame
        .lease()
        .await
        .ok_or_else(|| ApiError::unknown_frame(frame.id()))?;
    let worker_frame = frame.clone();
    let (batch_id, ingested) = blocking("ingest", move || {
        let batch = make_batch(&worker_frame)?;
        let ingested = worker_frame.ingest(&batch).map_err(|e| {
            reject_counted(batch.records.len() as u64, "samples");
            ApiError::from(e)
        })?;
        Ok(((batch.worker, batch.seq), ingested))
    })
    .await?;
    let (worker, seq) = batch_id;
    let durable_floor = app.durable.as_ref().map(|_| frame.durable_floor(worker));
    if ingested.duplicate {
        metrics::counter!("splatd_batches_duplicate_total").increment(1);
    } else {
        metrics::counter!("splatd_batches_ingested_total").increment(1);
        metrics::counter!("splatd_samples_ingested_total").increment(ingested.accepted);
    }
    Ok(Json(BatchAck {
        frame: frame.id().to_owned(),
        worker,
        seq,
        accepted: ingested.accepted,
        duplicate: ingested.duplicate,
        boot: app.boot,
        durable_floor,
    }))
}

/// Which layer a preview shows.
#[derive(Debug, Clone, Copy, Default, serde::Deserialize)]
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
#[derive(Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreviewQuery {
    /// The layer (default reweighted).
    #[serde(default)]
    pub layer: PreviewLayer,
    /// Exposure multiplier; by default chosen from the reweighted image, so that every layer
    /// of a frame is shown with the same exposure and compares fairly.
    pub exposure: Option<f32>,
    /// Ignored: lets pages defeat caches by naming the sample count they expect.
    pub samples: Option<u64>,
}

/// `GET /v1/frames/{id}/preview.png`: a tone-mapped 8-bit view of a layer, for the live page.
pub async fn get_preview(
    State(app): State<AppState>,
    Path(id): Path<String>,
    RawQuery(query): RawQuery,
) -> Result<Response, ApiError> {
    let query: PreviewQuery = parse_query(query.as_deref())?;
    if let Some(e) = query.exposure {
        if !(e.is_finite() && e > 0.0) {
            return Err(ApiError::bad_request(
                "bad_query",
                format!("exposure must be a positive number, got {e}"),
            ));
        }
    }
    let frame = app.store.get(&id)?;
    let params = frame.spec().resolve;
    let threads = app.resolve_threads;
    let png = blocking("preview", move || {
        let resolved = frame.cut().resolve(&params, threads);
        let exposure = query
            .exposure
            .unwrap_or_else(|| crate::preview::auto_exposure(&resolved.reweighted));
        let layer = match query.layer {
            PreviewLayer::Reweighted => &resolved.reweighted,
            PreviewLayer::Mean => &resolved.mean,
            PreviewLayer::Removed => &resolved.removed,
        };
        let pixels = crate::preview::tonemap(layer, exposure);
        crate::preview::encode_png(resolved.width, resolved.height, &pixels)
            .map_err(|e| ApiError::internal("PNG encoding", e))
    })
    .await?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        png,
    )
        .into_response())
}

/// Counts a batch refused before the frame saw it (body or decode errors).
fn reject(frame: &ShardedFrame, samples: u64, reason: &'static str) {
    frame.count_rejected(samples);
    reject_counted(samples, reason);
}

fn reject_counted(samples: u64, reason: &'static str) {
    metrics::counter!("splatd_batches_rejected_total", "reason" => reason).increment(1);
    metrics::counter!("splatd_samples_rejected_total").increment(samples);
}

/// `GET /v1/frames/{id}/image.exr`: resolves the frame as it is now.
pub async fn get_image(
    State(app): State<AppState>,
    Path(id): Path<String>,
    RawQuery(query): RawQuery,
) -> Result<Response, ApiError> {
    let query: ImageQuery = parse_query(query.as_deref())?;
    let frame = app.store.get(&id)?;
    let params = core_resolve_params(&query.apply(&frame.spec().request.resolve))
        .map_err(|e| ApiError::bad_request("invalid_parameters", e.to_string()))?;
    let threads = app.resolve_threads;
    let started = Instant::now();
    let exr = blocking("resolve", move || {
        let cut = frame.cut();
        let resolved = cut.resolve(&params, threads);
        let extra = if query.cascades {
            cascade_layers(cut.cascade_means())
        } else {
            Vec::new()
        };
        encode_exr(&resolved, &extra).map_err(|e| ApiError::internal("EXR encoding", e))
    })
    .await?;
    metrics::histogram!("splatd_resolve_seconds").record(started.elapsed().as_secs_f64());
    Ok(([(header::CONTENT_TYPE, "image/x-exr")], exr).into_response())
}

/// `GET /v1/frames/{id}/state`: the frame's accumulated cascades, for merging elsewhere.
pub async fn export_state(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let frame = app.store.get(&id)?;
    let bytes = blocking("export", move || {
        let cut = frame.cut();
        let mut out = Vec::with_capacity(frame.spec().memory_bytes() as usize + 4096);
        crate::export::write_bands(&cut.bands, frame.id(), None, &mut out)
            .expect("writing into a Vec<u8> is infallible");
        Ok(out)
    })
    .await?;
    metrics::counter!("splatd_exports_total").increment(1);
    Ok(([(header::CONTENT_TYPE, STATE_CONTENT_TYPE)], bytes).into_response())
}

/// `POST /v1/frames/{id}/state`: adds another node's state (or pushed delta) to the frame.
pub async fn import_state(
    State(app): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<ImportAck>, ApiError> {
    check_content_type(&headers, STATE_CONTENT_TYPE)?;
    let frame = app.store.get(&id)?;
    let target = frame.clone();
    // A state of this frame is its cells plus a header; allow a generous header.
    let cells = frame.spec().memory_bytes() / 8;
    let limit = frame.spec().memory_bytes() as usize + 64 * 1024;
    let bytes = read_body(body, limit).await?;
    // Held until the acknowledgement is ready, so a deletion is answered after it.
    let _lease = frame
        .lease()
        .await
        .ok_or_else(|| ApiError::unknown_frame(frame.id()))?;
    let (samples, applied) = blocking("import", move || {
        let dump = StateDump::decode(&bytes, cells).map_err(|e| ApiError::from(&e))?;
        let origin = dump.origin.clone();
        let name = dump.frame.clone();
        let state = crate::export::load(dump)
            .map_err(|e| ApiError::new(StatusCode::CONFLICT, "state_mismatch", e.to_string()))?;
        let applied = frame.import(&name, &state, origin.as_ref())?;
        Ok((state.total_samples(), applied))
    })
    .await?;
    // A pusher forgets a delta once it is acknowledged, so make it durable first.
    app.sync(&target).await?;
    metrics::counter!("splatd_imports_total", "result" => if applied { "applied" } else { "duplicate" })
        .increment(1);
    Ok(Json(ImportAck {
        frame: id,
        samples: if applied { samples } else { 0 },
        duplicate: !applied,
    }))
}

/// `POST /v1/frames/{id}/sync`: returns once everything applied to the frame is on disk.
pub async fn sync_frame(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<SyncAck>, ApiError> {
    let frame = app.store.get(&id)?;
    app.sync(&frame).await?;
    Ok(Json(SyncAck {
        frame: id,
        boot: app.boot,
        durable: app.durable.is_some(),
    }))
}

/// `GET /metrics`: Prometheus text format.
pub async fn metrics_text(State(app): State<AppState>) -> Response {
    match &app.metrics {
        Some(handle) => (
            [(
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/plain; version=0.0.4"),
            )],
            handle.render(),
        )
            .into_response(),
        None => ApiError::new(
            StatusCode::NOT_FOUND,
            "metrics_disabled",
            "this server was started without a metrics recorder",
        )
        .into_response(),
    }
}

/// Runs `f` on the blocking pool.
pub async fn blocking<T, F>(what: &'static str, f: F) -> Result<T, ApiError>
where
    T: Send + 'static,
    F: FnOnce() -> Result<T, ApiError> + Send + 'static,
{
    match tokio::task::spawn_blocking(f).await {
        Ok(result) => result,
        Err(e) => Err(ApiError::internal(what, e)),
    }
}

/// Refuses a body of the wrong type before reading it.
pub fn check_content_type(headers: &HeaderMap, expected: &str) -> Result<(), ApiError> {
    let found = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(|v| {
            v.split(';')
                .next()
                .unwrap_or("")
                .trim()
                .to_ascii_lowercase()
        });
    if found.as_deref() == Some(expected) {
        return Ok(());
    }
    Err(ApiError::new(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_content_type",
        format!(
            "expected Content-Type {expected}, got {}",
            found.map_or_else(|| "none".to_owned(), |f| format!("{f:?}"))
        ),
    ))
}

/// Reads a whole (already decompressed) body, refusing more than `limit` bytes with 413.
pub async fn read_body(body: Body, limit: usize) -> Result<Bytes, ApiError> {
    axum::body::to_bytes(body, limit).await.map_err(|e| {
        let inner = e.into_inner();
        let mut source: Option<&(dyn std::error::Error + 'static)> = Some(inner.as_ref());
        while let Some(err) = source {
            if err.is::<http_body_util::LengthLimitError>() {
                return ApiError::new(
                    StatusCode::PAYLOAD_TOO_LARGE,
                    "body_too_large",
                    format!("request body exceeds this endpoint's limit of {limit} bytes"),
                );
            }
            source = err.source();
        }
        ApiError::bad_request(
            "unreadable_body",
            format!("could not read the request body: {inner}"),
        )
    })
}

async fn read_json<T: DeserializeOwned>(headers: &HeaderMap, body: Body) -> Result<T, ApiError> {
    check_content_type(headers, "application/json")?;
    let bytes = read_body(body, MAX_JSON_BODY).await?;
    serde_json::from_slice(&bytes)
        .map_err(|e| ApiError::bad_request("bad_request", format!("invalid JSON body: {e}")))
}

/// Parses a query string strictly (unknown parameters are errors).
pub fn parse_query<T: DeserializeOwned>(query: Option<&str>) -> Result<T, ApiError> {
    serde_urlencoded::from_str(query.unwrap_or(""))
        .map_err(|e| ApiError::bad_request("bad_query", format!("invalid query string: {e}")))
}
