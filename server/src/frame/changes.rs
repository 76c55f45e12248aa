//! Where a frame changed, version by version: what lets a render patch its last resolve
//! instead of resolving the whole frame again ([`splatd_estimator::resolve_region_into`]).

use std::collections::VecDeque;

use splatd_estimator::Rect;

/// Most changes remembered; a render older than all of them resolves the whole frame.
const MAX_CHANGES: usize = 4096;

/// The pixels each recent version changed.
#[derive(Debug, Default)]
pub(super) struct Changes {
    /// `(version, rect)`: the version a change made and the pixels it touched, oldest first.
    entries: VecDeque<(u64, Rect)>,
    /// Every change that made a version above this one is in `entries`.
    complete_after: u64,
}

impl Changes {
    /// A log for a frame at `version` whose earlier changes are not known (a restored frame).
    pub(super) fn starting_at(version: u64) -> Changes {
        Changes {
            entries: VecDeque::new(),
            complete_after: version,
        }
    }

    /// Records that `version` changed the pixels in `rect`.
    pub(super) fn record(&mut self, version: u64, rect: Rect) {
        if self.entries.len() == MAX_CHANGES {
            if let Some((dropped, _)) = self.entries.pop_front() {
                self.complete_after = dropped;
            }
        }
        self.entries.push_back((version, rect));
    }

    /// The pixels changed by the versions after `from` up to `to`, or `None` if some of those
    /// changes are no longer remembered.
    pub(super) fn between(&self, from: u64, to: u64) -> Option<Vec<Rect>> {
        if from < self.complete_after {
            return None;
        }
        Some(
            self.entries
                .iter()
                .filter(|(v, _)| *v > from && *v <= to)
                .map(|(_, r)| *r)
                .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn changes_between_two_versions_are_the_ones_made_between() {
        let mut c = Changes::starting_at(3);
        let r = |x| Rect::new(x, 0, x + 1, 1);
        for v in 4..10 {
            c.record(v, r(v as u32));
        }
        assert_eq!(c.between(5, 7), Some(vec![r(6), r(7)]));
        assert_eq!(c.between(9, 9), Some(vec![]));
        assert_eq!(c.between(2, 9), None, "before the log began");
        for v in 10..10 + MAX_CHANGES as u64 {
            c.record(v, r(0));
        }
        assert_eq!(c.between(4, 20), None, "forgotten");
        assert!(c.between(10, 20).is_some());
    }
}
