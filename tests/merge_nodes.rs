//! Partial cascades from many machines merge exactly: three real `splatd serve` processes each
//! receive a third of one sample set, and their states, pulled, pushed or merged offline, resolve
//! to the very bytes a single server receiving every sample serves.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::common;
use crate::common::{runtime, Server, ServerProcess};
use bytes::Bytes;
use splatd_proto::api::{CascadeParams, CreateFrame, ImageQuery};
use splatd_proto::{Batch, Client, ClientError, Origin, Record, StateDump};
use splatd_scenes::synth::FireflyScene;

const W: u32 = 40;
const H: u32 = 28;
const PASSES: u64 = 24;
const FRAME: &str = "merge.f";
/// Concurrent clients per node.
const CLIENTS: u64 = 2;

fn scene() -> FireflyScene {
    FireflyScene::new(W, H, 2024)
}

fn create() -> CreateFrame {
    CreateFrame::new(FRAME, W, H)
}

fn total_samples() -> u64 {
    PASSES * (W * H) as u64
}

/// The image query compared everywhere: the resolved layers plus one raw layer per cascade, so
/// any difference in any cascade shows.
fn all_layers() -> ImageQuery {
    ImageQuery {
        cascades: true,
        ..ImageQuery::default()
    }
}

/// Posts `passes` of the scene to frame `FRAME` at `client`, from `CLIENTS` concurrent tasks with
/// their own worker ids, in batches that cut passes at odd places.
async fn post_passes(client: &Client, passes: Vec<u64>, worker_base: u64) {
    let scene = scene();
    let mut tasks = Vec::new();
    for c in 0..CLIENTS {
        let client = client.clone();
        let mine: Vec<u64> = passes
            .iter()
            .copied()
            .skip(c as usize)
            .step_by(CLIENTS as usize)
            .collect();
        tasks.push(tokio::spawn(async move {
            let mut seq = 0;
            for pass in mine {
                let records: Vec<Record> = scene
                    .pass(pass)
                    .map(|(x, y, rgb)| Record::new(x, y, rgb))
                    .collect();
                for chunk in records.chunks(347) {
                    let batch = Batch::new(FRAME, worker_base + c, seq, chunk.to_vec()).unwrap();
                    seq += 1;
                    let ack = client.post_batch(&batch).await.unwrap();
                    assert_eq!(ack.accepted, chunk.len() as u64);
                }
            }
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
}

/// Creates `FRAME` on every node and posts pass `p` to node `p % nodes.len()`, all nodes at once.
async fn post_split(nodes: &[Client]) {
    for n in nodes {
        n.create_frame(&create()).await.unwrap();
    }
    let k = nodes.len() as u64;
    let mut all = Vec::new();
    for (i, n) in nodes.iter().enumerate() {
        let passes: Vec<u64> = (0..PASSES).filter(|p| p % k == i as u64).collect();
        let n = n.clone();
        all.push(tokio::spawn(async move {
            post_passes(&n, passes, 100 * (i as u64 + 1)).await
        }));
    }
    for t in all {
        t.await.unwrap();
    }
}

/// A single node that received every sample: the reference images (all layers, and plain).
fn reference_images(rt: &tokio::runtime::Runtime) -> (Bytes, Bytes) {
    let single = Server::start(&[]);
    let client = Client::new(&single.url).unwrap();
    rt.block_on(async {
        client.create_frame(&create()).await.unwrap();
        post_passes(&client, (0..PASSES).collect(), 1).await;
        let info = client.frame_info(FRAME).await.unwrap();
        assert_eq!(info.samples, total_samples());
        let layers = client.image(FRAME, &all_layers()).await.unwrap();
        let plain = client.image(FRAME, &ImageQuery::default()).await.unwrap();
        (layers, plain)
    })
}

fn rejected(e: ClientError) -> (u16, String, String) {
    match e {
        ClientError::Rejected { status, body } => (status, body.error, body.message),
        other => panic!("expected a refusal, got {other}"),
    }
}

/// A state body renamed to another frame, optionally carrying a push origin.
fn retarget(state: &[u8], frame: &str, origin: Option<Origin>) -> Bytes {
    let mut dump = StateDump::decode(state, u64::MAX).unwrap();
    dump.frame = frame.to_owned();
    dump.origin = origin;
    Bytes::from(dump.encode())
}

/// Pull: states exported from three nodes and imported into a fourth resolve to the single
/// node's EXR byte for byte; so does `splatd merge` of the three state files followed by
/// `splatd resolve`. A delta replayed under the same origin counts once, and states or frames
/// with other parameters are refused by name without changing anything.
#[test]
fn pulled_and_offline_merges_equal_one_node() {
    let rt = runtime();
    let (reference, reference_plain) = reference_images(&rt);
    let nodes: Vec<ServerProcess> = (0..3).map(|_| Server::start(&[])).collect();
    let clients: Vec<Client> = nodes.iter().map(|n| Client::new(&n.url).unwrap()).collect();
    let merged = Server::start(&[]);
    let target = Client::new(&merged.url).unwrap();

    let states: Vec<Bytes> = rt.block_on(async {
        post_split(&clients).await;
        let mut states = Vec::new();
        for c in &clients {
            let info = c.frame_info(FRAME).await.unwrap();
            assert_eq!(info.samples, total_samples() / 3, "each node holds a third");
            assert_ne!(
                c.image(FRAME, &all_layers()).await.unwrap(),
                reference,
                "a third alone must not already look like the whole"
            );
            states.push(c.export_state(FRAME).await.unwrap());
        }
        states
    });

    // (a) pull: export from each, import into node 4.
    rt.block_on(async {
        target.create_frame(&create()).await.unwrap();
        for s in &states {
            let ack = target.import_state(FRAME, s.clone()).await.unwrap();
            assert!(!ack.duplicate);
            assert_eq!(ack.samples, total_samples() / 3);
        }
        let info = target.frame_info(FRAME).await.unwrap();
        assert_eq!(info.samples, total_samples());
        assert_eq!((info.spp_min, info.spp_max), (PASSES, PASSES));
        let got = target.image(FRAME, &all_layers()).await.unwrap();
        assert!(
            got == reference,
            "EXR of the pulled merge differs from the single node's"
        );
    });

    // Offline: `splatd merge` of the three files, then `splatd resolve`.
    let dir = tempfile::tempdir().unwrap();
    let mut files = Vec::new();
    for (i, s) in states.iter().enumerate() {
        let path = dir.path().join(format!("node{i}.state"));
        std::fs::write(&path, s).unwrap();
        files.push(path);
    }
    let merged_file = dir.path().join("merged.state");
    let exr = dir.path().join("merged.exr");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_splatd"))
        .arg("merge")
        .args(&files)
        .arg("-o")
        .arg(&merged_file)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "splatd merge failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_splatd"))
        .arg("resolve")
        .arg(&merged_file)
        .arg("-o")
        .arg(&exr)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "splatd resolve failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        std::fs::read(&exr).unwrap() == reference_plain[..],
        "offline merge + resolve differs from the single node's EXR"
    );
    let merged_state = std::fs::read(&merged_file).unwrap();
    let pulled_state = rt.block_on(target.export_state(FRAME)).unwrap();
    assert!(
        merged_state == pulled_state[..],
        "the offline merged state differs from the pulled one"
    );

    // A delta sent twice under one origin (a retried push) counts once.
    rt.block_on(async {
        let mut dup = create();
        dup.id = "dup.f".into();
        target.create_frame(&dup).await.unwrap();
        let origin = Origin {
            node: "replayed-node".into(),
            seq: 0,
        };
        let delta = retarget(&states[0], "dup.f", Some(origin));
        let first = target.import_state("dup.f", delta.clone()).await.unwrap();
        assert!(!first.duplicate);
        assert_eq!(first.samples, total_samples() / 3);
        let image = target.image("dup.f", &all_layers()).await.unwrap();
        let again = target.import_state("dup.f", delta).await.unwrap();
        assert!(again.duplicate, "a resent delta must be recognised");
        assert_eq!(again.samples, 0);
        let info = target.frame_info("dup.f").await.unwrap();
        assert_eq!(
            info.samples,
            total_samples() / 3,
            "the resent delta was added"
        );
        assert!(
            target.image("dup.f", &all_layers()).await.unwrap() == image,
            "the resent delta changed the image"
        );
        // The same origin with another seq is another delta.
        let next = retarget(
            &states[1],
            "dup.f",
            Some(Origin {
                node: "replayed-node".into(),
                seq: 1,
            }),
        );
        assert!(!target.import_state("dup.f", next).await.unwrap().duplicate);
        let info = target.frame_info("dup.f").await.unwrap();
        assert_eq!(info.samples, 2 * total_samples() / 3);
    });

    // Other parameters are refused, by name, and change nothing.
    rt.block_on(async {
        let mut wide = create();
        wide.id = "wrong.size".into();
        wide.width = W + 1;
        target.create_frame(&wide).await.unwrap();
        let err = target
            .import_state("wrong.size", retarget(&states[0], "wrong.size", None))
            .await
            .unwrap_err();
        let (status, code, message) = rejected(err);
        assert_eq!(
            (status, code.as_str()),
            (409, "state_mismatch"),
            "{message}"
        );
        assert!(
            message.contains(&format!("{}x{H}", W + 1)) && message.contains(&format!("{W}x{H}")),
            "the refusal should name both sizes: {message}"
        );
        let info = target.frame_info("wrong.size").await.unwrap();
        assert_eq!((info.samples, info.spp_max), (0, 0));

        let mut layered = create();
        layered.id = "wrong.layout".into();
        layered.cascades = CascadeParams {
            cascades: 8,
            ..CascadeParams::default()
        };
        target.create_frame(&layered).await.unwrap();
        let err = target
            .import_state("wrong.layout", retarget(&states[0], "wrong.layout", None))
            .await
            .unwrap_err();
        let (status, code, message) = rejected(err);
        assert_eq!(
            (status, code.as_str()),
            (409, "state_mismatch"),
            "{message}"
        );
        assert!(message.contains("cascade layout"), "{message}");
        assert_eq!(target.frame_info("wrong.layout").await.unwrap().samples, 0);

        // Creating the merge frame again with other parameters is refused too.
        let mut other = create();
        other.height = H + 2;
        let (status, code, message) = rejected(target.create_frame(&other).await.unwrap_err());
        assert_eq!((status, code.as_str()), (409, "frame_exists"), "{message}");
        assert!(message.contains("size"), "{message}");
        let got = target.image(FRAME, &all_layers()).await.unwrap();
        assert!(got == reference, "refusals changed the merged frame");
    });
}

/// A TCP proxy in front of one splatd, one request per connection, that loses the response of
/// the first state import the upstream applied: the import happened, but the sender sees its
/// connection close and has to retry.
struct LossyProxy {
    url: String,
    dropped: Arc<AtomicU32>,
}

impl LossyProxy {
    fn start(upstream: String) -> LossyProxy {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let dropped = Arc::new(AtomicU32::new(0));
        let counter = dropped.clone();
        // Plain threads: the proxy lives as long as the test process, which is short.
        std::thread::spawn(move || {
            for conn in listener.incoming() {
                let Ok(conn) = conn else { return };
                let (upstream, counter) = (upstream.clone(), counter.clone());
                std::thread::spawn(move || {
                    let _ = relay(conn, &upstream, &counter);
                });
            }
        });
        LossyProxy { url, dropped }
    }
}

/// Relays one request (headers plus a `Content-Length` body) and its response.
fn relay(mut conn: TcpStream, upstream: &str, dropped: &AtomicU32) -> std::io::Result<()> {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 16 * 1024];
    let head_end = loop {
        if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break i + 4;
        }
        let n = conn.read(&mut chunk)?;
        if n == 0 {
            return Ok(());
        }
        buf.extend_from_slice(&chunk[..n]);
    };
    let head = String::from_utf8_lossy(&buf[..head_end]).into_owned();
    let mut lines = head.split("\r\n");
    let request_line = lines.next().unwrap_or("").to_owned();
    let mut length = 0usize;
    let mut forwarded = format!("{request_line}\r\nconnection: close\r\n");
    for line in lines.filter(|l| !l.is_empty()) {
        let lower = line.to_ascii_lowercase();
        if let Some(v) = lower.strip_prefix("content-length:") {
            length = v.trim().parse().unwrap_or(0);
        }
        if !lower.starts_with("connection:") {
            forwarded.push_str(line);
            forwarded.push_str("\r\n");
        }
    }
    forwarded.push_str("\r\n");
    while buf.len() < head_end + length {
        let n = conn.read(&mut chunk)?;
        if n == 0 {
            return Ok(());
        }
        buf.extend_from_slice(&chunk[..n]);
    }
    let mut up = TcpStream::connect(upstream)?;
    up.write_all(forwarded.as_bytes())?;
    up.write_all(&buf[head_end..head_end + length])?;
    let mut response = Vec::new();
    up.read_to_end(&mut response)?;
    let is_import = request_line.starts_with("POST ") && request_line.contains("/state ");
    if is_import
        && response.starts_with(b"HTTP/1.1 200")
        && dropped
            .compare_exchange(0, 1, Ordering::SeqCst, Ordering::SeqCst)
            .is_ok()
    {
        // Applied upstream; the sender never hears of it.
        return Ok(());
    }
    conn.write_all(&response)?;
    conn.shutdown(std::net::Shutdown::Both)
}

