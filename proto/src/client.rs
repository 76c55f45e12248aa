//! Async HTTP client for render workers (feature `client`).
//!
//! Workers run for hours on farms where servers restart and networks hiccup,
//! so every request is retried on transient failures (connection errors,
//! timeouts, HTTP 5xx, 408 and 429) with capped exponential backoff and
//! jitter, honouring `Retry-After`. A retried batch is resent byte for byte,
//! with the same worker id and sequence number: when the first attempt did
//! reach the server and only the response was lost, the server recognises
//! `(worker, seq)` and answers with `duplicate: true` instead of counting the
//! samples twice. Any other 4xx is final and surfaces as
//! [`ClientError::Rejected`] with the server's [`ErrorBody`].
//!
//! [`Client`] sends one request at a time. Turning a stream of records into
//! numbered batches, and keeping them until the server has them on disk, is
//! the job of [`BatchWriter`] (module [`crate::writer`]).
//!
//! The client speaks plain HTTP/1.1 (reqwest without TLS or HTTP/2): farm
//! traffic stays on the internal network, and the dependency tree stays small.

use std::time::Duration;

use bytes::Bytes;
use reqwest::header::{CONTENT_TYPE, RETRY_AFTER};
use reqwest::{Method, StatusCode};
use serde::de::DeserializeOwned;

use crate::api::{
    BatchAck, CreateFrame, ErrorBody, FrameInfo, FrameList, ImageQuery, ImportAck, NeedMap,
    PutFrame,
};
use crate::batch::{validate_frame_id, Batch, WireError};
use crate::BATCH_CONTENT_TYPE;
// Also reachable as `client::BatchWriter`, where it lived before it got its own module.
pub use crate::writer::BatchWriter;

/// Header naming the frame of a `POST /v1/frames`, for routing proxies.
pub const FRAME_HEADER: &str = "x-splatd-frame";

/// Longest piece of a non-JSON error body kept in an error.
const MAX_BODY_EXCERPT: usize = 512;

/// Why a request failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The base URL given to [`Client::new`] is unusable.
    #[error("invalid server URL {url:?}: {reason}")]
    InvalidUrl {
        /// The URL as given.
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// An argument was refused before anything was sent.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// A batch or frame id was refused before anything was sent.
    #[error("refused locally before sending: {0}")]
    Wire(#[from] WireError),
    /// The server refused the request (a 4xx other than 408 and 429, or a 501: the server
    /// lacks the feature asked for).
    /// Resending the same request will fail the same way.
    #[error("server refused the request with HTTP {status}: {body}")]
    Rejected {
        /// HTTP status code.
        status: u16,
        /// The server's error body; synthesised (`error` = `"http_<status>"`)
        /// when the response did not carry one.
        body: ErrorBody,
    },
    /// The server restarted again and again while what it had lost was being resent
    /// (16 restarts within one call); what is kept stays kept for the next call.
    #[error("the server kept restarting while frame {0}'s kept batches and passes were resent")]
    Restarting(String),
    /// Every attempt failed transiently.
    #[error("{operation} failed after {attempts} attempts; last failure: {last}")]
    GaveUp {
        /// Method and path, e.g. `POST /v1/frames/f/samples`.
        operation: String,
        /// Attempts made.
        attempts: u32,
        /// The last transient failure.
        last: String,
    },
    /// The server answered in a way the protocol does not allow
    /// (unexpected status, or a success body that is not the expected JSON).
    #[error("unexpected response to {operation} (HTTP {status}): {reason}")]
    UnexpectedResponse {
        /// Method and path.
        operation: String,
        /// HTTP status code.
        status: u16,
        /// What was wrong with it.
        reason: String,
    },
    /// The request could not be built (not retried).
    #[error("could not send {operation}: {source}")]
    Http {
        /// Method and path.
        operation: String,
        /// The underlying error.
        #[source]
        source: reqwest::Error,
    },
}

/// When and how often to retry transient failures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RetryPolicy {
    /// Total attempts per request, the first included (at least 1).
    pub max_attempts: u32,
    /// Wait after the first failure; doubled after each further failure.
    pub initial_backoff: Duration,
    /// Cap of the wait between attempts (also caps `Retry-After`).
    pub max_backoff: Duration,
}

