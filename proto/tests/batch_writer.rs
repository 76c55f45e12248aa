//! [`BatchWriter`] against a scripted HTTP server on 127.0.0.1 (`common/mod.rs`): batch
//! numbering, resending a batch that failed under its original sequence number, and the
//! durability floor (keeping acknowledged batches until the server has them on disk, and
//! resending them after a restart). Every test runs under a timeout. The request client's own
//! retries are tested in `client_retry.rs`.
#![cfg(feature = "client")]

mod common;

use common::{ack_json, client, durable_ack_json, scripted_server, TEST_TIMEOUT};
use splatd_proto::batch::DEFAULT_MAX_RECORDS;
use splatd_proto::{Batch, BatchWriter, ClientError, Record, SyncAck};

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
async fn acknowledged_batches_are_kept_until_durable_and_resent_after_a_restart() {
    tokio::time::timeout(TEST_TIMEOUT, async {
        let sync = serde_json::to_string(&SyncAck {
            frame: "f".into(),
            boot: 8,
            durable: true,
        })
        .expect("serialises");
        let (base, server) = scripted_server(vec![
            // Boot 7 applies seq 0; nothing is on disk yet.
            ("200 OK", "", durable_ack_json("f", 3, 0, 1, 7, Some(0))),
            // Seq 1 applied, and a snapshot now holds seq 0: the writer may forget it.
            ("200 OK", "", durable_ack_json("f", 3, 1, 1, 7, Some(1))),
            // The server restarted (boot 8) and lost seq 1; seq 2 is applied by the new process.
            ("200 OK", "", durable_ack_json("f", 3, 2, 1, 8, Some(0))),
            // The writer resends what the dead process had acknowledged: seq 1 is applied again
            // (seq 2 was acknowledged by the new process and is not sent twice).
            ("200 OK", "", durable_ack_json("f", 3, 1, 1, 8, Some(0))),
            // sync: same process, everything applied is now on disk.
            ("200 OK", "", sync),
        ])
        .await;
        let mut w = client(&base)
            .batch_writer("f", 3, 0, 1)
            .expect("valid writer");
        let records: Vec<Record> = (0..3).map(|i| Record::new(i, 0, [1.0; 3])).collect();
        w.push(records[0]).await.expect("seq 0");
        assert_eq!(w.unconfirmed(), 1, "seq 0 is applied but not durable");
        w.push(records[1]).await.expect("seq 1");
        assert_eq!(w.unconfirmed(), 1, "the floor passed seq 0; seq 1 is kept");
        let acks = w.push(records[2]).await.expect("seq 2, then the resends");
        assert_eq!(acks.iter().map(|a| a.seq).collect::<Vec<_>>(), [2]);
        assert_eq!(w.resent(), 1, "seq 1 resent after the restart");
        assert_eq!(w.unconfirmed(), 2);
        w.sync().await.expect("synced");
        assert_eq!(w.unconfirmed(), 0, "sync confirmed everything");

        let seen = server.await.expect("server task");
        assert_eq!(seen[4].request_line, "POST /v1/frames/f/sync HTTP/1.1");
        let seqs: Vec<u64> = seen[..4]
            .iter()
            .map(|s| {
                Batch::decode(&s.body, &Default::default())
                    .expect("valid batch")
                    .seq
            })
            .collect();
        assert_eq!(seqs, [0, 1, 2, 1]);
        assert_eq!(seen[1].body, seen[3].body, "seq 1 resent byte for byte");
    })
    .await
    .expect("test timed out");
}

#[tokio::test]
async fn invalid_writer_arguments_are_refused_locally() {
    // Nothing listens on the discard port: these must fail before any request.
    let c = client("http://127.0.0.1:9");
    assert!(matches!(
        c.batch_writer("a b", 0, 0, 10),
        Err(ClientError::Wire(_))
    ));
    for size in [0, DEFAULT_MAX_RECORDS + 1] {
        assert!(
            matches!(
                BatchWriter::new(c.clone(), "ok", 0, 0, size),
                Err(ClientError::InvalidArgument(_))
            ),
            "batch size {size}"
        );
    }
}
