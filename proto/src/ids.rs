//! The one source of random ids: worker ids, node ids and server boot ids.
//!
//! Ids only need to differ between processes that talk to the same server, so 64 bits from the
//! standard library's per-process random seed (which comes from the operating system), mixed with
//! the time and the process id, are enough, and no random-number crate is needed.

use std::hash::{BuildHasher, RandomState};
use std::time::SystemTime;

/// 64 random bits, different in every call and in every process.
pub fn random_u64() -> u64 {
    RandomState::new().hash_one((SystemTime::now(), std::process::id()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calls_differ() {
        let ids: std::collections::HashSet<u64> = (0..1000).map(|_| random_u64()).collect();
        assert_eq!(ids.len(), 1000);
    }
}