impl Default for RetryPolicy {
    /// 10 attempts, 100 ms doubling up to 10 s: about a minute of retrying.
    fn default() -> Self {
        RetryPolicy {
            max_attempts: 10,
            initial_backoff: Duration::from_millis(100),
            max_backoff: Duration::from_secs(10),
        }
    }
}

impl RetryPolicy {
    /// The wait before retry number `retry` (0 = after the first failure),
    /// without jitter: `initial_backoff · 2^retry`, capped at `max_backoff`.
    pub fn backoff(&self, retry: u32) -> Duration {
        let factor = 1u32.checked_shl(retry).unwrap_or(u32::MAX);
        self.initial_backoff
            .saturating_mul(factor)
            .min(self.max_backoff)
    }

    /// The actual wait: [`RetryPolicy::backoff`] with "equal jitter" (a
    /// random point in its upper half, so that workers that failed together
    /// do not retry together), or the server's `Retry-After`, whichever is
    /// longer, capped at `max_backoff`.
    fn delay(&self, retry: u32, retry_after: Option<Duration>) -> Duration {
        let base = self.backoff(retry);
        let half = base / 2;
        let nanos = u64::try_from(half.as_nanos()).unwrap_or(u64::MAX);
        let jitter = match nanos {
            0 => Duration::ZERO,
            n => Duration::from_nanos(crate::ids::random_u64() % n),
        };
        (half + jitter)
            .max(retry_after.unwrap_or(Duration::ZERO))
            .min(self.max_backoff)
    }
}

/// A transient failure, kept for the [`ClientError::GaveUp`] message.
struct Transient {
    message: String,
    retry_after: Option<Duration>,
}

/// An async client of one splatd server. Cheap to clone (clones share the
/// connection pool).
#[derive(Debug, Clone)]
pub struct Client {
    http: reqwest::Client,
    base: String,
    token: Option<String>,
    retry: RetryPolicy,
}

