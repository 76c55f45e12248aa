//! [`Outbox`]: the worker's side of the durability contract (feature `client`;
//! `PROTOCOL.md`, "Exactly-once and durability"), written once for every kind
//! of body a worker posts: record batches and rendered passes.
//!
//! A `200` from a durable server means *applied*, not *on disk*: a server
//! killed before its next snapshot comes back without what it applied since.
//! So the outbox keeps every body it posted until the server reports it
//! durable (the acknowledgement's `durable_floor` passes its sequence number,
//! or a sync of the same server process answers `durable`), and when an answer
//! comes from another server process (`boot` changed) it resends what it kept,
//! byte for byte: what the snapshot held is answered `duplicate`, the rest is
//! applied. What [`Outbox::sync`] returns for is on disk, exactly once, across
//! any number of restarts. The Python client's `Outbox` is the same logic.

use std::collections::BTreeMap;
use std::path::PathBuf;

use bytes::Bytes;

use crate::api::{BatchAck, SyncAck};
use crate::batch::validate_frame_id;
use crate::client::{Client, ClientError};

/// How many server restarts one call rides out before it gives up.
const MAX_RESTARTS: usize = 16;

/// Bodies kept in memory before the outbox syncs by itself, by default.
pub const DEFAULT_MAX_KEPT_BYTES: usize = 256 << 20;

/// What a kept body is, so that it can be sent again.
#[derive(Debug, Clone)]
enum Route {
    /// `POST .../samples`: an encoded batch.
    Samples,
    /// `POST .../passes`, with the beauty's layer if one was named.
    Pass { layer: Option<String> },
}

/// Where a kept body's bytes are.
#[derive(Debug, Clone)]
enum Body {
    /// Held in memory.
    Memory(Bytes),
    /// In a file the caller posted from, read again to resend; `digest` is the XXH3-64 of the
    /// bytes that were posted, so a file changed since is refused, not sent as the same pass.
    File { path: PathBuf, digest: u64 },
}

#[derive(Debug, Clone)]
struct Kept {
    route: Route,
    body: Body,
    /// The server process that last acknowledged it.
    boot: u64,
}

/// Posts one worker's batches and passes to one frame, keeping each until it
/// is durable and resending it when the server restarted (see the module
/// docs).
///
/// Against a server without `--data-dir` (acknowledgements without
/// `durable_floor`) nothing is kept: such a server promises only *applied*.
/// Bodies kept in memory are bounded ([`Outbox::with_max_kept_bytes`]): past
/// the bound the outbox syncs, after which it can forget them all. Number a new
/// worker id's batches from 0 so that `durable_floor` can advance; bodies
/// numbered otherwise (passes numbered by a digest, say) are kept until the
/// next sync.
#[derive(Debug)]
pub struct Outbox {
    client: Client,
    frame: String,
    worker: u64,
    kept: BTreeMap<u64, Kept>,
    kept_bytes: usize,
    max_kept_bytes: usize,
    /// The server process last heard from.
    boot: Option<u64>,
    /// Server processes heard from before it: gone. With several posts in flight, one sent
    /// before a restart can be answered by the old process after a post answered by the new
    /// one; such an answer does not bring the old process back.
    gone: Vec<u64>,
    resent: u64,
}

impl Outbox {
    /// An outbox posting as `worker` to `frame`.
    pub fn new(
        client: Client,
        frame: impl Into<String>,
        worker: u64,
    ) -> Result<Outbox, ClientError> {
        let frame = frame.into();
        validate_frame_id(&frame)?;
        Ok(Outbox {
            client,
            frame,
            worker,
            kept: BTreeMap::new(),
            kept_bytes: 0,
            max_kept_bytes: DEFAULT_MAX_KEPT_BYTES,
            boot: None,
            gone: Vec::new(),
            resent: 0,
        })
    }

    /// Syncs by itself once the bodies kept in memory exceed `bytes`.
    pub fn with_max_kept_bytes(mut self, bytes: usize) -> Outbox {
        self.max_kept_bytes = bytes;
        self
    }

    /// The frame posted to.
    pub fn frame(&self) -> &str {
        &self.frame
    }

    /// The worker id posted as.
    pub fn worker(&self) -> u64 {
        self.worker
    }

    /// Posts an encoded batch of this worker numbered `seq` (see
    /// [`crate::Batch::encode`]).
    pub async fn post_batch(&mut self, seq: u64, body: Bytes) -> Result<BatchAck, ClientError> {
        let post = self.start(seq, Route::Samples, Body::Memory(body.clone()), body)?;
        self.send_and_keep(post).await
    }

    /// Posts a rendered pass (OpenEXR bytes) numbered `seq`, its beauty in
    /// `layer` or found by the server; kept in memory until durable.
    pub async fn post_pass(
        &mut self,
        seq: u64,
        layer: Option<&str>,
        exr: Bytes,
    ) -> Result<BatchAck, ClientError> {
        let route = Route::Pass {
            layer: layer.map(str::to_owned),
        };
        let post = self.start(seq, route, Body::Memory(exr.clone()), exr)?;
        self.send_and_keep(post).await
    }

