//! Resolved images shared between requests: one resolve per frame version and query.
//!
//! A resolve copies the frame's state (hundreds of megabytes for a 1080p frame) and writes its
//! layers; twelve dashboards asking for the same frame at once used to do that twelve times.
//! Here concurrent requests for the same frame version and query wait for one render and share
//! its encoded bytes (a `Bytes` is reference-counted, so a slow reader pins no copy of its own),
//! and the latest render of each query stays cached until the frame changes.
//!
//! The render reserves its working memory from the [`WorkBudget`] first; a request that cannot
//! get it in time fails with [`Busy`] and leaves nothing cached.
//!
//! A render runs on a thread of its own at a lower scheduling priority (nice [`RENDER_NICE`],
//! inherited by the resolve's own threads): a resolve may use every core, and at equal priority
//! it starved the request loop (`/healthz` took 374 ms behind 64 image requests on two cores).
//! At nice 10 it takes the cores the request loop and ingest leave idle.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use bytes::Bytes;
use tokio::sync::OnceCell;

use crate::frame::ShardedFrame;
use crate::work::{Busy, WorkBudget};

pub mod denoise;
pub mod figures;
mod kept;
pub use kept::{KeptResolves, Made, MAX_KEPT};

/// Which render of a frame: the frame's serial (so a deleted and re-created frame never hits
/// the old one's renders), its version, and the query in a canonical form.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Key {
    frame: u64,
    version: u64,
    query: String,
}

type Slot = Arc<OnceCell<Bytes>>;

pub use crate::priority::RENDER_NICE;

/// Runs `work` on a new thread of lower priority ([`RENDER_NICE`]); its result, or `Err` if it
/// panicked. A blocking-pool task waits for the thread, so tokio counts the render as work in
/// flight (a paused test clock does not jump past it).
async fn on_render_thread<T: Send + 'static>(
    work: impl FnOnce() -> T + Send + 'static,
) -> Result<T, tokio::task::JoinError> {
    crate::priority::on_low_priority_thread("splatd-render", work).await
}

/// Why a render failed.
#[derive(Debug, thiserror::Error)]
pub enum RenderError<E> {
    /// The working-memory budget stayed spent.
    #[error(transparent)]
    Busy(#[from] Busy),
    /// The render itself failed.
    #[error("{0}")]
    Failed(E),
}

/// Renders in progress and the latest finished one per frame and query.
#[derive(Debug)]
pub struct Renders {
    slots: Mutex<VecDeque<(Key, Slot)>>,
    /// Most renders kept; the oldest go first.
    max_slots: usize,
    budget: Arc<WorkBudget>,
    /// Renders run so far (shared ones count once).
    rendered: std::sync::atomic::AtomicU64,
    /// The latest resolve of the frames rendered last, which renders patch.
    kept: Arc<KeptResolves>,
}

impl Renders {
    /// An empty cache keeping at most `max_slots` renders, reserving from `budget`.
    pub fn new(max_slots: usize, budget: Arc<WorkBudget>) -> Renders {
        Renders {
            slots: Mutex::new(VecDeque::new()),
            max_slots: max_slots.max(1),
            budget,
            rendered: Default::default(),
            kept: Arc::default(),
        }
    }

    /// How many renders ran so far; requests that shared one count once.
    pub fn rendered(&self) -> u64 {
        self.rendered.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// The kept resolves that renders patch (see [`KeptResolves`]).
    pub fn kept(&self) -> &Arc<KeptResolves> {
        &self.kept
    }

    /// The budget renders reserve from.
    pub fn budget(&self) -> &Arc<WorkBudget> {
        &self.budget
    }

    fn slot(&self, key: Key) -> Slot {
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, slot)) = slots.iter().find(|(k, _)| *k == key) {
            return slot.clone();
        }
        // Older versions of the same render are stale from now on.
        slots.retain(|(k, _)| !(k.frame == key.frame && k.query == key.query));
        let slot = Slot::default();
        slots.push_back((key, slot.clone()));
        while slots.len() > self.max_slots {
            slots.pop_front();
        }
        slot
    }

    /// Forgets every render of `frame` (when it is deleted).
    pub fn forget(&self, frame: &ShardedFrame) {
        let serial = frame.serial();
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        slots.retain(|(k, _)| k.frame != serial);
        drop(slots);
        self.kept.forget(frame);
    }

