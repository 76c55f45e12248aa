//! The router in process: every route declares its role, the guards enforce exactly those roles,
//! and nothing a read token sends can change anything or get its body read.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::http::{header, Method, Request, StatusCode};
use http_body_util::{BodyExt, Full};

use super::{routes, Endpoint};
use crate::access::{Auth, Role};
use crate::{testing, AppState, Limits};

const READ: &str = "read-token-0123456789";
const WRITE: &str = "write-token-0123456789";
const ADMIN: &str = "admin-token-0123456789";

/// A server with one token per role, `--public-read` as given, and an 8x8 frame `f`.
fn app(public_read: bool) -> AppState {
    let auth = Auth::parse(
        &format!("read {READ}\nwrite {WRITE}\nadmin {ADMIN}"),
        public_read,
    )
    .unwrap();
    testing::with_frame(
        AppState::with_auth(Limits::default(), None, None, auth),
        "f",
        8,
        8,
    )
}

/// A body that records whether anything polled it (read or decompressed it).
fn tripwire() -> (Body, Arc<AtomicBool>) {
    let read = Arc::new(AtomicBool::new(false));
    let flag = read.clone();
    let body = Full::new(Bytes::from_static(b"\x1f\x8b not really gzip")).map_frame(move |f| {
        flag.store(true, Ordering::SeqCst);
        f
    });
    (Body::new(body), read)
}

/// Sends one request; returns the status, the `error` code of a JSON error (or "", and always
/// for `HEAD`, whose answers have no body) and the response headers.
async fn send(
    app: &AppState,
    method: Method,
    path: &str,
    token: Option<&str>,
    body: Body,
) -> (StatusCode, String, axum::http::HeaderMap) {
    let head = method == Method::HEAD;
    let mut request = Request::builder()
        .method(method)
        .uri(path)
        .header(header::CONTENT_TYPE, "application/json")
        .header(header::CONTENT_ENCODING, "gzip");
    if let Some(token) = token {
        request = request.header(header::AUTHORIZATION, format!("Bearer {token}"));
    }
    let reply = testing::send(app, request.body(body).unwrap()).await;
    let status = reply.status;
    let code = if !head && (status.is_client_error() || status.is_server_error()) {
        reply.json()["error"].as_str().unwrap().to_owned()
    } else {
        String::new()
    };
    (status, code, reply.headers)
}

fn concrete(path: &str) -> String {
    path.replace("{id}", "f")
}

/// The documented table (`auth` module docs, README, PROTOCOL): adding a route without a role,
/// or changing a role, fails here until the table (and the docs) say so too.
#[test]
fn every_route_declares_the_documented_role() {
    use Method as M;
    use Role::{Admin, Read, Write};
    let documented = [
        (M::GET, "/", None),
        (M::GET, "/healthz", None),
        (M::GET, "/metrics", Some(Read)),
        (M::POST, "/v1/frames", Some(Admin)),
        (M::GET, "/v1/frames", Some(Read)),
        (M::GET, "/v1/frames/{id}", Some(Read)),
        (M::PUT, "/v1/frames/{id}", Some(Write)),
        (M::DELETE, "/v1/frames/{id}", Some(Admin)),
        (M::POST, "/v1/frames/{id}/samples", Some(Write)),
        (M::POST, "/v1/frames/{id}/passes", Some(Write)),
        (M::POST, "/v1/frames/{id}/sync", Some(Write)),
        (M::GET, "/v1/frames/{id}/image.exr", Some(Read)),
        (M::GET, "/v1/frames/{id}/preview.png", Some(Read)),
        (M::GET, "/v1/frames/{id}/need", Some(Read)),
        (M::GET, "/v1/frames/{id}/state", Some(Read)),
        (M::POST, "/v1/frames/{id}/state", Some(Admin)),
    ];
    let key = |e: &Endpoint| (e.path, e.method.to_string());
    let mut want: Vec<Endpoint> = documented
        .into_iter()
        .map(|(method, path, role)| Endpoint { method, path, role })
        .collect();
    let mut declared = routes(&app(false)).endpoints;
    want.sort_by_key(key);
    declared.sort_by_key(key);
    assert_eq!(declared, want);
    for e in &declared {
        if e.method != Method::GET {
            assert!(
                matches!(e.role, Some(Role::Write | Role::Admin)),
                "{} {} changes the server but does not need write or admin",
                e.method,
                e.path
            );
        }
    }
}

