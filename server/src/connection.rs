//! Connections: how many may be open, how long each may take to say what it wants and to take
//! its answer, and what a client hears when its request head cannot be read.
//!
//! * [`Connections`] caps open connections (`--max-connections`). At the cap, a new connection
//!   first pushes out the oldest one that has no request in progress, preferring one that never
//!   sent a complete request head (a silent or trickling socket) over an idle keep-alive one; if
//!   every connection is serving a request, the new one is closed at once. Silent sockets
//!   therefore cannot lock out `/healthz` or a worker, and connections with work in progress are
//!   never touched.
//! * [`HeadGate`] sits between the socket and hyper and reads every request head itself before
//!   hyper sees a byte of it: the head must be complete within `--head-timeout` (from accept for
//!   the first request, from its first byte for the next ones on a keep-alive connection, which
//!   may idle for `--idle-timeout` before that byte), within [`MAX_HEAD_BYTES`], with a request
//!   line within [`MAX_REQUEST_LINE_BYTES`] and at most [`MAX_HEADERS`] headers, and parse. A head
//!   that breaks a rule is answered 400, 414 or 431 with a JSON `ErrorBody` and
//!   `Connection: close` (hyper's own answers to such heads have no body), through the same
//!   service as every other answer, so responses stay in order.
//! * A response must be handed to the socket within `--response-timeout` from its first byte:
//!   a client that stops reading is disconnected and the response's memory freed.
//!
//! The gate passes a request body with a `Content-Length` through byte for byte and then expects
//! the next head; after a chunked body it cannot tell where the next head starts, so such a
//! request is answered with `Connection: close` (see `http::manners`) and the rest of the
//! connection is passed through unchecked.

use std::collections::BTreeMap;
use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{ready, Context, Poll};
use std::time::Duration;

use axum::body::Body;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::IntoResponse;
use bytes::Bytes;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::Notify;
use tokio::time::{Instant, Sleep};

use crate::http::error::ApiError;

/// Longest request head (request line and headers) accepted: 431 beyond it.
pub const MAX_HEAD_BYTES: usize = 64 * 1024;
/// Longest request line (method, URI, version) accepted: 414 beyond it.
pub const MAX_REQUEST_LINE_BYTES: usize = 8 * 1024;
/// Most headers in one request: 431 beyond it.
pub const MAX_HEADERS: usize = 100;

/// The time limits of a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Deadlines {
    /// From accept (or from the first byte of a later request) to a complete request head.
    pub head: Duration,
    /// Longest a keep-alive connection may wait for the first byte of its next request.
    pub idle: Duration,
    /// From the first byte of a response to its last.
    pub response: Duration,
}

/// The open connections of a server, and the cap on them.
#[derive(Debug)]
pub struct Connections {
    max: usize,
    open: Mutex<BTreeMap<u64, Arc<Conn>>>,
    next: AtomicU64,
    refused: AtomicU64,
    evicted: AtomicU64,
    /// Connections pushed out whose sockets are not closed yet (their tasks have yet to run).
    closing: AtomicUsize,
    /// Wakes [`Connections::until_open_at_most`] when a connection closes.
    closed: Notify,
}

/// One open connection, as the accept loop, its gate and its service share it.
#[derive(Debug)]
pub struct Conn {
    id: u64,
    /// A complete request head has been read.
    had_head: AtomicBool,
    /// Pushed out to make room; its socket is still open until its task ends.
    evicted: AtomicBool,
    /// Requests being served (answered but not yet fully sent included).
    busy: AtomicUsize,
    /// When the response being sent began.
    responding_since: Mutex<Option<Instant>>,
    /// Wakes the connection's task when `responding_since` changes.
    changed: Notify,
    /// Tells the connection's task to close (the cap needs its place).
    evict: Notify,
    /// A request head the gate refused, to be answered by the service in its place.
    refusal: Mutex<Option<ApiError>>,
    /// The request whose response body has ended but may still sit in hyper's buffer: it
    /// ends when the socket next reports everything flushed.
    finishing: Mutex<Option<RequestGuard>>,
}

