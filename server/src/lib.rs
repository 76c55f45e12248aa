//! The splatd server: an axum shell around the estimator core. Its folders say what it does:
//!
//! * [`frame`]: one frame as row bands under separate locks: its spec, all-or-nothing batches
//!   and passes with duplicate detection ([`frame::dedup`]), imports and exports of states,
//!   consistent cuts that share the bands, and where each version changed the frame;
//! * [`store`]: the frames of a server and the limits on them;
//! * [`render`]: resolves shared between requests and patched where a frame changed, the
//!   figures of convergence ([`render::figures`]) and Open Image Denoise over a frame
//!   ([`render::denoise`]); [`work`]: the working-memory budget large requests reserve from;
//! * [`durable`]: snapshots, recovery and quarantine;
//! * [`transport`]: the cap on connections, their deadlines, and the check of every request
//!   head; [`http`]: the router, one handler file per concept, the JSON errors (the only place
//!   that knows a status code) and the guard of every route; [`access`]: who may do what
//!   (bearer tokens and their roles);
//! * [`server`]: the [`server::Server`] lifecycle (listener, background tasks, graceful
//!   shutdown with a final snapshot); [`config`]: every flag and default;
//! * [`push`]: push mode, forwarding exact deltas of every frame to an upstream splatd;
//!   [`viewer`]: pushing frames to tev; [`priority`]: background threads below the request
//!   loop; [`meters`]: every metric's name; [`memory`]: huge pages for large buffers;
//!   [`failpoint`]: fault injection for tests.
//!
//! The formats (EXR out, passes in, states, previews) are the `splatd-formats` crate's.

pub mod access;
pub mod config;
pub mod durable;
pub mod failpoint;
pub mod frame;
pub mod http;
pub mod memory;
pub mod meters;
pub mod priority;
pub mod push;
pub mod render;
pub mod server;
pub mod store;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod transport;
pub mod viewer;
pub mod work;

use std::ops::Deref;
use std::sync::Arc;
use std::time::Duration;

use metrics_exporter_prometheus::PrometheusHandle;
use splatd_proto::DecodeLimits;

use access::Auth;
pub use config::Config;
use durable::{DurabilityError, Durable};
use frame::ShardedFrame;
use store::FrameStore;

/// What a server refuses, so that no client can exhaust it.
#[derive(Debug, Clone)]
pub struct Limits {
    /// Most records in one batch (the body limit follows from it).
    pub max_records: usize,
    /// Most frames held at once.
    pub max_frames: usize,
    /// Most pixels in one frame.
    pub max_pixels: u64,
    /// Most cascades in one frame.
    pub max_cascades: u32,
    /// Most bytes of cascades over all frames; new frames beyond it are refused.
    pub max_memory_bytes: u64,
    /// Longest time one request may take, body included (a slow sender gets 408).
    pub request_timeout: Duration,
    /// Longest a keep-alive connection may wait between requests.
    pub idle_timeout: Duration,
    /// Longest from accept (or a later request's first byte) to a complete request head.
    pub head_timeout: Duration,
    /// Longest from the first byte of a response to its last.
    pub response_timeout: Duration,
    /// Most connections open at once ([`transport::Connections`]).
    pub max_connections: usize,
    /// Bytes that requests may hold at once beyond the frames themselves: copies being
    /// resolved or exported, encoded images, imported states ([`work::WorkBudget`]).
    pub work_memory_bytes: u64,
    /// Longest a request waits for working memory before it is answered 503.
    pub work_wait: Duration,
    /// Most of the wall time a changing frame's renders take ([`render::pace`]).
    pub render_share: f64,
}

impl Default for Limits {
    /// The limits of a server started with no flags (see [`Config`]).
    fn default() -> Self {
        Config::default().limits()
    }
}

