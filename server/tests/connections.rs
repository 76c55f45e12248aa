//! Connections against the real accept loop, in process on 127.0.0.1 with small limits: the cap,
//! the head and response deadlines, JSON answers to unreadable heads, `Connection: close` after
//! early refusals, `Expect: 100-continue`, and clients that half-close after their request.
//!
//! Every wait is for an event (a response, the server closing a socket, the count of open
//! connections) with [`PATIENCE`] only as a guard against a hang; nothing asserts on time. The
//! head and idle deadlines are out of reach except in the test of each, which waits for it to
//! expire and sends nothing that must beat it: no request races a deadline, however loaded the
//! machine.

use std::time::Duration;

use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Record};
use splatd_server::access::Auth;
use splatd_server::{server::serve, testing, AppState, Limits};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpSocket, TcpStream};

const PATIENCE: Duration = Duration::from_secs(120);
const ADMIN: &str = "admin-token-0123456789";

struct Running {
    addr: std::net::SocketAddr,
    app: AppState,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<std::io::Result<()>>>,
}

impl Running {
    async fn start(limits: Limits, auth: Auth) -> Running {
        let app = AppState::with_auth(limits, None, None, auth);
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (stop, stopped) = tokio::sync::oneshot::channel();
        let task = tokio::spawn(serve(listener, app.clone(), async {
            let _ = stopped.await;
        }));
        Running {
            addr,
            app,
            stop: Some(stop),
            task: Some(task),
        }
    }

    async fn connect(&self) -> TcpStream {
        TcpStream::connect(self.addr).await.unwrap()
    }

    async fn stop(mut self) {
        let _ = self.stop.take().unwrap().send(());
        let task = self.task.take().unwrap();
        tokio::time::timeout(PATIENCE, task)
            .await
            .expect("graceful shutdown within PATIENCE")
            .unwrap()
            .unwrap();
    }
}

/// A deadline the tests let expire: short, so that waiting for it is quick. Only a phase that
/// waits for the server to close a connection by itself runs with it; where a request must get
/// through, the deadlines are [`LONG`].
const SHORT: Duration = Duration::from_millis(300);
/// A deadline no test reaches: a loaded machine may take any time between two requests of a
/// test without the server closing the connection under it.
const LONG: Duration = Duration::from_secs(3600);

/// Small limits, with head and idle deadlines no test reaches.
fn small_limits() -> Limits {
    Limits {
        head_timeout: LONG,
        idle_timeout: LONG,
        ..Limits::default()
    }
}

/// One response read from `stream`: status, headers (names lowercased) and the body by
/// `Content-Length`.
async fn response(stream: &mut BufReader<TcpStream>) -> (u16, Vec<(String, String)>, Vec<u8>) {
    let read = async {
        let mut line = String::new();
        stream.read_line(&mut line).await.unwrap();
        let status: u16 = line
            .split(' ')
            .nth(1)
            .unwrap_or_else(|| panic!("status line {line:?}"))
            .parse()
            .unwrap();
        let mut headers = Vec::new();
        loop {
            let mut line = String::new();
            stream.read_line(&mut line).await.unwrap();
            let line = line.trim_end();
            if line.is_empty() {
                break;
            }
            let (name, value) = line.split_once(':').unwrap();
            headers.push((name.to_ascii_lowercase(), value.trim().to_owned()));
        }
        let len = headers
            .iter()
            .find(|(n, _)| n == "content-length")
            .map_or(0, |(_, v)| v.parse().unwrap());
        let mut body = vec![0; len];
        stream.read_exact(&mut body).await.unwrap();
        (status, headers, body)
    };
    tokio::time::timeout(PATIENCE, read)
        .await
        .expect("a response")
}

fn header<'a>(headers: &'a [(String, String)], name: &str) -> Option<&'a str> {
    headers
        .iter()
        .find(|(n, _)| n == name)
        .map(|(_, v)| v.as_str())
}

fn error_code(body: &[u8]) -> String {
    let v: serde_json::Value = serde_json::from_slice(body)
        .unwrap_or_else(|e| panic!("not a JSON body ({e}): {:?}", String::from_utf8_lossy(body)));
    v["error"].as_str().unwrap().to_owned()
}

/// Reads until the server closes the connection (end of stream or reset); the bytes read.
async fn until_closed(stream: &mut (impl AsyncReadExt + Unpin)) -> Vec<u8> {
    let mut got = Vec::new();
    let read = tokio::time::timeout(PATIENCE, stream.read_to_end(&mut got)).await;
    match read.expect("the server closed the connection within PATIENCE") {
        Ok(_) => {}
        Err(e) => assert_eq!(e.kind(), std::io::ErrorKind::ConnectionReset, "{e}"),
    }
    got
}

