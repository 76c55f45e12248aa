//! `splatd serve --tev HOST:PORT`: pushes resolved frames to a running tev viewer as samples
//! arrive.
//!
//! Every `interval`, each frame whose version changed since it was last shown is resolved and
//! sent (all layers: reweighted, mean, removed) with [`crate::viewer::tev::TevSink`], one frame
//! at a time. tev not running is not an error of the server: the feed connects before it
//! resolves anything for tev, logs once per outage, and catches up with the current images when
//! tev comes back.
//!
//! Watching in tev costs what any other watcher's render costs ([`crate::render`]): each
//! update is a render on a low-priority thread, with its working memory reserved, held to the
//! frame's pace while workers keep changing it (a frame whose pace is not over is shown in a
//! later round; one that has not changed since the round before is shown at once), and it
//! brings the frame's kept resolve up to date, which it shares with images, previews and
//! figures: after a batch that changed a corner of the frame, an update resolves that corner.
//! It used to resolve every changed frame whole, every round, at the request loop's priority,
//! outside the budget and uncounted. With `loadgen --kind records` posting 256 Mi records to a
//! 3840x2160 frame (2-core VM, 2 alternated runs each), tev watching took the server's CPU
//! time from 9-10 s to 16-23 s; now to 13-16 s (8.7-12.7 s without tev). Ingest still falls
//! with tev watching a frame that size, to 0.49-0.56 of the in-process splat against
//! 0.74-0.86 without (0.40-0.54 before): each update copies the frame's state as writers
//! change it under the render's cut and sends 300 MB to tev.

pub mod tev;

use std::collections::HashMap;
use std::time::Duration;

use splatd_estimator::Resolved;

use crate::frame::ShardedFrame;
use crate::viewer::tev::TevSink;

use super::AppState;

/// Runs until `stop` changes.
pub async fn run(
    app: AppState,
    addr: String,
    interval: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    let mut sink: Option<TevSink> = None;
    // The layers last sent, kept as buffers for the next update.
    let mut layers = Resolved::default();
    // Per frame, the version shown, and the version seen in the round before.
    let mut shown: HashMap<String, u64> = HashMap::new();
    let mut seen: HashMap<String, u64> = HashMap::new();
    let mut down = false;
    loop {
        tokio::select! {
            () = tokio::time::sleep(interval) => {}
            _ = stop.changed() => return,
        }
        for frame in app.store.list() {
            let version = frame.version();
            if shown.get(frame.id()) == Some(&version) {
                continue;
            }
            let quiet = seen.insert(frame.id().to_owned(), version) == Some(version);
            if !quiet && !app.renders.due(&frame) {
                // Its pace is not over: a later round shows it.
                continue;
            }
            // Connected first, so that nothing is reserved, resolved or counted for a tev that
            // is not there; a new connection (after a failed send too) may be a new tev, which
            // gets every image created again.
            let connected = match sink.take().filter(TevSink::is_connected) {
                Some(s) => Ok(s),
                None => {
                    let target = addr.clone();
                    tokio::task::spawn_blocking(move || TevSink::connect(&target))
                        .await
                        .expect("connecting does not panic")
                }
            };
            let mut s = match connected {
                Ok(s) => s,
                Err(e) => {
                    if !down {
                        tracing::warn!(%addr, error = %e, "tev is not reachable; will retry");
                        down = true;
                    }
                    shown.clear();
                    break;
                }
            };
            let r = &frame.spec().request;
            // The frame's cut (copied as writers change it) and the kept resolve's layers,
            // then the copy of three of them sent from.
            let cost = frame.spec().memory_bytes() + u64::from(r.width) * u64::from(r.height) * 96;
            let reservation = match app.renders.budget().reserve(cost).await {
                Ok(reservation) => reservation,
                Err(busy) => {
                    tracing::warn!(frame = frame.id(), error = %busy, "tev update postponed");
                    sink = Some(s);
                    continue;
                }
            };
            let (threads, params) = (app.resolve_threads, frame.spec().resolve);
            let kept = app.renders.kept().clone();
            let mut buffers = std::mem::take(&mut layers);
            let update = move |f: &ShardedFrame, wanted| {
                // Sent from a copy: a slow tev must not hold up the frame's other renders.
                kept.with_resolved_since(f, &params, threads, wanted, |resolved, _| {
                    copy_layers(resolved, &mut buffers)
                });
                let result = s.show(f.id(), &buffers);
                (s, buffers, result)
            };
            let (s, buffers, result) = app.renders.background(&frame, reservation, update).await;
            (sink, layers) = (Some(s), buffers);
            match result {
                Ok(()) => {
                    shown.insert(frame.id().to_owned(), version);
                    metrics::counter!(crate::meters::TEV_UPDATES).increment(1);
                    if down {
                        tracing::info!(%addr, "tev reachable again");
                        down = false;
                    }
                }
                Err(e) => {
                    // The next update connects again.
                    if !down {
                        tracing::warn!(%addr, error = %e, "sending to tev failed");
                        down = true;
                    }
                }
            }
        }
        // Forget deleted frames.
        let ids: std::collections::HashSet<String> =
            app.store.list().iter().map(|f| f.id().to_owned()).collect();
        shown.retain(|id, _| ids.contains(id));
        seen.retain(|id, _| ids.contains(id));
    }
}

