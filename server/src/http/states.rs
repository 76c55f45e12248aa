//! Frame states: export (`GET .../state`) for merging elsewhere, and import (`POST .../state`)
//! of another node's state or a pushed delta.

use std::pin::Pin;
use std::task::{Context, Poll};

use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use splatd_proto::api::ImportAck;
use splatd_proto::{StateDump, STATE_CONTENT_TYPE};

use crate::frame::ShardedFrame;
use crate::http::blocking::blocking;
use crate::http::error::ApiError;
use crate::http::extract::{Frame, FrameBody, Json, Upload};
use crate::work::Reservation;
use crate::AppState;
use splatd_formats::state::Importable;

/// Room for the applied batches in a state body, beyond its cells: 32 MiB, about four million
/// batches (a soak of a 64x64 frame reached 120 KB of them in three minutes).
pub const MAX_STATE_BATCH_BYTES: usize = 32 << 20;

/// A frame state in the wire format ([`STATE_CONTENT_TYPE`]).
pub struct StateBody;

impl Upload for StateBody {
    const CONTENT_TYPE: &'static str = STATE_CONTENT_TYPE;

    /// A state of this frame is at most its cells, plus a header and the batches it holds
    /// (16 bytes per worker, 16 per range of sequence numbers, 8 per batch): allow a generous
    /// header and [`MAX_STATE_BATCH_BYTES`] or one batch per cell, whichever is more.
    fn limit(_: &AppState, frame: &ShardedFrame) -> usize {
        let cells = frame.spec().memory_bytes() as usize;
        cells + (cells / 8).max(MAX_STATE_BATCH_BYTES) + 64 * 1024
    }

    /// The frame's AOV sums, if it has AOVs: a state's cells are checked and added from the
    /// body itself, a cache-sized piece at a time, but its AOV words are expanded into sums of
    /// the rows held (a state of another size, or with other AOVs, is refused before that).
    fn decoding_bytes(frame: &ShardedFrame, _: u64) -> u64 {
        let spec = frame.spec();
        match spec.aov_channels() {
            0 => 0,
            c => {
                let pixels = spec.request.width as u64 * spec.request.height as u64;
                pixels * splatd_estimator::aov_words(c) as u64 * 8
            }
        }
    }
}

/// `GET /v1/frames/{id}/state`: the frame's accumulated cascades, for merging elsewhere.
pub async fn export(
    State(app): State<AppState>,
    Frame(frame): Frame,
) -> Result<impl IntoResponse, ApiError> {
    // The encoding: the cells, a header, run headers and the applied batches.
    let room = frame.spec().memory_bytes() + 64 * 1024;
    let reservation = app
        .renders
        .budget()
        .reserve(room)
        .await
        .map_err(|busy| ApiError::busy(&busy))?;
    let (bytes, mut reservation) = blocking("export", move || {
        let mut out = crate::memory::faulted_buffer(room as usize);
        frame.write_state(&mut out);
        Ok((out, reservation))
    })
    .await?;
    metrics::counter!(crate::meters::EXPORTS).increment(1);
    reservation.shrink_to(bytes.len() as u64);
    // The encoded state stays reserved until the response is sent or dropped: a client that
    // reads slowly holds its share of the budget, not memory beside it.
    let body = Reserved {
        inner: Body::from(bytes),
        _reservation: reservation,
    };
    Ok((
        [(header::CONTENT_TYPE, STATE_CONTENT_TYPE)],
        Body::new(body),
    ))
}

/// A response body that holds working memory until it is dropped.
struct Reserved {
    inner: Body,
    _reservation: Reservation,
}

impl http_body::Body for Reserved {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// `POST /v1/frames/{id}/state`: adds another node's state (or pushed delta) to the frame,
/// exactly once per origin, and answers once the result is durable. A state holding a batch the
/// frame has applied already is refused (409 `batches_overlap`).
pub async fn import(
    State(app): State<AppState>,
    FrameBody {
        frame,
        bytes,
        reservation,
        ..
    }: FrameBody<StateBody>,
) -> Result<Json<ImportAck>, ApiError> {
    let cells = frame.spec().memory_bytes() / 8;
    // Held until the acknowledgement is ready, so a deletion is answered after it.
    let _lease = crate::http::extract::lease(&frame).await?;
    let target = frame.clone();
    let (samples, applied) = blocking("import", move || {
        let _reservation = reservation;
        let (dump, runs, aov_runs) = StateDump::decode_runs(&bytes, cells)?;
        // Refused before its AOV words are expanded (at most the frame's, reserved above).
        target.check_state_header(&dump.frame, dump.width, dump.height, &dump.aovs)?;
        let state = splatd_formats::state::load_runs(dump, runs, aov_runs)?;
        let dump = &state.dump;
        let applied = target.import(
            &dump.frame,
            &state,
            state.aovs(),
            dump.origin.as_ref(),
            &dump.batches,
        )?;
        Ok((state.samples(), applied))
    })
    .await?;
    // A pusher forgets a delta once it is acknowledged, so make it durable first.
    app.sync(&frame).await?;
    metrics::counter!(crate::meters::IMPORTS, "result" => if applied { "applied" } else { "duplicate" })
        .increment(1);
    Ok(Json(ImportAck {
        frame: frame.id().to_owned(),
        samples: if applied { samples } else { 0 },
        duplicate: !applied,
    }))
}
