//! Extractors that turn a request into what a handler needs, refusing it with the project's JSON
//! errors ([`ApiError`]) rather than axum's plain-text rejections, so every handler takes typed
//! arguments and none parses headers, bodies or query strings by hand.
//!
//! Order matters for what a client is told and for what the server spends: extractors run in the
//! order of a handler's arguments, and [`FrameBody`] checks the Content-Type and finds the frame
//! before it reads a byte of the body.

use std::marker::PhantomData;
use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::extract::{FromRequest, FromRequestParts, Path, Request};
use axum::http::request::Parts;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::frame::ShardedFrame;
use crate::http::error::ApiError;
use crate::memory::BodyPool;
use crate::work::Reservation;
use crate::AppState;

/// Largest JSON request body (a `CreateFrame` is a few hundred bytes).
pub const MAX_JSON_BODY: usize = 64 * 1024;

/// A JSON body in (`application/json`, at most [`MAX_JSON_BODY`] bytes, unknown fields refused
/// where the type says so), or a JSON response out.
///
/// Unlike `axum::Json`, a refusal is an [`ApiError`]: 415 `unsupported_content_type`, 413
/// `body_too_large` or 400 `bad_request` naming what serde found wrong.
#[derive(Debug, Clone, Copy, Default)]
pub struct Json<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for Json<T> {
    type Rejection = ApiError;

    async fn from_request(request: Request, _: &S) -> Result<Self, ApiError> {
        let (parts, body) = request.into_parts();
        check_content_type(&parts.headers, "application/json")?;
        let encoding = Encoding::of(&parts.headers)?;
        check_length(&parts.headers, MAX_JSON_BODY)?;
        let bytes = read_body(body, MAX_JSON_BODY, encoding, None).await?;
        serde_json::from_slice(&bytes)
            .map(Json)
            .map_err(|e| ApiError::bad_request("bad_request", format!("invalid JSON body: {e}")))
    }
}

impl<T: Serialize> IntoResponse for Json<T> {
    fn into_response(self) -> Response {
        axum::Json(self.0).into_response()
    }
}

/// A query string parsed strictly into `T` (give `T` `deny_unknown_fields` so a misspelt
/// parameter is an error, not silently ignored). A refusal is 400 `bad_query`.
#[derive(Debug, Clone, Copy, Default)]
pub struct Query<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequestParts<S> for Query<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, ApiError> {
        serde_urlencoded::from_str(parts.uri.query().unwrap_or(""))
            .map(Query)
            .map_err(|e| ApiError::bad_request("bad_query", format!("invalid query string: {e}")))
    }
}

/// The frame named by the route's `{id}`; 404 `unknown_frame` when the server has none.
#[derive(Debug, Clone)]
pub struct Frame(pub Arc<ShardedFrame>);

impl FromRequestParts<AppState> for Frame {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, app: &AppState) -> Result<Self, ApiError> {
        let Path(id) = Path::<String>::from_request_parts(parts, app)
            .await
            .map_err(|e| ApiError::new(e.status(), "http_error", e.body_text()))?;
        Ok(Frame(app.store.get(&id)?))
    }
}

/// A kind of body posted to a frame: what it must be labelled, how large it may be, and how much
/// memory decoding it takes.
pub trait Upload {
    /// The Content-Type the body must declare (parameters such as `charset` are ignored).
    const CONTENT_TYPE: &'static str;

    /// Most bytes (after decompression) accepted for `frame`; beyond it, 413.
    fn limit(app: &AppState, frame: &ShardedFrame) -> usize;

    /// Bytes that decoding and applying a body of `len` bytes allocates besides the body itself
    /// (decoded records, a decoded state), reserved from the working-memory budget with it.
    fn decoding_bytes(frame: &ShardedFrame, len: u64) -> u64;

    /// Called when the body could not be read (too large, cut off, badly compressed), so the
    /// refusal can be counted where the kind's other refusals are.
    fn refused(_frame: &ShardedFrame) {}

    /// The [`BodyPool`] a large body sent as it is, with a `Content-Length`, is read into
    /// rather than a fresh buffer; `None`: a fresh one. (Not used for bodies kept in pieces.)
    fn pool(_app: &AppState) -> Option<&Arc<BodyPool>> {
        None
    }

    /// Whether a body sent as it is stays in the pieces it arrived in ([`BodyBytes::pieces`]),
    /// for a kind whose decoder reads them in order, rather than being copied into one buffer.
    /// (A compressed body is inflated into one buffer, its one piece.)
    const IN_PIECES: bool = false;
}

