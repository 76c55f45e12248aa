//! Watching is free: reading the figures of frames that did not change renders nothing,
//! however many frames the server holds (more than the renders' cache keeps), and a change
//! costs one render of the frame that changed.

use axum::body::Body;
use axum::http::{Request, StatusCode};
use splatd_proto::{Batch, Record};

use crate::{testing, AppState, Limits};

/// More frames than the renders' cache holds (16).
const FRAMES: usize = 20;

async fn info(app: &AppState, id: &str) -> serde_json::Value {
    let request = Request::get(format!("/v1/frames/{id}"))
        .body(Body::empty())
        .unwrap();
    let reply = testing::send(app, request).await;
    assert_eq!(reply.status, StatusCode::OK);
    reply.json()
}

fn post(app: &AppState, id: &str, seq: u64) {
    let records = (0..16)
        .map(|i| Record::new(i % 8, i / 8, [1.0 + seq as f32, 2.0, 3.0]))
        .collect();
    let batch = Batch::new(id, 1, seq, records).unwrap();
    app.store.get(id).unwrap().ingest(&batch).unwrap();
}

#[tokio::test]
async fn polling_unchanged_frames_renders_nothing() {
    let mut app = AppState::new(Limits::default(), None, None);
    let ids: Vec<String> = (0..FRAMES).map(|i| format!("f{i}")).collect();
    for id in &ids {
        app = testing::with_frame(app, id, 8, 8);
        post(&app, id, 0);
    }
    for id in &ids {
        let c = &info(&app, id).await["convergence"];
        assert_eq!(c["samples"], 16, "{id}: {c}");
    }
    assert_eq!(
        app.renders.rendered(),
        FRAMES as u64,
        "one render per frame"
    );

    // A dashboard polling every frame, round after round: nothing changed, nothing renders.
    for _ in 0..3 {
        for id in &ids {
            info(&app, id).await;
        }
        for frame in app.store.list() {
            crate::render::figures::convergence(&app, &frame)
                .await
                .unwrap();
        }
    }
    assert_eq!(
        app.renders.rendered(),
        FRAMES as u64,
        "unchanged frames render nothing"
    );

    // One frame changes: the next round renders it, once.
    post(&app, "f7", 1);
    for _ in 0..2 {
        for id in &ids {
            info(&app, id).await;
        }
    }
    assert_eq!(app.renders.rendered(), FRAMES as u64 + 1);
    assert_eq!(info(&app, "f7").await["convergence"]["samples"], 32);
}
