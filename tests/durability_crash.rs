//! A durable server killed with SIGKILL at random moments, and in the middle of writing
//! snapshots, while 8 workers that retry keep posting: the final image is bit-identical to an
//! uninterrupted run of the same samples, with no batch lost and none counted twice.

mod common;

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::{free_port, runtime, Server};
use splatd_estimator::{CascadeLayout, FrameState, ResolveParams};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Client, Record, RetryPolicy};
use splatd_scenes::synth::{FireflyScene, SplitMix64};
use splatd_server::image::encode_exr;

const WORKERS: u64 = 8;
const BATCH: usize = 700;

/// How the killer picks its moments.
#[derive(Clone, Copy, Debug)]
enum Moments {
    /// After a random 150-600 ms of running.
    Random,
    /// As soon as a snapshot file is being written (`snapshot.tmp` exists).
    DuringSnapshot,
}

struct Outcome {
    kills: u32,
    resent: u64,
    samples: u64,
    expected: u64,
}

fn run(size: (u32, u32), passes: u64, kills: u32, moments: Moments, seed: u64) -> Outcome {
    let (w, h) = size;
    let scene = FireflyScene::new(w, h, seed);
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let data_arg = data.to_str().unwrap().to_owned();
    let addr = format!("127.0.0.1:{}", free_port());
    let args = ["--data-dir", &data_arg, "--snapshot-interval-ms", "40"];
    let mut server = Some(Server::start_at(&addr, &args, &[]));
    let url = format!("http://{addr}");
    let rt = runtime();
    let patient = RetryPolicy {
        max_attempts: 400,
        initial_backoff: Duration::from_millis(10),
        max_backoff: Duration::from_millis(50),
    };
    let client = Client::new(&url).unwrap().with_retry_policy(patient);
    rt.block_on(client.create_frame(&CreateFrame::new("crash", w, h)))
        .unwrap();

    // Eight workers, each sending its share of passes through a BatchWriter that keeps batches
    // until they are durable, then syncing.
    let done = Arc::new(AtomicBool::new(false));
    let mut workers = Vec::new();
    for worker in 0..WORKERS {
        let client = client.clone();
        let records: Vec<Record> = (worker..passes)
            .step_by(WORKERS as usize)
            .flat_map(|p| scene.pass(p).collect::<Vec<_>>())
            .map(|(x, y, rgb)| Record::new(x, y, rgb))
            .collect();
        workers.push(rt.spawn(async move {
            let mut writer = client
                .batch_writer("crash", 100 + worker, 0, BATCH)
                .unwrap();
            for chunk in records.chunks(BATCH) {
                writer.extend(chunk.iter().copied()).await.unwrap();
                // Pace the workers so the kills land in the middle of the stream.
                tokio::time::sleep(Duration::from_millis(3)).await;
            }
            writer.sync().await.unwrap();
            writer.resent()
        }));
    }

    // The killer.
    let mut rng = SplitMix64::new(seed ^ 0xdead);
    let mut kill_count = 0;
    let snapshot_tmp = data.join("frames/crash/snapshot.tmp");
    while kill_count < kills {
        let deadline = match moments {
            Moments::Random => Instant::now() + Duration::from_millis(150 + rng.next_u64() % 450),
            Moments::DuringSnapshot => Instant::now() + Duration::from_secs(20),
        };
        loop {
            if Instant::now() >= deadline {
                break;
            }
            if matches!(moments, Moments::DuringSnapshot) && snapshot_tmp.exists() {
                break;
            }
            std::thread::sleep(Duration::from_micros(200));
        }
        let caught_tmp = snapshot_tmp.exists();
        server.take().unwrap().kill();
        kill_count += 1;
        if matches!(moments, Moments::DuringSnapshot) {
            assert!(caught_tmp, "the kill did not land during a snapshot");
        }
        std::thread::sleep(Duration::from_millis(rng.next_u64() % 100));
        server = Some(Server::start_at(&addr, &args, &[]));
    }
    let resent: u64 = workers.into_iter().map(|w| rt.block_on(w).unwrap()).sum();
    done.store(true, Ordering::Relaxed);

    // One more crash after everyone synced: what they were told is durable must be.
    server.take().unwrap().kill();
    let _server = Server::start_at(&addr, &args, &[]);
    let info = rt.block_on(client.frame_info("crash")).unwrap();
    let got = rt
        .block_on(client.image("crash", &ImageQuery::default()))
        .unwrap();

    let mut reference = FrameState::new(w, h, CascadeLayout::with_defaults());
    for pass in 0..passes {
        reference.splat_all(scene.pass(pass));
    }
    let expected = encode_exr(&reference.resolve(&ResolveParams::with_defaults()), &[]).unwrap();
    let outcome = Outcome {
        kills: kill_count,
        resent,
        samples: info.samples,
        expected: reference.total_samples(),
    };
    assert_eq!(
        outcome.samples, outcome.expected,
        "samples after {kill_count} kills"
    );
    assert!(
        got[..] == expected[..],
        "image after {kill_count} kills differs from an uninterrupted run"
    );
    check_no_leftovers(&data);
    outcome
}

fn check_no_leftovers(data: &Path) {
    let tmp = data.join("frames/crash/snapshot.tmp");
    // A leftover from the last kill is removed on recovery.
    assert!(!tmp.exists(), "{} left behind", tmp.display());
}

fn report(name: &str, o: &Outcome) {
    let batches = o.expected / BATCH as u64;
    println!(
        "{name}: kills {}, batches resent after restarts {}, batches lost {}, batches counted \
         twice {} (about {batches} batches, {} samples)",
        o.kills,
        o.resent,
        o.expected.saturating_sub(o.samples).div_ceil(BATCH as u64),
        o.samples.saturating_sub(o.expected).div_ceil(BATCH as u64),
        o.expected
    );
}

#[test]
fn sigkill_at_random_moments_loses_nothing_and_counts_nothing_twice() {
    let o = run((64, 48), 96, 5, Moments::Random, 1);
    report("random kills", &o);
    assert!(o.resent > 0, "no kill landed between an ack and a snapshot");
}

#[test]
fn sigkill_while_a_snapshot_is_written_recovers_exactly() {
    // A larger frame, so writing a snapshot takes long enough to be caught in the act.
    let o = run((256, 192), 24, 3, Moments::DuringSnapshot, 2);
    report("kills during snapshots", &o);
}
