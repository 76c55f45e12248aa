//! A consistent cut of a frame, and the counters that go with it.

use std::sync::atomic::AtomicU64;
use std::sync::Arc;

use splatd_estimator::{self as estimator, resolve_bands, AovSums, FrameState, Resolved};

use super::dedup::Seen;
use crate::memory::CellPool;

/// Running totals of a frame (besides what the cascades themselves hold).
#[derive(Debug, Default)]
pub(super) struct Counters {
    pub(super) samples: AtomicU64,
    pub(super) batches: AtomicU64,
    pub(super) rejected_samples: AtomicU64,
    pub(super) rejected_batches: AtomicU64,
    pub(super) imports: AtomicU64,
}

/// Counter values, as saved in snapshots and restored from them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct CounterValues {
    /// Accepted samples (records of applied batches and samples of imported states).
    pub samples: u64,
    /// Applied batches.
    pub batches: u64,
    /// Samples of refused batches.
    pub rejected_samples: u64,
    /// Refused batches.
    pub rejected_batches: u64,
    /// Imported states and pushed deltas.
    pub imports: u64,
}

/// A consistent cut of a frame: what resolve, export and snapshots work from.
///
/// It shares the frame's bands and AOV sums instead of copying them ([`ShardedFrame::cut`](super::ShardedFrame::cut)):
/// a writer that changes a band while a cut holds it copies that band first (one band, under
/// that band's own lock), so the cut stays the frame as it was and nobody waits for a copy of
/// the whole frame.
#[derive(Debug, Clone)]
pub struct FrameCut {
    /// The bands, top to bottom.
    pub bands: Vec<Arc<FrameState>>,
    /// Senders seen when the copy was taken.
    pub seen: Seen,
    /// Counters when the copy was taken.
    pub counters: CounterValues,
    /// The frame's version when the copy was taken (see [`ShardedFrame::version`](super::ShardedFrame::version)).
    pub version: u64,
    /// The AOV sums of the whole frame, if it has AOVs.
    pub aovs: Option<Arc<AovSums>>,
    /// The frame's cell pool, which takes the bands this cut alone still holds when it ends.
    pub(super) pool: Option<Arc<CellPool>>,
}

impl Drop for FrameCut {
    /// Gives the cells of the bands only this cut still holds (the frame has moved on to
    /// copies of them) to the frame's pool, for its writers' next copies on write: a frame
    /// rendered while it takes samples then copies bands into memory already mapped instead of
    /// faulting in fresh pages for every render (see `CellPool`).
    fn drop(&mut self) {
        let Some(pool) = self.pool.take() else {
            return;
        };
        for band in self.bands.drain(..) {
            pool.give_band(band);
        }
        if let Some(sums) = self.aovs.take() {
            pool.give_aovs(sums);
        }
    }
}

impl FrameCut {
    /// The bands merged into one whole-frame state.
    pub fn whole(&self) -> FrameState {
        let first = &self.bands[0];
        let mut whole = FrameState::new(first.width(), first.height(), first.layout().clone());
        for band in &self.bands {
            whole
                .merge(band)
                .expect("bands of one frame fit the whole frame");
        }
        whole
    }

    /// The bands, top to bottom, as the estimator takes them.
    pub fn band_refs(&self) -> Vec<&FrameState> {
        self.bands.iter().map(|b| &**b).collect()
    }

    /// Resolves the cut on `threads` threads.
    pub fn resolve(&self, params: &estimator::ResolveParams, threads: usize) -> Resolved {
        resolve_bands(&self.band_refs(), params, threads).expect("a frame's bands tile it")
    }

    /// `B_j / N` per cascade over the whole frame (raw layers for the EXR).
    pub fn cascade_means(&self) -> Vec<Vec<[f32; 3]>> {
        let mut layers: Vec<Vec<[f32; 3]>> = Vec::new();
        for band in &self.bands {
            for (j, layer) in band.cascade_means().into_iter().enumerate() {
                match layers.get_mut(j) {
                    Some(all) => all.extend(layer),
                    None => layers.push(layer),
                }
            }
        }
        layers
    }
}