/// Each route's guard enforces the role it was declared with, and only that role.
#[tokio::test]
async fn guards_enforce_the_declared_roles() {
    for e in routes(&app(false)).endpoints {
        let path = concrete(e.path);
        let what = format!("{} {path}", e.method);
        let (allowed, refused): (&[&str], &[&str]) = match e.role {
            None => (&[], &[]),
            Some(Role::Read) => (&[READ, ADMIN], &[WRITE]),
            Some(Role::Write) => (&[WRITE, ADMIN], &[READ]),
            Some(Role::Admin) => (&[ADMIN], &[READ, WRITE]),
        };
        // A fresh server each time, so a DELETE does not hide the next request's answer.
        let server = app(false);
        let (status, code, headers) =
            send(&server, e.method.clone(), &path, None, Body::empty()).await;
        if e.role.is_some() {
            assert_eq!(
                (status, code.as_str()),
                (StatusCode::UNAUTHORIZED, "unauthorized"),
                "{what}"
            );
            assert_eq!(headers[header::WWW_AUTHENTICATE], "Bearer", "{what}");
        } else {
            assert_eq!(status, StatusCode::OK, "{what}");
        }
        let (status, _, _) = send(
            &server,
            e.method.clone(),
            &path,
            Some("not-a-token-of-this-server"),
            Body::empty(),
        )
        .await;
        assert_eq!(
            status,
            if e.role.is_some() {
                StatusCode::UNAUTHORIZED
            } else {
                StatusCode::OK
            },
            "{what} with an unknown token"
        );
        for token in refused {
            let (status, code, _) =
                send(&server, e.method.clone(), &path, Some(token), Body::empty()).await;
            assert_eq!(
                (status, code.as_str()),
                (StatusCode::FORBIDDEN, "forbidden"),
                "{what}"
            );
        }
        for token in allowed {
            let server = app(false);
            let (status, code, _) =
                send(&server, e.method.clone(), &path, Some(token), Body::empty()).await;
            assert!(
                !matches!(status, StatusCode::UNAUTHORIZED | StatusCode::FORBIDDEN),
                "{what} refused a token with its role: {status} {code}"
            );
        }
    }
}

/// A read token (or no token) sending any changing method to any route is refused before a
/// byte of its body is read, and the server is unchanged afterwards.
#[tokio::test]
async fn a_read_token_cannot_change_anything_nor_get_a_body_read() {
    let server = app(false);
    let endpoints = routes(&server).endpoints;
    let mut paths: Vec<&str> = endpoints.iter().map(|e| e.path).collect();
    paths.sort();
    paths.dedup();
    for path in paths {
        for method in [Method::POST, Method::PUT, Method::PATCH, Method::DELETE] {
            let declared = endpoints
                .iter()
                .any(|e| e.path == path && e.method == method);
            for token in [Some(READ), None] {
                let what = format!("{method} {path} with {token:?}");
                let (body, read) = tripwire();
                let (status, code, _) =
                    send(&server, method.clone(), &concrete(path), token, body).await;
                let want = match (declared, token) {
                    (false, _) => (StatusCode::METHOD_NOT_ALLOWED, "method_not_allowed"),
                    (true, Some(_)) => (StatusCode::FORBIDDEN, "forbidden"),
                    (true, None) => (StatusCode::UNAUTHORIZED, "unauthorized"),
                };
                assert_eq!((status, code.as_str()), want, "{what}");
                assert!(!read.load(Ordering::SeqCst), "{what}: the body was read");
            }
        }
    }
    let frames = server.store.list();
    assert_eq!(frames.len(), 1);
    assert_eq!(frames[0].info().samples, 0);

    // The tripwire works: a request the guard lets through does get its body read (here it is
    // not valid gzip, so the read fails).
    let (body, read) = tripwire();
    let (status, code, _) = send(&server, Method::POST, "/v1/frames", Some(ADMIN), body).await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::BAD_REQUEST, "unreadable_body")
    );
    assert!(read.load(Ordering::SeqCst));
}

/// Unknown routes and methods answer JSON errors whatever the token; `HEAD` is guarded like
/// the `GET` it runs.
#[tokio::test]
async fn unknown_routes_and_methods_answer_json() {
    let server = app(false);
    let (status, code, _) = send(&server, Method::GET, "/v2/whatever", None, Body::empty()).await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::NOT_FOUND, "unknown_route")
    );
    let (status, code, headers) = send(
        &server,
        Method::PUT,
        "/v1/frames",
        Some(ADMIN),
        Body::empty(),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::METHOD_NOT_ALLOWED, "method_not_allowed")
    );
    let allow = headers[header::ALLOW].to_str().unwrap();
    assert!(allow.contains("GET") && allow.contains("POST"), "{allow}");
    let (status, _, _) = send(&server, Method::HEAD, "/v1/frames", None, Body::empty()).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    let (status, _, _) = send(
        &server,
        Method::HEAD,
        "/v1/frames",
        Some(READ),
        Body::empty(),
    )
    .await;
    assert_eq!(status, StatusCode::OK);
}

