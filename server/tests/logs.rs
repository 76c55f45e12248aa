//! No secret in any log line: requests carrying tokens (in the header, or by mistake in the query
//! string) are logged at every level into a buffer, which must name the request but hold neither
//! token.
//!
//! A test binary of its own, with the capture as the process's global subscriber: tracing caches
//! each log call site's interest process-wide, and beside the library's other tests (threads
//! logging with no subscriber) a thread-local capture sometimes received nothing.

use std::io::Write;
use std::sync::{Arc, Mutex};

use axum::body::Body;
use axum::http::{header, Request, StatusCode};
use tower::ServiceExt;

use splatd_server::access::Auth;
use splatd_server::http::router;
use splatd_server::{AppState, Limits};

const READ: &str = "read-secret-0123456789abcdef";
const IN_QUERY: &str = "query-secret-0123456789abcdef";

/// A log destination the test can read back.
#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[tokio::test(flavor = "current_thread")]
async fn tokens_never_reach_the_log_at_any_level() {
    let log = Captured::default();
    let subscriber = tracing_subscriber::fmt()
        .with_max_level(tracing::Level::TRACE)
        .with_ansi(false)
        .with_writer({
            let log = log.clone();
            move || log.clone()
        })
        .finish();
    tracing::subscriber::set_global_default(subscriber).expect("the only subscriber of this test");

    let auth = Auth::parse(&format!("read {READ}"), false).unwrap();
    let app = AppState::with_auth(Limits::default(), None, None, auth);
    let requests = [
        // The token where it does not belong: refused, 401.
        (
            Request::get(format!("/v1/frames/f/image.exr?token={IN_QUERY}"))
                .body(Body::empty())
                .unwrap(),
            StatusCode::UNAUTHORIZED,
        ),
        // A valid token, and the other one in the query as well: an unknown parameter, 400.
        (
            Request::get(format!("/v1/frames?token={IN_QUERY}&x=1"))
                .header(header::AUTHORIZATION, format!("Bearer {READ}"))
                .body(Body::empty())
                .unwrap(),
            StatusCode::OK,
        ),
        (
            Request::get(format!("/v1/frames/f/preview.png?token={IN_QUERY}"))
                .header(header::AUTHORIZATION, format!("Bearer {READ}"))
                .body(Body::empty())
                .unwrap(),
            StatusCode::BAD_REQUEST,
        ),
    ];
    for (request, status) in requests {
        let response = router(app.clone()).oneshot(request).await.unwrap();
        assert_eq!(response.status(), status);
    }
    let text = String::from_utf8(log.0.lock().unwrap().clone()).unwrap();
    assert!(
        text.contains("/v1/frames/f/image.exr"),
        "requests are logged: {text}"
    );
    assert!(text.contains("/v1/frames/f/preview.png"), "{text}");
    assert!(!text.contains(IN_QUERY), "a query token in the log: {text}");
    assert!(!text.contains(READ), "a header token in the log: {text}");
}
