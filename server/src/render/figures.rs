//! How far each frame is from converged, and where it needs samples: need maps and convergence
//! figures computed from the shared renders, and each frame's convergence over time.
//!
//! A need map is one render like an image (see [`crate::render`]): requests for the same frame
//! version and tile size share one resolve, which reserves its memory from the working budget.
//! The need map at the default tile goes with the frame's kept resolve
//! ([`crate::render::KeptResolves`]), which files its whole-frame figures in the frame's
//! [`History`](crate::frame::history::History), so `GET /v1/frames/{id}`, `/metrics` and the
//! live page read the figures of the latest render instead of resolving again, and figures of a
//! version an image was just rendered at cost a need map, not a resolve. The estimator
//! does the arithmetic ([`splatd_estimator::NeedMap`]); this module only schedules it and keeps
//! the history.
//!
//! A `/metrics` scrape waits for the figures of frames that changed at most half the timeout
//! its scraper gives it (Prometheus says so in a header), and never more than [`SCRAPE_WAIT`],
//! all frames at once: a frame that workers keep changing is rendered at its pace
//! ([`crate::render::pace`]), which on a busy head can be longer than Prometheus waits for a
//! scrape (10 s by default, 5 s when it scrapes every 5 s). A scrape that stops waiting reports
//! the latest figures with their age and leaves the render running ([`Refreshes`]), so the next
//! scrape finds them fresher.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use splatd_estimator::{self as estimator, NeedMap};
use splatd_proto::api;

use crate::frame::ShardedFrame;
use crate::render::RenderError;
use crate::work::Busy;
use crate::AppState;

/// Most a `/metrics` scrape waits for figures of frames that changed since their last render,
/// half of Prometheus' default scrape timeout (a scraper that says its timeout is shorter is
/// answered within half of that).
pub const SCRAPE_WAIT: Duration = Duration::from_secs(5);