    /// The bytes of `query` rendered from `frame` as it is now: shared with every concurrent or
    /// earlier request for the same version and query, or rendered by `render` on the blocking
    /// pool after reserving `cost` bytes of working memory.
    ///
    /// The version is read before rendering; if samples arrive meanwhile, the bytes may show a
    /// slightly newer state than the version they are filed under, never an older one.
    pub async fn get_or_render<E: Send + 'static>(
        &self,
        frame: &Arc<ShardedFrame>,
        query: String,
        cost: u64,
        render: impl FnOnce(&ShardedFrame) -> Result<Bytes, E> + Send + 'static,
    ) -> Result<Bytes, RenderError<E>> {
        let key = Key {
            frame: frame.serial(),
            version: frame.version(),
            query,
        };
        let slot = self.slot(key);
        let frame = frame.clone();
        let budget = self.budget.clone();
        slot.get_or_try_init(|| async move {
            let reservation = budget.reserve(cost).await?;
            self.rendered
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let rendered = on_render_thread(move || {
                let bytes = render(&frame);
                drop(reservation);
                bytes
            })
            .await
            .expect("a render does not panic");
            rendered.map_err(RenderError::Failed)
        })
        .await
        .cloned()
        .inspect(|_| self.trim())
    }

    /// Drops the oldest finished renders while the kept ones hold more than a quarter of the
    /// working budget: cached bytes are memory too. Renders still in progress stay.
    fn trim(&self) {
        let cap = self.budget.capacity() / 4;
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        let held = |slots: &VecDeque<(Key, Slot)>| -> u64 {
            slots
                .iter()
                .filter_map(|(_, s)| s.get().map(|b| b.len() as u64))
                .sum()
        };
        while held(&slots) > cap {
            match slots.iter().position(|(_, s)| s.initialized()) {
                Some(oldest) => drop(slots.remove(oldest)),
                None => break,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::FrameSpec;
    use splatd_proto::api::CreateFrame;
    use splatd_proto::{Batch, Record};
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::time::Duration;

    fn frame() -> Arc<ShardedFrame> {
        Arc::new(ShardedFrame::new(
            FrameSpec::new(CreateFrame::new("f", 4, 4)).unwrap(),
        ))
    }

    fn counting(
        calls: &Arc<AtomicUsize>,
    ) -> impl FnOnce(&ShardedFrame) -> Result<Bytes, String> + Send + 'static {
        let calls = calls.clone();
        move |f: &ShardedFrame| {
            calls.fetch_add(1, Ordering::SeqCst);
            Ok(Bytes::from(format!("v{}", f.version())))
        }
    }

    #[tokio::test]
    async fn concurrent_requests_for_one_version_share_one_render() {
        let renders = Arc::new(Renders::new(8, WorkBudget::new(1 << 20, Duration::ZERO)));
        let f = frame();
        let calls = Arc::new(AtomicUsize::new(0));
        let mut tasks = Vec::new();
        for _ in 0..16 {
            let (renders, f, render) = (renders.clone(), f.clone(), counting(&calls));
            tasks.push(tokio::spawn(async move {
                renders
                    .get_or_render(&f, "q".into(), 100, render)
                    .await
                    .unwrap()
            }));
        }
        for t in tasks {
            assert_eq!(t.await.unwrap(), "v0");
        }
        assert_eq!(calls.load(Ordering::SeqCst), 1);

        // Another query renders on its own; a new version renders again.
        renders
            .get_or_render(&f, "other".into(), 100, counting(&calls))
            .await
            .unwrap();
        assert_eq!(calls.load(Ordering::SeqCst), 2);
        let batch = Batch::new("f", 1, 0, vec![Record::new(0, 0, [1.0; 3])]).unwrap();
        f.ingest(&batch).unwrap();
        let again = renders
            .get_or_render(&f, "q".into(), 100, counting(&calls))
            .await;
        assert_eq!(again.unwrap(), "v1");
        assert_eq!(calls.load(Ordering::SeqCst), 3);
    }

    /// A render runs at nice RENDER_NICE, read back by the render itself from the kernel, while
    /// the caller keeps its own priority.
    #[tokio::test]
    async fn renders_run_below_the_request_loop() {
        fn nice() -> i32 {
            // SAFETY: gettid and getpriority only read their arguments.
            unsafe {
                let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
                libc::getpriority(libc::PRIO_PROCESS, tid)
            }
        }
        let renders = Renders::new(8, WorkBudget::new(1 << 20, Duration::ZERO));
        let before = nice();
        let seen = renders
            .get_or_render(&frame(), "q".into(), 1, |_: &ShardedFrame| {
                Ok::<_, String>(Bytes::from(nice().to_string()))
            })
            .await
            .unwrap();
        let seen: i32 = std::str::from_utf8(&seen).unwrap().parse().unwrap();
        // A process already below nice 10 stays where it is (unprivileged, it cannot rise).
        assert!(
            seen == RENDER_NICE || (before > RENDER_NICE && seen == before),
            "render at nice {seen}, caller at {before}"
        );
        assert_eq!(nice(), before, "the caller's priority is its own");
    }

    #[tokio::test]
    async fn cached_bytes_stay_within_a_quarter_of_the_budget() {
        let renders = Renders::new(8, WorkBudget::new(400, Duration::ZERO));
        let f = frame();
        for q in 0..5 {
            let bytes = renders
                .get_or_render(&f, format!("q{q}"), 1, |_| {
                    Ok::<_, String>(Bytes::from(vec![0u8; 40]))
                })
                .await
                .unwrap();
            assert_eq!(
                bytes.len(),
                40,
                "the caller gets its bytes even if they are not kept"
            );
        }
        let slots = renders.slots.lock().unwrap();
        let held: usize = slots
            .iter()
            .filter_map(|(_, s)| s.get().map(Bytes::len))
            .sum();
        assert_eq!(held, 80, "two renders of 40 bytes fit 100");
        assert_eq!(slots.back().unwrap().0.query, "q4", "the newest is kept");
    }

    #[tokio::test(start_paused = true)]
    async fn a_render_without_memory_is_refused_and_not_cached() {
        let budget = WorkBudget::new(100, Duration::from_secs(3));
        let renders = Renders::new(8, budget.clone());
        let f = frame();
        let held = budget.reserve(80).await.unwrap();
        let calls = Arc::new(AtomicUsize::new(0));
        let err = renders
            .get_or_render(&f, "q".into(), 50, counting(&calls))
            .await
            .unwrap_err();
        assert!(matches!(err, RenderError::Busy(_)), "{err}");
        assert_eq!(calls.load(Ordering::SeqCst), 0);
        drop(held);
        let ok = renders
            .get_or_render(&f, "q".into(), 50, counting(&calls))
            .await;
        assert_eq!(ok.unwrap(), "v0");
        assert_eq!(budget.used(), 0, "the reservation ends with the render");
    }
}
