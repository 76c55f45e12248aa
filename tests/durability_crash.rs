//! A durable server that dies, by SIGKILL between an acknowledgement and the next snapshot, or by
//! an abort while a snapshot is half written, while four workers keep posting through
//! `BatchWriter`s: the final image is bit-identical to an uninterrupted run of the same samples,
//! no batch is lost and none counts twice.
//!
//! Nothing here depends on timing. Snapshots happen only when a worker syncs (the periodic ones
//! are an hour apart), the test decides when the server dies (after every worker's batches of a
//! phase are acknowledged), and the crash inside a snapshot comes from a failpoint
//! (`SPLATD_FAILPOINTS`), so exactly which batches are lost, and must be resent, is known in
//! advance. Clients reach the server through a forwarder whose port the test owns, so a
//! restarted server can take any free port.

use std::path::Path;
use std::time::Duration;

use crate::common;
use crate::common::{runtime, Forwarder, Server, ServerProcess};
use splatd_estimator::{CascadeLayout, FrameState, ResolveParams};
use splatd_formats::exr::{encode_exr, Provenance};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{BatchWriter, Client, Record, RetryPolicy};
use splatd_scenes::synth::FireflyScene;

const W: u32 = 64;
const H: u32 = 48;
const WORKERS: u64 = 4;
/// Passes per worker and phase.
const PASSES_PER_PHASE: u64 = 4;
const PHASES: u64 = 3;
/// Records per batch: a pass of 64x48 is exactly three batches.
const BATCH: usize = 1024;
const BATCHES_PER_PHASE: u64 = PASSES_PER_PHASE * (W * H) as u64 / BATCH as u64;
const FRAME: &str = "crash";

fn scene() -> FireflyScene {
    FireflyScene::new(W, H, 7)
}

/// The records of worker `w` in phase `phase`: its passes of that phase, in order.
fn records(w: u64, phase: u64) -> Vec<Record> {
    let scene = scene();
    (0..PASSES_PER_PHASE)
        .map(|i| (phase * PASSES_PER_PHASE + i) * WORKERS + w)
        .flat_map(|pass| scene.pass(pass).collect::<Vec<_>>())
        .map(|(x, y, rgb)| Record::new(x, y, rgb))
        .collect()
}

/// Sends every worker's records of `phase` (all acknowledged when this returns); then syncs
/// the workers in `syncing`, one after another, in order.
fn phase(
    rt: &tokio::runtime::Runtime,
    writers: Vec<BatchWriter>,
    phase: u64,
    syncing: &[u64],
) -> Vec<BatchWriter> {
    let tasks: Vec<_> = writers
        .into_iter()
        .enumerate()
        .map(|(w, mut writer)| {
            rt.spawn(async move {
                for chunk in records(w as u64, phase).chunks(BATCH) {
                    writer.extend(chunk.iter().copied()).await.unwrap();
                }
                writer.flush().await.unwrap();
                writer
            })
        })
        .collect();
    let mut writers: Vec<BatchWriter> =
        tasks.into_iter().map(|t| rt.block_on(t).unwrap()).collect();
    for &w in syncing {
        rt.block_on(writers[w as usize].sync()).unwrap();
    }
    writers
}

/// Syncs every worker after the server lost phase 1: each must resend exactly its phase 1.
fn sync_all_resending_phase_1(rt: &tokio::runtime::Runtime, writers: &mut [BatchWriter]) {
    sync_all(rt, writers);
    let resent: Vec<u64> = writers.iter().map(BatchWriter::resent).collect();
    assert_eq!(
        resent,
        vec![BATCHES_PER_PHASE; WORKERS as usize],
        "resent exactly phase 1"
    );
}

/// Syncs every worker (resending what a restart lost), one after another.
fn sync_all(rt: &tokio::runtime::Runtime, writers: &mut [BatchWriter]) {
    for writer in writers {
        rt.block_on(writer.sync()).unwrap();
    }
}

fn start(data: &Path, failpoints: Option<&str>) -> ServerProcess {
    let args = common::durable_args(data);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    match failpoints {
        Some(spec) => Server::start_with_env(&args, &[("SPLATD_FAILPOINTS", spec)]),
        None => Server::start(&args),
    }
}

/// Clients that wait out a dead server: a retry every 10-100 ms for a long while.
fn client(url: &str) -> Client {
    Client::new(url).unwrap().with_retry_policy(RetryPolicy {
        max_attempts: 2000,
        initial_backoff: Duration::from_millis(10),
        max_backoff: Duration::from_millis(100),
    })
}

fn writers(client: &Client) -> Vec<BatchWriter> {
    (0..WORKERS)
        .map(|w| client.batch_writer(FRAME, 100 + w, 0, BATCH).unwrap())
        .collect()
}

