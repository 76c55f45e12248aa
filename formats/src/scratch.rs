//! Working buffers kept between requests: decoding a pass, encoding an image, reading a body.
//!
//! A 1080p pass or image goes through a hundred or more megabytes of planes and buffers. Fresh
//! each time, every 4 KiB of them costs a page fault and a zeroed page (on a virtual machine
//! whose host takes freed memory back, a slow one); kept, they are already mapped. A request
//! takes a scratch from its [`Pool`] (or a new, empty one when none is free) and gives it back
//! when it is done, whatever the outcome. Scratches nobody took for a while are freed by
//! [`Pool::release_idle`], so a burst of large requests does not leave its memory held.

use std::time::{Duration, Instant};

/// A scratch a [`Pool`] can keep: a new one is empty ([`Default`]).
pub trait Reusable: Default {
    /// Bytes held.
    fn bytes(&self) -> usize;
}

/// At most `keep` idle scratches of type `S`, each with the time it was given back.
#[derive(Debug)]
pub struct Pool<S> {
    free: std::sync::Mutex<Vec<(Instant, S)>>,
    keep: usize,
}

impl<S: Reusable> Pool<S> {
    /// A pool that keeps at most `keep` idle scratches.
    pub fn new(keep: usize) -> Pool<S> {
        Pool {
            free: std::sync::Mutex::new(Vec::new()),
            keep,
        }
    }

    /// A free scratch (the one given back last), or a new empty one.
    pub fn take(&self) -> S {
        self.lock().pop().map(|(_, s)| s).unwrap_or_default()
    }

    /// The largest free scratch (by [`Reusable::bytes`]), or a new empty one: for scratches
    /// of any size, so that a large request finds the one that fits it already.
    pub fn take_largest(&self) -> S {
        let mut free = self.lock();
        let largest = (0..free.len()).max_by_key(|&i| free[i].1.bytes());
        largest.map(|i| free.swap_remove(i).1).unwrap_or_default()
    }

    /// Gives `scratch` back for a later request (dropped if `keep` are already idle).
    pub fn give(&self, scratch: S) {
        let mut free = self.lock();
        if free.len() < self.keep {
            free.push((Instant::now(), scratch));
        }
    }

    /// Frees the scratches given back more than `idle` before `now`; returns their bytes.
    pub fn release_idle(&self, now: Instant, idle: Duration) -> usize {
        let mut freed = 0;
        self.lock().retain(|(since, scratch)| {
            let keep = now.saturating_duration_since(*since) < idle;
            if !keep {
                freed += scratch.bytes();
            }
            keep
        });
        freed
    }

    /// Bytes held by the idle scratches.
    pub fn idle_bytes(&self) -> usize {
        self.lock().iter().map(|(_, s)| s.bytes()).sum()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<(Instant, S)>> {
        // A scratch holds no invariant a panic could break: a poisoned lock is still usable.
        self.free.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A plain byte buffer (a request body): its capacity is what it holds.
impl Reusable for Vec<u8> {
    fn bytes(&self) -> usize {
        self.capacity()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Default)]
    struct Buffer(Vec<u8>);

    impl Reusable for Buffer {
        fn bytes(&self) -> usize {
            self.0.capacity()
        }
    }

    /// A scratch given back is taken again; `keep` bounds the idle ones; the ones idle for the
    /// given time are freed, the younger kept (times passed in: nothing sleeps).
    #[test]
    fn idle_scratches_are_reused_then_freed() {
        let pool = Pool::<Buffer>::new(2);
        let minute = Duration::from_secs(60);
        pool.give(Buffer(Vec::with_capacity(100)));
        let given = Instant::now();
        assert_eq!(pool.take().0.capacity(), 100);
        assert_eq!(pool.take().0.capacity(), 0, "a new one when none is free");
        for n in [10, 20, 30] {
            pool.give(Buffer(Vec::with_capacity(n)));
        }
        assert_eq!(pool.idle_bytes(), 30, "the third was dropped: keep 2");
        assert_eq!(pool.release_idle(given, minute), 0);
        let later = Instant::now() + minute;
        assert_eq!(pool.release_idle(later, minute), 30);
        assert_eq!(pool.idle_bytes(), 0);
    }

    /// `take_largest` takes the largest idle scratch whatever order they came back in.
    #[test]
    fn the_largest_scratch_is_taken_first() {
        let pool = Pool::<Vec<u8>>::new(3);
        for n in [20, 50, 10] {
            pool.give(Vec::with_capacity(n));
        }
        assert_eq!(pool.take_largest().capacity(), 50);
        assert_eq!(pool.take_largest().capacity(), 20);
        assert_eq!(pool.take_largest().capacity(), 10);
        assert_eq!(
            pool.take_largest().capacity(),
            0,
            "a new one when none is free"
        );
    }
}
