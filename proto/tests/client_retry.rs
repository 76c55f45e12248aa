//! The client's retry behaviour against a scripted HTTP server on 127.0.0.1.
//!
//! The server is a few lines of tokio: it accepts a bounded number of
//! connections, records each request, answers with the next scripted
//! response and closes the connection. Every test runs under a timeout.
#![cfg(feature = "client")]

use std::time::Duration;

use splatd_proto::{
    Batch, BatchAck, Client, ClientError, CreateFrame, Record, RetryPolicy, BATCH_CONTENT_TYPE,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;

const TEST_TIMEOUT: Duration = Duration::from_secs(20);

/// One request as the server saw it.
#[derive(Debug, Clone)]
struct Seen {
    request_line: String,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Seen {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

/// Serves `responses` (status line, extra headers, body) one per connection,
/// in order, and returns the requests seen.
async fn scripted_server(
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

fn fast_retries() -> RetryPolicy {
    RetryPolicy {
        max_attempts: 4,
        initial_backoff: Duration::from_millis(5),
        max_backoff: Duration::from_millis(20),
    }
}

fn client(base: &str) -> Client {
    let http = reqwest::Client::builder()
        .no_proxy()
        .timeout(Duration::from_secs(5))
        .build()
        .expect("reqwest client");
    Client::with_http_client(base, http)
        .expect("valid base URL")
        .with_retry_policy(fast_retries())
}

fn ack_json(frame: &str, worker: u64, seq: u64, accepted: u64) -> String {
    serde_json::to_string(&BatchAck {
        frame: frame.into(),
        worker,
        seq,
        accepted,
        duplicate: false,
        boot: 1,
        durable_floor: None,
    })
    .expect("serialises")
}

fn sample_batch() -> Batch {
    Batch::new(
        "shot.010",
        77,
        5,
        vec![
            Record::new(0, 0, [1.0, 2.0, 3.0]),
            Record::new(3, 1, [0.5, 0.25, 0.125]),
        ],
    )
    .expect("valid batch")
}

#[tokio::test]
async fn batch_is_resent_byte_for_byte_after_503s() {
    tokio::time::timeout(TEST_TIMEOUT, async {
        let unavailable = r#"{"error":"unavailable","message":"restarting"}"#.to_owned();
        let (base, server) = scripted_server(vec![
            ("503 Service Unavailable", "", unavailable.clone()),
            ("503 Service Unavailable", "Retry-After: 0\r\n", unavailable),
            ("200 OK", "", ack_json("shot.010", 77, 5, 2)),
        ])
        .await;
        let batch = sample_batch();
        let ack = client(&base)
            .with_token("s3cret")
            .post_batch(&batch)
            .await
            .expect("third attempt succeeds");
        assert_eq!(ack.seq, 5);
        assert_eq!(ack.accepted, 2);

        let seen = server.await.expect("server task");
        assert_eq!(seen.len(), 3);
        let expected = batch.encode();
        for (i, req) in seen.iter().enumerate() {
            assert_eq!(
                req.request_line,
                "POST /v1/frames/shot.010/samples HTTP/1.1"
            );
            assert_eq!(req.header("content-type"), Some(BATCH_CONTENT_TYPE));
            assert_eq!(req.header("authorization"), Some("Bearer s3cret"));
            assert_eq!(req.body, expected, "attempt {i} sent different bytes");
        }
    })
    .await
    .expect("test timed out");
}

#[tokio::test]
async fn rate_limit_and_timeout_statuses_are_retried() {
    tokio::time::timeout(TEST_TIMEOUT, async {
        let (base, server) = scripted_server(vec![
            ("429 Too Many Requests", "", String::new()),
            ("408 Request Timeout", "", String::new()),
            ("200 OK", "", ack_json("shot.010", 77, 5, 2)),
        ])
        .await;
        client(&base)
            .post_batch(&sample_batch())
            .await
            .expect("retried to success");
        assert_eq!(server.await.expect("server task").len(), 3);
    })
    .await
    .expect("test timed out");
}

#[tokio::test]
async fn other_4xx_is_rejected_without_retry() {
    tokio::time::timeout(TEST_TIMEOUT, async {
        let body = r#"{"error":"pixel_out_of_range","message":"record 1: x 3 >= width 2"}"#;
        let (base, server) =
            scripted_server(vec![("422 Unprocessable Entity", "", body.to_owned())]).await;
        let err = client(&base)
            .post_batch(&sample_batch())
            .await
            .expect_err("422 is final");
        match &err {
            ClientError::Rejected { status, body } => {
                assert_eq!(*status, 422);
                assert_eq!(body.error, "pixel_out_of_range");
                assert_eq!(body.message, "record 1: x 3 >= width 2");
            }
            other => panic!("expected Rejected, got {other:?}"),
        }
        assert!(err.to_string().contains("pixel_out_of_range"), "{err}");
        assert_eq!(server.await.expect("server task").len(), 1);
    })
    .await
    .expect("test timed out");
}

#[tokio::test]
async fn gives_up_after_max_attempts() {
    tokio::time::timeout(TEST_TIMEOUT, async {
        let (base, server) =
            scripted_server(vec![
                ("500 Internal Server Error", "", "boom".to_owned());
                4
            ])
            .await;
        let err = client(&base)
            .post_batch(&sample_batch())
            .await
            .expect_err("all attempts fail");
        match &err {
            ClientError::GaveUp { attempts, last, .. } => {
                assert_eq!(*attempts, 4);
                assert!(last.contains("500") && last.contains("boom"), "{last}");
            }
            other => panic!("expected GaveUp, got {other:?}"),
        }
        assert_eq!(server.await.expect("server task").len(), 4);
    })
    .await
    .expect("test timed out");
}

#[tokio::test]
async fn connection_refused_is_retried_then_reported() {
    tokio::time::timeout(TEST_TIMEOUT, async {
        // Bind and drop a listener: nothing listens on that port afterwards.
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("addr");
        drop(listener);
        let err = client(&format!("http://{addr}"))
            .frame_info("f")
            .await
            .expect_err("nothing listens");
        assert!(
            matches!(err, ClientError::GaveUp { attempts: 4, .. }),
            "{err:?}"
        );
    })
    .await
    .expect("test timed out");
}

#[tokio::test]
async fn create_frame_and_frame_info() {
    tokio::time::timeout(TEST_TIMEOUT, async {
        let req = CreateFrame::new("f1", 4, 2);
        let info = splatd_proto::FrameInfo {
            id: "f1".into(),
            width: 4,
            height: 2,
            cascades: req.cascades.clone(),
            resolve: req.resolve.clone(),
            samples: 0,
            batches: 0,
            spp_min: 0,
            spp_mean: 0.0,
            spp_max: 0,
            rejected_samples: 0,
            rejected_batches: 0,
            memory_bytes: 1024,
        };
        let json = serde_json::to_string(&info).expect("serialises");
        let (base, server) = scripted_server(vec![
            ("201 Created", "", json.clone()),
            ("200 OK", "", json),
        ])
        .await;
        let c = client(&format!("{base}/"));
        assert_eq!(c.create_frame(&req).await.expect("created"), info);
        assert_eq!(c.frame_info("f1").await.expect("info"), info);
        let seen = server.await.expect("server task");
        assert_eq!(seen[0].request_line, "POST /v1/frames HTTP/1.1");
        assert_eq!(seen[0].header("content-type"), Some("application/json"));
        let sent: CreateFrame = serde_json::from_slice(&seen[0].body).expect("JSON body");
        assert_eq!(sent, req);
        assert_eq!(seen[1].request_line, "GET /v1/frames/f1 HTTP/1.1");
        assert_eq!(seen[1].header("authorization"), None);
    })
    .await
    .expect("test timed out");
}

#[tokio::test]
async fn batch_writer_numbers_batches_and_resends_a_failed_one() {
    tokio::time::timeout(TEST_TIMEOUT, async {
        let (base, server) = scripted_server(vec![
            ("200 OK", "", ack_json("f", 9, 100, 2)),
            // Seq 101 fails for good on the first push that fills it ...
            (
                "400 Bad Request",
                "",
                r#"{"error":"x","message":"y"}"#.to_owned(),
            ),
            // ... and is resent, unchanged, by the flush.
            ("200 OK", "", ack_json("f", 9, 101, 2)),
            ("200 OK", "", ack_json("f", 9, 102, 1)),
        ])
        .await;
        let mut w = client(&base)
            .batch_writer("f", 9, 100, 2)
            .expect("valid writer");
        let records: Vec<Record> = (0..5).map(|i| Record::new(i, 0, [i as f32; 3])).collect();
        assert!(w.push(records[0]).await.expect("buffered").is_empty());
        let acks = w.push(records[1]).await.expect("first batch sent");
        assert_eq!(acks.len(), 1);
        assert_eq!(acks[0].seq, 100);
        let err = w
            .extend(records[2..5].iter().copied())
            .await
            .expect_err("400");
        assert!(
            matches!(err, ClientError::Rejected { status: 400, .. }),
            "{err:?}"
        );
        assert_eq!(w.pending_seq(), Some(101));
        assert_eq!(w.buffered(), 0, "extend stopped after sealing seq 101");
        w.push(records[4])
            .await
            .expect("below batch size, nothing sent");
        let acks = w.flush().await.expect("flushed");
        assert_eq!(acks.iter().map(|a| a.seq).collect::<Vec<_>>(), [101, 102]);
        assert_eq!(w.next_seq(), 103);
        assert_eq!(w.pending_seq(), None);

        let seen = server.await.expect("server task");
        let decoded: Vec<Batch> = seen
            .iter()
            .map(|s| Batch::decode(&s.body, &Default::default()).expect("valid batch"))
            .collect();
        assert_eq!(
            decoded.iter().map(|b| b.seq).collect::<Vec<_>>(),
            [100, 101, 101, 102]
        );
        assert_eq!(seen[1].body, seen[2].body, "resent batch must be identical");
        assert_eq!(decoded[0].records, records[0..2]);
        assert_eq!(decoded[1].records, records[2..4]);
        assert_eq!(decoded[3].records, records[4..5]);
        assert!(decoded.iter().all(|b| b.worker == 9 && b.frame == "f"));
    })
    .await
    .expect("test timed out");
}

#[tokio::test]
async fn invalid_frame_ids_are_refused_locally() {
    let c = client("http://127.0.0.1:9");
    let err = c.frame_info("../etc").await.expect_err("invalid id");
    assert!(matches!(err, ClientError::Wire(_)), "{err:?}");
    assert!(c.batch_writer("a b", 0, 0, 10).is_err());
    assert!(c.batch_writer("ok", 0, 0, 0).is_err());
}
