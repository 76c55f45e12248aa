//! Which batches (and pushed deltas) a frame has already applied, so retries count once.

use std::collections::{BTreeSet, HashMap};

use serde::{Deserialize, Serialize};

/// Sequence numbers seen from one sender: everything below `floor`, plus the set `above`.
///
/// Senders number their batches 0, 1, 2, ... and send them roughly in order (a few in flight at
/// once), so the set stays tiny: whenever `floor` is in `above` it is absorbed into the floor.
/// A sender that skips numbers keeps them in `above` until they arrive, which costs 8 bytes each.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SeqSet {
    floor: u64,
    above: BTreeSet<u64>,
}

impl SeqSet {
    /// Records `seq`; false when it was already there.
    pub fn insert(&mut self, seq: u64) -> bool {
        if seq < self.floor || !self.above.insert(seq) {
            return false;
        }
        while self.above.remove(&self.floor) {
            self.floor += 1;
        }
        true
    }

    /// Whether `seq` was recorded.
    pub fn contains(&self, seq: u64) -> bool {
        seq < self.floor || self.above.contains(&seq)
    }

    /// Every number below this one was recorded.
    pub fn floor(&self) -> u64 {
        self.floor
    }

    /// Numbers recorded above the floor (out of order arrivals).
    pub fn gaps(&self) -> usize {
        self.above.len()
    }
}

/// The senders a frame has heard from: render workers by worker id, pushing nodes by node id.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Seen {
    /// Batches, by worker id.
    pub workers: HashMap<u64, SeqSet>,
    /// Pushed deltas, by the pushing node's id.
    pub nodes: HashMap<String, SeqSet>,
}

impl Seen {
    /// Records batch `seq` of `worker`; false for a duplicate.
    pub fn insert_batch(&mut self, worker: u64, seq: u64) -> bool {
        self.workers.entry(worker).or_default().insert(seq)
    }

    /// Records delta `seq` of `node`; false for a duplicate.
    pub fn insert_delta(&mut self, node: &str, seq: u64) -> bool {
        match self.nodes.get_mut(node) {
            Some(set) => set.insert(seq),
            None => self.nodes.entry(node.to_owned()).or_default().insert(seq),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn in_order_numbers_collapse_into_the_floor() {
        let mut s = SeqSet::default();
        for seq in 0..1000 {
            assert!(s.insert(seq));
        }
        assert_eq!((s.floor(), s.gaps()), (1000, 0));
        assert!(!s.insert(999), "a retry of an applied batch is a duplicate");
    }

    #[test]
    fn out_of_order_numbers_are_remembered_until_the_gap_closes() {
        let mut s = SeqSet::default();
        assert!(s.insert(2));
        assert!(s.insert(1));
        assert_eq!((s.floor(), s.gaps()), (0, 2));
        assert!(!s.contains(0));
        assert!(s.insert(0));
        assert_eq!((s.floor(), s.gaps()), (3, 0));
        assert!(!s.insert(2) && !s.insert(0) && s.contains(1));
    }

    #[test]
    fn senders_are_independent() {
        let mut seen = Seen::default();
        assert!(seen.insert_batch(1, 0));
        assert!(seen.insert_batch(2, 0));
        assert!(!seen.insert_batch(1, 0));
        assert!(seen.insert_delta("a", 0));
        assert!(!seen.insert_delta("a", 0));
        assert!(seen.insert_delta("b", 0));
    }
}