fn create_request(id: &str, w: u32, h: u32) -> Vec<u8> {
    let body = serde_json::to_vec(&CreateFrame::new(id, w, h)).unwrap();
    let mut request = format!(
        "POST /v1/frames HTTP/1.1\r\nhost: x\r\nauthorization: Bearer {ADMIN}\r\n\
         content-type: application/json\r\ncontent-length: {}\r\n\r\n",
        body.len()
    )
    .into_bytes();
    request.extend_from_slice(&body);
    request
}

#[tokio::test]
async fn silent_sockets_are_pushed_out_and_cannot_lock_out_healthz() {
    // No head deadline within the test (see `small_limits`): only the cap closes silent sockets.
    let server = Running::start(
        Limits {
            max_connections: 8,
            ..small_limits()
        },
        Auth::open(),
    )
    .await;
    // Four times the cap in sockets that never send a byte.
    let mut silent = Vec::new();
    for _ in 0..32 {
        silent.push(server.connect().await);
    }
    // The newest eight hold the cap; each earlier one was pushed out by a newer one.
    let mut newest = silent.split_off(24);
    for s in &mut silent {
        assert!(until_closed(s).await.is_empty());
    }
    // At the cap, health still answers on a fresh connection, pushing out the oldest silent one.
    let mut health = BufReader::new(server.connect().await);
    health
        .get_mut()
        .write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n")
        .await
        .unwrap();
    let (status, headers, _) = response(&mut health).await;
    assert_eq!(status, 200);
    assert_eq!(header(&headers, "connection"), None, "kept alive");
    assert!(until_closed(&mut newest[0]).await.is_empty());
    assert_eq!(server.app.connections.evicted(), 25);
    assert_eq!(server.app.connections.refused(), 0);
    drop((newest, health));
    tokio::time::timeout(PATIENCE, server.app.connections.until_open_at_most(0))
        .await
        .unwrap();
    server.stop().await;
}

/// Half a request line, then nothing: closed at the head deadline without an answer. (The idle
/// deadline is out of reach, so it is the head deadline that closes it.)
#[tokio::test]
async fn a_trickled_head_is_cut_at_the_head_deadline() {
    let server = Running::start(
        Limits {
            head_timeout: SHORT,
            ..small_limits()
        },
        Auth::open(),
    )
    .await;
    let mut s = server.connect().await;
    s.write_all(b"GET /heal").await.unwrap();
    assert!(until_closed(&mut s).await.is_empty());
    assert_eq!(server.app.connections.evicted(), 0, "not pushed out");
    server.stop().await;
}

/// Two pipelined requests in one write, then a third on the same connection: each answered, in
/// order, the connection kept alive. With deadlines out of reach, however slowly this test runs.
#[tokio::test]
async fn keep_alive_survives_pipelined_and_later_requests() {
    let server = Running::start(small_limits(), Auth::open()).await;
    let mut s = BufReader::new(server.connect().await);
    s.get_mut()
        .write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\nGET /nope HTTP/1.1\r\nhost: x\r\n\r\n")
        .await
        .unwrap();
    assert_eq!(response(&mut s).await.0, 200);
    let (status, _, body) = response(&mut s).await;
    assert_eq!((status, error_code(&body).as_str()), (404, "unknown_route"));
    s.get_mut()
        .write_all(&create_request("f", 4, 4))
        .await
        .unwrap();
    let (status, headers, _) = response(&mut s).await;
    assert_eq!(status, 201);
    assert_eq!(header(&headers, "connection"), None);
    // Still open: one more request is answered.
    s.get_mut()
        .write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n")
        .await
        .unwrap();
    assert_eq!(response(&mut s).await.0, 200);
    drop(s);
    server.stop().await;
}

/// After an answer, silence: the idle keep-alive connection is closed at the idle deadline.
/// (The head deadline is out of reach, and the request is sent whole before the idle deadline is
/// armed by its answer, so nothing here races the clock.)
#[tokio::test]
async fn an_idle_keep_alive_connection_is_closed_at_the_idle_deadline() {
    let server = Running::start(
        Limits {
            idle_timeout: SHORT,
            ..small_limits()
        },
        Auth::open(),
    )
    .await;
    let mut s = BufReader::new(server.connect().await);
    s.get_mut()
        .write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n")
        .await
        .unwrap();
    let (status, headers, _) = response(&mut s).await;
    assert_eq!(status, 200);
    assert_eq!(header(&headers, "connection"), None, "kept alive");
    assert!(until_closed(&mut s).await.is_empty());
    server.stop().await;
}