    /// [`Outbox::post_pass`] of the bytes read from `path`: only the path is
    /// kept, and the file is read again (and checked to hold the same bytes)
    /// if the pass must be resent, so posting many large files costs no memory.
    pub async fn post_pass_file(
        &mut self,
        seq: u64,
        layer: Option<&str>,
        path: PathBuf,
        exr: Bytes,
    ) -> Result<BatchAck, ClientError> {
        let post = self.start_pass_file(seq, layer, path, exr)?;
        self.send_and_keep(post).await
    }

    /// [`Outbox::post_pass_file`] in two halves, so that several passes can be in flight: this
    /// half checks the pass against those kept and returns the request, which owns all it
    /// needs (run it anywhere, a spawned task say); [`Outbox::received`] takes its answer.
    ///
    /// Hand the answers to `received` in the order the posts were started: what the outbox
    /// keeps and resends is then exactly what it would be with one post at a time, and a
    /// post answered by a server process the outbox already knows is gone (sent before a
    /// restart, answered after a later post was answered by the new process) is resent like
    /// the others that process acknowledged.
    pub fn start_pass_file(
        &self,
        seq: u64,
        layer: Option<&str>,
        path: PathBuf,
        exr: Bytes,
    ) -> Result<Post, ClientError> {
        let route = Route::Pass {
            layer: layer.map(str::to_owned),
        };
        let digest = xxhash_rust::xxh3::xxh3_64(&exr);
        self.start(seq, route, Body::File { path, digest }, exr)
    }

    /// Keeps the body of a post answered as applied until it is durable, and resends what a
    /// server restart lost (the second half of [`Outbox::start_pass_file`]).
    pub async fn received(&mut self, sent: Sent) -> Result<BatchAck, ClientError> {
        let Sent { post, answer } = sent;
        let ack = answer?;
        if ack.durable_floor.is_some() {
            let in_memory = post.body.in_memory();
            let kept = Kept {
                route: post.route,
                body: post.body,
                boot: ack.boot,
            };
            if let Some(old) = self.kept.insert(post.seq, kept) {
                self.kept_bytes -= old.body.in_memory();
            }
            self.kept_bytes += in_memory;
        }
        self.heard(ack.clone()).await?;
        if self.kept_bytes > self.max_kept_bytes {
            self.sync().await?;
        }
        Ok(ack)
    }

    /// Returns once everything this outbox had acknowledged is on disk,
    /// resending what a restart lost; then forgets it all. Against a server
    /// without durability it only asks (and forgets).
    pub async fn sync(&mut self) -> Result<SyncAck, ClientError> {
        for _ in 0..MAX_RESTARTS {
            let ack = self.client.sync(&self.frame).await?;
            if !ack.durable {
                self.forget(|_| true);
                return Ok(ack);
            }
            let stale = self.acknowledged_elsewhere(ack.boot);
            self.now_at(ack.boot);
            if stale.is_empty() {
                self.forget(|_| true);
                return Ok(ack);
            }
            // Acknowledged by a process that is gone: send to this one, then ask again.
            self.resend(&stale).await?;
        }
        Err(ClientError::Restarting(self.frame.clone()))
    }

    /// Bodies acknowledged as applied but not yet known to be on disk.
    pub fn kept(&self) -> usize {
        self.kept.len()
    }

    /// Bodies resent because the server restarted.
    pub fn resent(&self) -> u64 {
        self.resent
    }

    /// Both halves of a post, one after the other.
    async fn send_and_keep(&mut self, post: Post) -> Result<BatchAck, ClientError> {
        let sent = post.send().await;
        self.received(sent).await
    }

    /// A post of `bytes` as `seq`, refused if `seq` is kept with other content.
    fn start(&self, seq: u64, route: Route, body: Body, bytes: Bytes) -> Result<Post, ClientError> {
        if let Some(kept) = self.kept.get(&seq) {
            let same = match &kept.body {
                Body::Memory(b) => *b == bytes,
                Body::File { digest, .. } => *digest == xxhash_rust::xxh3::xxh3_64(&bytes),
            };
            if !same {
                return Err(ClientError::InvalidArgument(format!(
                    "seq {seq} of worker {} was already posted to {} with other content",
                    self.worker, self.frame
                )));
            }
        }
        Ok(Post {
            client: self.client.clone(),
            frame: self.frame.clone(),
            worker: self.worker,
            seq,
            route,
            body,
            bytes,
        })
    }