/// Everything the handlers share.
#[derive(Debug)]
pub struct Shared {
    /// The frames.
    pub store: FrameStore,
    /// Limits applied when decoding batches.
    pub decode_limits: DecodeLimits,
    /// Threads one resolve may use.
    pub resolve_threads: usize,
    /// Renders `/metrics`; `None` when no recorder could be installed.
    pub metrics: Option<PrometheusHandle>,
    /// The data directory, when frames are durable.
    pub durable: Option<Arc<Durable>>,
    /// Identifies this process (see `BatchAck::boot`): random at every start.
    pub boot: u64,
    /// Who may do what.
    pub auth: Auth,
    /// Resolved images shared between requests, and the working-memory budget they and
    /// every other large request reserve from.
    pub renders: render::Renders,
    /// The open connections and their cap (used by the accept loop; in-process router calls
    /// bypass it).
    pub connections: Arc<transport::Connections>,
    /// Decode buffers kept between passes (see [`splatd_formats::passes::ScratchPool`]).
    pub pass_scratch: splatd_formats::passes::ScratchPool,
    /// Encoding buffers kept between images (see [`splatd_formats::exr::ExrScratch`]): one,
    /// which a dashboard or farm fetching images one after another keeps reusing.
    pub exr_scratch: splatd_formats::scratch::Pool<splatd_formats::exr::ExrScratch>,
    /// Buffers kept for large request bodies (see [`memory::BodyPool`]).
    pub body_pool: Arc<memory::BodyPool>,
    /// The buffer kept for state bodies (imports and pushed deltas): one, as large as the last
    /// state received, until no state arrives for [`memory::CELL_POOL_IDLE`]. A fresh buffer
    /// of a 1080p state's 550 MB cost more in page faults than receiving it.
    pub state_pool: Arc<memory::BodyPool>,
    /// Open Image Denoise, or why this server has none.
    pub denoiser: render::denoise::Denoiser,
    /// Renders of figures started for `/metrics` scrapes and still running.
    pub refreshes: render::figures::Refreshes,
}

/// Finished renders kept for requests that ask again before the frame changes: enough for a
/// few viewers each looking at a few layers.
const RENDERS_KEPT: usize = 16;

/// A cheap handle on [`Shared`], the state of every handler.
#[derive(Debug, Clone)]
pub struct AppState(pub Arc<Shared>);

impl Deref for AppState {
    type Target = Shared;
    fn deref(&self) -> &Shared {
        &self.0
    }
}

impl AppState {
    /// Frees pooled memory that nothing took for [`memory::CELL_POOL_IDLE`] (a deleted frame's
    /// cells, pass and image scratches, request bodies, the kept state buffer), looking a few
    /// times per period, until `stop` turns true (a server's task): a burst of large requests
    /// does not leave its memory held.
    pub async fn release_idle_until(self, mut stop: tokio::sync::watch::Receiver<bool>) {
        let idle = memory::CELL_POOL_IDLE;
        loop {
            tokio::select! {
                () = tokio::time::sleep(idle / 4) => {}
                _ = stop.wait_for(|stopped| *stopped) => return,
            }
            // The runtime's clock, so that tests can pause it; the pools stamp with std's.
            let now = tokio::time::Instant::now().into_std();
            let cells = self.store.cell_pool().release_idle(now, idle);
            let scratches = self.pass_scratch.release_idle(now, idle)
                + self.exr_scratch.release_idle(now, idle)
                + self.body_pool.release_idle(now, idle)
                + self.state_pool.release_idle(now, idle);
            if cells > 0 || scratches > 0 {
                tracing::debug!(cells, scratches, "freed memory no request took");
            }
        }
    }

    /// A server state with an empty store.
    pub fn new(
        limits: Limits,
        metrics: Option<PrometheusHandle>,
        durable: Option<Arc<Durable>>,
    ) -> AppState {
        Self::with_auth(limits, metrics, durable, Auth::open())
    }

    /// A server state with an empty store and access rules.
    pub fn with_auth(
        limits: Limits,
        metrics: Option<PrometheusHandle>,
        durable: Option<Arc<Durable>>,
        auth: Auth,
    ) -> AppState {
        let none = render::denoise::Denoiser::unavailable(format!(
            "no denoiser was configured for this server ({})",
            render::denoise::HOW
        ));
        Self::with_denoiser(limits, metrics, durable, auth, none)
    }

    /// A server state with an empty store, access rules and a denoiser.
    pub fn with_denoiser(
        limits: Limits,
        metrics: Option<PrometheusHandle>,
        durable: Option<Arc<Durable>>,
        auth: Auth,
        denoiser: render::denoise::Denoiser,
    ) -> AppState {
        let decode_limits = DecodeLimits {
            max_records: limits.max_records,
            ..DecodeLimits::default()
        };
        let resolve_threads = frame::cores();
        let budget = work::WorkBudget::new(limits.work_memory_bytes, limits.work_wait);
        AppState(Arc::new(Shared {
            renders: render::Renders::new(RENDERS_KEPT, budget).paced(limits.render_share),
            connections: Arc::new(transport::Connections::new(limits.max_connections)),
            pass_scratch: splatd_formats::passes::ScratchPool::new(resolve_threads),
            exr_scratch: splatd_formats::scratch::Pool::new(1),
            body_pool: Arc::new(memory::BodyPool::new(resolve_threads)),
            state_pool: Arc::new(memory::BodyPool::new(1)),
            store: FrameStore::new(limits),
            decode_limits,
            resolve_threads,
            metrics,
            durable,
            boot: boot_id(),
            auth,
            denoiser,
            refreshes: Default::default(),
        }))
    }

