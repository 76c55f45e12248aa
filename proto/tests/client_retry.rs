//! The client's retry behaviour against a scripted HTTP server on 127.0.0.1
//! (`common/mod.rs`). Every test runs under a timeout. The batch writer built
//! on this client is tested in `batch_writer.rs`.
#![cfg(feature = "client")]

mod common;

use common::{ack_json, client, scripted_server, TEST_TIMEOUT};
use splatd_proto::{Batch, ClientError, CreateFrame, Record, BATCH_CONTENT_TYPE};
use tokio::net::TcpListener;

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
            aovs: vec![],
            denoise: Default::default(),
            denoise_guides: Default::default(),
            convergence: None,
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
async fn invalid_frame_ids_are_refused_locally() {
    let c = client("http://127.0.0.1:9");
    let err = c.frame_info("../etc").await.expect_err("invalid id");
    assert!(matches!(err, ClientError::Wire(_)), "{err:?}");
}