/// The value of one Prometheus series (0 when absent).
async fn metric(url: &str, series: &str) -> f64 {
    let text = reqwest::get(format!("{url}/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    text.lines()
        .filter_map(|l| l.strip_prefix(series))
        .filter_map(|rest| rest.trim().parse::<f64>().ok())
        .sum()
}

/// Push: three nodes started with `--upstream` push deltas while samples arrive; the upstream
/// ends up with every sample exactly once, and its EXR is the single node's byte for byte. One
/// node pushes through a proxy that loses the response of an applied delta: the node resends the
/// same delta, which the upstream recognises and does not add again. A frame whose parameters
/// conflict with the upstream's is not pushed and changes nothing there.
#[test]
fn pushed_deltas_aggregate_exactly_once() {
    let rt = runtime();
    let (reference, _) = reference_images(&rt);
    // Declared first, dropped last: the pushers' final pushes at shutdown still reach it.
    let upstream = Server::start(&[]);
    let head = Client::new(&upstream.url).unwrap();
    let proxy = LossyProxy::start(upstream.addr.clone());
    let push_args = |url: &str, node: &str| -> Vec<String> {
        [
            "--upstream",
            url,
            "--push-interval-ms",
            "100",
            "--node-id",
            node,
        ]
        .map(str::to_owned)
        .to_vec()
    };
    let nodes: Vec<ServerProcess> = [
        push_args(&proxy.url, "node-a"),
        push_args(&upstream.url, "node-b"),
        push_args(&upstream.url, "node-c"),
    ]
    .iter()
    .map(|args| Server::start(&args.iter().map(String::as_str).collect::<Vec<_>>()))
    .collect();
    let clients: Vec<Client> = nodes.iter().map(|n| Client::new(&n.url).unwrap()).collect();

    rt.block_on(async {
        // A frame the upstream holds with other parameters: pushes of it must be refused.
        let conflict = CreateFrame::new("conflict.f", 8, 8);
        head.create_frame(&conflict).await.unwrap();
        let local = CreateFrame::new("conflict.f", 7, 8);
        clients[1].create_frame(&local).await.unwrap();
        let batch = Batch::new("conflict.f", 5, 0, vec![Record::new(1, 1, [1.0; 3])]).unwrap();
        clients[1].post_batch(&batch).await.unwrap();

        post_split(&clients).await;

        let deadline = Instant::now() + common::PATIENCE;
        loop {
            match head.frame_info(FRAME).await {
                Ok(info) if info.samples == total_samples() => break,
                Ok(info) => assert!(
                    info.samples < total_samples(),
                    "upstream holds {} samples, more than the {} sent",
                    info.samples,
                    total_samples()
                ),
                Err(ClientError::Rejected { status: 404, .. }) => {}
                Err(e) => panic!("{e}"),
            }
            assert!(
                Instant::now() < deadline,
                "the upstream did not receive every sample in time"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let info = head.frame_info(FRAME).await.unwrap();
        assert_eq!(info.samples, total_samples());
        assert_eq!((info.spp_min, info.spp_max), (PASSES, PASSES));
        let got = head.image(FRAME, &all_layers()).await.unwrap();
        assert!(
            got == reference,
            "EXR of the pushed merge differs from the single node's"
        );

        assert_eq!(
            proxy.dropped.load(Ordering::SeqCst),
            1,
            "the proxy should have lost one response"
        );
        // The delta whose answer the proxy lost is resent on node-a's next round: wait for it.
        let deadline = Instant::now() + common::PATIENCE;
        while metric(&nodes[0].url, "splatd_pushes_total{result=\"duplicate\"}").await < 1.0 {
            assert!(
                Instant::now() < deadline,
                "node-a never resent the lost delta"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let dup_upstream =
            metric(&upstream.url, "splatd_imports_total{result=\"duplicate\"}").await;
        assert!(
            dup_upstream >= 1.0,
            "the upstream never saw the resent delta"
        );
        let dup_node = metric(&nodes[0].url, "splatd_pushes_total{result=\"duplicate\"}").await;
        assert!(dup_node >= 1.0, "node-a never counted a duplicate push");

        let info = head.frame_info("conflict.f").await.unwrap();
        assert_eq!(
            (info.width, info.samples),
            (8, 0),
            "a conflicting frame was pushed"
        );
        // (The refusal is the upstream's 409 state_mismatch; node-b logs it.)
        let refused = metric(&nodes[1].url, "splatd_pushes_total{result=\"refused\"}").await;
        assert!(refused >= 1.0, "node-b did not count the refused push");
    });

    // No push may count twice. Stopping the nodes ends with their final pushes, so once they
    // have exited nothing is in flight, and a spurious extra push would have landed.
    for node in nodes {
        node.terminate();
    }
    let info = rt.block_on(head.frame_info(FRAME)).unwrap();
    assert_eq!(
        info.samples,
        total_samples(),
        "samples after the nodes stopped"
    );
    let got = rt.block_on(head.image(FRAME, &all_layers())).unwrap();
    assert!(got == reference, "EXR after the nodes stopped differs");
}

/// SIGTERM on a pushing node makes a final push after the last request was answered: samples
/// acknowledged to workers reach the upstream even if the next round was minutes away.
#[test]
fn final_push_at_shutdown_delivers_everything() {
    let rt = runtime();
    let upstream = Server::start(&[]);
    let node = Server::start(&["--upstream", &upstream.url, "--push-interval-ms", "600000"]);
    let head = Client::new(&upstream.url).unwrap();
    let local = Client::new(&node.url).unwrap();
    let state = rt.block_on(async {
        local.create_frame(&create()).await.unwrap();
        post_passes(&local, (0..PASSES).collect(), 7).await;
        local.export_state(FRAME).await.unwrap()
    });
    assert!(
        matches!(
            rt.block_on(head.frame_info(FRAME)),
            Err(ClientError::Rejected { status: 404, .. })
        ),
        "the node pushed before its first interval ended"
    );
    assert_eq!(
        node.terminate(),
        Some(0),
        "the pushing node did not exit cleanly"
    );
    let pushed = rt.block_on(head.export_state(FRAME)).unwrap();
    assert!(
        pushed == state,
        "the upstream's state after the final push differs from the node's"
    );
}
