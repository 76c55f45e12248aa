//! The request timeout, in-process: the router is called directly on a paused clock, so the
//! timeout is measured in the runtime's virtual time. Nothing here depends on how loaded the
//! machine is, and the checks are exact: a request is cut off when its time is up, not before.
//!
//! (The header-read timeout lives in the accept loop, not the router; `tests/service_hostile.rs`
//! checks its outcome on a real process.)

use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use bytes::Bytes;
use http_body::Frame;
use splatd_proto::{Batch, Record};
use splatd_server::{testing, AppState, Limits};
use tokio::time::Instant;

const TIMEOUT: Duration = Duration::from_secs(2);

/// A body that sends `head`, then either waits `delay` (virtual time) and sends `tail`, or,
/// with no tail, never sends anything again: a stalled sender.
struct SlowBody {
    head: Option<Bytes>,
    tail: Option<(Pin<Box<tokio::time::Sleep>>, Option<Bytes>)>,
}

impl SlowBody {
    fn stalled(head: Bytes) -> Body {
        Body::new(SlowBody {
            head: Some(head),
            tail: None,
        })
    }

    fn delayed(head: Bytes, delay: Duration, tail: Bytes) -> Body {
        Body::new(SlowBody {
            head: Some(head),
            tail: Some((Box::pin(tokio::time::sleep(delay)), Some(tail))),
        })
    }
}

impl http_body::Body for SlowBody {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        if let Some(head) = self.head.take() {
            return Poll::Ready(Some(Ok(Frame::data(head))));
        }
        match &mut self.tail {
            // Stalled: nothing will ever wake this body; only the server's timeout ends it.
            None => Poll::Pending,
            Some((delay, tail)) => match delay.as_mut().poll(cx) {
                Poll::Pending => Poll::Pending,
                Poll::Ready(()) => Poll::Ready(tail.take().map(|t| Ok(Frame::data(t)))),
            },
        }
    }
}

fn app_with_frame() -> AppState {
    let limits = Limits {
        request_timeout: TIMEOUT,
        ..Limits::default()
    };
    testing::with_frame(AppState::new(limits, None, None), "f", 4, 4)
}

/// A valid batch of 4 samples for frame `f`, encoded.
fn batch() -> Bytes {
    let records = (0..4)
        .map(|i| Record::new(i, i, [1.0, 0.5, 0.25]))
        .collect();
    Bytes::from(Batch::new("f", 1, 0, records).unwrap().encode())
}

fn samples(body: Body, len: usize) -> Request<Body> {
    Request::post("/v1/frames/f/samples")
        .header("content-type", "application/x-splatd-batch")
        .header("content-length", len.to_string())
        .body(body)
        .unwrap()
}

async fn samples_in_frame(app: &AppState) -> serde_json::Value {
    let info = testing::send(
        app,
        Request::get("/v1/frames/f").body(Body::empty()).unwrap(),
    )
    .await;
    info.json()["samples"].clone()
}

#[tokio::test(start_paused = true)]
async fn a_stalled_body_is_answered_408_when_the_request_timeout_passes_and_not_before() {
    let app = app_with_frame();
    let body = batch();
    let stalled = samples(SlowBody::stalled(body.slice(..4)), body.len());
    let start = Instant::now();
    let mut call = tokio::spawn({
        let app = app.clone();
        async move { testing::send(&app, stalled).await }
    });

    // The clock is paused and only moves to the next timer when every task waits: this timer,
    // 1 ms short of the timeout, fires first, with the request still unanswered.
    let early = tokio::time::timeout(TIMEOUT - Duration::from_millis(1), &mut call).await;
    assert!(early.is_err(), "answered before the timeout: {early:?}");

    let reply = call.await.unwrap();
    assert_eq!(start.elapsed(), TIMEOUT, "virtual time at the answer");
    assert_eq!(reply.status, StatusCode::REQUEST_TIMEOUT);
    assert_eq!(reply.error().0, "request_timeout", "{reply:?}");

    // The stalled request changed nothing.
    assert_eq!(samples_in_frame(&app).await, 0);
}

#[tokio::test(start_paused = true)]
async fn a_slow_body_that_finishes_within_the_timeout_is_applied() {
    let app = app_with_frame();
    let body = batch();
    // Half the body, then the rest 1 ms before the time is up.
    let split = body.len() / 2;
    let slow = SlowBody::delayed(
        body.slice(..split),
        TIMEOUT - Duration::from_millis(1),
        body.slice(split..),
    );
    let reply = testing::send(&app, samples(slow, body.len())).await;
    assert_eq!(reply.status, StatusCode::OK);
    assert_eq!(samples_in_frame(&app).await, 4);
}