/// `--public-read` opens the read routes and nothing else; a server without tokens is open.
#[tokio::test]
async fn public_read_and_open_servers() {
    let server = app(true);
    let (status, _, _) = send(&server, Method::GET, "/v1/frames/f", None, Body::empty()).await;
    assert_eq!(status, StatusCode::OK);
    let (body, read) = tripwire();
    let (status, _, _) = send(&server, Method::POST, "/v1/frames/f/samples", None, body).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    assert!(!read.load(Ordering::SeqCst));

    let open = AppState::new(Limits::default(), None, None);
    let create = br#"{"id":"g","width":4,"height":4}"#;
    let request = Request::builder()
        .method(Method::POST)
        .uri("/v1/frames")
        .header(header::CONTENT_TYPE, "application/json")
        .body(Body::from(&create[..]))
        .unwrap();
    assert_eq!(
        testing::send(&open, request).await.status,
        StatusCode::CREATED
    );
    assert!(open.store.get("g").is_ok());
}

/// Sends `method path` with the given headers and body to `server`; returns the status, the
/// JSON error's `error` and `message` (empty for a success) and the response headers.
async fn exchange(
    server: &AppState,
    method: Method,
    path: &str,
    headers: &[(header::HeaderName, &str)],
    body: Body,
) -> (StatusCode, String, String, axum::http::HeaderMap) {
    let mut request = Request::builder().method(method).uri(path);
    for (name, value) in headers {
        request = request.header(name, *value);
    }
    let reply = testing::send(server, request.body(body).unwrap()).await;
    if reply.status.is_success() {
        return (reply.status, String::new(), String::new(), reply.headers);
    }
    let (code, message) = reply.error();
    (reply.status, code, message, reply.headers)
}

/// The extractors refuse a request in the order the handlers used to check it by hand, each with
/// its JSON code: query, then Content-Type, then the frame, and only then the body. So a client
/// is told the cheapest thing wrong first, and an unknown frame costs the server no body read.
#[tokio::test]
async fn extractors_refuse_in_order_with_json_codes() {
    let server = testing::with_frame(AppState::new(Limits::default(), None, None), "f", 8, 8);
    let exr = [(header::CONTENT_TYPE, "image/x-exr")];
    let json = [(header::CONTENT_TYPE, "application/json")];

    // Passes: a query without `seq` is refused before the Content-Type is looked at...
    let (body, read) = tripwire();
    let (status, code, _, _) = exchange(
        &server,
        Method::POST,
        "/v1/frames/nope/passes?worker=1",
        &json,
        body,
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::BAD_REQUEST, "bad_query")
    );
    assert!(!read.load(Ordering::SeqCst));
    // ...the Content-Type before the frame is looked up...
    let (body, read) = tripwire();
    let (status, code, _, _) = exchange(
        &server,
        Method::POST,
        "/v1/frames/nope/passes?worker=1&seq=1",
        &json,
        body,
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_content_type"
        )
    );
    assert!(!read.load(Ordering::SeqCst));
    // ...and the frame before a byte of the body is read.
    let (body, read) = tripwire();
    let (status, code, _, _) = exchange(
        &server,
        Method::POST,
        "/v1/frames/nope/passes?worker=1&seq=1",
        &exr,
        body,
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::NOT_FOUND, "unknown_frame")
    );
    assert!(!read.load(Ordering::SeqCst));
    // A body that is read but is no EXR is the pass's fault, not the server's.
    let (status, code, _, _) = exchange(
        &server,
        Method::POST,
        "/v1/frames/f/passes?worker=1&seq=1",
        &exr,
        Body::from("not an exr"),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, "invalid_pass")
    );

    // A compression this server does not speak: 415 with the decompression layer's code.
    let (status, code, _, _) = exchange(
        &server,
        Method::POST,
        "/v1/frames/f/samples",
        &[
            (header::CONTENT_TYPE, splatd_proto::BATCH_CONTENT_TYPE),
            (header::CONTENT_ENCODING, "br"),
        ],
        Body::from("whatever"),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_content_encoding"
        )
    );

    // JSON bodies: malformed (400), too large (413), mislabelled (415).
    let (status, code, message, _) = exchange(
        &server,
        Method::POST,
        "/v1/frames",
        &json,
        Body::from("{\"id\":"),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::BAD_REQUEST, "bad_request")
    );
    assert!(message.starts_with("invalid JSON body"), "{message}");
    let huge = format!(
        "{{\"id\":\"{}\"}}",
        "x".repeat(super::extract::MAX_JSON_BODY)
    );
    let (status, code, _, _) =
        exchange(&server, Method::POST, "/v1/frames", &json, Body::from(huge)).await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::PAYLOAD_TOO_LARGE, "body_too_large")
    );
    let (status, code, _, _) = exchange(
        &server,
        Method::POST,
        "/v1/frames",
        &[(header::CONTENT_TYPE, "text/plain")],
        Body::from(r#"{"id":"g","width":4,"height":4}"#),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_content_type"
        )
    );

    // Previews: an exposure that is not positive is a bad query, refused before the frame is
    // looked up; a good one gives a PNG.
    for exposure in ["0", "-1", "nan", "inf"] {
        let (status, code, message, _) = exchange(
            &server,
            Method::GET,
            &format!("/v1/frames/nope/preview.png?exposure={exposure}"),
            &[],
            Body::empty(),
        )
        .await;
        assert_eq!(
            (status, code.as_str()),
            (StatusCode::BAD_REQUEST, "bad_query"),
            "exposure={exposure}"
        );
        assert!(
            message.contains("exposure must be a positive number"),
            "{message}"
        );
    }
    let (status, _, _, headers) = exchange(
        &server,
        Method::GET,
        "/v1/frames/f/preview.png?exposure=2&layer=mean",
        &[],
        Body::empty(),
    )
    .await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(headers[header::CONTENT_TYPE], "image/png");

    // Images: a query the resolver refuses is `invalid_parameters`, an unknown one `bad_query`.
    let (status, code, _, _) = exchange(
        &server,
        Method::GET,
        "/v1/frames/f/image.exr?kappa=-1",
        &[],
        Body::empty(),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::BAD_REQUEST, "invalid_parameters")
    );
    let (status, code, _, _) = exchange(
        &server,
        Method::GET,
        "/v1/frames/f/image.exr?kapa=2",
        &[],
        Body::empty(),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::BAD_REQUEST, "bad_query")
    );
}

