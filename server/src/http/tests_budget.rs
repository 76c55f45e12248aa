//! Image requests in process: concurrent requests share one resolve, and a request that cannot
//! get working memory in time is answered 503 with `Retry-After`.

use std::time::Duration;

use axum::body::Body;
use axum::http::{header, Request, StatusCode};
use splatd_proto::{Batch, Record};

use crate::{testing, AppState, Limits};

fn app(limits: Limits) -> AppState {
    let app = testing::with_frame(AppState::new(limits, None, None), "f", 16, 16);
    let records = (0..256)
        .map(|i| Record::new(i % 16, i / 16, [1.0, 50.0, 0.5]))
        .collect();
    let batch = Batch::new("f", 1, 0, records).unwrap();
    app.store.get("f").unwrap().ingest(&batch).unwrap();
    app
}

async fn get(app: &AppState, path: &str) -> (StatusCode, axum::http::HeaderMap, axum::body::Bytes) {
    let reply = testing::send(app, Request::get(path).body(Body::empty()).unwrap()).await;
    (reply.status, reply.headers, reply.body)
}

#[tokio::test]
async fn concurrent_image_requests_share_one_resolve() {
    let app = app(Limits::default());
    let mut requests = Vec::new();
    for _ in 0..32 {
        let app = app.clone();
        requests.push(tokio::spawn(async move {
            get(&app, "/v1/frames/f/image.exr").await
        }));
    }
    let mut bodies = Vec::new();
    for r in requests {
        let (status, _, bytes) = r.await.unwrap();
        assert_eq!(status, StatusCode::OK);
        bodies.push(bytes);
    }
    assert!(
        bodies.windows(2).all(|w| w[0] == w[1]),
        "one image for one version"
    );
    assert_eq!(app.renders.rendered(), 1, "32 requests, one resolve");
    // Another query is another render; so is the same query after the frame changed.
    get(&app, "/v1/frames/f/image.exr?cascades=true").await;
    assert_eq!(app.renders.rendered(), 2);
    let batch = Batch::new("f", 1, 1, vec![Record::new(0, 0, [9.0; 3])]).unwrap();
    app.store.get("f").unwrap().ingest(&batch).unwrap();
    let (_, _, newer) = get(&app, "/v1/frames/f/image.exr").await;
    assert_ne!(newer, bodies[0]);
    assert_eq!(app.renders.rendered(), 3);
    assert_eq!(
        app.renders.budget().used(),
        0,
        "every reservation was given back"
    );
}

#[tokio::test(start_paused = true)]
async fn without_working_memory_an_image_is_refused_with_retry_after() {
    let app = app(Limits {
        work_memory_bytes: 1 << 20,
        work_wait: Duration::from_secs(3),
        ..Limits::default()
    });
    let held = app.renders.budget().reserve(1 << 20).await.unwrap();
    for path in [
        "/v1/frames/f/image.exr",
        "/v1/frames/f/preview.png",
        "/v1/frames/f/state",
    ] {
        let (status, headers, body) = get(&app, path).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{path}");
        assert_eq!(headers[header::RETRY_AFTER], "3", "{path}");
        let error: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(error["error"], "busy", "{path}");
        assert!(
            error["message"]
                .as_str()
                .unwrap()
                .contains("working memory"),
            "{error}"
        );
    }
    assert_eq!(app.renders.rendered(), 0, "nothing ran, nothing is cached");
    drop(held);
    let (status, _, _) = get(&app, "/v1/frames/f/image.exr").await;
    assert_eq!(status, StatusCode::OK);
}

fn post(path: &str, content_type: &str, body: Vec<u8>, zstd: bool) -> Request<Body> {
    let mut request = Request::post(path)
        .header(header::CONTENT_TYPE, content_type)
        .header(header::CONTENT_LENGTH, body.len());
    if zstd {
        request = request.header(header::CONTENT_ENCODING, "zstd");
    }
    request.body(Body::from(body)).unwrap()
}

async fn answer(
    app: &AppState,
    request: Request<Body>,
) -> (StatusCode, axum::http::HeaderMap, serde_json::Value) {
    let reply = testing::send(app, request).await;
    let json = reply.json();
    (reply.status, reply.headers, json)
}