#[tokio::test]
async fn unreadable_heads_get_json_answers_and_a_closed_connection() {
    let server = Running::start(small_limits(), Auth::open()).await;
    let long_uri = format!("GET /{} HTTP/1.1\r\nhost: x\r\n\r\n", "a".repeat(9000));
    let many_headers = format!(
        "GET / HTTP/1.1\r\n{}\r\n",
        (0..150)
            .map(|i| format!("x-{i}: 1\r\n"))
            .collect::<String>()
    );
    let huge_header = format!("GET / HTTP/1.1\r\nx: {}\r\n\r\n", "b".repeat(70_000));
    let cases: [(&[u8], u16, &str); 6] = [
        (b"GARBAGE\r\n\r\n", 400, "malformed_request"),
        (
            b"GET / HTTP/1.1\r\nno colon here\r\n\r\n",
            400,
            "malformed_request",
        ),
        (
            b"POST / HTTP/1.1\r\ncontent-length: 3\r\ncontent-length: 4\r\n\r\n",
            400,
            "malformed_request",
        ),
        (long_uri.as_bytes(), 414, "uri_too_long"),
        (many_headers.as_bytes(), 431, "headers_too_large"),
        (huge_header.as_bytes(), 431, "headers_too_large"),
    ];
    for (head, want_status, want_code) in cases {
        // After a good request on the same connection, so the refusal follows it in order.
        let mut s = BufReader::new(server.connect().await);
        let mut bytes = b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n".to_vec();
        bytes.extend_from_slice(head);
        // The server may answer and close before it has read all of a huge head.
        let _ = s.get_mut().write_all(&bytes).await;
        assert_eq!(response(&mut s).await.0, 200);
        let (status, headers, body) = response(&mut s).await;
        assert_eq!(
            (status, error_code(&body).as_str()),
            (want_status, want_code)
        );
        assert_eq!(header(&headers, "connection"), Some("close"));
        until_closed(&mut s).await;
    }
    server.stop().await;
}

#[tokio::test]
async fn early_refusals_say_connection_close_and_100_continue_waits_for_the_checks() {
    let auth = Auth::parse(&format!("admin {ADMIN}"), false).unwrap();
    let server = Running::start(
        Limits {
            max_records: 16,
            ..small_limits()
        },
        auth,
    )
    .await;
    let mut s = BufReader::new(server.connect().await);
    s.get_mut()
        .write_all(&create_request("f", 4, 4))
        .await
        .unwrap();
    assert_eq!(response(&mut s).await.0, 201);
    let batch = Batch::new("f", 1, 0, vec![Record::new(1, 1, [1.0; 3]); 4])
        .unwrap()
        .encode();
    let samples_to = |frame: &str, token: &str, len: usize, expect: bool| {
        format!(
            "POST /v1/frames/{frame}/samples HTTP/1.1\r\nhost: x\r\nauthorization: Bearer {token}\r\n\
             content-type: application/x-splatd-batch\r\ncontent-length: {len}\r\n{}\r\n",
            if expect { "expect: 100-continue\r\n" } else { "" }
        )
        .into_bytes()
    };
    let samples = |token: &str, len: usize, expect: bool| samples_to("f", token, len, expect);

    // Refused before the body is read: a wrong token, a Content-Length over the limit, an
    // unknown frame. Each answer comes without the body having been sent (so without
    // `100 Continue`), says `Connection: close`, and the connection is closed.
    let too_long = 38 + 128 + 20 * 16 + 1;
    for (head, status, code) in [
        (
            samples("wrong-token-0123456789", batch.len(), true),
            401,
            "unauthorized",
        ),
        (samples(ADMIN, too_long, true), 413, "body_too_large"),
        (
            [
                samples_to("nope", ADMIN, batch.len(), false),
                b"SPLB".to_vec(),
            ]
            .concat(),
            404,
            "unknown_frame",
        ),
    ] {
        let mut s = BufReader::new(server.connect().await);
        s.get_mut().write_all(&head).await.unwrap();
        let (got, headers, body) = response(&mut s).await;
        assert_eq!((got, error_code(&body).as_str()), (status, code));
        assert_eq!(header(&headers, "connection"), Some("close"), "{code}");
        until_closed(&mut s).await;
    }

    // Accepted: `100 Continue` first, then the body is read and applied, and the connection
    // stays open for the next request.
    let mut s = BufReader::new(server.connect().await);
    s.get_mut()
        .write_all(&samples(ADMIN, batch.len(), true))
        .await
        .unwrap();
    let (status, _, _) = response(&mut s).await;
    assert_eq!(status, 100);
    s.get_mut().write_all(&batch).await.unwrap();
    let (status, headers, _) = response(&mut s).await;
    assert_eq!(status, 200);
    assert_eq!(header(&headers, "connection"), None);
    assert_eq!(server.app.store.get("f").unwrap().info().samples, 4);
    server.stop().await;
}