/// Why a connection was not served.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refused {
    /// Every open connection is serving a request: the new one is closed at once.
    Full,
}

impl Connections {
    /// No connections yet; at most `max` at once.
    pub fn new(max: usize) -> Connections {
        Connections {
            max: max.max(1),
            open: Mutex::new(BTreeMap::new()),
            next: AtomicU64::new(0),
            refused: AtomicU64::new(0),
            evicted: AtomicU64::new(0),
            closing: AtomicUsize::new(0),
            closed: Notify::new(),
        }
    }

    /// Returns once at most `n` connections are open.
    pub async fn until_open_at_most(&self, n: usize) {
        loop {
            let closed = self.closed.notified();
            tokio::pin!(closed);
            closed.as_mut().enable();
            if self.open() <= n {
                return;
            }
            closed.await;
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Arc<Conn>>> {
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The cap.
    pub fn max(&self) -> usize {
        self.max
    }

    /// Connections open now (not counting those pushed out and still closing).
    pub fn open(&self) -> usize {
        self.lock().len()
    }

    /// Most connections pushed out and not yet closed at once: an eighth of the cap, at least
    /// 64 (the open-file limit leaves a quarter of itself, at least 64, beyond the cap).
    pub fn closing_allowance(&self) -> usize {
        (self.max / 8).max(64)
    }

    /// Connections closed at once because every place was serving a request.
    pub fn refused(&self) -> u64 {
        self.refused.load(Ordering::Relaxed)
    }

    /// Connections closed to make room for a new one.
    pub fn evicted(&self) -> u64 {
        self.evicted.load(Ordering::Relaxed)
    }

    /// Admits a new connection, pushing out an unoccupied one when at the cap. The returned
    /// [`Registered`] takes the connection's place back when dropped.
    ///
    /// Connections pushed out keep their sockets until their tasks run, so the sockets open
    /// are at most the cap plus the connections still closing; at most [`Self::closing_allowance`]
    /// may be closing at once, beyond that a new connection is refused instead.
    pub fn admit(self: &Arc<Self>) -> Result<Registered, Refused> {
        let mut open = self.lock();
        if open.len() >= self.max {
            if self.closing.load(Ordering::Acquire) >= self.closing_allowance() {
                self.refused.fetch_add(1, Ordering::Relaxed);
                metrics::counter!("splatd_connections_closed_total", "reason" => "full")
                    .increment(1);
                return Err(Refused::Full);
            }
            // Oldest first (ids grow), those that never sent a head before idle keep-alive ones.
            let idle = |c: &&Arc<Conn>| c.busy.load(Ordering::Acquire) == 0;
            let victim = open
                .values()
                .filter(idle)
                .find(|c| !c.had_head.load(Ordering::Acquire))
                .or_else(|| open.values().find(idle))
                .map(|c| c.id);
            match victim {
                Some(id) => {
                    let conn = open.remove(&id).expect("found above");
                    conn.evicted.store(true, Ordering::Release);
                    self.closing.fetch_add(1, Ordering::AcqRel);
                    conn.evict.notify_one();
                    self.evicted.fetch_add(1, Ordering::Relaxed);
                    metrics::counter!("splatd_connections_closed_total", "reason" => "evicted")
                        .increment(1);
                }
                None => {
                    self.refused.fetch_add(1, Ordering::Relaxed);
                    metrics::counter!("splatd_connections_closed_total", "reason" => "full")
                        .increment(1);
                    return Err(Refused::Full);
                }
            }
        }
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let conn = Arc::new(Conn {
            id,
            had_head: AtomicBool::new(false),
            evicted: AtomicBool::new(false),
            busy: AtomicUsize::new(0),
            responding_since: Mutex::new(None),
            changed: Notify::new(),
            evict: Notify::new(),
            refusal: Mutex::new(None),
            finishing: Mutex::new(None),
        });
        open.insert(id, conn.clone());
        Ok(Registered {
            connections: self.clone(),
            conn,
        })
    }
}

/// A connection's place among the open ones; given back when dropped.
#[derive(Debug)]
pub struct Registered {
    connections: Arc<Connections>,
    conn: Arc<Conn>,
}

impl Registered {
    /// The connection's shared state.
    pub fn conn(&self) -> &Arc<Conn> {
        &self.conn
    }
}

impl Drop for Registered {
    fn drop(&mut self) {
        // A response still waiting for its flush ends with the connection (and the cycle
        // between the connection and that request's guard with it).
        drop(self.conn.finish());
        if self.conn.evicted.load(Ordering::Acquire) {
            self.connections.closing.fetch_sub(1, Ordering::AcqRel);
        }
        self.connections.lock().remove(&self.conn.id);
        self.connections.closed.notify_waiters();
    }
}

/// How a connection's task ended.
#[derive(Debug)]
pub enum Ended<E> {
    /// Hyper finished the connection (the client closed it, or keep-alive ended).
    Done(Result<(), E>),
    /// Closed to make room under the cap.
    Evicted,
    /// A response took longer than the response deadline to send.
    SlowReader,
}

impl Conn {
    /// Drives `connection` until it ends, is evicted, or a response on it outlives
    /// `response_timeout`; dropping the connection closes the socket and frees the response.
    pub async fn drive<E>(
        &self,
        connection: impl Future<Output = Result<(), E>>,
        response_timeout: Duration,
    ) -> Ended<E> {
        tokio::pin!(connection);
        loop {
            let since = *self
                .responding_since
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            let deadline = since.map(|s| s + response_timeout);
            tokio::select! {
                done = &mut connection => return Ended::Done(done),
                () = self.evict.notified() => return Ended::Evicted,
                () = self.changed.notified() => {}
                () = sleep_until_some(deadline) => {
                    metrics::counter!("splatd_connections_closed_total", "reason" => "slow_reader")
                        .increment(1);
                    return Ended::SlowReader;
                }
            }
        }
    }

    fn begin_request(self: &Arc<Self>) -> RequestGuard {
        self.busy.fetch_add(1, Ordering::AcqRel);
        RequestGuard {
            conn: self.clone(),
            responding: false,
        }
    }

    /// Ends the request whose response was waiting to be flushed, if any.
    fn finish(&self) -> Option<RequestGuard> {
        self.finishing
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
    }

    fn take_refusal(&self) -> Option<ApiError> {
        self.refusal
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
    }
}

async fn sleep_until_some(deadline: Option<Instant>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d).await,
        None => std::future::pending().await,
    }
}

/// A request in progress on a connection: from the service call to the response's last byte.
#[derive(Debug)]
struct RequestGuard {
    conn: Arc<Conn>,
    responding: bool,
}

impl RequestGuard {
    /// The response is about to be sent: its deadline starts.
    fn responding(&mut self) {
        self.responding = true;
        *self
            .conn
            .responding_since
            .lock()
            .unwrap_or_else(|e| e.into_inner()) = Some(Instant::now());
        self.conn.changed.notify_one();
    }
}

impl Drop for RequestGuard {
    fn drop(&mut self) {
        if self.responding {
            *self
                .conn
                .responding_since
                .lock()
                .unwrap_or_else(|e| e.into_inner()) = None;
            self.conn.changed.notify_one();
        }
        self.conn.busy.fetch_sub(1, Ordering::AcqRel);
    }
}

/// A response body that hands its request's guard over to be ended at the next complete flush
/// once its last frame is taken (so the request counts as in progress, and under the response
/// deadline, until its last byte is in the socket), or ends it when dropped unsent.
pub struct ResponseBody {
    inner: Body,
    guard: Option<RequestGuard>,
}

impl http_body::Body for ResponseBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        let frame = ready!(Pin::new(&mut self.inner).poll_frame(cx));
        if frame.is_none() || self.inner.is_end_stream() {
            if let Some(guard) = self.guard.take() {
                let conn = guard.conn.clone();
                let earlier = conn
                    .finishing
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .replace(guard);
                drop(earlier);
            }
        }
        Poll::Ready(frame)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// Serves one connection's requests with `router`: answers a head the gate refused in its
/// place, and tracks each request from its call to its response's last byte.
pub fn service(
    router: axum::Router,
    conn: Arc<Conn>,
) -> impl hyper::service::Service<
    hyper::Request<hyper::body::Incoming>,
    Response = hyper::Response<ResponseBody>,
    Error = Infallible,
    Future = impl Future<Output = Result<hyper::Response<ResponseBody>, Infallible>> + Send,
> + Clone {
    use tower::ServiceExt;
    hyper::service::service_fn(move |request: hyper::Request<hyper::body::Incoming>| {
        let router = router.clone();
        let conn = conn.clone();
        async move {
            let mut guard = conn.begin_request();
            let stand_in = request.method().as_str() == STAND_IN_METHOD;
            let refusal = if stand_in { conn.take_refusal() } else { None };
            let response = match refusal {
                Some(refusal) => {
                    let mut response = refusal.into_response();
                    response
                        .headers_mut()
                        .insert(header::CONNECTION, HeaderValue::from_static("close"));
                    response
                }
                None => {
                    let Ok(response) = router.oneshot(request.map(Body::new)).await;
                    response
                }
            };
            guard.responding();
            Ok(response.map(|inner| ResponseBody {
                inner,
                guard: Some(guard),
            }))
        }
    })
}

/// What the gate passes to hyper after a head.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Framing {
    /// A body of this many bytes (0: none), then the next head.
    Length(u64),
    /// A chunked body: the rest of the connection passes unchecked.
    Chunked,
}