/// `PUT /v1/frames/{id}` with `token` and a JSON body; returns the status and the JSON answer
/// (a `FrameInfo`, or an error body).
async fn put_frame(
    server: &AppState,
    id: &str,
    token: &str,
    body: serde_json::Value,
) -> (StatusCode, serde_json::Value) {
    let request = Request::builder()
        .method(Method::PUT)
        .uri(format!("/v1/frames/{id}"))
        .header(header::CONTENT_TYPE, "application/json")
        .header(header::AUTHORIZATION, format!("Bearer {token}"))
        .body(Body::from(body.to_string()))
        .unwrap();
    let reply = testing::send(server, request).await;
    (reply.status, reply.json())
}

/// Create-or-get with each role: `read` is refused and nothing is created; `write` and `admin`
/// create (201), get the same frame again (200), and are refused with the differing parameters
/// named (409) when the parameters differ, which leaves the frame as it was.
#[tokio::test]
async fn put_creates_or_gets_a_frame_for_write_and_admin_only() {
    use serde_json::json;
    let server = app(false);
    let params = json!({"width": 6, "height": 4, "resolve": {"kappa": 2.0}});
    let (status, body) = put_frame(&server, "w", READ, params.clone()).await;
    assert_eq!(
        (status, body["error"].as_str()),
        (StatusCode::FORBIDDEN, Some("forbidden"))
    );
    assert!(
        server.store.get("w").is_err(),
        "a read token created a frame"
    );

    for (token, id) in [(WRITE, "w"), (ADMIN, "a")] {
        let (status, created) = put_frame(&server, id, token, params.clone()).await;
        assert_eq!(status, StatusCode::CREATED, "{id}: {created}");
        assert_eq!(
            (created["id"].as_str(), created["width"].as_u64()),
            (Some(id), Some(6))
        );
        assert_eq!(created["resolve"]["kappa"], 2.0);
        let frame = server.store.get(id).expect("the frame PUT created");
        assert_eq!(frame.info().height, 4);

        // Again, with the id also in the body: the same frame, 200.
        let mut same = params.clone();
        same["id"] = json!(id);
        let (status, again) = put_frame(&server, id, token, same).await;
        assert_eq!((status, &again), (StatusCode::OK, &created), "{id}");

        // Other parameters: 409 naming each difference; the frame is untouched.
        let other = json!({"width": 8, "height": 4, "resolve": {"kappa": 3.0}});
        let (status, err) = put_frame(&server, id, token, other).await;
        assert_eq!(
            (status, err["error"].as_str()),
            (StatusCode::CONFLICT, Some("frame_exists"))
        );
        let message = err["message"].as_str().unwrap();
        assert!(
            message.contains("size 6x4 here, 8x4 requested"),
            "{message}"
        );
        assert!(message.contains("resolve"), "{message}");
        assert!(!message.contains("cascades"), "{message}");
        assert!(Arc::ptr_eq(&frame, &server.store.get(id).unwrap()));
        assert_eq!(frame.info().width, 6);

        // A body naming another frame, or parameters breaking their rules: 400, nothing made.
        let (status, err) = put_frame(
            &server,
            "x",
            token,
            json!({"id": "y", "width": 2, "height": 2}),
        )
        .await;
        assert_eq!(
            (status, err["error"].as_str()),
            (StatusCode::BAD_REQUEST, Some("frame_mismatch"))
        );
        let (status, err) = put_frame(&server, "x", token, json!({"width": 0, "height": 2})).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{err}");
        assert!(server.store.get("x").is_err() && server.store.get("y").is_err());
    }
    // `write` still may not delete.
    let (status, code, _) = send(
        &server,
        Method::DELETE,
        "/v1/frames/w",
        Some(WRITE),
        Body::empty(),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::FORBIDDEN, "forbidden")
    );
}