/// The body of a `POST` to a frame, of kind `K`.
///
/// Checks, in this order: the Content-Type and Content-Encoding (415), that the frame exists
/// (404), that a declared `Content-Length` is within `K`'s limit for that frame (413, before
/// reading anything), then reserves working memory for the body and its decoding (503 `busy`
/// when the budget stays spent), and only then reads the body within the limit, inflating a
/// compressed one on the blocking pool up to the limit (413, or 400 `unreadable_body`). So a
/// client learns of a wrong label, an unknown frame or an oversized body without the server
/// reading, let alone decompressing, the body; and no number of concurrent uploads (zstd bombs
/// included) can hold more than the budget.
///
/// A body sent as it is (no `Content-Encoding`) with a `Content-Length` reserves exactly that
/// length; a compressed or chunked body reserves the whole limit (plus its compressed bytes), as
/// its size is known only once it has been read.
pub struct FrameBody<K> {
    /// The frame posted to.
    pub frame: Arc<ShardedFrame>,
    /// The whole body, decompressed.
    pub bytes: BodyBytes,
    /// Working memory held for the body and its decoding; keep it until they are dropped.
    pub reservation: Reservation,
    kind: PhantomData<fn() -> K>,
}

impl<K: Upload> FromRequest<AppState> for FrameBody<K> {
    type Rejection = ApiError;

    async fn from_request(request: Request, app: &AppState) -> Result<Self, ApiError> {
        let (mut parts, body) = request.into_parts();
        check_content_type(&parts.headers, K::CONTENT_TYPE)?;
        let encoding = Encoding::of(&parts.headers)?;
        let Frame(frame) = Frame::from_request_parts(&mut parts, app).await?;
        let limit = K::limit(app, &frame);
        let declared = check_length(&parts.headers, limit).inspect_err(|_| K::refused(&frame))?;
        // The bytes on the wire, and what they inflate to (for a compressed body, at most the
        // limit; its real size is unknown until then).
        let (wire, inflated) = match declared {
            Some(len) if encoding == Encoding::Identity => (0, len),
            Some(len) => (len, limit as u64),
            None => (0, limit as u64),
        };
        let reservation = app
            .renders
            .budget()
            .reserve(wire + inflated + K::decoding_bytes(&frame, inflated))
            .await
            .map_err(|busy| ApiError::busy(&busy))?;
        let pool = K::pool(app).filter(|_| encoding == Encoding::Identity);
        let bytes = match (declared, pool) {
            (Some(_), _) if K::IN_PIECES && encoding == Encoding::Identity => {
                read_pieces(body, limit).await
            }
            (Some(len), Some(pool)) if len >= POOLED_MIN => {
                read_pooled(body, limit, pool.clone(), len as usize).await
            }
            _ => read_body(body, limit, encoding, declared)
                .await
                .map(BodyBytes::Shared),
        }
        .inspect_err(|_| K::refused(&frame))?;
        Ok(FrameBody {
            frame,
            bytes,
            reservation,
            kind: PhantomData,
        })
    }
}

/// Refuses a body whose `Content-Length` already says it is longer than `limit`: 413
/// `body_too_large` before a byte of it is read (and so before `Expect: 100-continue` is
/// answered). The declared length, if any, is returned. (For a compressed body the length is
/// that of the compressed bytes: a body that large on the wire is refused too.)
pub fn check_length(headers: &HeaderMap, limit: usize) -> Result<Option<u64>, ApiError> {
    let Some(value) = headers.get(header::CONTENT_LENGTH) else {
        return Ok(None);
    };
    let declared = value
        .to_str()
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .ok_or_else(|| ApiError::bad_request("bad_request", "invalid Content-Length header"))?;
    if declared > limit as u64 {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "body_too_large",
            format!(
                "request body of {declared} bytes (Content-Length) exceeds this endpoint's \
                 limit of {limit} bytes"
            ),
        ));
    }
    Ok(Some(declared))
}

fn too_large(limit: usize) -> ApiError {
    ApiError::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "body_too_large",
        format!("request body exceeds this endpoint's limit of {limit} bytes"),
    )
}

/// Refuses a body of the wrong type before reading it: 415 `unsupported_content_type`.
fn check_content_type(headers: &HeaderMap, expected: &str) -> Result<(), ApiError> {
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

/// How a request body is compressed (`Content-Encoding`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    /// Not compressed.
    Identity,
    /// gzip (RFC 1952), one or more members.
    Gzip,
    /// zstd (RFC 8878), one or more frames.
    Zstd,
}

