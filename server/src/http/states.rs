//! Frame states: export (`GET .../state`) for merging elsewhere, and import (`POST .../state`)
//! of another node's state or a pushed delta.

use std::ops::Range;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use splatd_estimator::FrameState;
use splatd_proto::api::ImportAck;
use splatd_proto::state::le_bytes;
use splatd_proto::{StateDump, StateWrite, STATE_CONTENT_TYPE};

use crate::frame::ShardedFrame;
use crate::http::blocking::blocking;
use crate::http::error::ApiError;
use crate::http::extract::{Frame, FrameBody, Json, Upload};
use crate::memory::BodyPool;
use crate::work::Reservation;
use crate::AppState;

/// Room for the applied batches in a state body, beyond its cells: 32 MiB, about four million
/// batches (a soak of a 64x64 frame reached 120 KB of them in three minutes).
pub const MAX_STATE_BATCH_BYTES: usize = 32 << 20;

/// A frame state in the wire format ([`STATE_CONTENT_TYPE`]).
pub struct StateBody;

impl Upload for StateBody {
    const CONTENT_TYPE: &'static str = STATE_CONTENT_TYPE;

    /// The server's one kept state buffer: a node receiving states repeatedly (pulls, pushed
    /// deltas) receives each into memory already mapped.
    fn pool(app: &AppState) -> Option<&Arc<BodyPool>> {
        Some(&app.state_pool)
    }

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

/// Bytes of one piece of a streamed export: large enough that a piece is one cheap write to
/// the socket, small enough that the pieces in flight are a few MiB whatever the frame.
const EXPORT_PIECE: usize = 1 << 20;

/// Pieces encoded ahead of the connection: the encoder keeps this many ready while the
/// connection sends, so encoding and sending overlap.
const EXPORT_AHEAD: usize = 4;

/// Pieces of one export that exist at once: those queued, the one being filled, and those the
/// connection holds while writing them.
const EXPORT_PIECES: u64 = EXPORT_AHEAD as u64 + 3;

/// `GET /v1/frames/{id}/state`: the frame's accumulated cascades, for merging elsewhere.
///
/// Streamed (chunked): the state is encoded from a cut of the frame on the blocking pool, a
/// piece at a time, while the connection sends the pieces before it. Run headers and short runs
/// are copied into pieces; long runs are sent from the cut's bands themselves, with no copy.
/// Nothing as large as the state is allocated for it (on a VM a fresh buffer of a 1080p state's
/// 550 MB cost more in page faults than sending it), and no pass over the cells is spent
/// finding the length first. A
/// response that stops short (the encoder failed) ends without the last chunk, so a client sees
/// a cut-off body, never a short state.
pub async fn export(
    State(app): State<AppState>,
    Frame(frame): Frame,
) -> Result<impl IntoResponse, ApiError> {
    // Until the response is sent, the cut it is sent from shares the frame's bands: writers
    // copy a band they change meanwhile, up to the frame's cells. Then the pieces in flight.
    let budget = app.renders.budget();
    let cut_room = budget
        .reserve(frame.spec().memory_bytes())
        .await
        .map_err(|busy| ApiError::busy(&busy))?;
    let pieces_room = budget
        .reserve(EXPORT_PIECES * EXPORT_PIECE as u64)
        .await
        .map_err(|busy| ApiError::busy(&busy))?;
    let (pieces, rx) = tokio::sync::mpsc::channel(EXPORT_AHEAD);
    tokio::task::spawn_blocking(move || {
        let free = Arc::new(BodyPool::new(EXPORT_PIECES as usize));
        let cut = frame.cut();
        let mut out = PieceWriter {
            pieces,
            piece: free.take(EXPORT_PIECE),
            free,
            bands: cut.bands.clone(),
        };
        let written = frame
            .write_state(&cut, &mut out)
            .and_then(|()| out.finish());
        if let Err(e) = written {
            // The client went away (the connection dropped the pieces' receiver).
            tracing::debug!(frame = %frame.id(), "export stopped: {e}");
        }
    });
    metrics::counter!(crate::meters::EXPORTS).increment(1);
    let body = StreamedState {
        pieces: rx,
        ended: false,
        // The pieces queued share the cut's bands: its room goes back once they are all sent.
        _reservations: [pieces_room, cut_room],
    };
    Ok((
        [(header::CONTENT_TYPE, STATE_CONTENT_TYPE)],
        Body::new(body),
    ))
}

/// Cuts what is written into pieces of [`EXPORT_PIECE`] bytes and queues each for the
/// connection (`Some`; `None` once the encoding is whole), waiting while [`EXPORT_AHEAD`] are
/// queued; fails once the connection is gone. A long stretch of a band's cells is queued as it
/// lies in the cut's band, not copied.
struct PieceWriter {
    pieces: tokio::sync::mpsc::Sender<Option<Bytes>>,
    piece: Vec<u8>,
    /// The export's idle piece buffers, reused so that a piece lands in memory already mapped.
    free: Arc<BodyPool>,
    /// The bands of the cut being written, top to bottom.
    bands: Vec<Arc<FrameState>>,
}

impl PieceWriter {
    fn send(&mut self) -> std::io::Result<()> {
        if self.piece.is_empty() {
            return Ok(());
        }
        let next = self.free.take(EXPORT_PIECE);
        let piece = Recycled {
            bytes: std::mem::replace(&mut self.piece, next),
            free: self.free.clone(),
        };
        self.queue(Some(Bytes::from_owner(piece)))
    }