/// AOV declarations: checked like the other parameters (400 naming the problem, nothing made),
/// part of what create-or-get compares (409 naming both sets), and their memory counted against
/// the server's limit (409 `memory_limit` for a frame whose cascades alone would fit).
#[tokio::test]
async fn aov_declarations_are_checked_compared_and_counted() {
    use serde_json::json;
    let auth = Auth::parse(&format!("write {WRITE}"), false).unwrap();
    // Room for a 64x64 frame's cascades (25 words per pixel, 800 KiB) but not its AOVs too.
    let limits = Limits {
        max_memory_bytes: 1 << 20,
        ..Limits::default()
    };
    let server = AppState::with_auth(limits, None, None, auth);
    let albedo = json!([{"name": "albedo", "channels": ["R", "G", "B"]}]);
    for (aovs, mentions) in [
        (json!([{"name": "mean", "channels": ["R"]}]), "\"mean\""),
        (
            json!([{"name": "cascade2", "channels": ["R"]}]),
            "\"cascade2\"",
        ),
        (json!([{"name": "n", "channels": []}]), "no channels"),
        (json!([{"name": "n", "channels": ["X", "X"]}]), "\"X\""),
        (
            json!([{"name": "a", "channels": ["R"]}, {"name": "a", "channels": ["G"]}]),
            "twice",
        ),
    ] {
        let (status, err) = put_frame(
            &server,
            "x",
            WRITE,
            json!({"width": 4, "height": 4, "aovs": aovs}),
        )
        .await;
        assert_eq!(
            (status, err["error"].as_str()),
            (StatusCode::BAD_REQUEST, Some("invalid_parameters")),
            "{aovs}"
        );
        let message = err["message"].as_str().unwrap();
        assert!(message.contains(mentions), "{message}");
        assert!(server.store.get("x").is_err());
    }
    let (status, created) = put_frame(
        &server,
        "f",
        WRITE,
        json!({"width": 4, "height": 4, "aovs": albedo}),
    )
    .await;
    assert_eq!(status, StatusCode::CREATED, "{created}");
    // 25 cascade words and 1 + 2 * 3 AOV words per pixel.
    assert_eq!(created["memory_bytes"], 16 * (25 + 7) * 8);
    assert_eq!(created["aovs"], albedo, "the frame lists its AOVs");
    let (status, again) = put_frame(
        &server,
        "f",
        WRITE,
        json!({"width": 4, "height": 4, "aovs": albedo}),
    )
    .await;
    assert_eq!((status, &again), (StatusCode::OK, &created));
    let (status, err) = put_frame(&server, "f", WRITE, json!({"width": 4, "height": 4})).await;
    assert_eq!(
        (status, err["error"].as_str()),
        (StatusCode::CONFLICT, Some("frame_exists"))
    );
    let message = err["message"].as_str().unwrap();
    assert!(
        message.contains("aovs \"albedo\" (R, G, B) here, none requested"),
        "{message}"
    );

    let (status, big) = put_frame(&server, "big", WRITE, json!({"width": 64, "height": 64})).await;
    assert_eq!(status, StatusCode::CREATED, "{big}");
    server.store.remove("big").unwrap();
    let (status, err) = put_frame(
        &server,
        "big",
        WRITE,
        json!({"width": 64, "height": 64, "aovs": albedo}),
    )
    .await;
    assert_eq!(
        (status, err["error"].as_str()),
        (StatusCode::CONFLICT, Some("memory_limit")),
        "{err}"
    );
    assert!(server.store.get("big").is_err());
}

/// A request body that arrives in the given pieces (as hyper hands a body over, frame by
/// frame, as it reads it from the socket).
struct InPieces(std::collections::VecDeque<Bytes>);

impl http_body::Body for InPieces {
    type Data = Bytes;
    type Error = std::convert::Infallible;

    fn poll_frame(
        mut self: std::pin::Pin<&mut Self>,
        _: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        std::task::Poll::Ready(self.0.pop_front().map(|b| Ok(http_body::Frame::data(b))))
    }
}

