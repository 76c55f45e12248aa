//! Push mode: a node forwards what it accumulates to an upstream splatd, as exact deltas.
//!
//! `splatd serve --upstream URL` runs [`spawn`]: every `--push-interval-ms` it looks at each
//! local frame, and when the frame changed since the last push it sends the difference
//! `delta = now - baseline` to `POST {upstream}/v1/frames/{id}/state`, where *baseline* is the
//! state as of the last push the upstream acknowledged. Cascade states add cell by cell,
//! exactly, so the upstream ends up with the sum of every node's samples, bit for bit what one
//! server receiving all of them would hold. A frame the upstream does not know (404) is created
//! there first with the local frame's parameters; if the upstream holds a frame of that id with
//! other parameters (409) the frame is not pushed, and the error is logged.
//!
//! # Exactly once
//!
//! Each delta carries an [`Origin`] `{node, seq}`: this node's id and a per-frame sequence
//! number, 0, 1, 2, ... The upstream remembers the pairs it applied and answers a repeated pair
//! with `"duplicate": true` without adding it again. So a push whose response was lost (a
//! timeout, a dropped connection, an upstream restart after applying it) is simply resent, and
//! counts once. That holds because of three rules this module keeps:
//!
//! * **A sequence number names one content.** Once a delta is encoded under `seq`, exactly
//!   those bytes are resent until the upstream acknowledges them (or recognises them as a
//!   duplicate). Samples that arrive meanwhile are not folded into it; they go into the next
//!   delta, under `seq + 1`, computed only after `seq` was acknowledged.
//! * **The baseline moves only on acknowledgement**, to exactly the state the acknowledged
//!   delta was computed from, so no sample is left out or sent twice between two deltas.
//! * **Node ids are unique per process lifetime.** Sequence numbers restart with the process
//!   (they are not persisted), so a restarted node must push under a new id, or the upstream
//!   would take its new deltas for old ones and drop them. The default id is 64 random bits
//!   chosen at start-up; `--node-id` is for logs and dashboards and must not be reused across
//!   restarts. A consequence: a node restored from a snapshot would push its restored samples
//!   again, in full, under its new id, so `splatd serve` refuses `--upstream` together with
//!   `--data-dir`: a pushing node keeps its frames in memory, and the upstream is where
//!   durability lives.
//!
//! Sequence numbers of a frame id are kept for the life of the process even when the frame is
//! deleted, so a frame deleted and created again continues its numbering (from an empty
//! baseline) instead of reusing numbers the upstream has seen.
//!
//! # Costs
//!
//! The baseline is a full copy of each pushed frame's cascades (the state's size again: 415 MB
//! for a 1080p frame with six cascades), and every round that finds a frame changed takes a
//! consistent cut of it, subtracts and encodes on the blocking pool. A delta carries only the
//! pixels that changed (the state format sends runs of non-empty pixels), so a round in which 1 %
//! of the pixels changed sends about 1 % of the state.
//!
//! # Batches in two nodes
//!
//! A delta also lists the batches it holds (those applied since the baseline). A worker whose
//! node failed may have resent a batch to another node, and then both nodes' deltas hold it; the
//! upstream refuses the second with 409 `batches_overlap` naming the batch, rather than counting
//! it twice. That refusal is counted as `refused` and logged; it needs an operator.
//!
//! Results are counted in `splatd_pushes_total{result}`: `applied`, `duplicate` (a retry that
//! had reached the upstream before), `failed` (transient; resent next round) and `refused` (the
//! upstream refused the frame or the delta; retried after [`REFUSED_RETRY`]).

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};

use bytes::Bytes;
use splatd_proto::api::CreateFrame;
use splatd_proto::{Client, ClientError, Origin, RetryPolicy};

use super::frame::ShardedFrame;
use super::AppState;
use crate::frame::dedup::Seen;
use splatd_estimator::FrameState;

/// How long a frame whose push the upstream refused (409, 4xx) is left alone before trying
/// again: such errors need an operator (delete the conflicting frame upstream, raise a limit).
pub const REFUSED_RETRY: Duration = Duration::from_secs(30);

/// Longest the final push at shutdown may take; after that the unsent deltas are given up.
pub const FINAL_PUSH_TIMEOUT: Duration = Duration::from_secs(20);

/// Where and how a node pushes.
#[derive(Debug, Clone)]
pub struct PushConfig {
    /// Base URL of the upstream splatd, e.g. `http://render-head:7878`.
    pub upstream: String,
    /// This node's id in the [`Origin`] of its deltas; unique per process lifetime.
    pub node: String,
    /// Time between two rounds.
    pub interval: Duration,
    /// Bearer token for the upstream, if it requires one.
    pub token: Option<String>,
}