#[derive(Debug)]
enum Mode {
    /// Reading a head; `started` once its first byte arrived (or from accept).
    Head { started: bool },
    /// Handing hyper `left` bytes of an accepted head, then the body.
    Release { left: usize, then: Framing },
    /// Handing hyper `left` bytes of body.
    Body { left: u64 },
    /// Everything as it comes.
    Passthrough,
    /// Handing hyper the stand-in head of a refused one, then nothing.
    StandIn { at: usize },
    /// Nothing more, ever: hyper answers the stand-in and closes the connection (an end of
    /// stream instead would make hyper drop the connection before it answers).
    Hold,
    /// End of stream.
    Closed,
}

/// The method of the stand-in request; the gate refuses it from clients, so only a stand-in
/// carries it.
const STAND_IN_METHOD: &str = "SPLATD-REFUSED-HEAD";
/// What hyper reads in place of a refused head: a request the service answers with the refusal
/// (which the gate may have found while hyper still had earlier requests to answer).
const STAND_IN: &[u8] = b"SPLATD-REFUSED-HEAD / HTTP/1.1\r\nconnection: close\r\n\r\n";

/// The socket as hyper sees it: request heads are read and checked here first (see the module
/// docs). Writes pass straight through.
pub struct HeadGate<T> {
    io: T,
    conn: Arc<Conn>,
    deadlines: Deadlines,
    /// Bytes read from the socket, not yet handed to hyper.
    buf: Vec<u8>,
    mode: Mode,
    timer: Pin<Box<Sleep>>,
}

