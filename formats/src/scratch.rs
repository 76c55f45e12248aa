//! Working buffers kept between requests: decoding a pass, encoding an image, reading a body,
//! and the cells of a deleted frame kept for the next one.
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
    free: std::sync::Mutex<Free<S>>,
    keep: usize,
    /// Told the idle bytes after every change, under the pool's lock, so that what it sets (a
    /// gauge) is never left behind by a change that raced it.
    watch: Option<fn(usize)>,
}

/// Idle scratches, each with the time it was given back.
type Free<S> = Vec<(Instant, S)>;

impl<S: Reusable> Pool<S> {
    /// A pool that keeps at most `keep` idle scratches.
    pub fn new(keep: usize) -> Pool<S> {
        Pool {
            free: std::sync::Mutex::new(Vec::new()),
            keep,
            watch: None,
        }
    }

    /// [`Pool::new`], calling `watch` with the idle bytes whenever they change.
    pub fn watched(keep: usize, watch: fn(usize)) -> Pool<S> {
        Pool {
            watch: Some(watch),
            ..Pool::new(keep)
        }
    }

    /// A free scratch (the one given back last), or a new empty one.
    pub fn take(&self) -> S {
        self.change(|free| free.pop().map(|(_, s)| s))
            .unwrap_or_default()
    }

    /// The largest free scratch (by [`Reusable::bytes`]), or a new empty one: for scratches
    /// of any size, so that a large request finds the one that fits it already.
    pub fn take_largest(&self) -> S {
        self.change(|free| {
            let largest = (0..free.len()).max_by_key(|&i| free[i].1.bytes());
            largest.map(|i| free.swap_remove(i).1)
        })
        .unwrap_or_default()
    }

    /// The smallest free scratch holding at least `bytes` and at most `most`, or a new empty
    /// one: for scratches that must have room for a size (a frame's cells), so a large one is
    /// left for a large request.
    pub fn take_fitting(&self, bytes: usize, most: usize) -> S {
        self.change(|free| {
            let fit = (0..free.len())
                .filter(|&i| (bytes..=most).contains(&free[i].1.bytes()))
                .min_by_key(|&i| free[i].1.bytes());
            fit.map(|i| free.swap_remove(i).1)
        })
        .unwrap_or_default()
    }

    /// Gives `scratch` back for a later request (dropped if `keep` are already idle).
    pub fn give(&self, scratch: S) {
        self.change(|free| {
            if free.len() < self.keep {
                free.push((Instant::now(), scratch));
            }
        })
    }

    /// Frees the scratches given back more than `idle` before `now`; returns their bytes.
    pub fn release_idle(&self, now: Instant, idle: Duration) -> usize {
        self.change(|free| {
            let mut freed = 0;
            free.retain(|(since, scratch)| {
                let keep = now.saturating_duration_since(*since) < idle;
                if !keep {
                    freed += scratch.bytes();
                }
                keep
            });
            freed
        })
    }

    /// Bytes held by the idle scratches.
    pub fn idle_bytes(&self) -> usize {
        idle_bytes(&self.lock())
    }

    /// Makes `change` to the idle scratches, then tells the watcher, under the lock.
    fn change<T>(&self, change: impl FnOnce(&mut Free<S>) -> T) -> T {
        let mut free = self.lock();
        let result = change(&mut free);
        if let Some(watch) = self.watch {
            watch(idle_bytes(&free));
        }
        result
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Free<S>> {
        // A scratch holds no invariant a panic could break: a poisoned lock is still usable.
        self.free.lock().unwrap_or_else(|p| p.into_inner())
    }
}

fn idle_bytes<S: Reusable>(free: &Free<S>) -> usize {
    free.iter().map(|(_, s)| s.bytes()).sum()
}

/// A plain byte buffer (a request body): its capacity is what it holds.
impl Reusable for Vec<u8> {
    fn bytes(&self) -> usize {
        self.capacity()
    }
}

/// A plain word buffer (a frame's cells): its capacity is what it holds.
impl Reusable for Vec<u64> {
    fn bytes(&self) -> usize {
        self.capacity() * 8
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

    /// `take_fitting` takes the smallest idle scratch with room for the size asked and no larger
    /// than the most asked, leaving larger ones for larger requests; the watcher hears every
    /// change of the idle bytes.
    #[test]
    fn the_smallest_fitting_scratch_is_taken_and_watched() {
        static IDLE: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let pool = Pool::<Vec<u64>>::watched(usize::MAX, |bytes| {
            IDLE.store(bytes, std::sync::atomic::Ordering::Relaxed)
        });
        let idle = || IDLE.load(std::sync::atomic::Ordering::Relaxed);
        for n in [30, 10, 20] {
            pool.give(Vec::with_capacity(n));
        }
        assert_eq!(idle(), 60 * 8);
        assert_eq!(pool.take_fitting(12 * 8, usize::MAX).capacity(), 20);
        assert_eq!(idle(), 40 * 8);
        assert_eq!(
            pool.take_fitting(31 * 8, usize::MAX).capacity(),
            0,
            "none has room: a new one"
        );
        assert_eq!(
            pool.take_fitting(2 * 8, 9 * 8).capacity(),
            0,
            "none is small enough: a new one"
        );
        assert_eq!(pool.take_fitting(1, usize::MAX).capacity(), 10);
        assert_eq!(idle(), 30 * 8);
        let later = Instant::now() + Duration::from_secs(60);
        assert_eq!(pool.release_idle(later, Duration::from_secs(1)), 30 * 8);
        assert_eq!((idle(), pool.idle_bytes()), (0, 0));
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
