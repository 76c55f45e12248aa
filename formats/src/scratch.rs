//! Working buffers kept between requests: decoding a pass, encoding an image.
//!
//! A 1080p pass or image goes through a hundred or more megabytes of planes and buffers. Fresh
//! each time, every 4 KiB of them costs a page fault and a zeroed page (on a virtual machine
//! whose host takes freed memory back, a slow one); kept, they are already mapped. A request
//! takes a scratch from its [`Pool`] (or a new, empty one when none is free) and gives it back
//! when it is done, whatever the outcome.

/// A scratch a [`Pool`] can keep: a new one is empty ([`Default`]).
pub trait Reusable: Default {
    /// Bytes held.
    fn bytes(&self) -> usize;
}

/// At most `keep` idle scratches of type `S`.
#[derive(Debug)]
pub struct Pool<S> {
    free: std::sync::Mutex<Vec<S>>,
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

    /// A free scratch, or a new empty one.
    pub fn take(&self) -> S {
        self.lock().pop().unwrap_or_default()
    }

    /// Gives `scratch` back for a later request (dropped if `keep` are already idle).
    pub fn give(&self, scratch: S) {
        let mut free = self.lock();
        if free.len() < self.keep {
            free.push(scratch);
        }
    }

    /// Bytes held by the idle scratches.
    pub fn idle_bytes(&self) -> usize {
        self.lock().iter().map(S::bytes).sum()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<S>> {
        // A scratch holds no invariant a panic could break: a poisoned lock is still usable.
        self.free.lock().unwrap_or_else(|p| p.into_inner())
    }
}