    /// Forgets what `ack` reports durable; resends the rest if the server restarted.
    async fn heard(&mut self, mut ack: BatchAck) -> Result<(), ClientError> {
        for _ in 0..MAX_RESTARTS {
            if let Some(floor) = ack.durable_floor {
                // On disk is on disk, whichever process wrote it: the next one recovers it.
                self.forget(|seq| seq < floor);
            }
            let Some(last) = self.boot else {
                self.boot = Some(ack.boot);
                return Ok(());
            };
            if ack.boot == last {
                return Ok(());
            }
            // A new process, or a late answer of one already gone (which stays gone): either
            // way, what a process other than the current one acknowledged is sent again.
            if !self.gone.contains(&ack.boot) {
                self.now_at(ack.boot);
            }
            let current = self.boot.expect("set above");
            let stale = self.acknowledged_elsewhere(current);
            match self.resend(&stale).await? {
                Some(again) => ack = again,
                None => return Ok(()),
            }
        }
        Err(ClientError::Restarting(self.frame.clone()))
    }

    /// Records that `boot` is the server process now answering; the one before it is gone.
    fn now_at(&mut self, boot: u64) {
        if let Some(old) = self.boot.filter(|&b| b != boot) {
            self.gone.push(old);
        }
        self.gone.retain(|&b| b != boot);
        self.boot = Some(boot);
    }

    /// Resends kept bodies, lowest number first; returns the last answer, or the first one
    /// from yet another server process (which the caller then handles as a restart).
    async fn resend(&mut self, seqs: &[u64]) -> Result<Option<BatchAck>, ClientError> {
        let mut last = None;
        for &seq in seqs {
            let kept = self.kept.get(&seq).expect("resending a kept body").clone();
            let bytes = match &kept.body {
                Body::Memory(b) => b.clone(),
                Body::File { path, digest } => read_same(path, *digest)?,
            };
            let again = send(
                &self.client,
                &self.frame,
                self.worker,
                &kept.route,
                seq,
                bytes,
            )
            .await?;
            self.resent += 1;
            if let Some(k) = self.kept.get_mut(&seq) {
                k.boot = again.boot;
            }
            let other = Some(again.boot) != self.boot;
            last = Some(again);
            if other {
                break;
            }
        }
        Ok(last)
    }

    /// The kept bodies last acknowledged by another server process than `boot`, lowest first.
    fn acknowledged_elsewhere(&self, boot: u64) -> Vec<u64> {
        self.kept
            .iter()
            .filter(|(_, k)| k.boot != boot)
            .map(|(&seq, _)| seq)
            .collect()
    }

    fn forget(&mut self, durable: impl Fn(u64) -> bool) {
        let gone: Vec<u64> = self.kept.keys().copied().filter(|&s| durable(s)).collect();
        for seq in gone {
            if let Some(k) = self.kept.remove(&seq) {
                self.kept_bytes -= k.body.in_memory();
            }
        }
    }
}

/// A post started by [`Outbox::start_pass_file`]: everything the request needs, owned, so that
/// it can run while the outbox starts the next one.
#[derive(Debug)]
pub struct Post {
    client: Client,
    frame: String,
    worker: u64,
    seq: u64,
    route: Route,
    body: Body,
    bytes: Bytes,
}

impl Post {
    /// Sends the request (retrying what the client retries) and returns its answer, for
    /// [`Outbox::received`].
    pub async fn send(mut self) -> Sent {
        // The bytes go with the request; what is kept to resend is `body`.
        let bytes = std::mem::take(&mut self.bytes);
        let answer = send(
            &self.client,
            &self.frame,
            self.worker,
            &self.route,
            self.seq,
            bytes,
        )
        .await;
        Sent { post: self, answer }
    }
}

/// A [`Post`] and the server's answer to it.
#[derive(Debug)]
pub struct Sent {
    post: Post,
    answer: Result<BatchAck, ClientError>,
}

async fn send(
    client: &Client,
    frame: &str,
    worker: u64,
    route: &Route,
    seq: u64,
    bytes: Bytes,
) -> Result<BatchAck, ClientError> {
    match route {
        Route::Samples => client.post_encoded(frame, bytes).await,
        Route::Pass { layer } => {
            client
                .post_pass_layer(frame, worker, seq, layer.as_deref(), bytes)
                .await
        }
    }
}

impl Body {
    /// Bytes this body holds in memory (a file's are on disk).
    fn in_memory(&self) -> usize {
        match self {
            Body::Memory(b) => b.len(),
            Body::File { .. } => 0,
        }
    }
}

/// The bytes of `path`, if they are still those posted (digest `digest`).
fn read_same(path: &std::path::Path, digest: u64) -> Result<Bytes, ClientError> {
    let bytes = std::fs::read(path).map_err(|e| {
        ClientError::InvalidArgument(format!(
            "{}: cannot read it again to resend it after the server restarted: {e}",
            path.display()
        ))
    })?;
    if xxhash_rust::xxh3::xxh3_64(&bytes) != digest {
        return Err(ClientError::InvalidArgument(format!(
            "{} changed after it was posted; the server restarted and lost it, and a changed \
             file cannot be resent as the same pass: post it again",
            path.display()
        )));
    }
    Ok(Bytes::from(bytes))
}
