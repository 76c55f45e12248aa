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
use axum::Router;
use bytes::Bytes;
use http_body::Frame;
use http_body_util::BodyExt;
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Record};
use splatd_server::{http::router, AppState, Limits};
use tokio::time::Instant;
use tower::ServiceExt;

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

async fn app_with_frame() -> Router {
    let limits = Limits {
        request_timeout: TIMEOUT,
        ..Limits::default()
    };
    let app = router(AppState::new(limits, None, None));
    let create = Request::post("/v1/frames")
        .header("content-type", "application/json")
        .body(Body::from(
            serde_json::to_vec(&CreateFrame::new("f", 4, 4)).unwrap(),
        ))
        .unwrap();
    let response = app.clone().oneshot(create).await.unwrap();
    assert!(response.status().is_success(), "{response:?}");
    app
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

async fn json(response: axum::response::Response) -> serde_json::Value {
    let bytes = response.into_body().collect().await.unwrap().to_bytes();
    serde_json::from_slice(&bytes).unwrap()
}

async fn samples_in_frame(app: Router) -> serde_json::Value {
    let info = app
        .oneshot(Request::get("/v1/frames/f").body(Body::empty()).unwrap())
        .await
        .unwrap();
    json(info).await["samples"].clone()
}

#[tokio::test(start_paused = true)]
async fn a_stalled_body_is_answered_408_when_the_request_timeout_passes_and_not_before() {
    let app = app_with_frame().await;
    let body = batch();
    let stalled = samples(SlowBody::stalled(body.slice(..4)), body.len());
    let start = Instant::now();
    let mut call = tokio::spawn(app.clone().oneshot(stalled));

    // The clock is paused and only moves to the next timer when every task waits: this timer,
    // 1 ms short of the timeout, fires first, with the request still unanswered.
    let early = tokio::time::timeout(TIMEOUT - Duration::from_millis(1), &mut call).await;
    assert!(early.is_err(), "answered before the timeout: {early:?}");

    let response = call.await.unwrap().unwrap();
    assert_eq!(start.elapsed(), TIMEOUT, "virtual time at the answer");
    assert_eq!(response.status(), StatusCode::REQUEST_TIMEOUT);
    let error = json(response).await;
    assert_eq!(error["error"], "request_timeout", "{error}");

    // The stalled request changed nothing.
    assert_eq!(samples_in_frame(app).await, 0);
}

#[tokio::test(start_paused = true)]
async fn a_slow_body_that_finishes_within_the_timeout_is_applied() {
    let app = app_with_frame().await;
    let body = batch();
    // Half the body, then the rest 1 ms before the time is up.
    let split = body.len() / 2;
    let slow = SlowBody::delayed(
        body.slice(..split),
        TIMEOUT - Duration::from_millis(1),
        body.slice(split..),
    );
    let response = app
        .clone()
        .oneshot(samples(slow, body.len()))
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    assert_eq!(samples_in_frame(app).await, 4);
}
