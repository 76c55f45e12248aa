//! Image requests in process: concurrent requests share one resolve, and a request that cannot
//! get working memory in time is answered 503 with `Retry-After`.

use std::time::Duration;

use axum::body::Body;
use axum::http::{header, Request, StatusCode};
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Record};
use tower::ServiceExt;

use super::router;
use crate::{AppState, Limits};

fn app(limits: Limits) -> AppState {
    let app = AppState::new(limits, None, None);
    let spec = app.store.check(CreateFrame::new("f", 16, 16)).unwrap();
    app.store.create(spec).unwrap();
    let records = (0..256)
        .map(|i| Record::new(i % 16, i / 16, [1.0, 50.0, 0.5]))
        .collect();
    let batch = Batch::new("f", 1, 0, records).unwrap();
    app.store.get("f").unwrap().ingest(&batch).unwrap();
    app
}

async fn get(app: &AppState, path: &str) -> (StatusCode, axum::http::HeaderMap, axum::body::Bytes) {
    let request = Request::get(path).body(Body::empty()).unwrap();
    let response = router(app.clone()).oneshot(request).await.unwrap();
    let (status, headers) = (response.status(), response.headers().clone());
    let bytes = axum::body::to_bytes(response.into_body(), usize::MAX)
        .await
        .unwrap();
    (status, headers, bytes)
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