/// Small pieces of a body are copied together, large ones kept as they came (the same bytes,
/// not a copy), in order; past the limit, 413.
#[tokio::test]
async fn a_body_keeps_its_large_pieces_and_copies_its_small_ones() {
    use super::extract::{read_pieces, BodyBytes, KEEP_PIECE};
    let large = Bytes::from(vec![7u8; KEEP_PIECE]);
    let pieces: std::collections::VecDeque<Bytes> = [
        Bytes::from_static(b"ab"),
        Bytes::from_static(b"c"),
        large.clone(),
        Bytes::from_static(b"de"),
        large.clone(),
    ]
    .into();
    let total = 5 + 2 * KEEP_PIECE;
    let body = read_pieces(Body::new(InPieces(pieces.clone())), total)
        .await
        .unwrap();
    let BodyBytes::Pieces(read) = &body else {
        panic!("a body in pieces")
    };
    let lens: Vec<usize> = read.iter().map(Bytes::len).collect();
    assert_eq!(lens, [3, KEEP_PIECE, 2, KEEP_PIECE]);
    assert_eq!(read[0], &b"abc"[..]);
    assert_eq!(read[2], &b"de"[..]);
    assert!(read[1].as_ptr() == large.as_ptr() && read[3].as_ptr() == large.as_ptr());
    let joined: Vec<u8> = body.pieces().concat();
    assert_eq!(
        joined,
        pieces.iter().flatten().copied().collect::<Vec<u8>>()
    );
    let over = read_pieces(Body::new(InPieces(pieces)), total - 1).await;
    assert_eq!(
        over.err().map(|e| e.status),
        Some(StatusCode::PAYLOAD_TOO_LARGE)
    );
}

/// A batch that arrives in many pieces (records cut between them, pieces of one byte) is
/// applied exactly as the same batch in one piece; one cut short is refused whole, as it would
/// be in one piece, and changes nothing.
#[tokio::test]
async fn a_batch_arriving_in_pieces_is_applied_as_in_one() {
    use splatd_proto::{Batch, Record};
    let (w, h) = (64, 48);
    let records: Vec<Record> = (0..9000u32)
        .map(|i| Record::new(i % w, (i / 7) % h, [(i % 13) as f32 * 0.5, 1.0, 250.0]))
        .collect();
    let body = |seq: u64| Batch::new("f", 3, seq, records.clone()).unwrap().encode();
    let post = |server: &AppState, bytes: Vec<u8>, piece: usize| {
        let server = server.clone();
        async move {
            let length = bytes.len().to_string();
            let pieces = bytes
                .chunks(piece)
                .map(Bytes::copy_from_slice)
                .collect::<std::collections::VecDeque<_>>();
            let headers = [
                (header::CONTENT_TYPE, splatd_proto::BATCH_CONTENT_TYPE),
                (header::CONTENT_LENGTH, length.as_str()),
            ];
            let path = "/v1/frames/f/samples";
            let body = Body::new(InPieces(pieces));
            let (status, code, _, _) = exchange(&server, Method::POST, path, &headers, body).await;
            (status, code)
        }
    };
    let whole = testing::with_frame(AppState::new(Limits::default(), None, None), "f", w, h);
    let cut = testing::with_frame(AppState::new(Limits::default(), None, None), "f", w, h);
    for (seq, piece) in [(1, 1), (2, 7), (3, 4096)] {
        let bytes = body(seq);
        let n = bytes.len();
        assert_eq!(
            post(&whole, bytes.clone(), n).await,
            (StatusCode::OK, String::new())
        );
        assert_eq!(
            post(&cut, bytes, piece).await,
            (StatusCode::OK, String::new()),
            "pieces of {piece} bytes"
        );
    }
    let (a, b) = (whole.store.get("f").unwrap(), cut.store.get("f").unwrap());
    assert_eq!(a.samples(), 3 * 9000);
    assert!(a.cut().whole() == b.cut().whole(), "the same cells");
    // Cut short in the middle of a record: refused, nothing applied.
    let mut short = body(4);
    short.truncate(short.len() - 30);
    let (status, code) = post(&cut, short, 7).await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::BAD_REQUEST, "truncated_batch")
    );
    assert_eq!(b.samples(), 3 * 9000);
}

/// An uncompressed RGB float EXR of `w x h` pixels, pixel `i` = `(i, 2i, 3i) / 1000`.
fn rgb_exr(w: usize, h: usize) -> Vec<u8> {
    splatd_formats::testing::uncompressed_rgb(w, h, |i| {
        [1.0, 2.0, 3.0].map(|c| i as f32 * c / 1000.0)
    })
}