impl<T> HeadGate<T> {
    /// A gate on a freshly accepted socket: its first head is due within the head deadline.
    pub fn new(io: T, conn: Arc<Conn>, deadlines: Deadlines) -> HeadGate<T> {
        HeadGate {
            io,
            conn,
            deadlines,
            buf: Vec::new(),
            mode: Mode::Head { started: true },
            timer: Box::pin(tokio::time::sleep(deadlines.head)),
        }
    }

    fn arm(&mut self, after: Duration) {
        self.timer.as_mut().reset(Instant::now() + after);
    }

    fn refuse(&mut self, refusal: ApiError) {
        tracing::debug!(
            status = refusal.status.as_u16(),
            code = refusal.code,
            "request head refused"
        );
        *self.conn.refusal.lock().unwrap_or_else(|e| e.into_inner()) = Some(refusal);
        self.buf.clear();
        self.mode = Mode::StandIn { at: 0 };
    }

    /// Hands hyper up to `n` buffered bytes.
    fn hand_over(&mut self, out: &mut ReadBuf<'_>, n: usize) -> usize {
        let n = n.min(self.buf.len()).min(out.remaining());
        out.put_slice(&self.buf[..n]);
        self.buf.drain(..n);
        n
    }
}

impl<T: AsyncRead + Unpin> HeadGate<T> {
    /// Reads more of the socket into the buffer: `Ok(false)` at end of stream.
    fn fill(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<bool>> {
        let mut chunk = [0u8; 16 * 1024];
        let mut read = ReadBuf::new(&mut chunk);
        ready!(Pin::new(&mut self.io).poll_read(cx, &mut read))?;
        self.buf.extend_from_slice(read.filled());
        Poll::Ready(Ok(!read.filled().is_empty()))
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for HeadGate<T> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        out: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        loop {
            match this.mode {
                Mode::Closed => return Poll::Ready(Ok(())),
                Mode::Hold => return Poll::Pending,
                Mode::StandIn { at } => {
                    let n = (STAND_IN.len() - at).min(out.remaining());
                    out.put_slice(&STAND_IN[at..at + n]);
                    this.mode = if at + n == STAND_IN.len() {
                        Mode::Hold
                    } else {
                        Mode::StandIn { at: at + n }
                    };
                    return Poll::Ready(Ok(()));
                }
                Mode::Release { left, then } => {
                    let n = this.hand_over(out, left);
                    if n == left {
                        this.mode = match then {
                            Framing::Length(0) => {
                                this.arm(this.deadlines.idle);
                                Mode::Head { started: false }
                            }
                            Framing::Length(n) => Mode::Body { left: n },
                            Framing::Chunked => Mode::Passthrough,
                        };
                    } else {
                        this.mode = Mode::Release {
                            left: left - n,
                            then,
                        };
                    }
                    return Poll::Ready(Ok(()));
                }
                Mode::Body { left } => {
                    if this.buf.is_empty() && !ready!(this.fill(cx))? {
                        return Poll::Ready(Ok(()));
                    }
                    let n = this.hand_over(out, left.min(usize::MAX as u64) as usize) as u64;
                    this.mode = if n == left {
                        this.arm(this.deadlines.idle);
                        Mode::Head { started: false }
                    } else {
                        Mode::Body { left: left - n }
                    };
                    return Poll::Ready(Ok(()));
                }
                Mode::Passthrough => {
                    if !this.buf.is_empty() {
                        this.hand_over(out, usize::MAX);
                        return Poll::Ready(Ok(()));
                    }
                    return Pin::new(&mut this.io).poll_read(cx, out);
                }
                Mode::Head { started } => {
                    if !this.buf.is_empty() {
                        if !started {
                            this.arm(this.deadlines.head);
                            this.mode = Mode::Head { started: true };
                        }
                        match check_head(&this.buf) {
                            Ok(Some((len, framing))) => {
                                this.conn.had_head.store(true, Ordering::Release);
                                this.mode = Mode::Release {
                                    left: len,
                                    then: framing,
                                };
                                continue;
                            }
                            Ok(None) => {}
                            Err(refusal) => {
                                this.refuse(refusal);
                                continue;
                            }
                        }
                    }
                    match this.fill(cx) {
                        Poll::Ready(Ok(true)) => continue,
                        // The client went away (between requests, or mid-head).
                        Poll::Ready(Ok(false)) => {
                            this.mode = Mode::Closed;
                            continue;
                        }
                        Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                        Poll::Pending => {
                            ready!(this.timer.as_mut().poll(cx));
                            tracing::debug!(
                                started,
                                "no complete request head in time: closing the connection"
                            );
                            metrics::counter!(
                                "splatd_connections_closed_total",
                                "reason" => if started { "head_timeout" } else { "idle" }
                            )
                            .increment(1);
                            this.mode = Mode::Closed;
                            continue;
                        }
                    }
                }
            }
        }
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for HeadGate<T> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        data: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write(cx, data)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    /// Hyper flushes after writing, its own buffer first: once this is ready, every byte of a
    /// response whose body has ended is in the socket, and its request is over.
    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        ready!(Pin::new(&mut this.io).poll_flush(cx))?;
        drop(this.conn.finish());
        Poll::Ready(Ok(()))
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

/// Checks the request head at the start of `buf`: `Ok(None)` while it is incomplete (and within
/// the limits), its length and body framing once complete, or the refusal to answer.
fn check_head(buf: &[u8]) -> Result<Option<(usize, Framing)>, ApiError> {
    let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
    let mut request = httparse::Request::new(&mut headers);
    let len = match request.parse(buf) {
        Ok(httparse::Status::Complete(len)) => len,
        Ok(httparse::Status::Partial) => {
            let line_end = buf.iter().position(|&b| b == b'\n');
            if line_end.unwrap_or(buf.len()) > MAX_REQUEST_LINE_BYTES {
                return Err(uri_too_long());
            }
            if buf.len() > MAX_HEAD_BYTES {
                return Err(head_too_large(format!(
                    "the request head exceeds {MAX_HEAD_BYTES} bytes"
                )));
            }
            return Ok(None);
        }
        Err(httparse::Error::TooManyHeaders) => {
            return Err(head_too_large(format!(
                "the request has more than {MAX_HEADERS} headers"
            )))
        }
        Err(e) => return Err(malformed(format!("{e}"))),
    };
    let line_end = buf.iter().position(|&b| b == b'\n').unwrap_or(len);
    if line_end > MAX_REQUEST_LINE_BYTES {
        return Err(uri_too_long());
    }
    if len > MAX_HEAD_BYTES {
        return Err(head_too_large(format!(
            "the request head exceeds {MAX_HEAD_BYTES} bytes"
        )));
    }
    // What hyper would refuse after parsing, refused here with a body instead.
    let method = request.method.unwrap_or_default();
    axum::http::Method::from_bytes(method.as_bytes())
        .ok()
        .filter(|m| m.as_str() != STAND_IN_METHOD)
        .ok_or_else(|| malformed(format!("invalid method {method:?}")))?;
    let path = request.path.unwrap_or_default();
    axum::http::Uri::try_from(path).map_err(|e| malformed(format!("invalid URI: {e}")))?;
    let mut length: Option<u64> = None;
    let mut chunked = false;
    for h in request.headers.iter() {
        if h.name.eq_ignore_ascii_case("content-length") {
            for value in h.value.split(|&b| b == b',') {
                let parsed = std::str::from_utf8(value)
                    .ok()
                    .map(str::trim)
                    .filter(|v| !v.is_empty() && v.bytes().all(|b| b.is_ascii_digit()))
                    .and_then(|v| v.parse::<u64>().ok())
                    .ok_or_else(|| malformed("invalid Content-Length".into()))?;
                if length.is_some_and(|l| l != parsed) {
                    return Err(malformed("conflicting Content-Length headers".into()));
                }
                length = Some(parsed);
            }
        } else if h.name.eq_ignore_ascii_case("transfer-encoding") {
            let last = h
                .value
                .rsplit(|&b| b == b',')
                .next()
                .map(|v| v.trim_ascii())
                .unwrap_or_default();
            if !last.eq_ignore_ascii_case(b"chunked") {
                return Err(malformed(
                    "a Transfer-Encoding must end with chunked".into(),
                ));
            }
            if request.version == Some(0) {
                return Err(malformed(
                    "Transfer-Encoding is not allowed in HTTP/1.0".into(),
                ));
            }
            chunked = true;
        }
    }
    let framing = if chunked {
        Framing::Chunked
    } else {
        Framing::Length(length.unwrap_or(0))
    };
    Ok(Some((len, framing)))
}

fn malformed(detail: String) -> ApiError {
    ApiError::bad_request(
        "malformed_request",
        format!("the request head could not be read: {detail}"),
    )
}

fn uri_too_long() -> ApiError {
    ApiError::new(
        StatusCode::URI_TOO_LONG,
        "uri_too_long",
        format!("the request line exceeds {MAX_REQUEST_LINE_BYTES} bytes"),
    )
}

fn head_too_large(detail: String) -> ApiError {
    ApiError::new(
        StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
        "headers_too_large",
        detail,
    )
}

/// Raises this process's soft limit on open files to its hard limit, logging both, and returns
/// the soft limit now in force (`None` where there is no such limit to read).
pub fn raise_descriptor_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes into the struct it is given.
        if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
            tracing::warn!(error = %io::Error::last_os_error(), "reading RLIMIT_NOFILE");
            return None;
        }
        let before = limit.rlim_cur;
        if limit.rlim_cur < limit.rlim_max {
            let raised = libc::rlimit {
                rlim_cur: limit.rlim_max,
                rlim_max: limit.rlim_max,
            };
            // SAFETY: setrlimit reads the struct it is given.
            if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
                limit.rlim_cur = limit.rlim_max;
            } else {
                tracing::warn!(error = %io::Error::last_os_error(), "raising RLIMIT_NOFILE");
            }
        }
        tracing::info!(
            soft_before = before,
            soft = limit.rlim_cur,
            hard = limit.rlim_max,
            "open file limit"
        );
        Some(limit.rlim_cur)
    }
    #[cfg(not(unix))]
    None
}