    fn queue(&self, piece: Option<Bytes>) -> std::io::Result<()> {
        self.pieces.blocking_send(piece).map_err(|_| {
            std::io::Error::new(std::io::ErrorKind::BrokenPipe, "the response was dropped")
        })
    }

    /// Sends what is left and marks the encoding whole.
    fn finish(&mut self) -> std::io::Result<()> {
        self.send()?;
        self.queue(None)
    }
}

impl std::io::Write for PieceWriter {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        let n = data.len().min(EXPORT_PIECE - self.piece.len());
        self.piece.extend_from_slice(&data[..n]);
        if self.piece.len() == EXPORT_PIECE {
            self.send()?;
        }
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.send()
    }
}

impl StateWrite for PieceWriter {
    fn write_cells(
        &mut self,
        part: usize,
        words: Range<usize>,
        cells: &[u64],
    ) -> std::io::Result<()> {
        let band = self.bands[part].clone();
        debug_assert!(std::ptr::eq(&band.cells()[words.clone()], cells));
        if le_bytes(cells).is_none() {
            // A big-endian machine: its cells are not their wire bytes.
            let bytes: Vec<u8> = cells.iter().flat_map(|c| c.to_le_bytes()).collect();
            return std::io::Write::write_all(self, &bytes);
        }
        // What was gathered before them goes first.
        self.send()?;
        self.queue(Some(Bytes::from_owner(BandCells { band, words })))
    }
}

/// Cells of a cut's band, sent from where they lie: the band is kept until they are sent.
struct BandCells {
    band: Arc<FrameState>,
    words: Range<usize>,
}

impl AsRef<[u8]> for BandCells {
    fn as_ref(&self) -> &[u8] {
        le_bytes(&self.band.cells()[self.words.clone()])
            .expect("queued only where cells are their bytes")
    }
}

/// A piece that goes back to its export's free list once the connection has sent it.
struct Recycled {
    bytes: Vec<u8>,
    free: Arc<BodyPool>,
}

impl AsRef<[u8]> for Recycled {
    fn as_ref(&self) -> &[u8] {
        &self.bytes
    }
}

impl Drop for Recycled {
    fn drop(&mut self) {
        self.free.give(std::mem::take(&mut self.bytes));
    }
}

/// The response body of an export: the pieces as the encoder queues them, until the encoder
/// marks the encoding whole (`ended`), holding the working memory of the pieces and of the cut
/// they share until it is dropped.
/// An encoder that stops short (a panic) ends the body with an error instead, so the client
/// sees a cut-off response rather than a short state.
struct StreamedState {
    pieces: tokio::sync::mpsc::Receiver<Option<Bytes>>,
    ended: bool,
    _reservations: [Reservation; 2],
}

impl http_body::Body for StreamedState {
    type Data = Bytes;
    type Error = std::io::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, std::io::Error>>> {
        if self.ended {
            return Poll::Ready(None);
        }
        match std::task::ready!(self.pieces.poll_recv(cx)) {
            Some(Some(piece)) => Poll::Ready(Some(Ok(http_body::Frame::data(piece)))),
            Some(None) => {
                self.ended = true;
                Poll::Ready(None)
            }
            None => Poll::Ready(Some(Err(std::io::Error::other(
                "the state's encoding stopped before its end",
            )))),
        }
    }

    fn is_end_stream(&self) -> bool {
        self.ended
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
    let added = blocking("import", move || {
        let _reservation = reservation;
        let (dump, runs, aov_runs) = StateDump::decode_runs(bytes.whole(), cells)?;
        // Refused before its AOV words are expanded (at most the frame's, reserved above).
        target.check_state_header(&dump.frame, dump.width, dump.height, &dump.aovs)?;
        // Its cells are checked as they are added.
        let state = splatd_formats::state::load_runs(dump, runs, aov_runs)?;
        let dump = &state.dump;
        Ok(target.import(
            &dump.frame,
            &state,
            state.aovs(),
            dump.origin.as_ref(),
            &dump.batches,
        )?)
    })
    .await?;
    let applied = added.is_some();
    // A pusher forgets a delta once it is acknowledged, so make it durable first.
    app.sync(&frame).await?;
    metrics::counter!(crate::meters::IMPORTS, "result" => if applied { "applied" } else { "duplicate" })
        .increment(1);
    Ok(Json(ImportAck {
        frame: frame.id().to_owned(),
        samples: added.unwrap_or(0),
        duplicate: !applied,
    }))
}