/// Every sample of every worker and phase, accumulated without interruption, and its EXR.
fn reference() -> (u64, Vec<u8>) {
    let mut state = FrameState::new(W, H, CascadeLayout::with_defaults());
    for w in 0..WORKERS {
        for p in 0..PHASES {
            state.splat_all(records(w, p).into_iter().map(|r| (r.x, r.y, r.rgb)));
        }
    }
    let params = ResolveParams::with_defaults();
    let provenance = Provenance {
        layout: state.layout(),
        params: &params,
    };
    let exr = encode_exr(&state.resolve(&params), &[], &[], &provenance).unwrap();
    (state.total_samples(), exr)
}

/// The frame behind `client` holds exactly the reference.
fn check_exact(rt: &tokio::runtime::Runtime, client: &Client, when: &str) {
    let (samples, exr) = reference();
    let info = rt.block_on(client.frame_info(FRAME)).unwrap();
    assert_eq!(info.samples, samples, "samples {when}");
    let got = rt
        .block_on(client.image(FRAME, &ImageQuery::default()))
        .unwrap();
    assert!(
        got[..] == exr[..],
        "image {when} differs from an uninterrupted run"
    );
}

/// SIGKILL after the batches of phase 1 were acknowledged but before any snapshot held them:
/// the restarted server lost exactly those batches, every worker resends exactly those, and
/// nothing counts twice.
#[test]
fn a_kill_between_acknowledgement_and_snapshot_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let rt = runtime();
    let server = start(&data, None);
    let forwarder = Forwarder::start(&server.addr);
    let client = client(&forwarder.url);
    rt.block_on(client.create_frame(&CreateFrame::new(FRAME, W, H)))
        .unwrap();

    // Phase 0 ends on disk; phase 1 is acknowledged, not durable.
    let all: Vec<u64> = (0..WORKERS).collect();
    let writers = phase(&rt, writers(&client), 0, &all);
    let mut writers = phase(&rt, writers, 1, &[]);
    for w in &writers {
        assert_eq!(
            w.unconfirmed() as u64,
            BATCHES_PER_PHASE,
            "kept until durable"
        );
    }
    server.kill();
    let server = start(&data, None);
    forwarder.point_at(Some(&server.addr));

    sync_all_resending_phase_1(&rt, &mut writers);
    let mut writers = phase(&rt, writers, 2, &all);
    check_exact(&rt, &client, "after a kill between ack and snapshot");

    // What the workers were told is durable survives another kill.
    server.kill();
    let server = start(&data, None);
    forwarder.point_at(Some(&server.addr));
    check_exact(&rt, &client, "after a kill once everything was synced");
    sync_all(&rt, &mut writers);
    assert!(
        writers.iter().all(|w| w.resent() == BATCHES_PER_PHASE),
        "nothing more was lost"
    );
    drop(server);
}

/// The server dies while writing a snapshot: the new snapshot is in `snapshot.tmp`, synced but
/// not renamed over the previous one. Recovery reads the previous snapshot, removes the
/// temporary file, and the workers' resends restore the rest, exactly once.
#[test]
fn a_crash_while_a_snapshot_is_written_recovers_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let rt = runtime();
    // The second snapshot of the frame aborts the process between writing and renaming.
    let server = start(&data, Some("snapshot.bin:before_rename=abort@2"));
    let forwarder = Forwarder::start(&server.addr);
    let client = client(&forwarder.url);
    rt.block_on(client.create_frame(&CreateFrame::new(FRAME, W, H)))
        .unwrap();

    // One sync per phase, by worker 0: phase 0 is snapshot 1.
    let writers = phase(&rt, writers(&client), 0, &[0]);
    let writers = phase(&rt, writers, 1, &[]);
    // Snapshot 2 (phase 1) aborts the server; worker 0's sync keeps retrying meanwhile.
    let syncing = {
        let mut writers = writers;
        rt.spawn(async move {
            writers[0].sync().await.unwrap();
            writers
        })
    };
    assert_eq!(server.wait_exit(), None, "the failpoint aborted the server");
    let frame_dir = data.join("frames").join(FRAME);
    assert!(
        frame_dir.join("snapshot.tmp").exists(),
        "the crash left the half-done snapshot"
    );
    let server = start(&data, None);
    forwarder.point_at(Some(&server.addr));
    let mut writers = rt.block_on(syncing).unwrap();
    assert!(
        !frame_dir.join("snapshot.tmp").exists(),
        "recovery removes the half-done snapshot"
    );

    sync_all_resending_phase_1(&rt, &mut writers);
    let all: Vec<u64> = (0..WORKERS).collect();
    phase(&rt, writers, 2, &all);
    check_exact(&rt, &client, "after a crash inside a snapshot");
    drop(server);
}
