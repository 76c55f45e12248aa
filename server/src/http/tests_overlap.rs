//! States carry the batches they hold, so that no merge counts a batch twice: the case of a worker
//! whose node failed and that resent a batch to another node, whose two states then both hold it.
//! In process, three servers: two nodes and the head they are merged into.

use axum::body::Body;
use axum::http::{header, Method, Request, StatusCode};
use splatd_proto::{Batch, Record, StateDump, BATCH_CONTENT_TYPE, STATE_CONTENT_TYPE};
use splatd_scenes::synth::SplitMix64;

use crate::{testing, AppState, Limits};

const W: u32 = 16;
const H: u32 = 16;

/// A server with an empty 16x16 frame `f` and no tokens.
fn server() -> AppState {
    testing::with_frame(AppState::new(Limits::default(), None, None), "f", W, H)
}

/// Batch `seq` of worker 7: 64 random samples, some of them fireflies, drawn from `seed`.
fn batch(seq: u64, seed: u64) -> Batch {
    let mut rng = SplitMix64::new(seed);
    let records = (0..64)
        .map(|_| {
            let x = (rng.next_u64() % W as u64) as u32;
            let y = (rng.next_u64() % H as u64) as u32;
            let v = if rng.next_u64().is_multiple_of(16) {
                5000.0
            } else {
                0.5
            };
            Record {
                x,
                y,
                rgb: [v, v * 0.5, v * 0.25],
            }
        })
        .collect();
    Batch {
        frame: "f".into(),
        worker: 7,
        seq,
        records,
    }
}

/// Sends one request; the status and the body.
async fn call(
    app: &AppState,
    method: Method,
    path: &str,
    kind: &str,
    body: Vec<u8>,
) -> (StatusCode, Vec<u8>) {
    let request = Request::builder()
        .method(method)
        .uri(path)
        .header(header::CONTENT_TYPE, kind)
        .body(Body::from(body))
        .unwrap();
    let reply = testing::send(app, request).await;
    (reply.status, reply.body.to_vec())
}

async fn post(app: &AppState, b: &Batch) -> serde_json::Value {
    let (status, body) = call(
        app,
        Method::POST,
        "/v1/frames/f/samples",
        BATCH_CONTENT_TYPE,
        b.encode(),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    serde_json::from_slice(&body).unwrap()
}

async fn export(app: &AppState) -> Vec<u8> {
    let (status, body) = call(app, Method::GET, "/v1/frames/f/state", "", vec![]).await;
    assert_eq!(status, StatusCode::OK);
    body
}

async fn import(app: &AppState, state: Vec<u8>) -> (StatusCode, serde_json::Value) {
    let (status, body) = call(
        app,
        Method::POST,
        "/v1/frames/f/state",
        STATE_CONTENT_TYPE,
        state,
    )
    .await;
    (status, serde_json::from_slice(&body).unwrap())
}

/// The head's cells, from its exported state.
async fn cells(app: &AppState) -> Vec<u64> {
    StateDump::decode(&export(app).await, u64::MAX)
        .unwrap()
        .cells
}

#[tokio::test]
async fn a_batch_in_two_states_is_refused_by_name_and_changes_nothing() {
    let (a, b, head, reference) = (server(), server(), server(), server());
    // The worker sends batches 0..4 to node a; a's answer to batch 3 is lost, a fails, and the
    // worker resends batch 3 to node b, then goes on there with 4 and 5.
    for seq in 0..4 {
        post(&a, &batch(seq, seq)).await;
    }
    for seq in 3..6 {
        post(&b, &batch(seq, seq)).await;
    }
    // What one server holds that applied every batch once.
    for seq in 0..6 {
        post(&reference, &batch(seq, seq)).await;
    }

    let state_a = export(&a).await;
    let listed = StateDump::decode(&state_a, u64::MAX).unwrap().batches;
    assert_eq!(listed.len(), 1);
    assert_eq!((listed[0].worker, listed[0].len()), (7, 4));
    assert_eq!((listed[0].ranges[0].start, listed[0].ranges[0].end), (0, 4));
    let (status, ack) = import(&head, state_a.clone()).await;
    assert_eq!(status, StatusCode::OK, "{ack}");
    let before = cells(&head).await;

    // b's state holds batch 3 too: adding it would count batch 3 twice.
    let (status, err) = import(&head, export(&b).await).await;
    assert_eq!(status, StatusCode::CONFLICT, "{err}");
    assert_eq!(err["error"], "batches_overlap");
    let message = err["message"].as_str().unwrap();
    assert!(
        message.contains("worker 7, seq 3") && message.contains("1 batch"),
        "{message}"
    );
    assert_eq!(
        cells(&head).await,
        before,
        "a refused state changed the frame"
    );
    // Nor is a's state taken twice.
    let (status, err) = import(&head, state_a).await;
    assert_eq!(
        (status, err["error"].as_str()),
        (StatusCode::CONFLICT, Some("batches_overlap"))
    );
    assert_eq!(cells(&head).await, before);

    // The head knows batch 3 now: the worker's resend straight to it is a retry, and the id
    // reused for other records is refused (the digests travelled with the state).
    let ack = post(&head, &batch(3, 3)).await;
    assert_eq!(ack["duplicate"], true, "{ack}");
    let (status, body) = call(
        &head,
        Method::POST,
        "/v1/frames/f/samples",
        BATCH_CONTENT_TYPE,
        batch(3, 99).encode(),
    )
    .await;
    assert_eq!(
        status,
        StatusCode::CONFLICT,
        "{}",
        String::from_utf8_lossy(&body)
    );
    // What b holds that the head lacks, applied directly: the head equals the reference.
    for seq in 4..6 {
        post(&head, &batch(seq, seq)).await;
    }
    assert_eq!(cells(&head).await, cells(&reference).await);
}