impl PushConfig {
    /// A configuration with a fresh random node id and a one-second interval.
    pub fn new(upstream: impl Into<String>) -> PushConfig {
        PushConfig {
            upstream: upstream.into(),
            node: random_node_id(),
            interval: Duration::from_secs(1),
            token: None,
        }
    }

    /// The client of the upstream. Requests are retried a few times within a round; a delta
    /// still unacknowledged after that is resent by the next round anyway.
    pub fn client(&self) -> Result<Client, ClientError> {
        let client = Client::new(&self.upstream)?.with_retry_policy(RetryPolicy {
            max_attempts: 4,
            initial_backoff: Duration::from_millis(50),
            max_backoff: Duration::from_secs(1),
        });
        Ok(match &self.token {
            Some(t) => client.with_token(t.clone()),
            None => client,
        })
    }
}

/// 64 random bits as 16 hex digits: a node id no other process will pick.
pub fn random_node_id() -> String {
    format!("{:016x}", splatd_proto::ids::random_u64())
}

/// A delta with its final bytes and sequence number, not yet acknowledged.
#[derive(Debug)]
struct Pending {
    seq: u64,
    body: Bytes,
    /// The frame's state the delta was computed from: the baseline once acknowledged.
    whole: Baseline,
    /// The frame's version at that state.
    version: u64,
    /// Samples the delta adds, for the logs.
    samples: u64,
    /// The frame it was computed from.
    frame: Weak<ShardedFrame>,
    /// That frame's parameters, to create it upstream if needed.
    request: CreateFrame,
}

/// A frame as of one cut: its cells and the batches they hold.
#[derive(Debug)]
struct Baseline {
    state: FrameState,
    seen: Seen,
    /// The AOV sums, if the frame has AOVs.
    aovs: Option<splatd_estimator::AovSums>,
}

/// What this node knows about one frame id's pushes.
#[derive(Debug, Default)]
struct Track {
    /// The local frame the baseline belongs to (a deleted and re-created frame is another).
    frame: Weak<ShardedFrame>,
    /// State as of the last acknowledged push; `None` means empty.
    baseline: Option<Baseline>,
    /// The frame's version at the baseline; `None` before the first look.
    version: Option<u64>,
    /// Sequence number of the next new delta.
    next_seq: u64,
    pending: Option<Pending>,
    /// The upstream refused this frame; when to try again.
    refused_until: Option<Instant>,
}

/// What one round did, frame by frame.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct PushReport {
    /// Deltas the upstream applied.
    pub applied: u32,
    /// Deltas the upstream had applied before (a lost response, resent).
    pub duplicate: u32,
    /// Deltas that could not be delivered and stay pending.
    pub failed: u32,
    /// Frames the upstream refused (conflicting parameters and other final errors).
    pub refused: u32,
}

impl PushReport {
    /// Nothing is left to send.
    pub fn is_clean(&self) -> bool {
        self.failed == 0 && self.refused == 0
    }
}

/// How sending one delta ended.
enum Sent {
    Applied,
    Duplicate,
    Failed(ClientError),
    Refused(String),
}

/// Pushes one node's frames to its upstream.
#[derive(Debug)]
pub struct Pusher {
    app: AppState,
    client: Client,
    upstream: String,
    node: String,
    interval: Duration,
    tracks: HashMap<String, Track>,
}

impl Pusher {
    /// A pusher of `app`'s frames; fails only on an unusable upstream URL.
    pub fn new(app: AppState, cfg: &PushConfig) -> Result<Pusher, ClientError> {
        Ok(Pusher {
            client: cfg.client()?,
            upstream: cfg.upstream.clone(),
            node: cfg.node.clone(),
            interval: cfg.interval,
            tracks: HashMap::new(),
            app,
        })
    }

    /// This node's id.
    pub fn node(&self) -> &str {
        &self.node
    }

