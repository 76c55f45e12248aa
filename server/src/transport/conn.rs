//! One connection's shared state: its deadlines, the requests in progress on it, and the
//! service that answers them.

use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{ready, Context, Poll};
use std::time::Duration;

use axum::body::Body;
use axum::http::{header, HeaderValue};
use axum::response::IntoResponse;
use bytes::Bytes;
use tokio::sync::Notify;
use tokio::time::Instant;

use super::head::{HeadError, STAND_IN_METHOD};

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

/// One open connection, as the accept loop, its gate and its service share it.
#[derive(Debug)]
pub struct Conn {
    pub(super) id: u64,
    /// A complete request head has been read.
    pub(super) had_head: AtomicBool,
    /// Pushed out to make room; its socket is still open until its task ends.
    pub(super) evicted: AtomicBool,
    /// Requests being served (answered but not yet fully sent included).
    pub(super) busy: AtomicUsize,
    /// When the response being sent began.
    pub(super) responding_since: Mutex<Option<Instant>>,
    /// Wakes the connection's task when `responding_since` changes.
    pub(super) changed: Notify,
    /// Tells the connection's task to close (the cap needs its place).
    pub(super) evict: Notify,
    /// A request head the gate refused, to be answered by the service in its place.
    pub(super) refusal: Mutex<Option<HeadError>>,
    /// The request whose response body has ended but may still sit in hyper's buffer: it
    /// ends when the socket next reports everything flushed.
    pub(super) finishing: Mutex<Option<RequestGuard>>,
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
                    metrics::counter!(crate::meters::CONNECTIONS_CLOSED, "reason" => "slow_reader")
                        .increment(1);
                    return Ended::SlowReader;
                }
            }
        }
    }

    pub(super) fn begin_request(self: &Arc<Self>) -> RequestGuard {
        self.busy.fetch_add(1, Ordering::AcqRel);
        RequestGuard {
            conn: self.clone(),
            responding: false,
        }
    }

    /// Ends the request whose response was waiting to be flushed, if any.
    pub(super) fn finish(&self) -> Option<RequestGuard> {
        self.finishing
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
    }

    pub(super) fn take_refusal(&self) -> Option<HeadError> {
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
pub(super) struct RequestGuard {
    pub(super) conn: Arc<Conn>,
    pub(super) responding: bool,
}

impl RequestGuard {
    /// The response is about to be sent: its deadline starts.
    pub(super) fn responding(&mut self) {
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
///
/// A refused head is answered with its [`HeadError`]'s `IntoResponse`, which the HTTP layer
/// implements (`http::error`): the transport knows why a head was refused, not which status or
/// error code says so.
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
