//! A state's batch list cannot make the server drop a real batch (PROTOCOL.md, "Exactly-once and
//! durability"). An imported state names the batches whose samples it holds, each with a digest
//! of its records, or 0 where the sender recorded none. Before, an import naming `(worker, seq)`
//! with digest 0 made every later post of those ids answer 200 `duplicate: true`, its samples
//! dropped (4 of 4 in issue 21, and in this test run against the old build). Now such a post is
//! 409 `batch_id_unverified`, applies nothing, is counted as rejected, and stays so across a
//! restart; batches a state names with their real digest are still told apart (a retry is a
//! duplicate, other records are `batch_id_reused`). Against a real `splatd serve` with tokens,
//! the import made with an `admin` token as the was.
//!
//! `SPLATD_BIN=/path/to/splatd` runs it against another build.

use std::path::PathBuf;

use serde_json::Value;
use splatd_harness::{Options, ServerProcess};
use splatd_proto::{Applied, Batch, Record, StateDump};

const ADMIN: &str = "admin-token-0123456789";
const WORKER: &str = "worker-token-0123456789";

fn start(data: &str) -> ServerProcess {
    let binary = std::env::var_os("SPLATD_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_splatd")));
    let tokens = format!("admin {ADMIN}\nwrite {WORKER}\n");
    let args = ["--data-dir", data];
    let env = [("SPLATD_TOKENS", tokens.as_str())];
    ServerProcess::launch(&Options {
        env: &env,
        ..Options::new(binary, &args)
    })
    .unwrap_or_else(|e| panic!("{e}"))
}

fn http() -> reqwest::blocking::Client {
    reqwest::blocking::Client::new()
}

fn answer(r: reqwest::blocking::Response) -> (u16, Value) {
    let status = r.status().as_u16();
    let text = r.text().unwrap();
    (
        status,
        serde_json::from_str(&text).unwrap_or(Value::String(text)),
    )
}

fn records(seed: u32) -> Vec<Record> {
    (0..6)
        .map(|i| Record::new(i % 8, (i + seed) % 4, [0.5 + seed as f32, 1.0, 2.0]))
        .collect()
}

fn post(server: &ServerProcess, worker: u64, seq: u64, records: Vec<Record>) -> (u16, Value) {
    let batch = Batch::new("f", worker, seq, records).unwrap();
    answer(
        http()
            .post(format!("{}/v1/frames/f/samples", server.url))
            .bearer_auth(WORKER)
            .header("content-type", splatd_proto::BATCH_CONTENT_TYPE)
            .body(batch.encode())
            .send()
            .unwrap(),
    )
}

fn info(server: &ServerProcess) -> Value {
    let (status, info) = answer(
        http()
            .get(format!("{}/v1/frames/f", server.url))
            .bearer_auth(ADMIN)
            .send()
            .unwrap(),
    );
    assert_eq!(status, 200, "{info}");
    info
}

#[test]
fn a_state_naming_batches_without_digests_cannot_make_their_posts_duplicates() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().to_str().unwrap();
    let server = start(data);
    let (status, body) = answer(
        http()
            .put(format!("{}/v1/frames/f", server.url))
            .bearer_auth(WORKER)
            .json(&serde_json::json!({"width": 8, "height": 4}))
            .send()
            .unwrap(),
    );
    assert_eq!(status, 201, "{body}");

    // The frame's own (empty) state, naming worker 7's batches 0..4 without digests and
    // worker 8's batch 0 with the digest of its records.
    let exported = http()
        .get(format!("{}/v1/frames/f/state", server.url))
        .bearer_auth(ADMIN)
        .send()
        .unwrap()
        .bytes()
        .unwrap();
    let mut state = StateDump::decode(&exported, u64::MAX).unwrap();
    let known = Batch::new("f", 8, 0, records(8)).unwrap().content_digest();
    state.batches = vec![
        Applied::from_batches(7, (0..4).map(|seq| (seq, None))),
        Applied::from_batches(8, [(0, Some(known))]),
    ];
    assert_eq!(state.batches[0].digests, [0; 4], "digest 0 on the wire");
    let (status, ack) = answer(
        http()
            .post(format!("{}/v1/frames/f/state", server.url))
            .bearer_auth(ADMIN)
            .header("content-type", splatd_proto::STATE_CONTENT_TYPE)
            .body(state.encode())
            .send()
            .unwrap(),
    );
    assert_eq!(status, 200, "{ack}");

    for seq in 0..4 {
        let (status, body) = post(&server, 7, seq, records(seq as u32));
        assert_eq!(
            status, 409,
            "worker 7 seq {seq}: the state's word is not a digest; answered {body}"
        );
        assert_eq!(body["error"], "batch_id_unverified", "{body}");
        let message = body["message"].as_str().unwrap();
        assert!(
            message.contains(&format!("worker 7, seq {seq}")),
            "{message}"
        );
    }
    let after = info(&server);
    assert_eq!(after["samples"], 0, "nothing applied: {after}");
    assert_eq!(
        after["rejected_batches"], 4,
        "and nothing dropped silently: {after}"
    );

    // Ids the state names with a digest: a retry is a duplicate, other records a conflict.
    let (status, ack) = post(&server, 8, 0, records(8));
    assert_eq!(
        (status, &ack["duplicate"]),
        (200, &Value::Bool(true)),
        "{ack}"
    );
    let (status, body) = post(&server, 8, 0, records(9));
    assert_eq!(
        (status, &body["error"]),
        (409, &Value::from("batch_id_reused"))
    );
    // A number the state does not name is new.
    let (status, ack) = post(&server, 7, 4, records(4));
    assert_eq!(status, 200, "{ack}");
    assert_eq!(
        (ack["accepted"].as_u64(), &ack["duplicate"]),
        (Some(6), &Value::Bool(false))
    );

    // The mark is part of the snapshot: after a restart the ids are still refused.
    let (status, body) = answer(
        http()
            .post(format!("{}/v1/frames/f/sync", server.url))
            .bearer_auth(WORKER)
            .send()
            .unwrap(),
    );
    assert_eq!(status, 200, "{body}");
    assert_eq!(server.terminate(), Some(0));
    let server = start(data);
    let (status, body) = post(&server, 7, 0, records(0));
    assert_eq!(
        (status, &body["error"]),
        (409, &Value::from("batch_id_unverified")),
        "{body}"
    );
    let (status, ack) = post(&server, 8, 0, records(8));
    assert_eq!(
        (status, &ack["duplicate"]),
        (200, &Value::Bool(true)),
        "{ack}"
    );
    assert_eq!(info(&server)["samples"], 6);
}
