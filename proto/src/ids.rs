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

/// Ids that travel as JSON numbers (a server's `boot`, a worker id) stay below this, so that
/// JavaScript's `JSON.parse`, which reads numbers as doubles, keeps them exact.
pub const MAX_JSON_SAFE_ID: u64 = (1 << 53) - 1;

/// A random id in `1..=MAX_JSON_SAFE_ID`: 53 random bits, never 0.
pub fn random_id() -> u64 {
    (random_u64() >> 11).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_exact_in_json_doubles() {
        for _ in 0..1000 {
            let id = random_id();
            assert!((1..=MAX_JSON_SAFE_ID).contains(&id));
            assert_eq!(id as f64 as u64, id);
        }
    }

    #[test]
    fn calls_differ() {
        let ids: std::collections::HashSet<u64> = (0..1000).map(|_| random_u64()).collect();
        assert_eq!(ids.len(), 1000);
    }
}
