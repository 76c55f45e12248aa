//! How far each frame is from converged, and where it needs samples: need maps and convergence
//! figures computed from the shared renders, and each frame's convergence over time.
//!
//! A need map is one render like an image (see [`crate::render`]): requests for the same frame
//! version and tile size share one resolve, which reserves its memory from the working budget.
//! Every render of a new version also files the frame's whole-frame figures in the frame's
//! [`History`], so `GET /v1/frames/{id}`, `/metrics` and the live page read the figures of the
//! latest render instead of resolving again. The estimator does the arithmetic
//! ([`splatd_estimator::NeedMap`]); this module only schedules it and keeps the history.

use std::sync::Arc;
use std::time::Instant;

use bytes::Bytes;
use splatd_estimator::{self as estimator, NeedMap};
use splatd_proto::api::{self, ConvergencePoint};

use crate::frame::ShardedFrame;
use crate::render::RenderError;
use crate::work::Busy;
use crate::AppState;

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

/// Most points a frame's history keeps; when full, every other point is dropped, so the
/// history always spans the frame's whole life at a coarser and coarser step.
pub const MAX_HISTORY: usize = 512;

/// Seconds over which samples/s is measured, at least.
const RATE_WINDOW: f64 = 1.0;

/// A frame's convergence over time: one point per rendered version.
#[derive(Debug)]
pub struct History {
    started: Instant,
    latest: Option<(u64, estimator::Convergence)>,
    points: Vec<ConvergencePoint>,
}

impl Default for History {
    fn default() -> Self {
        History {
            started: Instant::now(),
            latest: None,
            points: Vec::new(),
        }
    }
}

impl History {
    /// The version the latest figures are of, if any were filed.
    pub fn latest_version(&self) -> Option<u64> {
        self.latest.map(|(v, _)| v)
    }

    /// Seconds since the frame was taken in.
    pub fn seconds(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// Files the figures of `version`, rendered at `seconds`; a version filed before (or older
    /// than the latest) is ignored.
    pub fn record(&mut self, version: u64, seconds: f64, c: estimator::Convergence) {
        if self.latest.is_some_and(|(v, _)| v >= version) {
            return;
        }
        self.latest = Some((version, c));
        if self.points.len() >= MAX_HISTORY {
            let mut i = 0;
            self.points.retain(|_| {
                i += 1;
                i % 2 == 1
            });
        }
        self.points.push(ConvergencePoint {
            seconds,
            samples: c.samples,
            spp_mean: c.spp_mean,
            removed_fraction: c.removed_fraction,
        });
    }

    /// Samples per second from the newest point at least `RATE_WINDOW` (1 s) before `seconds` (or
    /// the oldest point) to `samples` at `seconds`; 0 without a point or time between.
    pub fn rate(&self, seconds: f64, samples: u64) -> f64 {
        let from = self
            .points
            .iter()
            .rev()
            .find(|p| p.seconds <= seconds - RATE_WINDOW)
            .or(self.points.first());
        match from {
            Some(p) if seconds > p.seconds => {
                samples.saturating_sub(p.samples) as f64 / (seconds - p.seconds)
            }
            _ => 0.0,
        }
    }

    /// The latest figures and the history, as the API shows them, with the rate at `seconds`
    /// for `samples` (the frame's count now).
    pub fn convergence(
        &self,
        seconds: f64,
        samples: u64,
        threshold: f64,
    ) -> Option<api::Convergence> {
        let (_, c) = self.latest?;
        Some(api::Convergence {
            samples: c.samples,
            spp_min: c.spp_min,
            spp_mean: c.spp_mean,
            spp_max: c.spp_max,
            removed_fraction: c.removed_fraction,
            deficit_fraction: c.deficit_fraction,
            samples_per_second: self.rate(seconds, samples),
            converged_below: threshold,
            converged: c.converged(threshold),
            history: self.points.clone(),
        })
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
    let bytes = app
        .renders
        .get_or_render(frame, format!("need {tile}"), cost, move |frame| {
            let cut = frame.cut();
            let bands = cut.band_refs();
            let map = kept.with_resolved(frame, &cut, &params, threads, |resolved, _| {
                NeedMap::build(&bands, resolved, &params, tile)
            });
            let map = map.map_err(|e| FiguresError::internal("need map", e))?;
            {
                let mut history = frame.history();
                let seconds = history.seconds();
                history.record(cut.version, seconds, map.convergence());
            }
            let body = to_api(frame.id(), &map);
            serde_json::to_vec(&body)
                .map(Bytes::from)
                .map_err(|e| FiguresError::internal("need map JSON", e))
        })
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
    let filed = frame.history().latest_version();
    if filed != Some(frame.version()) {
        need_map(app, frame, estimator::DEFAULT_NEED_TILE).await?;
    }
    let samples = frame.samples();
    let threshold = frame.spec().request.converged_below;
    let history = frame.history();
    history
        .convergence(history.seconds(), samples, threshold)
        .ok_or_else(|| FiguresError::internal("convergence", "a render filed no figures"))
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

#[cfg(test)]
mod tests {
    use super::*;

    fn figures(samples: u64, removed_fraction: f64) -> estimator::Convergence {
        estimator::Convergence {
            samples,
            spp_min: 1,
            spp_mean: samples as f64 / 10.0,
            spp_max: samples / 10,
            removed_fraction,
            deficit_fraction: 0.0,
        }
    }

    #[test]
    fn history_keeps_one_point_per_version_and_measures_the_rate() {
        let mut h = History::default();
        assert!(
            h.convergence(0.0, 0, 0.01).is_none(),
            "nothing rendered yet"
        );
        h.record(1, 0.0, figures(100, 0.5));
        h.record(1, 0.5, figures(100, 0.5));
        h.record(3, 2.0, figures(300, 0.2));
        h.record(2, 2.5, figures(200, 0.3));
        assert_eq!(h.points.len(), 2, "repeated and older versions are ignored");
        // At 3.0 s with 500 samples: from the newest point at least 1 s older (2.0 s, 300).
        assert_eq!(h.rate(3.0, 500), 200.0);
        // At 2.5 s only the point at 0.0 s is a second older: (500 - 100) / 2.5.
        assert_eq!(h.rate(2.5, 500), 160.0);
        let c = h.convergence(3.0, 500, 0.25).unwrap();
        assert_eq!(
            (c.samples, c.removed_fraction, c.converged),
            (300, 0.2, true)
        );
        assert_eq!(c.samples_per_second, 200.0);
        assert!(!h.convergence(3.0, 500, 0.1).unwrap().converged);
    }

    #[test]
    fn a_full_history_drops_every_other_point() {
        let mut h = History::default();
        for v in 0..MAX_HISTORY as u64 {
            h.record(v + 1, v as f64, figures(v, 0.1));
        }
        assert_eq!(h.points.len(), MAX_HISTORY);
        h.record(MAX_HISTORY as u64 + 1, 1e6, figures(9, 0.1));
        assert_eq!(h.points.len(), MAX_HISTORY / 2 + 1);
        assert_eq!(h.points[0].seconds, 0.0, "the first point stays");
        assert_eq!(h.points[1].seconds, 2.0);
        assert_eq!(
            h.points.last().unwrap().seconds,
            1e6,
            "the new point is added"
        );
    }
}