/// The connection cap to use under a descriptor limit of `nofile`: `wanted`, or less when that
/// would leave fewer than a quarter of the descriptors (at least 64) for everything else (the
/// data directory's files, the listener, outgoing pushes).
pub fn cap_for(wanted: usize, nofile: Option<u64>) -> usize {
    match nofile {
        Some(n) => {
            let spare = (n / 4).max(64);
            wanted.min(n.saturating_sub(spare).max(1) as usize)
        }
        None => wanted,
    }
    .max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heads_are_checked_like_hyper_would_but_answered_with_a_body() {
        let ok = b"POST /v1/frames/f/samples HTTP/1.1\r\nhost: x\r\ncontent-length: 5\r\n\r\nhello";
        assert_eq!(
            check_head(ok).unwrap(),
            Some((ok.len() - 5, Framing::Length(5)))
        );
        assert_eq!(check_head(&ok[..20]).unwrap(), None, "incomplete");
        let bare_lf = b"GET / HTTP/1.1\nhost: x\n\n";
        assert_eq!(
            check_head(bare_lf).unwrap(),
            Some((bare_lf.len(), Framing::Length(0)))
        );
        let chunked = b"POST / HTTP/1.1\r\ntransfer-encoding: chunked\r\n\r\n";
        assert_eq!(check_head(chunked).unwrap().unwrap().1, Framing::Chunked);

        let code = |head: &[u8]| {
            let e = check_head(head).unwrap_err();
            (e.status.as_u16(), e.code)
        };
        assert_eq!(
            code(b"GET / HTTP/1.1\r\nbad header\r\n\r\n"),
            (400, "malformed_request")
        );
        assert_eq!(
            code(b"GET / HTTP/1.1\r\ncontent-length: 5\r\ncontent-length: 6\r\n\r\n"),
            (400, "malformed_request")
        );
        assert_eq!(
            code(b"POST / HTTP/1.1\r\ntransfer-encoding: gzip\r\n\r\n"),
            (400, "malformed_request")
        );
        let long_uri = format!("GET /{} HTTP/1.1\r\n", "a".repeat(MAX_REQUEST_LINE_BYTES));
        assert_eq!(code(long_uri.as_bytes()), (414, "uri_too_long"));
        let many: String = (0..=MAX_HEADERS).map(|i| format!("x-{i}: 1\r\n")).collect();
        assert_eq!(
            code(format!("GET / HTTP/1.1\r\n{many}\r\n").as_bytes()),
            (431, "headers_too_large")
        );
        let big = format!("GET / HTTP/1.1\r\nx: {}\r\n", "b".repeat(MAX_HEAD_BYTES));
        assert_eq!(code(big.as_bytes()), (431, "headers_too_large"));
    }

    #[test]
    fn the_cap_leaves_room_for_other_descriptors() {
        assert_eq!(cap_for(4096, Some(20_000)), 4096);
        assert_eq!(cap_for(4096, Some(1024)), 768);
        assert_eq!(cap_for(4096, Some(100)), 36);
        assert_eq!(cap_for(10, None), 10);
    }

    #[test]
    fn at_the_cap_a_connection_without_work_makes_room() {
        let connections = Arc::new(Connections::new(2));
        let a = connections.admit().unwrap();
        let b = connections.admit().unwrap();
        // `a` has a request in progress; `b` sent a head and idles: `b` goes.
        let _request = a.conn().begin_request();
        b.conn().had_head.store(true, Ordering::Release);
        let c = connections.admit().unwrap();
        assert_eq!(connections.evicted(), 1);
        assert_eq!(connections.open(), 2);
        // `c` is silent and `b` was already pushed out: `c` goes next, before anything busy.
        let d = connections.admit().unwrap();
        assert_eq!(connections.evicted(), 2);
        // Everyone left is serving a request: a new connection is refused.
        let _busy = d.conn().begin_request();
        assert_eq!(connections.admit().unwrap_err(), Refused::Full);
        assert_eq!(connections.refused(), 1);
        drop((b, c));
        assert_eq!(connections.open(), 2);
        assert_eq!(connections.closing.load(Ordering::Acquire), 0);
    }

    #[test]
    fn connections_still_closing_count_against_the_cap() {
        let connections = Arc::new(Connections::new(4));
        let allowance = connections.closing_allowance();
        let mut held: Vec<Registered> = (0..4).map(|_| connections.admit().unwrap()).collect();
        // Each new one pushes out an old one whose task has not closed it yet.
        for _ in 0..allowance {
            held.push(connections.admit().unwrap());
        }
        assert_eq!(connections.closing.load(Ordering::Acquire), allowance);
        assert_eq!(connections.admit().unwrap_err(), Refused::Full);
        // One closes: room for one more.
        held.remove(0);
        assert!(connections.admit().is_ok());
    }

    #[test]
    fn a_response_counts_until_flushed() {
        let connections = Arc::new(Connections::new(1));
        let a = connections.admit().unwrap();
        a.conn().had_head.store(true, Ordering::Release);
        // The body has ended, the bytes may still be in hyper's buffer: not idle yet.
        let mut guard = a.conn().begin_request();
        guard.responding();
        *a.conn().finishing.lock().unwrap() = Some(guard);
        assert_eq!(connections.admit().unwrap_err(), Refused::Full);
        assert!(a.conn().responding_since.lock().unwrap().is_some());
        // Flushed: the request is over and the connection may make room.
        drop(a.conn().finish());
        assert!(a.conn().responding_since.lock().unwrap().is_none());
        let _b = connections.admit().unwrap();
        assert_eq!(connections.evicted(), 1);
        // A connection that ends with a response unflushed drops it (no cycle left behind).
        let c = Arc::new(Connections::new(1)).admit().unwrap();
        *c.conn().finishing.lock().unwrap() = Some(c.conn().begin_request());
        let conn = c.conn().clone();
        drop(c);
        assert_eq!(conn.busy.load(Ordering::Acquire), 0);
        assert_eq!(Arc::strong_count(&conn), 1);
    }
}