/// A compressed body reserves the endpoint's whole limit before a byte is inflated (its size is
/// unknown until then), a plain one its Content-Length: with the budget taken, a 2.6 KB zstd
/// bomb waits and is refused 503 without being inflated, while a small plain batch still fits.
#[tokio::test(start_paused = true)]
async fn compressed_bodies_reserve_their_limit_before_inflating() {
    let max_records = 64 * 1024;
    let limit = (38 + 128 + 20 * max_records) as u64;
    let app = app(Limits {
        max_records,
        // Room for one bomb and its decoding, not for a bomb beside anything else.
        work_memory_bytes: 2 * limit,
        work_wait: Duration::from_secs(2),
        ..Limits::default()
    });
    let samples = || app.store.get("f").unwrap().info().samples;
    let before = samples();
    let bomb = splatd_scenes::hostile::zstd_bomb("f", 7, 0, max_records);
    assert!(bomb.len() < 4096, "{} bytes", bomb.len());

    let held = app.renders.budget().reserve(1024).await.unwrap();
    let (status, headers, error) = answer(
        &app,
        post(
            "/v1/frames/f/samples",
            "application/x-splatd-batch",
            bomb.clone(),
            true,
        ),
    )
    .await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
    assert_eq!(headers[header::RETRY_AFTER], "2");
    assert_eq!(error["error"], "busy");
    assert_eq!(samples(), before, "nothing applied");

    let small = Batch::new("f", 8, 0, vec![Record::new(2, 2, [1.0; 3]); 10])
        .unwrap()
        .encode();
    let (status, _, _) = answer(
        &app,
        post(
            "/v1/frames/f/samples",
            "application/x-splatd-batch",
            small,
            false,
        ),
    )
    .await;
    assert_eq!(
        status,
        StatusCode::OK,
        "a plain body reserves only its length"
    );
    assert_eq!(app.renders.budget().used(), 1024, "and gave it back");

    // Once the budget is free the bomb is inflated, within its cap, and applied.
    drop(held);
    let (status, _, ack) = answer(
        &app,
        post(
            "/v1/frames/f/samples",
            "application/x-splatd-batch",
            bomb,
            true,
        ),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{ack}");
    assert_eq!(samples(), before + 10 + max_records as u64);
    assert_eq!(app.renders.budget().used(), 0);

    // A bomb inflating past the limit stops at the limit: 413, nothing applied.
    let over = splatd_scenes::hostile::zstd_bomb("f", 7, 1, max_records + 8);
    let (status, _, error) = answer(
        &app,
        post(
            "/v1/frames/f/samples",
            "application/x-splatd-batch",
            over,
            true,
        ),
    )
    .await;
    assert_eq!(
        (status, error["error"].as_str()),
        (StatusCode::PAYLOAD_TOO_LARGE, Some("body_too_large"))
    );
    assert_eq!(samples(), before + 10 + max_records as u64);
    assert_eq!(app.renders.budget().used(), 0);
}

/// Imports reserve their body (all an import holds) before reading it; 413 comes straight from a
/// Content-Length over the limit.
#[tokio::test(start_paused = true)]
async fn imports_wait_for_working_memory_and_long_bodies_are_refused_from_their_length() {
    let app = app(Limits {
        work_memory_bytes: 1 << 20,
        work_wait: Duration::from_secs(1),
        ..Limits::default()
    });
    let frame = app.store.get("f").unwrap();
    let mut state = Vec::new();
    let cut = frame.cut();
    let bands = cut.band_refs();
    splatd_formats::state::write_bands(&bands, None, "f", None, vec![], &mut state).unwrap();
    let held = app.renders.budget().reserve(1 << 20).await.unwrap();
    let (status, _, error) = answer(
        &app,
        post(
            "/v1/frames/f/state",
            splatd_proto::STATE_CONTENT_TYPE,
            state.clone(),
            false,
        ),
    )
    .await;
    assert_eq!(
        (status, error["error"].as_str()),
        (StatusCode::SERVICE_UNAVAILABLE, Some("busy"))
    );
    drop(held);
    let (status, _, ack) = answer(
        &app,
        post(
            "/v1/frames/f/state",
            splatd_proto::STATE_CONTENT_TYPE,
            state,
            false,
        ),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{ack}");
    assert_eq!(ack["samples"], 256);

    // A declared length over the limit is refused before the body is polled at all: this body
    // would panic if read.
    let limit =
        <crate::http::states::StateBody as crate::http::extract::Upload>::limit(&app, &frame);
    let request = Request::post("/v1/frames/f/state")
        .header(header::CONTENT_TYPE, splatd_proto::STATE_CONTENT_TYPE)
        .header(header::CONTENT_LENGTH, limit + 1)
        .body(Body::new(NeverRead))
        .unwrap();
    let (status, headers, error) = answer(&app, request).await;
    assert_eq!(
        (status, error["error"].as_str()),
        (StatusCode::PAYLOAD_TOO_LARGE, Some("body_too_large"))
    );
    assert_eq!(
        headers[header::CONNECTION],
        "close",
        "the body was left unread"
    );
}

/// A body that fails the test if anything polls it.
struct NeverRead;

impl http_body::Body for NeverRead {
    type Data = axum::body::Bytes;
    type Error = std::io::Error;

    fn poll_frame(
        self: std::pin::Pin<&mut Self>,
        _: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<Self::Data>, Self::Error>>> {
        panic!("the body was read");
    }
}