/// Large pass bodies are read into buffers the server keeps, exactly their declared length, and
/// decoded into kept buffers: each pass is applied as before, a refused one changes nothing and
/// still gives its buffers back, and a second pass reuses them rather than growing the pool.
#[tokio::test]
async fn large_pass_bodies_and_decodes_reuse_kept_buffers() {
    let (w, h) = (320, 320);
    let server = testing::with_frame(AppState::new(Limits::default(), None, None), "big", w, h);
    let exr = rgb_exr(w as usize, h as usize);
    assert!(exr.len() as u64 >= super::extract::POOLED_MIN);
    let length = exr.len().to_string();
    let headers = [
        (header::CONTENT_TYPE, "image/x-exr"),
        (header::CONTENT_LENGTH, length.as_str()),
    ];
    let post = |seq: u64, body: Vec<u8>| {
        let server = server.clone();
        let headers = headers.clone();
        async move {
            let path = format!("/v1/frames/big/passes?worker=7&seq={seq}");
            let (status, code, _, _) =
                exchange(&server, Method::POST, &path, &headers, Body::from(body)).await;
            (status, code)
        }
    };
    let frame = server.store.get("big").unwrap();
    let pixels = u64::from(w * h);

    assert_eq!(post(1, exr.clone()).await, (StatusCode::OK, String::new()));
    assert_eq!(frame.samples(), pixels);
    assert_eq!(
        server.body_pool.idle_bytes(),
        exr.len(),
        "kept, exactly its length"
    );
    let scratch = server.pass_scratch.idle_bytes();
    // Write counts (1 byte a pixel) and the samples (12).
    assert_eq!(scratch, pixels as usize * 13);

    // Not an EXR, of the same length: refused, nothing applied, the buffers back in the pool.
    let mut junk = exr.clone();
    junk[0] = b'X';
    let (status, code) = post(2, junk).await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, "invalid_pass")
    );
    assert_eq!(frame.samples(), pixels);
    assert_eq!(server.body_pool.idle_bytes(), exr.len());

    // Another pass, and a retry of the first: reused buffers, the same accounting as ever.
    assert_eq!(post(3, exr.clone()).await, (StatusCode::OK, String::new()));
    assert_eq!(post(1, exr.clone()).await, (StatusCode::OK, String::new()));
    assert_eq!(frame.samples(), 2 * pixels);
    assert_eq!(server.body_pool.idle_bytes(), exr.len());
    assert_eq!(server.pass_scratch.idle_bytes(), scratch);
}

/// Images are encoded in a scratch the server keeps; the scratches of passes and images, the
/// buffers of large pass and state bodies, and a deleted frame's cells, that no request takes
/// for `CELL_POOL_IDLE` are freed by the server's sweeper (time paused: nothing waits for
/// real).
#[tokio::test(start_paused = true)]
async fn idle_scratches_and_cells_are_freed() {
    let (w, h) = (64, 48);
    let server = testing::with_frame(AppState::new(Limits::default(), None, None), "f", w, h);
    // A frame large enough that its pass and its state are bodies the server keeps buffers for
    // (sent as they are, with their length).
    let server = testing::with_frame(server, "big", 320, 320);
    let post_sized = |path: &'static str, content_type: &'static str, body: Vec<u8>| {
        let server = server.clone();
        async move {
            let length = body.len().to_string();
            let headers = [
                (header::CONTENT_TYPE, content_type),
                (header::CONTENT_LENGTH, length.as_str()),
            ];
            exchange(&server, Method::POST, path, &headers, Body::from(body))
                .await
                .0
        }
    };
    let pass = "/v1/frames/big/passes?worker=7&seq=1";
    let status = post_sized(pass, "image/x-exr", rgb_exr(320, 320)).await;
    assert_eq!(status, StatusCode::OK);
    let mut state = Vec::new();
    let cut = server.store.get("big").unwrap().cut();
    splatd_formats::state::write_bands(&cut.band_refs(), None, "big", None, vec![], &mut state)
        .unwrap();
    drop(cut);
    let content_type = splatd_proto::STATE_CONTENT_TYPE;
    let status = post_sized("/v1/frames/big/state", content_type, state).await;
    assert_eq!(status, StatusCode::OK);
    assert!(server.body_pool.idle_bytes() >= super::extract::POOLED_MIN as usize);
    assert!(server.state_pool.idle_bytes() >= 320 * 320 * 200);

    let exr = rgb_exr(w as usize, h as usize);
    let headers = [(header::CONTENT_TYPE, "image/x-exr")];
    let path = "/v1/frames/f/passes?worker=7&seq=1";
    let (status, ..) = exchange(&server, Method::POST, path, &headers, Body::from(exr)).await;
    assert_eq!(status, StatusCode::OK);
    let (status, ..) = exchange(
        &server,
        Method::GET,
        "/v1/frames/f/image.exr",
        &[],
        Body::empty(),
    )
    .await;
    assert_eq!(status, StatusCode::OK);
    let pixels = (w * h) as usize;
    // Ten channels of 4 bytes a pixel, and the uncompressed file at least as large.
    assert!(server.exr_scratch.idle_bytes() >= 2 * 10 * 4 * pixels);
    assert!(server.pass_scratch.idle_bytes() > 0);
    let (status, ..) = exchange(&server, Method::DELETE, "/v1/frames/f", &[], Body::empty()).await;
    assert_eq!(status, StatusCode::NO_CONTENT);
    assert!(server.store.cell_pool().idle_bytes() > 0);

    let (stop, stopped) = tokio::sync::watch::channel(false);
    let sweeper = tokio::spawn(server.clone().release_idle_until(stopped));
    tokio::time::sleep(crate::memory::CELL_POOL_IDLE / 2).await;
    assert!(
        server.exr_scratch.idle_bytes() > 0,
        "not idle long enough yet"
    );
    assert!(server.body_pool.idle_bytes() > 0 && server.state_pool.idle_bytes() > 0);
    tokio::time::sleep(crate::memory::CELL_POOL_IDLE).await;
    assert_eq!(server.exr_scratch.idle_bytes(), 0);
    assert_eq!(server.pass_scratch.idle_bytes(), 0);
    assert_eq!(server.body_pool.idle_bytes(), 0);
    assert_eq!(server.state_pool.idle_bytes(), 0);
    assert_eq!(server.store.cell_pool().idle_bytes(), 0);
    stop.send(true).unwrap();
    sweeper.await.unwrap();
}