impl Encoding {
    /// The encoding a request declares; 415 `unsupported_content_encoding` for any other than
    /// none, `identity`, `gzip` and `zstd`.
    pub fn of(headers: &HeaderMap) -> Result<Encoding, ApiError> {
        let Some(value) = headers.get(header::CONTENT_ENCODING) else {
            return Ok(Encoding::Identity);
        };
        let value = value.to_str().unwrap_or("").trim().to_ascii_lowercase();
        match value.as_str() {
            "" | "identity" => Ok(Encoding::Identity),
            "gzip" | "x-gzip" => Ok(Encoding::Gzip),
            "zstd" => Ok(Encoding::Zstd),
            _ => Err(ApiError::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "unsupported_content_encoding",
                format!("unsupported Content-Encoding {value:?}; use gzip, zstd or none"),
            )),
        }
    }
}

/// Reads a whole body, refusing more than `limit` bytes with 413, and inflates a compressed one
/// on the blocking pool (never on the threads that answer other requests), stopping at `limit`
/// inflated bytes: past it, 413 too. A body whose length was `declared` (and checked against
/// `limit`) is read into one buffer of that length as it arrives.
async fn read_body(
    body: Body,
    limit: usize,
    encoding: Encoding,
    declared: Option<u64>,
) -> Result<Bytes, ApiError> {
    let wire = match declared {
        Some(len) => read_sized(body, limit, len).await?,
        None => axum::body::to_bytes(body, limit)
            .await
            .map_err(|e| body_error(e, limit))?,
    };
    if encoding == Encoding::Identity {
        return Ok(wire);
    }
    crate::http::blocking::blocking("inflating a body", move || inflate(&wire, encoding, limit))
        .await
}

/// Reads a body of declared length `len` into one buffer of that length (on huge pages when it
/// is large), instead of a list of chunks copied into one at the end: a state body is as large
/// as its frame, and a second copy of it cost as much as the rest of its import.
async fn read_sized(mut body: Body, limit: usize, len: u64) -> Result<Bytes, ApiError> {
    let mut out = Vec::with_capacity(len.min(limit as u64) as usize);
    crate::memory::advise_or_log(out.spare_capacity_mut());
    append_body(&mut body, limit, &mut out).await?;
    Ok(Bytes::from(out))
}

/// Appends the rest of `body` to `out`, refusing with 413 once `out` would pass `limit` bytes.
async fn append_body(body: &mut Body, limit: usize, out: &mut Vec<u8>) -> Result<(), ApiError> {
    each_piece(body, limit, |data| out.extend_from_slice(&data)).await
}

/// Hands each piece (data frame) of the rest of `body` to `take`, in order, refusing with 413
/// once they would pass `limit` bytes in all.
async fn each_piece(
    body: &mut Body,
    limit: usize,
    mut take: impl FnMut(Bytes),
) -> Result<(), ApiError> {
    use http_body_util::BodyExt;
    let mut read = 0;
    while let Some(frame) = body.frame().await {
        let frame = frame.map_err(|e| body_error(e, limit))?;
        if let Ok(data) = frame.into_data() {
            read += data.len();
            if read > limit {
                return Err(too_large(limit));
            }
            take(data);
        }
    }
    Ok(())
}

/// Reads a body as the pieces it arrives in, refusing more than `limit` bytes with 413 like
/// [`read_body`]: a piece of [`KEEP_PIECE`] bytes or more is kept as hyper read it from the
/// socket (not copied), smaller ones are copied, together, into pieces of their own.
///
/// A piece hyper hands over shares the allocation of its read buffer (at most 408 KiB, hyper's
/// default `max_buf_size`), which stays allocated while any piece of it is held. Over loopback
/// a 1.3 MB batch comes as one small piece (what was read with the headers) and four of about
/// 408 KiB, each the whole buffer; but a client sending a few bytes at a time would make every
/// byte pin a buffer. Kept only from `KEEP_PIECE` up, a piece pins at most 1.6 times its size.
pub(super) async fn read_pieces(mut body: Body, limit: usize) -> Result<BodyBytes, ApiError> {
    let (mut pieces, mut small) = (Vec::new(), Vec::new());
    each_piece(&mut body, limit, |data| {
        if data.len() >= KEEP_PIECE {
            if !small.is_empty() {
                pieces.push(Bytes::from(std::mem::take(&mut small)));
            }
            pieces.push(data);
        } else {
            small.extend_from_slice(&data);
        }
    })
    .await?;
    if !small.is_empty() {
        pieces.push(Bytes::from(small));
    }
    Ok(BodyBytes::Pieces(pieces))
}

/// The smallest piece of a body that [`read_pieces`] keeps as it came.
pub(super) const KEEP_PIECE: usize = 256 << 10;

