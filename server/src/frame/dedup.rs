//! Which batches (and pushed deltas) a frame has already applied, so retries count once.
//!
//! A batch is identified by `(worker, seq)`, chosen by the worker. The same id arriving again is
//! normally a retry, but it may also be a mistake: two workers that picked the same id, or a
//! worker rerun that numbers new work from 0 again. Answering such a batch "duplicate" would drop
//! its samples while telling the worker all is well, so every applied batch also leaves a digest
//! of its records ([`splatd_proto::Batch::content_digest`]); an id seen before is a retry only if
//! the digest matches, and a conflict otherwise. The digests cost 8 bytes (plus a hash map's
//! overhead) per applied batch.

use std::collections::{BTreeSet, HashMap};

use serde::{Deserialize, Serialize};
use splatd_proto::Applied;

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

    /// Every recorded number, in increasing order.
    pub fn iter(&self) -> impl Iterator<Item = u64> + '_ {
        (0..self.floor).chain(self.above.iter().copied())
    }

    /// The first recorded number in `range`.
    fn first_in(&self, range: std::ops::Range<u64>) -> Option<u64> {
        if range.start < self.floor {
            return (range.start < range.end).then_some(range.start);
        }
        self.above.range(range).next().copied()
    }
}

/// The senders a frame has heard from: render workers by worker id, pushing nodes by node id.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Seen {
    /// Batches, by worker id.
    pub workers: HashMap<u64, SeqSet>,
    /// Pushed deltas, by the pushing node's id.
    pub nodes: HashMap<String, SeqSet>,
    /// The content digest of every applied batch, by worker id and sequence number. Batches
    /// restored from snapshots written before digests were kept have none; batches an imported
    /// state names without a digest have [`UNVERIFIED`].
    pub digests: HashMap<u64, HashMap<u64, u64>>,
}

/// The digest recorded for a batch that an imported state names with digest 0 (none): the
/// frame holds its samples but cannot tell a later post of its id from another batch under a
/// reused id. (A batch whose records really hash to 0, one in 2^64, shares the fate.)
pub const UNVERIFIED: u64 = 0;

/// Batches of a state that a frame has applied already (so the state would count them twice).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Overlap {
    /// The worker of the first such batch.
    pub worker: u64,
    /// Its sequence number.
    pub seq: u64,
    /// How many batches of the state were applied already.
    pub count: u64,
}

/// What a batch id was, before [`Seen::check_batch`] or [`Seen::insert_batch`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchId {
    /// Never applied.
    New,
    /// Applied before with the same records (or before digests were kept): a retry.
    Retry,
    /// Applied before with other records: the id was reused for a different batch.
    Conflict {
        /// Digest of the records applied under this id.
        applied: u64,
    },
    /// Applied before by an imported state that recorded no digest of it: neither a retry nor
    /// a conflict can be told, so the batch is refused rather than dropped as a duplicate.
    Unverified,
}

impl Seen {
    /// What batch `seq` of `worker` with records of digest `digest` would be, without recording
    /// anything.
    pub fn check_batch(&self, worker: u64, seq: u64, digest: u64) -> BatchId {
        if !self.workers.get(&worker).is_some_and(|s| s.contains(seq)) {
            return BatchId::New;
        }
        match self.digests.get(&worker).and_then(|d| d.get(&seq)) {
            Some(&UNVERIFIED) => BatchId::Unverified,
            Some(&applied) if applied != digest => BatchId::Conflict { applied },
            // The same records, or an id restored from a version 1 snapshot of this server's own
            // (no digest): the server applied it itself, so this is its retry.
            _ => BatchId::Retry,
        }
    }

    /// Records batch `seq` of `worker` with content digest `digest` when it is new; returns
    /// what it was.
    pub fn insert_batch(&mut self, worker: u64, seq: u64, digest: u64) -> BatchId {
        let id = self.check_batch(worker, seq, digest);
        if id == BatchId::New {
            self.workers.entry(worker).or_default().insert(seq);
            self.digests.entry(worker).or_default().insert(seq, digest);
        }
        id
    }

    /// The batches applied, in the form states carry them.
    pub fn applied(&self) -> Vec<Applied> {
        self.applied_since(&Seen::default())
    }

    /// The batches applied that `base` (an earlier copy of this set) does not hold.
    pub fn applied_since(&self, base: &Seen) -> Vec<Applied> {
        let mut workers: Vec<u64> = self.workers.keys().copied().collect();
        workers.sort_unstable();
        workers
            .into_iter()
            .map(|w| {
                let old = base.workers.get(&w);
                let digests = self.digests.get(&w);
                let seqs = self.workers[&w]
                    .iter()
                    .filter(|&s| !old.is_some_and(|o| o.contains(s)))
                    .map(|s| (s, digests.and_then(|d| d.get(&s)).copied()));
                Applied::from_batches(w, seqs)
            })
            .filter(|a| !a.is_empty())
            .collect()
    }

