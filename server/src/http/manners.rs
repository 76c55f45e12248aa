//! HTTP manners towards clients that keep connections alive: a response sent before the request
//! body was read whole says `Connection: close`.
//!
//! A server that answers early (401, 404, 413, 503 ... before the body is read, or a handler
//! that never reads one) cannot read the next request from that connection: the rest of the
//! body is in the way. Hyper then closes the connection after the response, and a keep-alive
//! client that was not told so sends its next request into a closing socket (EPIPE or a reset).
//! With `Connection: close` on the response the client knows to open a new connection.
//!
//! Chunked request bodies are answered with `Connection: close` too: the accept loop's head
//! check cannot tell where the next request starts after one (see `crate::transport`).
//!
//! This also keeps `Expect: 100-continue` honest: hyper sends `100 Continue` only when a
//! handler starts reading the body, so a request refused before that (authentication, the
//! `Content-Length` limit, an unknown frame) gets its final answer instead, and the connection
//! is closed rather than left waiting for a body the client will not send.

use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::task::{ready, Context, Poll};

use axum::body::{Body, Bytes};
use axum::extract::Request;
use axum::http::{header, HeaderValue};
use axum::middleware::Next;
use axum::response::Response;
use http_body::{Body as _, Frame, SizeHint};

/// Middleware: adds `Connection: close` to a response sent while its request's body was not
/// read to the end, or whose request body was chunked.
pub async fn close_unless_read(request: Request, next: Next) -> Response {
    let headers = request.headers();
    let chunked = headers.contains_key(header::TRANSFER_ENCODING);
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    let has_body = chunked || declared.is_some_and(|n| n > 0) || !request.body().is_end_stream();
    if !has_body {
        return next.run(request).await;
    }
    let read = Arc::new(AtomicBool::new(false));
    let request = request.map(|body| {
        Body::new(Watched {
            inner: body,
            read: read.clone(),
        })
    });
    let mut response = next.run(request).await;
    if chunked || !read.load(Ordering::Acquire) {
        response
            .headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    response
}

/// A request body that records when it has been read to its end.
struct Watched {
    inner: Body,
    read: Arc<AtomicBool>,
}

impl http_body::Body for Watched {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        let frame = ready!(Pin::new(&mut self.inner).poll_frame(cx));
        if frame.is_none() || self.inner.is_end_stream() {
            self.read.store(true, Ordering::Release);
        }
        Poll::Ready(frame)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}