/// What a client is told when its body could not be read.
fn body_error(e: axum::Error, limit: usize) -> ApiError {
    let inner = e.into_inner();
    let mut source: Option<&(dyn std::error::Error + 'static)> = Some(inner.as_ref());
    while let Some(err) = source {
        if err.is::<http_body_util::LengthLimitError>() {
            return too_large(limit);
        }
        source = err.source();
    }
    ApiError::bad_request(
        "unreadable_body",
        format!("could not read the request body: {inner}"),
    )
}

/// Bodies smaller than this are read into fresh buffers: the allocator keeps such sizes
/// mapped already, and pooling them would gain nothing.
pub const POOLED_MIN: u64 = 1 << 20;

/// Reads a body declared `len` bytes long (sent as it is) into a buffer of `pool`, refusing
/// more than `limit` bytes with 413 like [`read_body`].
async fn read_pooled(
    mut body: Body,
    limit: usize,
    pool: Arc<BodyPool>,
    len: usize,
) -> Result<BodyBytes, ApiError> {
    // Given back to the pool however the read ends.
    let mut bytes = BodyBytes::Pooled(pool.take(len), pool);
    let BodyBytes::Pooled(buffer, _) = &mut bytes else {
        unreachable!("made pooled just above")
    };
    append_body(&mut body, limit, buffer).await?;
    Ok(bytes)
}

/// A request body's bytes: shared, or in a buffer of a [`BodyPool`] that goes back to it
/// when they are dropped.
#[derive(Debug)]
pub enum BodyBytes {
    /// Bytes of their own.
    Shared(Bytes),
    /// A pool's buffer and the pool it goes back to.
    Pooled(Vec<u8>, Arc<BodyPool>),
    /// The pieces the body arrived in, in order (only for an [`Upload::IN_PIECES`] kind).
    Pieces(Vec<Bytes>),
}

impl BodyBytes {
    /// The body's bytes as slices, in order: one, or the pieces it arrived in.
    pub fn pieces(&self) -> Vec<&[u8]> {
        match self {
            BodyBytes::Shared(bytes) => vec![bytes],
            BodyBytes::Pooled(buffer, _) => vec![buffer],
            BodyBytes::Pieces(pieces) => pieces.iter().map(|p| &p[..]).collect(),
        }
    }

    /// Bytes in all.
    pub fn len(&self) -> usize {
        match self {
            BodyBytes::Shared(bytes) => bytes.len(),
            BodyBytes::Pooled(buffer, _) => buffer.len(),
            BodyBytes::Pieces(pieces) => pieces.iter().map(Bytes::len).sum(),
        }
    }

    /// Whether the body is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The body as one slice.
    ///
    /// # Panics
    /// For a body kept in pieces: a kind that reads its body whole does not set
    /// [`Upload::IN_PIECES`].
    pub fn whole(&self) -> &[u8] {
        match self {
            BodyBytes::Shared(bytes) => bytes,
            BodyBytes::Pooled(buffer, _) => buffer,
            BodyBytes::Pieces(_) => panic!("a body kept in pieces read as one slice"),
        }
    }
}

impl Drop for BodyBytes {
    fn drop(&mut self) {
        if let BodyBytes::Pooled(buffer, pool) = self {
            pool.give(std::mem::take(buffer));
        }
    }
}

/// `wire` inflated, at most `limit` bytes of it.
fn inflate(wire: &[u8], encoding: Encoding, limit: usize) -> Result<Bytes, ApiError> {
    use std::io::Read;
    let unreadable = |e: std::io::Error| {
        ApiError::bad_request(
            "unreadable_body",
            format!("could not decompress the request body: {e}"),
        )
    };
    let reader: Box<dyn Read + '_> = match encoding {
        Encoding::Identity => Box::new(wire),
        Encoding::Gzip => Box::new(flate2::read::MultiGzDecoder::new(wire)),
        Encoding::Zstd => {
            Box::new(zstd::stream::read::Decoder::with_buffer(wire).map_err(unreadable)?)
        }
    };
    let mut out = Vec::new();
    reader
        .take(limit as u64 + 1)
        .read_to_end(&mut out)
        .map_err(unreadable)?;
    if out.len() > limit {
        return Err(too_large(limit));
    }
    Ok(Bytes::from(out))
}

/// A lease on `frame` for a request that changes it (see `ShardedFrame::lease`); 404
/// `unknown_frame` once the frame is being deleted.
pub async fn lease(frame: &crate::frame::ShardedFrame) -> Result<crate::frame::Lease, ApiError> {
    frame
        .lease()
        .await
        .ok_or_else(|| ApiError::unknown_frame(frame.id()))
}