    /// One round: for every frame, resends the pending delta if there is one, then, if the
    /// frame changed, computes and sends the next one.
    ///
    /// A pending delta of a frame deleted here since is still delivered: its samples were
    /// acknowledged to workers, and its sequence number may have reached the upstream already.
    pub async fn push_once(&mut self) -> PushReport {
        let mut report = PushReport::default();
        let mut frames: BTreeMap<String, Option<Arc<ShardedFrame>>> = self
            .app
            .store
            .list()
            .into_iter()
            .map(|f| (f.id().to_owned(), Some(f)))
            .collect();
        for (id, track) in &self.tracks {
            if track.pending.is_some() {
                frames.entry(id.clone()).or_insert(None);
            }
        }
        for (id, frame) in frames {
            let track = self.tracks.entry(id.clone()).or_default();
            if track.refused_until.is_some_and(|t| Instant::now() < t) {
                report.refused += 1;
                continue;
            }
            track.refused_until = None;
            match &frame {
                Some(f) if !Weak::ptr_eq(&track.frame, &Arc::downgrade(f)) => {
                    // First look at this frame, or the id was deleted and created again:
                    // start from empty, keep the numbering.
                    track.frame = Arc::downgrade(f);
                    track.baseline = None;
                    track.version = None;
                }
                Some(_) => {}
                None => {
                    track.baseline = None;
                    track.version = None;
                }
            }
            // At most two sends per frame and round (a pending delta, then a fresh one), so a
            // frame under constant load cannot hold the round forever.
            for _ in 0..2 {
                if track.pending.is_none() {
                    let Some(f) = frame
                        .as_ref()
                        .filter(|f| track.version != Some(f.version()))
                    else {
                        break;
                    };
                    match next_delta(f, track, &self.node).await {
                        Some(p) => track.pending = Some(p),
                        None => break,
                    }
                }
                let pending = track.pending.as_ref().expect("set above");
                let result = send(&self.client, &id, pending).await;
                let acknowledged = matches!(result, Sent::Applied | Sent::Duplicate);
                let label = match result {
                    Sent::Applied | Sent::Duplicate => {
                        let duplicate = matches!(result, Sent::Duplicate);
                        let p = track.pending.take().expect("pending was just sent");
                        tracing::debug!(
                            frame = id,
                            seq = p.seq,
                            samples = p.samples,
                            duplicate,
                            "delta pushed"
                        );
                        // The frame may have been replaced while the delta was in flight; the
                        // replacement's baseline is its empty start, not this state.
                        if Weak::ptr_eq(&p.frame, &track.frame) && p.frame.strong_count() > 0 {
                            track.baseline = Some(p.whole);
                            track.version = Some(p.version);
                        }
                        if duplicate {
                            report.duplicate += 1;
                            "duplicate"
                        } else {
                            report.applied += 1;
                            "applied"
                        }
                    }
                    Sent::Failed(e) => {
                        tracing::warn!(
                            frame = id,
                            seq = pending.seq,
                            error = %e,
                            "push failed; the same delta is resent next round"
                        );
                        report.failed += 1;
                        "failed"
                    }
                    Sent::Refused(why) => {
                        tracing::error!(
                            frame = id,
                            seq = pending.seq,
                            upstream = self.upstream,
                            "upstream refused the frame; not pushing it for {} s: {why}",
                            REFUSED_RETRY.as_secs()
                        );
                        track.refused_until = Some(Instant::now() + REFUSED_RETRY);
                        report.refused += 1;
                        "refused"
                    }
                };
                metrics::counter!(crate::meters::PUSHES, "result" => label).increment(1);
                if !acknowledged {
                    break;
                }
            }
        }
        report
    }

    /// Pushes every `interval` until `stop` resolves, then once more (bounded by
    /// [`FINAL_PUSH_TIMEOUT`]), so that samples acknowledged to workers before shutdown reach the
    /// upstream. Call it after the server stopped taking requests for the final push to hold
    /// everything.
    pub async fn run_until(mut self, stop: impl Future<Output = ()>) {
        tracing::info!(node = self.node, "pushing to upstream");
        // The first round comes one interval after start, not at once (`interval` ticks
        // immediately): "every interval" then means the same thing however the runtime schedules
        // this task against the first requests.
        let mut ticks =
            tokio::time::interval_at(tokio::time::Instant::now() + self.interval, self.interval);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        tokio::pin!(stop);
        loop {
            tokio::select! {
                _ = ticks.tick() => {
                    self.push_once().await;
                }
                () = &mut stop => break,
            }
        }
        match tokio::time::timeout(FINAL_PUSH_TIMEOUT, self.final_push()).await {
            Ok(report) if report.is_clean() => tracing::info!("final push done"),
            Ok(report) => tracing::error!(
                undelivered = report.failed,
                refused = report.refused,
                "final push incomplete: the samples of these frames never reach the upstream"
            ),
            Err(_) => tracing::error!(
                "final push took longer than {}s; unsent samples are lost",
                FINAL_PUSH_TIMEOUT.as_secs()
            ),
        }
    }

    /// Rounds until nothing is pending, or a round makes no progress; the last round's report.
    async fn final_push(&mut self) -> PushReport {
        loop {
            let report = self.push_once().await;
            if report.is_clean() || report.applied + report.duplicate == 0 {
                return report;
            }
        }
    }
}