/// Why a need map or a frame's figures could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum FiguresError {
    /// A parameter of the request makes no sense (the tile size).
    #[error(transparent)]
    Param(#[from] estimator::ParamError),
    /// The working memory stayed spent.
    #[error(transparent)]
    Busy(#[from] Busy),
    /// Something that cannot fail did.
    #[error("{what}: {detail}")]
    Internal {
        /// What was being done.
        what: &'static str,
        /// What went wrong.
        detail: String,
    },
}

impl FiguresError {
    fn internal(what: &'static str, detail: impl std::fmt::Display) -> FiguresError {
        FiguresError::Internal {
            what,
            detail: detail.to_string(),
        }
    }
}

impl From<RenderError<FiguresError>> for FiguresError {
    fn from(e: RenderError<FiguresError>) -> FiguresError {
        match e {
            RenderError::Busy(busy) => FiguresError::Busy(busy),
            RenderError::Failed(e) => e,
        }
    }
}

/// The need map of `frame` as it is now, in tiles of `tile` pixels, as JSON bytes
/// ([`api::NeedMap`]); shared with every request for the same version and tile.
pub async fn need_map(
    app: &AppState,
    frame: &Arc<ShardedFrame>,
    tile: u32,
) -> Result<Bytes, FiguresError> {
    let tile = estimator::check_tile(tile)?;
    let params = frame.spec().resolve;
    let threads = app.resolve_threads;
    let r = &frame.spec().request;
    let pixels = u64::from(r.width) * u64::from(r.height);
    // The copy of the state and the resolved layers (three RGB layers and the counts).
    let cost = frame.spec().memory_bytes() + pixels * 44;
    let kept = app.renders.kept().clone();
    // While this request waits, renders of other kinds that resolve the frame make the map too.
    let _wanted = (tile == estimator::DEFAULT_NEED_TILE).then(|| kept.want_figures(frame));
    let bytes = app
        .renders
        .get_or_render(
            frame,
            format!("need {tile}"),
            cost,
            move |frame, wanted, _| {
                // The need map at the default tile goes with the kept resolve, which files its
                // figures: a render that started with this one may just have made both.
                let body = if tile == estimator::DEFAULT_NEED_TILE {
                    kept.with_need_since(frame, threads, wanted, |map, _| to_api(frame.id(), map))
                } else {
                    let map = kept.with_resolved(frame, &params, threads, |resolved, cut, _| {
                        NeedMap::build_on(&cut.band_refs(), resolved, &params, tile, threads)
                    });
                    to_api(
                        frame.id(),
                        &map.map_err(|e| FiguresError::internal("need map", e))?,
                    )
                };
                serde_json::to_vec(&body)
                    .map(Bytes::from)
                    .map_err(|e| FiguresError::internal("need map JSON", e))
            },
        )
        .await?;
    Ok(bytes)
}

/// The frame's convergence now: renders its need map at the default tile size if the frame
/// changed since the figures were last filed (shared with everyone asking), then reads the
/// history. An unchanged frame costs no render however many frames the server holds: the
/// figures are kept with the frame, not in the renders' cache.
pub async fn convergence(
    app: &AppState,
    frame: &Arc<ShardedFrame>,
) -> Result<api::Convergence, FiguresError> {
    if frame.history().latest_version() != Some(frame.version()) {
        need_map(app, frame, estimator::DEFAULT_NEED_TILE).await?;
    }
    filed(frame)
        .map(|(c, _)| c)
        .ok_or_else(|| FiguresError::internal("convergence", "a render filed no figures"))
}

/// The latest figures filed for `frame`, with its sample count and rate now, and their age in
/// seconds (since the render they come from); `None` if no render filed any.
fn filed(frame: &ShardedFrame) -> Option<(api::Convergence, f64)> {
    let samples = frame.samples();
    let threshold = frame.spec().request.converged_below;
    let history = frame.history();
    let now = history.seconds();
    let c = history.convergence(now, samples, threshold)?;
    let age = c.history.last().map_or(0.0, |p| (now - p.seconds).max(0.0));
    Some((c, age))
}

/// The renders of figures that scrapes started and that are still running, by frame serial: a
/// scrape that stops waiting leaves its render running, and the next scrape waits for that one
/// instead of starting another beside it.
#[derive(Debug, Default)]
pub struct Refreshes(Mutex<HashMap<u64, tokio::sync::watch::Receiver<()>>>);

impl Refreshes {
    /// A receiver whose `changed()` ends when the render of `frame`'s figures now running, or
    /// one started now, has ended.
    fn start(&self, app: &AppState, frame: &Arc<ShardedFrame>) -> tokio::sync::watch::Receiver<()> {
        let mut running = self.0.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(done) = running.get(&frame.serial()) {
            return done.clone();
        }
        let (ended, done) = tokio::sync::watch::channel(());
        running.insert(frame.serial(), done.clone());
        let (app, frame) = (app.clone(), frame.clone());
        tokio::spawn(async move {
            if let Err(e) = need_map(&app, &frame, estimator::DEFAULT_NEED_TILE).await {
                tracing::warn!(frame = frame.id(), "no convergence figures: {e}");
            }
            let mut running = app.refreshes.0.lock().unwrap_or_else(|e| e.into_inner());
            running.remove(&frame.serial());
            drop(ended);
        });
        done
    }
}

/// The frame's figures for a scrape, and their age in seconds (since the render they come
/// from): the latest filed, after waiting until `deadline` at most for a render of the frame
/// as it is now; `None` if no render ever filed any (it could not get working memory).
pub async fn latest_convergence(
    app: &AppState,
    frame: &Arc<ShardedFrame>,
    deadline: tokio::time::Instant,
) -> Option<(api::Convergence, f64)> {
    let wanted = frame.version();
    // Twice at most: a render running may have read an older version than `wanted`.
    for _ in 0..2 {
        if frame
            .history()
            .latest_version()
            .is_some_and(|v| v >= wanted)
        {
            break;
        }
        let mut done = app.refreshes.start(app, frame);
        if tokio::time::timeout_at(deadline, done.changed())
            .await
            .is_err()
        {
            break;
        }
    }
    filed(frame)
}

/// The wire form of a need map.
fn to_api(frame: &str, map: &NeedMap) -> api::NeedMap {
    let tiles = &map.tiles;
    api::NeedMap {
        frame: frame.to_owned(),
        width: map.width,
        height: map.height,
        tile: map.tile,
        tiles_x: map.tiles_x,
        tiles_y: map.tiles_y,
        samples: tiles.iter().map(|t| t.samples).sum(),
        need: tiles.iter().map(|t| t.need).collect(),
        removed_fraction: tiles.iter().map(|t| t.removed_fraction()).collect(),
        deficit_fraction: tiles.iter().map(|t| t.deficit_fraction()).collect(),
        spp_mean: tiles.iter().map(|t| t.spp_mean()).collect(),
        spp_min: tiles.iter().map(|t| t.spp_min).collect(),
    }
}