    /// The first batch of `batches` that was applied here, and how many of them were.
    pub fn overlap(&self, batches: &[Applied]) -> Option<Overlap> {
        let mut first = None;
        let mut count = 0u64;
        for a in batches {
            let Some(set) = self.workers.get(&a.worker) else {
                continue;
            };
            for r in &a.ranges {
                let mut from = r.start;
                while let Some(seq) = set.first_in(from..r.end) {
                    first.get_or_insert((a.worker, seq));
                    count += 1;
                    from = seq + 1;
                }
            }
        }
        first.map(|(worker, seq)| Overlap { worker, seq, count })
    }

    /// Records `batches` (none of which may have been applied: see [`Seen::overlap`]), the
    /// batches of a state: those without a digest as [`UNVERIFIED`], so that a later post of
    /// one of them is refused ([`BatchId::Unverified`]) instead of taken for a retry and dropped.
    pub fn insert_applied(&mut self, batches: &[Applied]) {
        for a in batches {
            let set = self.workers.entry(a.worker).or_default();
            let digests = self.digests.entry(a.worker).or_default();
            for (seq, digest) in a.batches() {
                set.insert(seq);
                digests.insert(seq, digest.unwrap_or(UNVERIFIED));
            }
        }
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
    fn an_id_reused_for_other_records_is_a_conflict_not_a_retry() {
        let mut seen = Seen::default();
        assert_eq!(seen.insert_batch(7, 0, 0xAAAA), BatchId::New);
        assert_eq!(seen.insert_batch(7, 0, 0xAAAA), BatchId::Retry);
        assert_eq!(
            seen.insert_batch(7, 0, 0xBBBB),
            BatchId::Conflict { applied: 0xAAAA }
        );
        assert_eq!(seen.check_batch(7, 1, 0xBBBB), BatchId::New);
        // Ids restored without digests (old snapshots) can only be taken for retries.
        seen.workers.entry(8).or_default().insert(0);
        assert_eq!(seen.check_batch(8, 0, 1), BatchId::Retry);
    }

    /// The set round-trips through the states' form, a delta holds what was added since a
    /// copy, and overlaps are found wherever they lie (below the floor or above it).
    #[test]
    fn applied_batches_travel_and_overlaps_are_found() {
        let mut seen = Seen::default();
        for seq in [0, 1, 2, 5, 9] {
            seen.insert_batch(4, seq, 100 + seq);
        }
        seen.workers.entry(8).or_default().insert(3); // an old snapshot's id, no digest
        let applied = seen.applied();
        assert_eq!(applied.len(), 2);
        assert_eq!(applied[0].ranges, vec![0..3, 5..6, 9..10]);
        assert_eq!(applied[0].digests, vec![100, 101, 102, 105, 109]);
        assert_eq!(applied[1].digests, vec![0]);
        let mut copy = Seen::default();
        copy.insert_applied(&applied);
        assert_eq!(copy.applied(), applied);
        assert_eq!(
            copy.check_batch(4, 9, 1),
            BatchId::Conflict { applied: 109 }
        );
        // A state's batch without a digest is not a retry of whatever is posted under its id.
        assert_eq!(copy.check_batch(8, 3, 1), BatchId::Unverified);
        assert_eq!(
            seen.check_batch(8, 3, 1),
            BatchId::Retry,
            "a restored id of its own"
        );

        let base = seen.clone();
        seen.insert_batch(4, 3, 103);
        seen.insert_batch(6, 0, 600);
        let delta = seen.applied_since(&base);
        assert_eq!(delta.len(), 2);
        let spans = |a: &Applied| {
            (
                a.worker,
                a.ranges.iter().map(|r| (r.start, r.end)).collect(),
            )
        };
        assert_eq!(spans(&delta[0]), (4, vec![(3, 4)]));
        assert_eq!(spans(&delta[1]), (6, vec![(0, 1)]));
        assert_eq!(base.overlap(&delta), None);
        assert_eq!(
            seen.overlap(&delta),
            Some(Overlap {
                worker: 4,
                seq: 3,
                count: 2
            })
        );
        // Below the floor (seq 1) and above it (seq 9).
        let probe = [Applied::from_batches(4, [(1, None), (7, None), (9, None)])];
        assert_eq!(
            base.overlap(&probe),
            Some(Overlap {
                worker: 4,
                seq: 1,
                count: 2
            })
        );
    }

    #[test]
    fn senders_are_independent() {
        let mut seen = Seen::default();
        assert_eq!(seen.insert_batch(1, 0, 5), BatchId::New);
        assert_eq!(seen.insert_batch(2, 0, 5), BatchId::New);
        assert_eq!(seen.insert_batch(1, 0, 5), BatchId::Retry);
        assert!(seen.insert_delta("a", 0));
        assert!(!seen.insert_delta("a", 0));
        assert!(seen.insert_delta("b", 0));
    }
}