/// Starts pushing `app`'s frames to `cfg.upstream` every `cfg.interval`, forever.
pub fn spawn(app: AppState, cfg: PushConfig) -> tokio::task::JoinHandle<()> {
    spawn_until(app, cfg, std::future::pending())
}

/// Like [`spawn`], stopping (after a final push) once `stop` resolves; await the handle to
/// wait for the final push.
pub fn spawn_until(
    app: AppState,
    cfg: PushConfig,
    stop: impl Future<Output = ()> + Send + 'static,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        match Pusher::new(app, &cfg) {
            Ok(pusher) => pusher.run_until(stop).await,
            Err(e) => tracing::error!(error = %e, "push mode disabled"),
        }
    })
}

/// Cuts the frame and encodes its delta against the baseline under the next sequence number;
/// `None` when nothing changed (the baseline then moves to the cut's version).
async fn next_delta(frame: &Arc<ShardedFrame>, track: &mut Track, node: &str) -> Option<Pending> {
    let frame2 = frame.clone();
    let baseline = track.baseline.take();
    let origin = Origin {
        node: node.to_owned(),
        seq: track.next_seq,
    };
    let computed = tokio::task::spawn_blocking(move || {
        let mut cut = frame2.cut();
        let whole = Baseline {
            state: cut.whole(),
            seen: std::mem::take(&mut cut.seen),
            // The baseline outlives the cut: it owns a copy (sharing the frame's sums would
            // make every later pass copy them).
            aovs: cut.aovs.as_deref().cloned(),
        };
        let (delta, batches, aov_delta) = match &baseline {
            Some(b) => (
                whole
                    .state
                    .delta_since(&b.state)
                    .expect("a frame's states share its size and layout"),
                whole.seen.applied_since(&b.seen),
                match (&whole.aovs, &b.aovs) {
                    (Some(now), Some(then)) => Some(
                        now.delta_since(then)
                            .expect("a frame's AOV sums only grow, in one geometry"),
                    ),
                    (now, _) => now.clone(),
                },
            ),
            None => (
                whole.state.clone(),
                whole.seen.applied(),
                whole.aovs.clone(),
            ),
        };
        let samples = delta.total_samples();
        let empty = delta.cells().iter().all(|&c| c == 0);
        let specs = frame2.spec().request.aovs.as_slice();
        let aovs = aov_delta.as_ref().map(|sums| (specs, sums));
        let body = (!empty).then(|| {
            splatd_formats::state::dump(&delta, aovs, frame2.id(), Some(origin), batches).encode()
        });
        (baseline, whole, cut.version, samples, body)
    })
    .await;
    let (baseline, whole, version, samples, body) = match computed {
        Ok(c) => c,
        Err(e) => {
            tracing::error!(frame = frame.id(), error = %e, "computing a push delta failed");
            return None;
        }
    };
    track.baseline = baseline;
    let Some(body) = body else {
        track.baseline = Some(whole);
        track.version = Some(version);
        return None;
    };
    let seq = track.next_seq;
    track.next_seq += 1;
    Some(Pending {
        seq,
        body: Bytes::from(body),
        whole,
        version,
        samples,
        frame: Arc::downgrade(frame),
        request: frame.spec().request.clone(),
    })
}

/// Sends one delta, creating the frame upstream if it answers 404.
async fn send(client: &Client, id: &str, pending: &Pending) -> Sent {
    let mut created = false;
    loop {
        match client.import_state(id, pending.body.clone()).await {
            Ok(ack) if ack.duplicate => return Sent::Duplicate,
            Ok(_) => return Sent::Applied,
            Err(ClientError::Rejected { status: 404, body })
                if body.error == "unknown_frame" && !created =>
            {
                match client.create_frame(&pending.request).await {
                    Ok(_) => {
                        tracing::info!(frame = id, "created the frame upstream");
                        created = true;
                    }
                    Err(ClientError::Rejected { status, body }) => {
                        return Sent::Refused(format!(
                            "creating the frame upstream: HTTP {status} {}: {}",
                            body.error, body.message
                        ))
                    }
                    Err(e) => return Sent::Failed(e),
                }
            }
            Err(ClientError::Rejected { status, body }) => {
                return Sent::Refused(format!("HTTP {status} {}: {}", body.error, body.message))
            }
            Err(e) => return Sent::Failed(e),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_ids_are_random_hex() {
        let a = random_node_id();
        let b = random_node_id();
        assert_eq!(a.len(), 16);
        assert!(a.chars().all(|c| c.is_ascii_hexdigit()), "{a}");
        assert_ne!(a, b);
    }
}
