//! Test support: a server in process (an [`AppState`], no listener) and one request sent to its
//! router with tower's `oneshot`, the answer read whole.
//!
//! Compiled for the crate's own tests, and with the `testing` feature for its integration tests
//! (`server/tests`, which enable it through the crate's dev-dependency on itself). Not part of
//! the server.

use axum::body::{Body, Bytes};
use axum::http::{HeaderMap, Request, StatusCode};
use splatd_proto::api::CreateFrame;
use tower::ServiceExt;

use crate::http::router;
use crate::AppState;

/// A response read whole.
#[derive(Debug)]
pub struct Reply {
    pub status: StatusCode,
    pub headers: HeaderMap,
    pub body: Bytes,
}

impl Reply {
    /// The body as JSON; panics naming the status and the body when it is not JSON.
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!(
                "{} without a JSON body ({e}): {:?}",
                self.status,
                String::from_utf8_lossy(&self.body)
            )
        })
    }

    /// The `error` code and `message` of a JSON error body (each "" when absent).
    pub fn error(&self) -> (String, String) {
        let error = self.json();
        let text = |key: &str| error[key].as_str().unwrap_or_default().to_owned();
        (text("error"), text("message"))
    }
}

/// `app` with a frame `id` of `width` x `height` and default parameters in its store.
pub fn with_frame(app: AppState, id: &str, width: u32, height: u32) -> AppState {
    let spec = app
        .store
        .check(CreateFrame::new(id, width, height))
        .unwrap();
    app.store.create(spec).unwrap();
    app
}

/// Sends `request` to the router of `app` (built for this one request, as a connection would
/// get it) and reads the whole answer.
pub async fn send(app: &AppState, request: Request<Body>) -> Reply {
    let response = router(app.clone()).oneshot(request).await.unwrap();
    let (status, headers) = (response.status(), response.headers().clone());
    let body = axum::body::to_bytes(response.into_body(), usize::MAX)
        .await
        .unwrap();
    Reply {
        status,
        headers,
        body,
    }
}