    /// A server state as `config` describes it: its tokens read, its data directory opened and
    /// every frame in it recovered (or quarantined). For in-process use too: nothing listens.
    pub fn from_config(
        config: &Config,
        metrics: Option<PrometheusHandle>,
    ) -> anyhow::Result<AppState> {
        use anyhow::Context;
        let durable = match &config.data_dir {
            Some(dir) => Some(Arc::new(
                Durable::open(dir, config.snapshot_interval())
                    .with_context(|| format!("opening data directory {}", dir.display()))?,
            )),
            None => None,
        };
        let mut token_text = String::new();
        if let Some(path) = &config.tokens_file {
            token_text = std::fs::read_to_string(path)
                .with_context(|| format!("reading tokens file {}", path.display()))?;
        }
        if let Ok(env) = std::env::var("SPLATD_TOKENS") {
            token_text.push('\n');
            token_text.push_str(&env);
        }
        let auth = Auth::parse(&token_text, config.public_read).context("invalid tokens")?;
        if auth.enabled() {
            tracing::info!(
                tokens = auth.len(),
                public_read = config.public_read,
                "bearer tokens required"
            );
        } else {
            tracing::warn!("no tokens configured: anyone who can reach this server may use it");
        }
        let denoiser =
            render::denoise::Denoiser::load(config.oidn_lib.as_deref(), config.oidn_memory());
        match denoiser.oidn() {
            Ok(oidn) => tracing::info!(
                version = %oidn.version(),
                library = %oidn.path().display(),
                min_memory_mib = config.oidn_min_memory_mib,
                max_memory_mib = ?config.oidn_max_memory_mib,
                "Open Image Denoise loaded: image.exr?denoise=oidn is served"
            ),
            Err(e) if config.oidn_lib.is_some() => {
                tracing::warn!(
                    "Open Image Denoise not loaded, denoise requests will be refused: {e}"
                )
            }
            Err(e) => tracing::info!(
                "Open Image Denoise not loaded, denoise requests will be refused: {e}"
            ),
        }
        let app =
            AppState::with_denoiser(config.limits(), metrics, durable.clone(), auth, denoiser);
        if let Some(durable) = &durable {
            let n = durable
                .recover(&app.store)
                .context("recovering frames from the data directory")?;
            tracing::info!(frames = n, "recovered");
        }
        Ok(app)
    }

    /// Called once a new frame is in the store, before the client hears of it.
    pub async fn on_created(&self, frame: &Arc<ShardedFrame>) -> Result<(), DurabilityError> {
        match &self.durable {
            Some(durable) => durable
                .frame_created(frame)
                .await
                .map_err(DurabilityError::new("writing the frame to disk")),
            None => Ok(()),
        }
    }

    /// Deletes a frame, in an order that keeps every promise made about it:
    ///
    /// 1. the frame is retired: batches being applied finish and are answered, later ones are
    ///    refused, so no batch is acknowledged after the deletion is;
    /// 2. it leaves the store, so a new frame of the same id can be created;
    /// 3. its files are removed (after any snapshot being written), so it is not recovered.
    ///
    /// If step 3 fails, the frame is put back as it was and the deletion is refused: a deletion
    /// is durable before it is acknowledged, and a failed one changes nothing.
    pub async fn delete_frame(&self, frame: &Arc<ShardedFrame>) -> Result<(), DurabilityError> {
        frame.retire_and_drain().await;
        self.renders.forget(frame);
        self.store.remove_frame(frame);
        let Some(durable) = &self.durable else {
            return Ok(());
        };
        if let Err(e) = durable.frame_deleted(frame).await {
            frame.unretire();
            if !self.store.reinsert(frame.clone()) {
                tracing::error!(
                    frame = frame.id(),
                    "a frame of the same id was created while the deletion failed"
                );
            }
            return Err(DurabilityError::new("removing the frame from disk")(e));
        }
        Ok(())
    }

    /// Returns once everything applied to `frame` so far is on disk (at once when the server
    /// is not durable).
    pub async fn sync(&self, frame: &Arc<ShardedFrame>) -> Result<(), DurabilityError> {
        match &self.durable {
            Some(durable) => durable
                .snapshot(frame)
                .await
                .map_err(DurabilityError::new("writing a snapshot")),
            None => Ok(()),
        }
    }
}

/// A process id unlikely to repeat across restarts; never 0, which old servers (without the
/// field) report, and below 2^53 so JavaScript clients read it exactly.
fn boot_id() -> u64 {
    splatd_proto::ids::random_id()
}
