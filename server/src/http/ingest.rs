//! Samples in: batches of records (`POST .../samples`) and rendered passes (`POST .../passes`).
//!
//! Both are applied whole or not at all, once per `(worker, seq)`, and acknowledged with a
//! [`BatchAck`]; decoding and splatting run on the blocking pool.

use std::sync::Arc;

use axum::extract::State;
use axum::http::StatusCode;
use splatd_proto::api::BatchAck;
use splatd_proto::{Batch, BATCH_CONTENT_TYPE};

use crate::frame::ShardedFrame;
use crate::http::blocking::blocking;
use crate::http::error::ApiError;
use crate::http::extract::{FrameBody, Json, Query, Upload};
use crate::memory::BodyPool;
use crate::work::Reservation;
use crate::AppState;

/// Content type of EXR bodies.
pub const EXR_CONTENT_TYPE: &str = "image/x-exr";

/// A batch of records in the wire format ([`BATCH_CONTENT_TYPE`]).
pub struct Samples;

impl Upload for Samples {
    const CONTENT_TYPE: &'static str = BATCH_CONTENT_TYPE;

    /// The largest batch the decode limits allow.
    fn limit(app: &AppState, _: &ShardedFrame) -> usize {
        app.decode_limits.max_body_len()
    }

    /// The decoded records take as many bytes as their wire form (20 per record); the body's
    /// pieces may pin up to 0.6 of its length more in hyper's read buffers (see
    /// `read_pieces`), and the frame's ingest notes the records' runs per band: twice the body
    /// covers them.
    fn decoding_bytes(_: &ShardedFrame, len: u64) -> u64 {
        2 * len
    }

    fn refused(frame: &ShardedFrame) {
        reject(frame, 0, "body");
    }

    /// The records are decoded straight from the pieces the body arrived in: copying a batch
    /// into one buffer first was 3.4 % of the server's CPU under `loadgen`'s record ingest.
    const IN_PIECES: bool = true;
}

/// One rendered pass as an OpenEXR file ([`EXR_CONTENT_TYPE`]).
pub struct Pass;

impl Upload for Pass {
    const CONTENT_TYPE: &'static str = EXR_CONTENT_TYPE;

    /// An EXR of the frame's size: its floats (16 channels, and two more per AOV channel of
    /// the frame), plus generous room for headers and poor compression.
    fn limit(_: &AppState, frame: &ShardedFrame) -> usize {
        (pass_pixels(frame) as usize)
            .saturating_mul(4 * (16 + 2 * frame.spec().aov_channels()))
            .saturating_add(1 << 20)
    }

    /// The decoder's write counts (1 byte per pixel), the decoded pixels (12) and the `exr`
    /// crate's own buffers, generously; and per AOV channel its values (4 bytes, counted
    /// twice).
    fn decoding_bytes(frame: &ShardedFrame, _: u64) -> u64 {
        pass_pixels(frame) * (48 + 8 * frame.spec().aov_channels() as u64)
    }

    fn refused(frame: &ShardedFrame) {
        reject(frame, 0, "body");
    }

    fn pool(app: &AppState) -> Option<&Arc<BodyPool>> {
        Some(&app.body_pool)
    }
}

fn pass_pixels(frame: &ShardedFrame) -> u64 {
    let spec = &frame.spec().request;
    spec.width as u64 * spec.height as u64
}

