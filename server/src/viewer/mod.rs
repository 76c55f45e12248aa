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
use std::sync::{Arc, Mutex};
use std::time::Duration;

use splatd_estimator::Resolved;

use crate::viewer::tev::{TevError, TevSink};

use super::AppState;

/// The connection to tev and the layers last sent, kept for the next update.
#[derive(Default)]
struct Feed {
    sink: Option<TevSink>,
    layers: Resolved,
}

impl Feed {
    /// Connects to tev at `addr` unless connected (a new connection, after a failed send too,
    /// may be a new tev, which gets every image created again), then fills the layers with
    /// `fill` and shows them as tev's image `name`. So nothing is resolved for a tev that is
    /// not there.
    fn update(
        &mut self,
        addr: &str,
        name: &str,
        fill: impl FnOnce(&mut Resolved),
    ) -> Result<(), TevError> {
        let sink = match self.sink.take().filter(TevSink::is_connected) {
            Some(sink) => self.sink.insert(sink),
            None => self.sink.insert(TevSink::connect(addr)?),
        };
        fill(&mut self.layers);
        sink.show(name, &self.layers)
    }
}

/// Runs until `stop` changes.
pub async fn run(
    app: AppState,
    addr: String,
    interval: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    // Used by one update at a time, on its render thread.
    let feed = Arc::new(Mutex::new(Feed::default()));
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
            let threads = app.resolve_threads;
            let params = frame.spec().resolve;
            let kept = app.renders.kept().clone();
            let (target, feed) = (addr.clone(), feed.clone());
            let r = &frame.spec().request;
            // The frame's cut (copied as writers change it) and the kept resolve's layers,
            // then the copy of three of them sent from.
            let cost = frame.spec().memory_bytes() + u64::from(r.width) * u64::from(r.height) * 96;
            let update = app
                .renders
                .render_if_due(&frame, quiet, cost, move |f, wanted| {
                    let mut feed = feed.lock().unwrap_or_else(|e| e.into_inner());
                    // Sent from a copy: a slow tev must not hold up the frame's other renders.
                    feed.update(&target, f.id(), |layers| {
                        kept.with_resolved_since(f, &params, threads, wanted, |resolved, _| {
                            copy_layers(resolved, layers)
                        })
                    })
                });
            let result = match update.await {
                Ok(Some(result)) => result,
                // Its pace is not over: a later round shows it.
                Ok(None) => continue,
                Err(busy) => {
                    tracing::warn!(frame = frame.id(), error = %busy, "tev update postponed");
                    continue;
                }
            };
            match result {
                Ok(()) => {
                    shown.insert(frame.id().to_owned(), version);
                    metrics::counter!(crate::meters::TEV_UPDATES).increment(1);
                    if down {
                        tracing::info!(%addr, "tev reachable again");
                        down = false;
                    }
                }
                Err(e @ TevError::Connect { .. }) => {
                    if !down {
                        tracing::warn!(%addr, error = %e, "tev is not reachable; will retry");
                        down = true;
                    }
                    shown.clear();
                    break;
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
    use crate::frame::ShardedFrame;
    use crate::{testing, Limits};
    use splatd_proto::{Batch, Record};
    use std::io::Read;
    use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering::SeqCst};

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