/// Copies the layers tev shows into `to`, into the buffers it holds.
fn copy_layers(from: &Resolved, to: &mut Resolved) {
    (to.width, to.height) = (from.width, from.height);
    to.reweighted.clone_from(&from.reweighted);
    to.mean.clone_from(&from.mean);
    to.removed.clone_from(&from.removed);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{testing, Limits};
    use splatd_proto::{Batch, Record};
    use std::io::Read;
    use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering::SeqCst};
    use std::sync::Arc;

    /// A tev stand-in on loopback: accepts connections and reads what each sends, counting
    /// both, until `done` is set.
    struct StandIn {
        addr: String,
        connections: Arc<AtomicUsize>,
        bytes: Arc<AtomicU64>,
        done: Arc<AtomicBool>,
    }

    impl StandIn {
        fn start() -> StandIn {
            let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            listener.set_nonblocking(true).unwrap();
            let tev = StandIn {
                addr: listener.local_addr().unwrap().to_string(),
                connections: Arc::default(),
                bytes: Arc::default(),
                done: Arc::default(),
            };
            let (connections, bytes, done) =
                (tev.connections.clone(), tev.bytes.clone(), tev.done.clone());
            std::thread::spawn(move || {
                while !done.load(SeqCst) {
                    let Ok((mut stream, _)) = listener.accept() else {
                        std::thread::sleep(Duration::from_millis(2));
                        continue;
                    };
                    connections.fetch_add(1, SeqCst);
                    stream.set_nonblocking(false).unwrap();
                    let bytes = bytes.clone();
                    // Ends when the feed closes the connection.
                    std::thread::spawn(move || {
                        let mut buf = vec![0u8; 1 << 16];
                        while let Ok(n @ 1..) = stream.read(&mut buf) {
                            bytes.fetch_add(n as u64, SeqCst);
                        }
                    });
                }
            });
            tev
        }
    }

    impl Drop for StandIn {
        fn drop(&mut self) {
            self.done.store(true, SeqCst);
        }
    }

    fn post(frame: &ShardedFrame, seq: u64) {
        let records = (0..16)
            .map(|i| Record::new(i % 8, i / 8, [1.0 + seq as f32, 2.0, 3.0]))
            .collect();
        frame
            .ingest(&Batch::new("f", 1, seq, records).unwrap())
            .unwrap();
    }

    /// Waits until `done`, for 10 s at most.
    async fn until(what: &str, done: impl Fn() -> bool) {
        for _ in 0..2000 {
            if done() {
                return;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        panic!("{what}: not within 10 s");
    }

    /// With no tev listening, the feed tries to connect every round and does nothing else: no
    /// render is counted, reserved or run, nothing is resolved.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn without_tev_nothing_is_rendered() {
        // An address nothing listens on: connections to it are refused.
        let addr = {
            let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            listener.local_addr().unwrap().to_string()
        };
        let app = testing::with_frame(AppState::new(Limits::default(), None, None), "f", 8, 8);
        let frame = app.store.get("f").unwrap();
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let feed = tokio::spawn(run(app.clone(), addr, Duration::from_millis(5), stopped));
        // Some 40 rounds, the frame changing between them.
        for seq in 0..40 {
            post(&frame, seq);
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        stop.send(true).unwrap();
        feed.await.unwrap();
        assert_eq!(app.renders.rendered(), 0, "renders");
        let kept = app.renders.kept();
        assert_eq!(kept.whole() + kept.patched(), 0, "resolves");
        assert_eq!(app.renders.budget().used(), 0, "working memory reserved");
    }

    /// While workers keep changing a frame whose render pace is not over, the feed skips the
    /// frame round after round, keeping its connection to tev (tev would lose the image's
    /// place and be sent a new one each time), and shows the frame once it goes quiet.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_frame_held_to_its_pace_is_skipped_on_the_same_connection_until_quiet() {
        let tev = StandIn::start();
        let app = testing::with_frame(AppState::new(Limits::default(), None, None), "f", 8, 8);
        let frame = app.store.get("f").unwrap();
        post(&frame, 0);
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let feed = tokio::spawn(run(
            app.clone(),
            tev.addr.clone(),
            Duration::from_millis(20),
            stopped,
        ));
        until("the first update", || tev.bytes.load(SeqCst) > 0).await;

        // As after a render of 1000 s: the frame's pace, 4000 s at the default share, holds
        // every render of it while it changes.
        let paces = app.renders.paces();
        let now = tokio::time::Instant::now();
        paces.rendered(&frame, frame.version(), now, Duration::from_secs(1000));
        for seq in 1..=60 {
            post(&frame, seq);
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let (renders, bytes) = (app.renders.rendered(), tev.bytes.load(SeqCst));
        until("an update once the frame is quiet", || {
            app.renders.rendered() > renders && tev.bytes.load(SeqCst) > bytes
        })
        .await;
        assert_eq!(tev.connections.load(SeqCst), 1, "one connection to tev");
        stop.send(true).unwrap();
        feed.await.unwrap();
    }
}
