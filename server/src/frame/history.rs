//! A frame's convergence over time: the figures of each rendered version, kept with the frame
//! so that reading them costs no render (see `render::figures`, which files them).

use std::time::Instant;

use splatd_estimator as estimator;
use splatd_proto::api::{self, ConvergencePoint};

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

    /// The latest figures filed and the version they are of.
    pub fn latest(&self) -> Option<(u64, estimator::Convergence)> {
        self.latest
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
        let waiting_on = api::WaitingOn::of(c.verdict(threshold));
        Some(api::Convergence {
            samples: c.samples,
            spp_min: c.spp_min,
            spp_mean: c.spp_mean,
            spp_max: c.spp_max,
            removed_fraction: c.removed_fraction,
            deficit_fraction: c.deficit_fraction,
            samples_per_second: self.rate(seconds, samples),
            converged_below: threshold,
            own_count_from: c.own_count_from,
            converged: waiting_on.is_none(),
            waiting_on,
            history: self.points.clone(),
        })
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
            own_count_from: 16,
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
