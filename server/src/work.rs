//! The working-memory budget: what requests may allocate beyond the frames themselves.
//!
//! Frames are admitted against `--max-memory-mib` when they are created. Everything else a
//! request allocates in proportion to a frame (a consistent copy to resolve or export, the
//! resolved layers, an encoded EXR or PNG, an imported state, a decompressed batch) comes out of
//! one shared budget instead, so that no mix of clients can multiply the state: a request
//! reserves its estimated bytes before it allocates them, waits a bounded time when the budget is
//! spent, and is then refused (the HTTP layer answers 503 with `Retry-After`).
//!
//! A request larger than the whole budget is not refused forever: it runs when it would be the
//! only reservation, so a frame bigger than the budget can still be resolved, one at a time.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::Notify;

/// A shared allowance of bytes, reserved by requests while they hold large buffers.
#[derive(Debug)]
pub struct WorkBudget {
    capacity: u64,
    wait: Duration,
    used: Mutex<u64>,
    released: Notify,
}

/// Bytes reserved from a [`WorkBudget`]; given back when dropped.
#[derive(Debug)]
pub struct Reservation {
    budget: Arc<WorkBudget>,
    bytes: u64,
}

/// The budget stayed spent for longer than a request may wait.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "the server's working memory is in use ({used} of {capacity} bytes reserved; this request \
     needs {needed}); retry in {} s",
    retry_after.as_secs()
)]
pub struct Busy {
    /// Bytes the request asked for.
    pub needed: u64,
    /// Bytes reserved by others when it gave up.
    pub used: u64,
    /// The whole budget.
    pub capacity: u64,
    /// When a retry is likely to succeed.
    pub retry_after: Duration,
}

impl WorkBudget {
    /// A budget of `capacity` bytes; a request waits at most `wait` for its share.
    pub fn new(capacity: u64, wait: Duration) -> Arc<WorkBudget> {
        Arc::new(WorkBudget {
            capacity,
            wait,
            used: Mutex::new(0),
            released: Notify::new(),
        })
    }

    /// The whole budget in bytes.
    pub fn capacity(&self) -> u64 {
        self.capacity
    }

    /// Bytes reserved now.
    pub fn used(&self) -> u64 {
        *self.lock()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, u64> {
        self.used.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Reserves without waiting; `None` when it does not fit now.
    pub fn try_reserve(self: &Arc<Self>, bytes: u64) -> Option<Reservation> {
        let mut used = self.lock();
        let fits = used.saturating_add(bytes) <= self.capacity || *used == 0;
        fits.then(|| {
            *used += bytes;
            Reservation {
                budget: self.clone(),
                bytes,
            }
        })
    }

    /// Reserves without waiting, or the [`Busy`] a request that waited would have got.
    pub fn reserve_now(self: &Arc<Self>, bytes: u64) -> Result<Reservation, Busy> {
        self.try_reserve(bytes).ok_or_else(|| Busy {
            needed: bytes,
            used: self.used(),
            capacity: self.capacity,
            retry_after: self.wait.max(Duration::from_secs(1)),
        })
    }

    /// Reserves `bytes`, waiting up to the budget's wait for others to give theirs back.
    pub async fn reserve(self: &Arc<Self>, bytes: u64) -> Result<Reservation, Busy> {
        let deadline = tokio::time::Instant::now() + self.wait;
        loop {
            // Registered before trying, so a release between the try and the wait is not missed.
            let released = self.released.notified();
            tokio::pin!(released);
            released.as_mut().enable();
            if let Some(r) = self.try_reserve(bytes) {
                return Ok(r);
            }
            if tokio::time::timeout_at(deadline, released).await.is_err() {
                return Err(Busy {
                    needed: bytes,
                    used: self.used(),
                    capacity: self.capacity,
                    retry_after: self.wait.max(Duration::from_secs(1)),
                });
            }
        }
    }
}

impl Reservation {
    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Gives back all but `bytes` of the reservation (when a request's working memory shrinks,
    /// e.g. a copy of the state dropped while its encoding is still being sent).
    pub fn shrink_to(&mut self, bytes: u64) {
        if bytes < self.bytes {
            *self.budget.lock() -= self.bytes - bytes;
            self.bytes = bytes;
            self.budget.released.notify_waiters();
        }
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        *self.budget.lock() -= self.bytes;
        self.budget.released.notify_waiters();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn requests_wait_for_room_and_give_up_after_the_wait() {
        let budget = WorkBudget::new(100, Duration::from_secs(5));
        let a = budget.reserve(60).await.unwrap();
        let b = budget.reserve(40).await.unwrap();
        assert_eq!(budget.used(), 100);

        // Room comes back before the wait ends: the waiter gets it.
        let waiter = tokio::spawn({
            let budget = budget.clone();
            async move { budget.reserve(50).await.map(|r| r.bytes()) }
        });
        tokio::time::sleep(Duration::from_secs(2)).await;
        drop(a);
        assert_eq!(waiter.await.unwrap(), Ok(50));

        // Shrinking gives the difference back at once.
        let mut b = b;
        b.shrink_to(10);
        assert_eq!((b.bytes(), budget.used()), (10, 10));
        let more = budget.try_reserve(90).expect("room given back");
        drop(more);

        // No room within the wait: refused with what was in use.
        let _c = budget.reserve(60).await.unwrap();
        let _d = budget.reserve(30).await.unwrap();
        let err = budget.reserve(50).await.unwrap_err();
        assert_eq!((err.needed, err.used, err.capacity), (50, 100, 100));
        drop(b);
    }

    #[tokio::test(start_paused = true)]
    async fn a_request_larger_than_the_budget_runs_alone() {
        let budget = WorkBudget::new(100, Duration::from_secs(5));
        let big = budget.reserve(250).await.unwrap();
        assert!(budget.try_reserve(1).is_none(), "nothing fits beside it");
        drop(big);
        assert_eq!(budget.used(), 0);
        let small = budget.reserve(10).await.unwrap();
        assert!(
            budget.reserve(250).await.is_err(),
            "not beside another request"
        );
        drop(small);
    }
}
