//! The cap on open connections: who is admitted, and who is pushed out to make room.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::Notify;

use super::conn::Conn;

/// The open connections of a server, and the cap on them.
#[derive(Debug)]
pub struct Connections {
    max: usize,
    open: Mutex<BTreeMap<u64, Arc<Conn>>>,
    next: AtomicU64,
    refused: AtomicU64,
    evicted: AtomicU64,
    /// Connections pushed out whose sockets are not closed yet (their tasks have yet to run).
    closing: AtomicUsize,
    /// Wakes [`Connections::until_open_at_most`] when a connection closes.
    closed: Notify,
}

/// Why a connection was not served.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refused {
    /// Every open connection is serving a request: the new one is closed at once.
    Full,
}

impl Connections {
    /// No connections yet; at most `max` at once.
    pub fn new(max: usize) -> Connections {
        Connections {
            max: max.max(1),
            open: Mutex::new(BTreeMap::new()),
            next: AtomicU64::new(0),
            refused: AtomicU64::new(0),
            evicted: AtomicU64::new(0),
            closing: AtomicUsize::new(0),
            closed: Notify::new(),
        }
    }

    /// Returns once at most `n` connections are open.
    pub async fn until_open_at_most(&self, n: usize) {
        loop {
            let closed = self.closed.notified();
            tokio::pin!(closed);
            closed.as_mut().enable();
            if self.open() <= n {
                return;
            }
            closed.await;
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Arc<Conn>>> {
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The cap.
    pub fn max(&self) -> usize {
        self.max
    }

    /// Connections open now (not counting those pushed out and still closing).
    pub fn open(&self) -> usize {
        self.lock().len()
    }

    /// Most connections pushed out and not yet closed at once: an eighth of the cap, at least
    /// 64 (the open-file limit leaves a quarter of itself, at least 64, beyond the cap).
    pub fn closing_allowance(&self) -> usize {
        (self.max / 8).max(64)
    }

    /// Connections closed at once because every place was serving a request.
    pub fn refused(&self) -> u64 {
        self.refused.load(Ordering::Relaxed)
    }

    /// Connections closed to make room for a new one.
    pub fn evicted(&self) -> u64 {
        self.evicted.load(Ordering::Relaxed)
    }

    /// Admits a new connection, pushing out an unoccupied one when at the cap. The returned
    /// [`Registered`] takes the connection's place back when dropped.
    ///
    /// Connections pushed out keep their sockets until their tasks run, so the sockets open
    /// are at most the cap plus the connections still closing; at most [`Self::closing_allowance`]
    /// may be closing at once, beyond that a new connection is refused instead.
    pub fn admit(self: &Arc<Self>) -> Result<Registered, Refused> {
        let mut open = self.lock();
        if open.len() >= self.max {
            if self.closing.load(Ordering::Acquire) >= self.closing_allowance() {
                self.refused.fetch_add(1, Ordering::Relaxed);
                metrics::counter!(crate::meters::CONNECTIONS_CLOSED, "reason" => "full")
                    .increment(1);
                return Err(Refused::Full);
            }
            // Oldest first (ids grow), those that never sent a head before idle keep-alive ones.
            let idle = |c: &&Arc<Conn>| c.busy.load(Ordering::Acquire) == 0;
            let victim = open
                .values()
                .filter(idle)
                .find(|c| !c.had_head.load(Ordering::Acquire))
                .or_else(|| open.values().find(idle))
                .map(|c| c.id);
            match victim {
                Some(id) => {
                    let conn = open.remove(&id).expect("found above");
                    conn.evicted.store(true, Ordering::Release);
                    self.closing.fetch_add(1, Ordering::AcqRel);
                    conn.evict.notify_one();
                    self.evicted.fetch_add(1, Ordering::Relaxed);
                    metrics::counter!(crate::meters::CONNECTIONS_CLOSED, "reason" => "evicted")
                        .increment(1);
                }
                None => {
                    self.refused.fetch_add(1, Ordering::Relaxed);
                    metrics::counter!(crate::meters::CONNECTIONS_CLOSED, "reason" => "full")
                        .increment(1);
                    return Err(Refused::Full);
                }
            }
        }
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let conn = Arc::new(Conn {
            id,
            had_head: AtomicBool::new(false),
            evicted: AtomicBool::new(false),
            busy: AtomicUsize::new(0),
            responding_since: Mutex::new(None),
            changed: Notify::new(),
            evict: Notify::new(),
            refusal: Mutex::new(None),
            finishing: Mutex::new(None),
        });
        open.insert(id, conn.clone());
        Ok(Registered {
            connections: self.clone(),
            conn,
        })
    }
}

/// A connection's place among the open ones; given back when dropped.
#[derive(Debug)]
pub struct Registered {
    connections: Arc<Connections>,
    conn: Arc<Conn>,
}

impl Registered {
    /// The connection's shared state.
    pub fn conn(&self) -> &Arc<Conn> {
        &self.conn
    }
}

impl Drop for Registered {
    fn drop(&mut self) {
        // A response still waiting for its flush ends with the connection (and the cycle
        // between the connection and that request's guard with it).
        drop(self.conn.finish());
        if self.conn.evicted.load(Ordering::Acquire) {
            self.connections.closing.fetch_sub(1, Ordering::AcqRel);
        }
        self.connections.lock().remove(&self.conn.id);
        self.connections.closed.notify_waiters();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn at_the_cap_a_connection_without_work_makes_room() {
        let connections = Arc::new(Connections::new(2));
        let a = connections.admit().unwrap();
        let b = connections.admit().unwrap();
        // `a` has a request in progress; `b` sent a head and idles: `b` goes.
        let _request = a.conn().begin_request();
        b.conn().had_head.store(true, Ordering::Release);
        let c = connections.admit().unwrap();
        assert_eq!(connections.evicted(), 1);
        assert_eq!(connections.open(), 2);
        // `c` is silent and `b` was already pushed out: `c` goes next, before anything busy.
        let d = connections.admit().unwrap();
        assert_eq!(connections.evicted(), 2);
        // Everyone left is serving a request: a new connection is refused.
        let _busy = d.conn().begin_request();
        assert_eq!(connections.admit().unwrap_err(), Refused::Full);
        assert_eq!(connections.refused(), 1);
        drop((b, c));
        assert_eq!(connections.open(), 2);
        assert_eq!(connections.closing.load(Ordering::Acquire), 0);
    }

    #[test]
    fn connections_still_closing_count_against_the_cap() {
        let connections = Arc::new(Connections::new(4));
        let allowance = connections.closing_allowance();
        let mut held: Vec<Registered> = (0..4).map(|_| connections.admit().unwrap()).collect();
        // Each new one pushes out an old one whose task has not closed it yet.
        for _ in 0..allowance {
            held.push(connections.admit().unwrap());
        }
        assert_eq!(connections.closing.load(Ordering::Acquire), allowance);
        assert_eq!(connections.admit().unwrap_err(), Refused::Full);
        // One closes: room for one more.
        held.remove(0);
        assert!(connections.admit().is_ok());
    }

    #[test]
    fn a_response_counts_until_flushed() {
        let connections = Arc::new(Connections::new(1));
        let a = connections.admit().unwrap();
        a.conn().had_head.store(true, Ordering::Release);
        // The body has ended, the bytes may still be in hyper's buffer: not idle yet.
        let mut guard = a.conn().begin_request();
        guard.responding();
        *a.conn().finishing.lock().unwrap() = Some(guard);
        assert_eq!(connections.admit().unwrap_err(), Refused::Full);
        assert!(a.conn().responding_since.lock().unwrap().is_some());
        // Flushed: the request is over and the connection may make room.
        drop(a.conn().finish());
        assert!(a.conn().responding_since.lock().unwrap().is_none());
        let _b = connections.admit().unwrap();
        assert_eq!(connections.evicted(), 1);
        // A connection that ends with a response unflushed drops it (no cycle left behind).
        let c = Arc::new(Connections::new(1)).admit().unwrap();
        *c.conn().finishing.lock().unwrap() = Some(c.conn().begin_request());
        let conn = c.conn().clone();
        drop(c);
        assert_eq!(conn.busy.load(Ordering::Acquire), 0);
        assert_eq!(Arc::strong_count(&conn), 1);
    }
}
