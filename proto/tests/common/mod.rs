//! A scripted HTTP server on 127.0.0.1 and a fast-retrying client, shared by the tests of
//! [`splatd_proto::Client`] (`client_retry.rs`) and of [`splatd_proto::BatchWriter`]
//! (`batch_writer.rs`).
//!
//! The server is a few lines of tokio: it accepts a bounded number of
//! connections, records each request, answers with the next scripted
//! response and closes the connection.

// Each test file uses its own subset of these helpers.
#![allow(dead_code)]

use std::time::Duration;

use splatd_proto::{BatchAck, Client, RetryPolicy};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;

pub const TEST_TIMEOUT: Duration = Duration::from_secs(20);

/// One request as the server saw it.
#[derive(Debug, Clone)]
pub struct Seen {
    pub request_line: String,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Seen {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

/// Serves `responses` (status line, extra headers, body) one per connection,
/// in order, and returns the requests seen.
pub async fn scripted_server(
    responses: Vec<(&'static str, &'static str, String)>,
) -> (String, JoinHandle<Vec<Seen>>) {
    let listener = TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let addr = listener.local_addr().expect("local addr");
    let handle = tokio::spawn(async move {
        let mut seen = Vec::new();
        for (status, extra_headers, body) in responses {
            let (mut sock, _) = listener.accept().await.expect("accept");
            seen.push(read_request(&mut sock).await);
            let response = format!(
                "HTTP/1.1 {status}\r\nContent-Type: application/json\r\n{extra_headers}\
                 Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
            sock.write_all(response.as_bytes()).await.expect("write");
            sock.shutdown().await.ok();
        }
        seen
    });
    (format!("http://{addr}"), handle)
}

async fn read_request(sock: &mut tokio::net::TcpStream) -> Seen {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 8192];
    let head_end = loop {
        if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break i + 4;
        }
        let n = sock.read(&mut chunk).await.expect("read head");
        assert!(n > 0, "connection closed inside the request head");
        buf.extend_from_slice(&chunk[..n]);
    };
    let head = String::from_utf8(buf[..head_end].to_vec()).expect("ASCII head");
    let mut lines = head.split("\r\n");
    let request_line = lines.next().unwrap_or_default().to_owned();
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(n, v)| (n.trim().to_owned(), v.trim().to_owned()))
        .collect();
    let len: usize = headers
        .iter()
        .find(|(n, _)| n.eq_ignore_ascii_case("content-length"))
        .map(|(_, v)| v.parse().expect("numeric content-length"))
        .unwrap_or(0);
    let mut body = buf[head_end..].to_vec();
    while body.len() < len {
        let n = sock.read(&mut chunk).await.expect("read body");
        assert!(n > 0, "connection closed inside the body");
        body.extend_from_slice(&chunk[..n]);
    }
    Seen {
        request_line,
        headers,
        body,
    }
}

pub fn fast_retries() -> RetryPolicy {
    RetryPolicy {
        max_attempts: 4,
        initial_backoff: Duration::from_millis(5),
        max_backoff: Duration::from_millis(20),
    }
}

pub fn client(base: &str) -> Client {
    let http = reqwest::Client::builder()
        .no_proxy()
        .timeout(Duration::from_secs(5))
        .build()
        .expect("reqwest client");
    Client::with_http_client(base, http)
        .expect("valid base URL")
        .with_retry_policy(fast_retries())
}

/// The JSON of a [`BatchAck`] from an in-memory server (boot 1, no `durable_floor`).
pub fn ack_json(frame: &str, worker: u64, seq: u64, accepted: u64) -> String {
    durable_ack_json(frame, worker, seq, accepted, 1, None)
}

/// The JSON of a [`BatchAck`] from the server process `boot`, with its `durable_floor` for the
/// worker (`None` for a server without durability). `accepted == 0` marks it a duplicate.
pub fn durable_ack_json(
    frame: &str,
    worker: u64,
    seq: u64,
    accepted: u64,
    boot: u64,
    durable_floor: Option<u64>,
) -> String {
    serde_json::to_string(&BatchAck {
        frame: frame.into(),
        worker,
        seq,
        accepted,
        duplicate: accepted == 0,
        boot,
        durable_floor,
        snapshots_failing: false,
    })
    .expect("serialises")
}