/// `POST /v1/frames/{id}/samples`: one batch, applied whole or not at all.
pub async fn post_samples(
    State(app): State<AppState>,
    FrameBody {
        frame,
        bytes,
        reservation,
        ..
    }: FrameBody<Samples>,
) -> Result<Json<BatchAck>, ApiError> {
    metrics::counter!(crate::meters::INGEST_BYTES).increment(bytes.len() as u64);
    let limits = app.decode_limits;
    ingest(&app, frame, reservation, move |frame| {
        // The records are checked and hashed as they are decoded, while still in the cache.
        let mut check = frame.record_check();
        let pieces = bytes.pieces();
        let batch = Batch::decode_pieces_visiting(&pieces, &limits, |records| check.add(records))
            .map_err(|e| {
            reject(frame, 0, e.code());
            ApiError::from(&e)
        })?;
        let ingested = applied(batch.records.len(), frame.ingest_checked(&batch, check))?;
        Ok(((batch.worker, batch.seq), ingested))
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
    /// The layer holding the beauty; when absent it is found automatically (see
    /// [`splatd_formats::passes`]).
    #[serde(default)]
    pub layer: Option<String>,
}

/// `POST /v1/frames/{id}/passes?worker=W&seq=S[&layer=L]`: one rendered pass as an EXR; each
/// pixel of its beauty layer is one sample. Applied whole or not at all, and once per
/// `(worker, seq)`, like a batch.
pub async fn post_pass(
    State(app): State<AppState>,
    Query(query): Query<PassQuery>,
    FrameBody {
        frame,
        bytes,
        reservation,
        ..
    }: FrameBody<Pass>,
) -> Result<Json<BatchAck>, ApiError> {
    metrics::counter!(crate::meters::INGEST_BYTES).increment(bytes.len() as u64);
    let pool = app.clone();
    ingest(&app, frame, reservation, move |frame| {
        // Decoded into buffers kept from earlier passes (counted in this request's reservation
        // while in use), given back whatever the outcome.
        let mut scratch = pool.pass_scratch.take();
        let result = apply_pass(frame, &query, bytes.whole(), &mut scratch);
        pool.pass_scratch.give(scratch);
        result
    })
    .await
}

/// Decodes a pass into `scratch`, checks it and applies it to `frame`.
fn apply_pass(
    frame: &ShardedFrame,
    query: &PassQuery,
    bytes: &[u8],
    scratch: &mut splatd_formats::passes::Scratch,
) -> Result<((u64, u64), crate::frame::Ingested), ApiError> {
    let refuse = |e: splatd_formats::passes::PassError| {
        reject(frame, 0, "pass");
        ApiError::invalid_pass(frame.id(), &e)
    };
    let spec = &frame.spec().request;
    let layer = query.layer.as_deref();
    let pass = splatd_formats::passes::decode_pass_reusing(
        bytes,
        layer,
        pass_pixels(frame),
        &spec.aovs,
        scratch,
    )
    .map_err(refuse)?;
    let result = (|| {
        pass.check(spec.width, spec.height).map_err(refuse)?;
        let aovs = pass.aovs.as_deref();
        if let Some(values) = aovs {
            check_aovs(frame, values)?;
        }
        // Splatted row by row straight from the decoded pixels (no records made).
        let (worker, seq) = (query.worker, query.seq);
        let result = frame.ingest_pass(worker, seq, &pass.rgb, aovs);
        let ingested = applied(pass.rgb.len(), result)?;
        Ok(((worker, seq), ingested))
    })();
    // The samples and AOV values go back to the scratch for the next pass.
    scratch.recycle(pass);
    result
}

/// The outcome of a frame's ingest of `samples` samples, as the route answers it.
fn applied(
    samples: usize,
    result: Result<crate::frame::Ingested, crate::frame::IngestError>,
) -> Result<crate::frame::Ingested, ApiError> {
    result.map_err(|e| {
        reject_counted(samples as u64, "samples");
        ApiError::from(e)
    })
}

/// Decodes and applies a body on the blocking pool (`apply` returns the batch's
/// `(worker, seq)` and what the frame did with it) and acknowledges it; the working memory
/// reserved for the body is given back once the batch is applied.
async fn ingest(
    app: &AppState,
    frame: Arc<ShardedFrame>,
    reservation: Reservation,
    apply: impl FnOnce(&ShardedFrame) -> Result<((u64, u64), crate::frame::Ingested), ApiError>
        + Send
        + 'static,
) -> Result<Json<BatchAck>, ApiError> {
    // Held until the acknowledgement is ready, so a deletion is answered after it.
    let _lease = crate::http::extract::lease(&frame).await?;
    let worker_frame = frame.clone();
    let (batch_id, ingested) = blocking("ingest", move || {
        // The body's and the batch's working memory is held until both are gone.
        let _reservation = reservation;
        apply(&worker_frame)
    })
    .await?;
    let (worker, seq) = batch_id;
    let durable_floor = app.durable.as_ref().map(|_| frame.durable_floor(worker));
    if ingested.duplicate {
        metrics::counter!(crate::meters::BATCHES_DUPLICATE).increment(1);
    } else {
        metrics::counter!(crate::meters::BATCHES_INGESTED).increment(1);
        metrics::counter!(crate::meters::SAMPLES_INGESTED).increment(ingested.accepted);
    }
    Ok(Json(BatchAck {
        frame: frame.id().to_owned(),
        worker,
        seq,
        accepted: ingested.accepted,
        duplicate: ingested.duplicate,
        boot: app.boot,
        durable_floor,
        snapshots_failing: app
            .durable
            .as_ref()
            .is_some_and(|d| d.is_failing(frame.id())),
    }))
}

/// Refuses a pass whose AOV values are outside the AOV bounds (see
/// [`splatd_estimator::AovSums`]): 422 `invalid_aov` naming the layer, channel and pixel.
fn check_aovs(frame: &ShardedFrame, values: &[f32]) -> Result<(), ApiError> {
    let spec = frame.spec();
    let Err((pixel, channel, error)) =
        splatd_estimator::check_aov_values(values, spec.aov_channels())
    else {
        return Ok(());
    };
    let name = spec
        .request
        .aovs
        .iter()
        .flat_map(|a| a.channels.iter().map(move |c| format!("{}.{c}", a.name)))
        .nth(channel)
        .unwrap_or_default();
    let width = spec.request.width as usize;
    reject(frame, pass_pixels(frame), "aov");
    Err(ApiError::new(
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_aov",
        format!(
            "pass for frame {:?}: AOV channel {name:?} at pixel ({}, {}): {error}",
            frame.id(),
            pixel % width,
            pixel / width
        ),
    ))
}

/// Counts a batch refused before the frame saw it (body or decode errors).
fn reject(frame: &ShardedFrame, samples: u64, reason: &'static str) {
    frame.count_rejected(samples);
    reject_counted(samples, reason);
}

fn reject_counted(samples: u64, reason: &'static str) {
    metrics::counter!(crate::meters::BATCHES_REJECTED, "reason" => reason).increment(1);
    metrics::counter!(crate::meters::SAMPLES_REJECTED).increment(samples);
}