impl Client {
    /// A client of the server at `base_url` (e.g. `http://render-head:7878`),
    /// with a 10 s connect timeout, a 120 s request timeout, no redirects and
    /// the default [`RetryPolicy`].
    pub fn new(base_url: impl Into<String>) -> Result<Client, ClientError> {
        let base_url = base_url.into();
        let http = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(10))
            .timeout(Duration::from_secs(120))
            .redirect(reqwest::redirect::Policy::none())
            .build()
            .map_err(|e| ClientError::InvalidUrl {
                url: base_url.clone(),
                reason: format!("could not set up the HTTP client: {e}"),
            })?;
        Client::with_http_client(base_url, http)
    }

    /// Like [`Client::new`] with a preconfigured reqwest client (timeouts,
    /// proxies, ...).
    pub fn with_http_client(
        base_url: impl Into<String>,
        http: reqwest::Client,
    ) -> Result<Client, ClientError> {
        let url = base_url.into();
        let invalid = |reason: &str| ClientError::InvalidUrl {
            url: url.clone(),
            reason: reason.to_owned(),
        };
        let parsed = reqwest::Url::parse(&url).map_err(|e| invalid(&e.to_string()))?;
        if parsed.scheme() != "http" {
            return Err(invalid(
                "only http:// is supported (this client is built without TLS)",
            ));
        }
        if parsed.query().is_some() || parsed.fragment().is_some() {
            return Err(invalid("the base URL must not have a query or fragment"));
        }
        let base = url.trim_end_matches('/').to_owned();
        Ok(Client {
            http,
            base,
            token: None,
            retry: RetryPolicy::default(),
        })
    }

    /// Sends `Authorization: Bearer <token>` with every request.
    pub fn with_token(mut self, token: impl Into<String>) -> Client {
        self.token = Some(token.into());
        self
    }

    /// Replaces the retry policy.
    pub fn with_retry_policy(mut self, retry: RetryPolicy) -> Client {
        self.retry = retry;
        self
    }

    /// The retry policy in use.
    pub fn retry_policy(&self) -> RetryPolicy {
        self.retry
    }

    /// `POST /v1/frames`: creates a frame (HTTP 201).
    ///
    /// If an attempt reached the server but its response was lost, the retry
    /// may be refused with 409 because the frame now exists; check with
    /// [`Client::frame_info`], or use [`Client::create_or_get`], which is
    /// idempotent (and needs only a `write` token).
    pub async fn create_frame(&self, req: &CreateFrame) -> Result<FrameInfo, ClientError> {
        validate_frame_id(&req.id)?;
        let body = serde_json::to_vec(req).map_err(|e| {
            ClientError::InvalidArgument(format!("could not serialise the frame request: {e}"))
        })?;
        // The id also goes in a header, for proxies that route frames to nodes by id without
        // parsing bodies (see `deploy/nginx/`).
        let (status, bytes) = self
            .send_with(
                Method::POST,
                "/v1/frames",
                Some((Bytes::from(body), "application/json")),
                Some((FRAME_HEADER, req.id.as_str())),
            )
            .await?;
        parse_json("POST /v1/frames", status, &bytes)
    }

    /// `PUT /v1/frames/{id}`: creates the frame, or returns it when it exists with exactly
    /// these parameters; [`ClientError::Rejected`] with 409 `frame_exists` (naming the
    /// parameters that differ) when it exists with others. Allowed to `write` tokens, so a
    /// render worker needs no `admin` token, and idempotent, so a retry after a lost answer
    /// gets the frame rather than a conflict.
    pub async fn create_or_get(&self, req: &CreateFrame) -> Result<FrameInfo, ClientError> {
        validate_frame_id(&req.id)?;
        let body = serde_json::to_vec(&PutFrame::from(req)).map_err(|e| {
            ClientError::InvalidArgument(format!("could not serialise the frame request: {e}"))
        })?;
        let path = format!("/v1/frames/{}", req.id);
        let (status, bytes) = self
            .send(
                Method::PUT,
                &path,
                Some((Bytes::from(body), "application/json")),
            )
            .await?;
        parse_json(&format!("PUT {path}"), status, &bytes)
    }

    /// `GET /v1/frames/{id}`: the state of a frame.
    pub async fn frame_info(&self, id: &str) -> Result<FrameInfo, ClientError> {
        self.get_info(id, "").await
    }

    /// `GET /v1/frames/{id}?convergence=latest`: the frame's latest convergence figures at
    /// once, never waiting for a render (see [`InfoConvergence::Latest`]).
    ///
    /// [`InfoConvergence::Latest`]: crate::api::InfoConvergence::Latest
    pub async fn frame_info_latest(&self, id: &str) -> Result<FrameInfo, ClientError> {
        self.get_info(id, "?convergence=latest").await
    }

    /// `GET /v1/frames/{id}?convergence=none`: the frame's counts (samples, batches, spp)
    /// without its convergence, which never wait for a render: what a tool that reports the
    /// frame's totals after posting asks for.
    pub async fn frame_counts(&self, id: &str) -> Result<FrameInfo, ClientError> {
        self.get_info(id, "?convergence=none").await
    }

    async fn get_info(&self, id: &str, query: &str) -> Result<FrameInfo, ClientError> {
        validate_frame_id(id)?;
        let path = format!("/v1/frames/{id}{query}");
        let (status, bytes) = self.send(Method::GET, &path, None).await?;
        parse_json(&format!("GET {path}"), status, &bytes)
    }

    /// `POST /v1/frames/{frame}/samples`: sends one batch.
    ///
    /// The batch is encoded once and the same bytes are resent on retries. One request: it
    /// keeps nothing for after a server restart; workers post through an
    /// [`Outbox`](crate::Outbox) (or a [`BatchWriter`]), which does.
    pub async fn post_batch(&self, batch: &Batch) -> Result<BatchAck, ClientError> {
        batch.validate()?;
        self.post_encoded(&batch.frame, Bytes::from(batch.encode()))
            .await
    }

    /// Sends an already encoded batch for `frame` (see [`Batch::encode`]).
    pub async fn post_encoded(&self, frame: &str, body: Bytes) -> Result<BatchAck, ClientError> {
        validate_frame_id(frame)?;
        let path = format!("/v1/frames/{frame}/samples");
        let (status, bytes) = self
            .send(Method::POST, &path, Some((body, BATCH_CONTENT_TYPE)))
            .await?;
        parse_json(&format!("POST {path}"), status, &bytes)
    }

    /// `POST /v1/frames/{id}/sync`: returns once everything the frame has
    /// applied is on disk (see [`crate::SyncAck`]).
    pub async fn sync(&self, id: &str) -> Result<crate::SyncAck, ClientError> {
        validate_frame_id(id)?;
        let path = format!("/v1/frames/{id}/sync");
        let (status, bytes) = self.send(Method::POST, &path, None).await?;
        parse_json(&format!("POST {path}"), status, &bytes)
    }

    /// `POST /v1/frames/{id}/passes?worker=W&seq=S`: one rendered pass as OpenEXR bytes (each
    /// pixel one sample), its beauty layer found by the server. `(worker, seq)` make it
    /// exactly-once, as for batches.
    pub async fn post_pass(
        &self,
        id: &str,
        worker: u64,
        seq: u64,
        exr: Bytes,
    ) -> Result<BatchAck, ClientError> {
        self.post_pass_layer(id, worker, seq, None, exr).await
    }

    /// [`Client::post_pass`] with the beauty read from the layer named `layer` (`&layer=`; see
    /// PROTOCOL.md for the names a file's layers have), or found automatically when `None`.
    pub async fn post_pass_layer(
        &self,
        id: &str,
        worker: u64,
        seq: u64,
        layer: Option<&str>,
        exr: Bytes,
    ) -> Result<BatchAck, ClientError> {
        validate_frame_id(id)?;
        let mut path = format!("/v1/frames/{id}/passes?worker={worker}&seq={seq}");
        if let Some(layer) = layer {
            path.push_str("&layer=");
            path.push_str(&percent_encode(layer));
        }
        let (status, bytes) = self
            .send(Method::POST, &path, Some((exr, "image/x-exr")))
            .await?;
        parse_json(&format!("POST {path}"), status, &bytes)
    }

    /// `GET /v1/frames`: every frame on the server.
    pub async fn list_frames(&self) -> Result<Vec<FrameInfo>, ClientError> {
        let (status, bytes) = self.send(Method::GET, "/v1/frames", None).await?;
        let list: FrameList = parse_json("GET /v1/frames", status, &bytes)?;
        Ok(list.frames)
    }

    /// `DELETE /v1/frames/{id}`.
    pub async fn delete_frame(&self, id: &str) -> Result<(), ClientError> {
        validate_frame_id(id)?;
        self.send(Method::DELETE, &format!("/v1/frames/{id}"), None)
            .await
            .map(|_| ())
    }

    /// `GET /v1/frames/{id}/image.exr`: the frame resolved now, as OpenEXR bytes.
    pub async fn image(&self, id: &str, query: &ImageQuery) -> Result<Bytes, ClientError> {
        validate_frame_id(id)?;
        let query = image_query_string(query);
        let path = format!("/v1/frames/{id}/image.exr{query}");
        self.send(Method::GET, &path, None).await.map(|(_, b)| b)
    }

    /// `GET /v1/frames/{id}/need?tile=T`: the frame's need map as JSON (tile edge `tile`, or
    /// the server's default, [`crate::api::DEFAULT_NEED_TILE`]).
    pub async fn need(&self, id: &str, tile: Option<u32>) -> Result<NeedMap, ClientError> {
        validate_frame_id(id)?;
        let query = tile.map(|t| format!("?tile={t}")).unwrap_or_default();
        let path = format!("/v1/frames/{id}/need{query}");
        let (status, bytes) = self.send(Method::GET, &path, None).await?;
        parse_json(&format!("GET {path}"), status, &bytes)
    }

    /// `GET /v1/frames/{id}/state`: the frame's accumulated state (see [`crate::StateDump`]).
    pub async fn export_state(&self, id: &str) -> Result<Bytes, ClientError> {
        validate_frame_id(id)?;
        let path = format!("/v1/frames/{id}/state");
        self.send(Method::GET, &path, None).await.map(|(_, b)| b)
    }

    /// [`Client::export_state`] into `out` (cleared first), read as it arrives: a node that
    /// pulls states repeatedly reuses one buffer instead of allocating (and faulting in) one as
    /// large as the frame per pull.
    pub async fn export_state_into(&self, id: &str, out: &mut Vec<u8>) -> Result<(), ClientError> {
        validate_frame_id(id)?;
        let path = format!("/v1/frames/{id}/state");
        self.send_into(Method::GET, &path, None, None, Some(out))
            .await
            .map(|_| ())
    }

    /// `POST /v1/frames/{id}/state`: adds an encoded state to the frame. A state carrying an
    /// [`crate::Origin`] is applied once however often it is resent.
    pub async fn import_state(&self, id: &str, state: Bytes) -> Result<ImportAck, ClientError> {
        validate_frame_id(id)?;
        let path = format!("/v1/frames/{id}/state");
        let (status, bytes) = self
            .send(
                Method::POST,
                &path,
                Some((state, crate::STATE_CONTENT_TYPE)),
            )
            .await?;
        parse_json(&format!("POST {path}"), status, &bytes)
    }

    /// A [`BatchWriter`] for `frame` that numbers its batches from `first_seq`.
    pub fn batch_writer(
        &self,
        frame: impl Into<String>,
        worker: u64,
        first_seq: u64,
        batch_size: usize,
    ) -> Result<BatchWriter, ClientError> {
        BatchWriter::new(self.clone(), frame, worker, first_seq, batch_size)
    }

    /// Sends a request, retrying transient failures; returns a 2xx status and
    /// its body.
    async fn send(
        &self,
        method: Method,
        path: &str,
        body: Option<(Bytes, &'static str)>,
    ) -> Result<(StatusCode, Bytes), ClientError> {
        self.send_with(method, path, body, None).await
    }

    /// [`Client::send`] with one extra request header.
    async fn send_with(
        &self,
        method: Method,
        path: &str,
        body: Option<(Bytes, &'static str)>,
        header: Option<(&'static str, &str)>,
    ) -> Result<(StatusCode, Bytes), ClientError> {
        self.send_into(method, path, body, header, None).await
    }

    /// [`Client::send_with`], reading a successful response's body into `sink` instead (the
    /// `Bytes` returned are then empty).
    async fn send_into(
        &self,
        method: Method,
        path: &str,
        body: Option<(Bytes, &'static str)>,
        header: Option<(&'static str, &str)>,
        mut sink: Option<&mut Vec<u8>>,
    ) -> Result<(StatusCode, Bytes), ClientError> {
        let operation = format!("{method} {path}");
        let url = format!("{}{path}", self.base);
        let attempts = self.retry.max_attempts.max(1);
        let mut last = None;
        for attempt in 0..attempts {
            if let Some(Transient { retry_after, .. }) = &last {
                tokio::time::sleep(self.retry.delay(attempt - 1, *retry_after)).await;
            }
            let mut req = self.http.request(method.clone(), &url);
            if let Some(token) = &self.token {
                req = req.bearer_auth(token);
            }
            if let Some((name, value)) = header {
                req = req.header(name, value);
            }
            if let Some((bytes, content_type)) = &body {
                // Bytes clones share the buffer: every attempt sends the same bytes.
                req = req.header(CONTENT_TYPE, *content_type).body(bytes.clone());
            }
            let response = match req.send().await {
                Ok(r) => r,
                Err(e) if e.is_builder() => {
                    return Err(ClientError::Http {
                        operation,
                        source: e,
                    })
                }
                Err(e) => {
                    last = Some(Transient {
                        message: error_chain(&e),
                        retry_after: None,
                    });
                    continue;
                }
            };
            let status = response.status();
            let retry_after = response
                .headers()
                .get(RETRY_AFTER)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.trim().parse::<u64>().ok())
                .map(Duration::from_secs);
            let read = match sink.as_deref_mut() {
                Some(out) if status.is_success() => {
                    read_into(response, out).await.map(|()| Bytes::new())
                }
                _ => response.bytes().await,
            };
            let bytes = match read {
                Ok(b) => b,
                Err(e) => {
                    last = Some(Transient {
                        message: format!("reading the HTTP {status} response: {}", error_chain(&e)),
                        retry_after: None,
                    });
                    continue;
                }
            };
            if status.is_success() {
                return Ok((status, bytes));
            }
            if is_transient(status) {
                last = Some(Transient {
                    message: format!("HTTP {status}: {}", excerpt(&bytes)),
                    retry_after,
                });
                continue;
            }
            // 501: the server lacks the feature (`denoiser_unavailable`); final like a 4xx.
            if status.is_client_error() || status == StatusCode::NOT_IMPLEMENTED {
                return Err(ClientError::Rejected {
                    status: status.as_u16(),
                    body: error_body(status, &bytes),
                });
            }
            return Err(ClientError::UnexpectedResponse {
                operation,
                status: status.as_u16(),
                reason: excerpt(&bytes),
            });
        }
        Err(ClientError::GaveUp {
            operation,
            attempts,
            last: last.map_or_else(|| "none".to_owned(), |t| t.message),
        })
    }
}

/// Reads `response`'s body into `out`, cleared first, with room for its declared length.
async fn read_into(mut response: reqwest::Response, out: &mut Vec<u8>) -> reqwest::Result<()> {
    out.clear();
    if let Some(len) = response.content_length() {
        out.reserve(len as usize);
    }
    while let Some(chunk) = response.chunk().await? {
        out.extend_from_slice(&chunk);
    }
    Ok(())
}

/// `text` as a query value: every byte but the unreserved ones (RFC 3986) as `%XX`, so layer
/// names with spaces, dots, `&` or UTF-8 reach the server as written.
fn percent_encode(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for b in text.bytes() {
        if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'.' | b'_' | b'~') {
            out.push(char::from(b));
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// `?a=1&b=2` for the parameters of an image request that are set, or nothing.
fn image_query_string(q: &ImageQuery) -> String {
    let mut parts = Vec::new();
    if let Some(v) = q.variant {
        parts.push(format!("variant={v}"));
    }
    for (name, value) in [
        ("kappa", q.kappa),
        ("kappa_min", q.kappa_min),
        ("kappa_exponent", q.kappa_exponent),
    ] {
        if let Some(v) = value {
            parts.push(format!("{name}={v}"));
        }
    }
    if q.cascades {
        parts.push("cascades=1".to_owned());
    }
    if let Some(d) = q.denoise {
        parts.push(format!("denoise={}", d.as_str()));
    }
    if let Some(d) = q.denoise_quality {
        parts.push(format!("denoise_quality={}", d.as_str()));
    }
    if parts.is_empty() {
        String::new()
    } else {
        format!("?{}", parts.join("&"))
    }
}

/// Statuses worth retrying: the server or something in front of it is
/// overloaded or restarting, or the request timed out. Not 501: the server lacks the
/// feature (e.g. `denoiser_unavailable`), and asking again does not give it one.
fn is_transient(status: StatusCode) -> bool {
    (status.is_server_error() && status != StatusCode::NOT_IMPLEMENTED)
        || status == StatusCode::REQUEST_TIMEOUT
        || status == StatusCode::TOO_MANY_REQUESTS
}

/// The server's [`ErrorBody`], or one made up from the status and raw body.
fn error_body(status: StatusCode, bytes: &[u8]) -> ErrorBody {
    serde_json::from_slice(bytes).unwrap_or_else(|_| {
        ErrorBody::new(
            format!("http_{}", status.as_u16()),
            format!(
                "HTTP {status} without a JSON error body: {}",
                excerpt(bytes)
            ),
        )
    })
}

/// Decodes a success body.
fn parse_json<T: DeserializeOwned>(
    operation: &str,
    status: StatusCode,
    bytes: &[u8],
) -> Result<T, ClientError> {
    serde_json::from_slice(bytes).map_err(|e| ClientError::UnexpectedResponse {
        operation: operation.to_owned(),
        status: status.as_u16(),
        reason: format!("body is not the expected JSON ({e}): {}", excerpt(bytes)),
    })
}

/// The start of a body, lossily decoded, for error messages.
fn excerpt(bytes: &[u8]) -> String {
    let text = String::from_utf8_lossy(&bytes[..bytes.len().min(MAX_BODY_EXCERPT)]);
    let more = if bytes.len() > MAX_BODY_EXCERPT {
        "..."
    } else {
        ""
    };
    format!("{:?}{more}", text.trim())
}

/// An error and its sources on one line (reqwest's own Display hides the cause).
fn error_chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut out = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        out.push_str(": ");
        out.push_str(&s.to_string());
        source = s.source();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_and_caps() {
        let p = RetryPolicy {
            max_attempts: 5,
            initial_backoff: Duration::from_millis(100),
            max_backoff: Duration::from_secs(1),
        };
        let waits: Vec<_> = (0..6).map(|r| p.backoff(r).as_millis()).collect();
        assert_eq!(waits, [100, 200, 400, 800, 1000, 1000]);
        assert_eq!(p.backoff(u32::MAX), Duration::from_secs(1));
    }

    #[test]
    fn delay_is_jittered_within_the_upper_half_and_honours_retry_after() {
        let p = RetryPolicy {
            max_attempts: 5,
            initial_backoff: Duration::from_millis(100),
            max_backoff: Duration::from_secs(2),
        };
        for retry in 0..8 {
            let d = p.delay(retry, None);
            assert!(d >= p.backoff(retry) / 2 && d <= p.backoff(retry), "{d:?}");
        }
        assert_eq!(
            p.delay(0, Some(Duration::from_secs(1))),
            Duration::from_secs(1)
        );
        assert_eq!(
            p.delay(0, Some(Duration::from_secs(60))),
            Duration::from_secs(2)
        );
    }

    #[test]
    fn transient_statuses() {
        for s in [500, 502, 503, 504, 408, 429] {
            assert!(is_transient(StatusCode::from_u16(s).expect("valid")), "{s}");
        }
        for s in [400, 401, 404, 409, 413, 415, 422, 501] {
            assert!(
                !is_transient(StatusCode::from_u16(s).expect("valid")),
                "{s}"
            );
        }
    }

    #[test]
    fn base_url_checks() {
        assert!(Client::new("http://127.0.0.1:7878/").is_ok());
        for bad in [
            "https://host",
            "127.0.0.1:7878",
            "http://h/?q=1",
            "not a url",
        ] {
            assert!(
                matches!(Client::new(bad), Err(ClientError::InvalidUrl { .. })),
                "{bad}"
            );
        }
    }

    #[test]
    fn query_values_are_percent_encoded() {
        assert_eq!(percent_encode("ViewLayer.Combined"), "ViewLayer.Combined");
        assert_eq!(percent_encode("Noisy Image&x=1"), "Noisy%20Image%26x%3D1");
        assert_eq!(percent_encode("é"), "%C3%A9");
    }

    #[test]
    fn error_body_falls_back_for_non_json() {
        let b = error_body(StatusCode::NOT_FOUND, b"<html>nope</html>");
        assert_eq!(b.error, "http_404");
        assert!(b.message.contains("nope"), "{}", b.message);
        let b = error_body(
            StatusCode::UNPROCESSABLE_ENTITY,
            br#"{"error":"pixel_out_of_range","message":"x 9 >= width 4"}"#,
        );
        assert_eq!(b, ErrorBody::new("pixel_out_of_range", "x 9 >= width 4"));
    }
}