/// A client that asks for a large response and does not read it is disconnected at the
/// response deadline; what it received is a cut-off part of the response.
#[tokio::test]
async fn a_reader_that_stops_reading_is_dropped_at_the_response_deadline() {
    let server = Running::start(
        Limits {
            response_timeout: SHORT,
            ..small_limits()
        },
        Auth::open(),
    )
    .await;
    let spec = server
        .app
        .store
        .check(CreateFrame::new("big", 384, 384))
        .unwrap();
    server.app.store.create(spec).unwrap();
    // Samples in every pixel, so that the state is megabytes, far more than the socket buffers
    // hold: the response cannot be flushed whole, and only its deadline can close the
    // connection (the head and idle deadlines are out of reach).
    let records = (0..384 * 384)
        .map(|i| Record::new(i % 384, i / 384, [1.0, 50.0, 0.5]))
        .collect();
    let batch = Batch::new("big", 1, 0, records).unwrap();
    server.app.store.get("big").unwrap().ingest(&batch).unwrap();
    let whole = testing::send(
        &server.app,
        axum::http::Request::get("/v1/frames/big/state")
            .body(axum::body::Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(whole.status, 200);
    let state_len = whole.body.len() as u64;
    assert!(state_len > 8 << 20, "{state_len} bytes");

    // A small receive window, so the server's writes block soon.
    let socket = TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let mut s = socket.connect(server.addr).await.unwrap();
    s.write_all(b"GET /v1/frames/big/state HTTP/1.1\r\nhost: x\r\n\r\n")
        .await
        .unwrap();
    // The response has begun (so the connection is open and counted)...
    let mut status = [0u8; 12];
    tokio::time::timeout(PATIENCE, s.read_exact(&mut status))
        .await
        .expect("a response within PATIENCE")
        .unwrap();
    assert_eq!(&status, b"HTTP/1.1 200");
    // ... and, not read any further, the server gives up on the connection by itself.
    tokio::time::timeout(PATIENCE, server.app.connections.until_open_at_most(0))
        .await
        .expect("the slow reader's connection was closed");
    let mut got = status.to_vec();
    got.extend(until_closed(&mut s).await);
    assert!(
        (got.len() as u64) < state_len,
        "{} of {state_len} bytes",
        got.len()
    );
    server.stop().await;
}

#[tokio::test]
async fn a_client_that_shuts_its_write_side_after_a_request_still_gets_the_answer() {
    // `printf 'GET ...' | nc` and many HTTP/1.0-era tools send a request and then shut their
    // side of the socket. The answer must still come, also when it is not ready at once: an
    // image is resolved on the render thread, so hyper reads the socket's end of stream while
    // the response is pending, and without half-close support it dropped the request there.
    let auth = Auth::parse(&format!("admin {ADMIN}"), false).unwrap();
    let server = Running::start(small_limits(), auth).await;
    let mut s = BufReader::new(server.connect().await);
    s.get_mut()
        .write_all(&create_request("half", 64, 48))
        .await
        .unwrap();
    assert_eq!(response(&mut s).await.0, 201);
    for _ in 0..8 {
        let mut s = server.connect().await;
        s.write_all(
            format!(
                "GET /v1/frames/half/image.exr HTTP/1.1\r\nhost: x\r\n\
                 authorization: Bearer {ADMIN}\r\n\r\n"
            )
            .as_bytes(),
        )
        .await
        .unwrap();
        s.shutdown().await.unwrap();
        let got = until_closed(&mut s).await;
        let head = String::from_utf8_lossy(&got[..got.len().min(200)]).into_owned();
        assert!(head.starts_with("HTTP/1.1 200"), "answer: {head:?}");
        assert!(
            got.windows(4).any(|w| w == [0x76, 0x2f, 0x31, 0x01]),
            "an EXR body"
        );
    }
    server.stop().await;
}