/// A server without a denoiser refuses every denoise (asked for, or the frame's default) with
/// 501 `denoiser_unavailable` before reserving or resolving anything, and serves the rest; the
/// frame lists its guides, chosen by name, and `denoised` is no AOV name.
#[tokio::test]
async fn without_a_denoiser_only_denoising_is_refused() {
    use serde_json::json;
    let server = app(true);
    let aovs = json!([
        {"name": "ViewLayer.Normal", "channels": ["X", "Y", "Z"]},
        {"name": "ViewLayer.DiffCol", "channels": ["R", "G", "B"]}
    ]);
    let (status, created) = put_frame(
        &server,
        "d",
        WRITE,
        json!({"width": 4, "height": 4, "aovs": aovs, "denoise": "oidn"}),
    )
    .await;
    assert_eq!(status, StatusCode::CREATED, "{created}");
    assert_eq!(created["denoise"], "oidn");
    assert_eq!(
        created["denoise_guides"],
        json!({"albedo": "ViewLayer.DiffCol", "normal": "ViewLayer.Normal"})
    );
    for path in [
        "/v1/frames/d/image.exr",
        "/v1/frames/f/image.exr?denoise=oidn",
        "/v1/frames/f/image.exr?denoise=oidn&denoise_quality=fast",
        "/v1/frames/f/preview.png?layer=denoised",
    ] {
        let (status, code, _) = send(&server, Method::GET, path, None, Body::empty()).await;
        assert_eq!(
            (status, code.as_str()),
            (StatusCode::NOT_IMPLEMENTED, "denoiser_unavailable"),
            "{path}"
        );
    }
    assert_eq!(
        server.renders.rendered(),
        0,
        "nothing was resolved for them"
    );
    for path in [
        "/v1/frames/d/image.exr?denoise=none",
        "/v1/frames/f/image.exr",
        "/v1/frames/f/preview.png",
    ] {
        let (status, code, _) = send(&server, Method::GET, path, None, Body::empty()).await;
        assert_eq!((status, code.as_str()), (StatusCode::OK, ""), "{path}");
    }
    let (status, code, _) = send(
        &server,
        Method::GET,
        "/v1/frames/f/image.exr?denoise=bm3d",
        None,
        Body::empty(),
    )
    .await;
    assert_eq!(
        (status, code.as_str()),
        (StatusCode::BAD_REQUEST, "bad_query")
    );
    let (status, err) = put_frame(
        &server,
        "x",
        WRITE,
        json!({"width": 4, "height": 4, "aovs": [{"name": "denoised", "channels": ["R"]}]}),
    )
    .await;
    assert_eq!(
        (status, err["error"].as_str()),
        (StatusCode::BAD_REQUEST, Some("invalid_parameters")),
        "{err}"
    );
    // Another default denoiser is another frame.
    let (status, err) = put_frame(
        &server,
        "d",
        WRITE,
        json!({"width": 4, "height": 4, "aovs": aovs}),
    )
    .await;
    assert_eq!(status, StatusCode::CONFLICT, "{err}");
    assert!(
        err["message"]
            .as_str()
            .unwrap()
            .contains("denoise oidn here, none requested"),
        "{err}"
    );
}
