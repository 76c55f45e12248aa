//! Resolved images shared between requests: one render at a time per frame and query, shared by
//! every request it can answer.
//!
//! A resolve reads the whole frame (hundreds of megabytes of state for a 1080p frame) and writes
//! its layers; twelve dashboards asking for the same frame at once used to do that twelve times,
//! and while workers add samples every request saw a new version and started a render of its
//! own beside the others. Here each frame and query has one render in flight at most: a request
//! is answered by the latest render if that render read the frame at the request's version or
//! later (it then holds every sample acknowledged before the request came); otherwise it waits
//! for the render in flight, and if that one read an older version, the next render (one, for
//! everyone who waited) answers it. A dashboard polling a frame that workers keep changing thus
//! costs at most one render after another per frame and query, however many watch it. Bytes are
//! reference-counted, so a slow reader pins no copy of its own, and the latest render of each
//! query stays cached.
//!
//! While workers keep changing a frame, its renders take at most a set share of the wall time
//! ([`pace`]): a request then waits for the frame's pace, and is still answered by a render
//! that holds every sample acknowledged before it came.
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

use crate::frame::ShardedFrame;
use crate::work::{Busy, Reservation, WorkBudget};

pub mod denoise;
pub mod figures;
mod kept;
pub mod pace;
pub use kept::{FiguresWanted, KeptResolves, Made, MAX_KEPT};

/// Which render of a frame: the frame's serial (so a deleted and re-created frame never hits
/// the old one's renders) and the query in a canonical form.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Key {
    frame: u64,
    query: String,
}

/// One frame and query: its latest render, and the turn its renders take one at a time.
#[derive(Debug, Default)]
struct Entry {
    /// The latest render's bytes and the version of the frame read before it began (the bytes
    /// hold every sample of that version, perhaps a few more).
    latest: Mutex<Option<(u64, Bytes)>>,
    /// Held by the render in flight (by its thread, so a request that gives up waiting does not
    /// let a second render start beside the first).
    turn: Arc<tokio::sync::Mutex<()>>,
}

impl Entry {
    /// The latest bytes if they hold the frame's version `wanted` or a later one.
    fn answering(&self, wanted: u64) -> Option<Bytes> {
        let latest = self.latest.lock().unwrap_or_else(|e| e.into_inner());
        latest
            .as_ref()
            .filter(|(version, _)| *version >= wanted)
            .map(|(_, bytes)| bytes.clone())
    }

    /// Files a render of `version` unless a newer one is filed.
    fn file(&self, version: u64, bytes: &Bytes) {
        let mut latest = self.latest.lock().unwrap_or_else(|e| e.into_inner());
        if latest.as_ref().is_none_or(|(v, _)| *v <= version) {
            *latest = Some((version, bytes.clone()));
        }
    }

    /// Bytes held by the latest render.
    fn held(&self) -> u64 {
        let latest = self.latest.lock().unwrap_or_else(|e| e.into_inner());
        latest.as_ref().map_or(0, |(_, b)| b.len() as u64)
    }
}

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

/// The renders of each frame and query: the latest finished one and the one in flight.
#[derive(Debug)]
pub struct Renders {
    slots: Mutex<VecDeque<(Key, Arc<Entry>)>>,
    /// Most frames and queries kept; the oldest go first.
    max_slots: usize,
    budget: Arc<WorkBudget>,
    /// Renders run so far (shared ones count once).
    rendered: std::sync::atomic::AtomicU64,
    /// The latest resolve of the frames rendered last, which renders patch.
    kept: Arc<KeptResolves>,
    /// How often a changing frame is rendered.
    paces: Arc<pace::Paces>,
}

impl Renders {
    /// An empty cache keeping at most `max_slots` renders, reserving from `budget`, rendering a
    /// changing frame back to back.
    pub fn new(max_slots: usize, budget: Arc<WorkBudget>) -> Renders {
        Renders {
            slots: Mutex::new(VecDeque::new()),
            max_slots: max_slots.max(1),
            budget,
            rendered: Default::default(),
            kept: Arc::default(),
            paces: Arc::new(pace::Paces::new(1.0)),
        }
    }

    /// These renders, a changing frame's taking at most `share` of the wall time (see
    /// [`pace`]).
    pub fn paced(self, share: f64) -> Renders {
        Renders {
            paces: Arc::new(pace::Paces::new(share)),
            ..self
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

    /// How often changing frames are rendered.
    #[cfg(test)]
    pub(crate) fn paces(&self) -> &pace::Paces {
        &self.paces
    }

    /// The budget renders reserve from.
    pub fn budget(&self) -> &Arc<WorkBudget> {
        &self.budget
    }

    fn entry(&self, key: Key) -> Arc<Entry> {
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, entry)) = slots.iter().find(|(k, _)| *k == key) {
            return entry.clone();
        }
        let entry = Arc::<Entry>::default();
        slots.push_back((key, entry.clone()));
        while slots.len() > self.max_slots {
            slots.pop_front();
        }
        entry
    }

    /// Forgets every render of `frame` (when it is deleted).
    pub fn forget(&self, frame: &ShardedFrame) {
        let serial = frame.serial();
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        slots.retain(|(k, _)| k.frame != serial);
        drop(slots);
        self.kept.forget(frame);
        self.paces.forget(frame);
    }

    /// The bytes of `query` rendered from `frame` with every sample it holds now: the latest
    /// render's if it read this version or a later one, else the next render's, rendered by
    /// `render` on a thread of its own after reserving `cost` bytes of working memory and shared
    /// with everyone waiting for it. `render` holds that reservation, to give back what it no
    /// longer needs ([`Reservation::shrink_to`]) before its slow part.
    ///
    /// The version is read before rendering (after the frame's pace, [`pace`]) and given to
    /// `render`; if samples arrive meanwhile, the bytes may show a slightly newer state than the
    /// version they are filed under, never an older one. So `render` may answer with anything
    /// that holds that version: a kept resolve that a render of another kind, started at the
    /// same moment, just made (the render threads run at a low priority, and on a busy head
    /// writers post several times before the second of them gets to read the version itself).
    pub async fn get_or_render<E: Send + 'static>(
        &self,
        frame: &Arc<ShardedFrame>,
        query: String,
        cost: u64,
        render: impl FnOnce(&ShardedFrame, u64, &mut Reservation) -> Result<Bytes, E> + Send + 'static,
    ) -> Result<Bytes, RenderError<E>> {
        let wanted = frame.version();
        let entry = self.entry(Key {
            frame: frame.serial(),
            query,
        });
        if let Some(bytes) = entry.answering(wanted) {
            return Ok(bytes);
        }
        let turn = entry.turn.clone().lock_owned().await;
        // The render that held the turn may have read this version or a later one.
        if let Some(bytes) = entry.answering(wanted) {
            return Ok(bytes);
        }
        let waited = self.paces.wait(frame).await;
        if !waited.is_zero() {
            metrics::histogram!(crate::meters::RENDER_PACE_SECONDS).record(waited.as_secs_f64());
        }
        let version = frame.version();
        let mut reservation = self.budget.reserve(cost).await?;
        let filed = entry.clone();
        let rendered = self
            .run(frame, version, turn, move |frame, version| {
                let bytes = render(frame, version, &mut reservation);
                drop(reservation);
                if let Ok(bytes) = &bytes {
                    filed.file(version, bytes);
                }
                bytes
            })
            .await;
        let bytes = rendered.map_err(RenderError::Failed)?;
        self.trim();
        Ok(bytes)
    }

    /// Whether the pace of `frame` lets a render of it start now ([`pace::Paces::due`]): for
    /// renders that no request waits for, which skip a frame until then rather than wait (a
    /// loop over frames would wait out each frame's pace in turn).
    pub fn due(&self, frame: &ShardedFrame) -> bool {
        self.paces.due(frame)
    }

    /// Runs `work` as a render of `frame` that no request waits for (the tev feed), holding
    /// `reservation` of the working budget: on a render thread, given the version read before
    /// it, counted and filed with the frame's pace like any render. Renders of other kinds may
    /// share the kept resolve it makes ([`KeptResolves`]). The caller checks [`Renders::due`]
    /// first.
    pub async fn background<T: Send + 'static>(
        &self,
        frame: &Arc<ShardedFrame>,
        reservation: Reservation,
        work: impl FnOnce(&ShardedFrame, u64) -> T + Send + 'static,
    ) -> T {
        let version = frame.version();
        self.run(frame, version, reservation, work).await
    }

    /// Counts a render of `frame` at `version` and runs `work` on a render thread, which files
    /// the render with the frame's pace and then lets `hold` go (the turn of the render's
    /// query, a reservation): so the next render in line finds the pace set. The thread owns
    /// `hold`, so a request that gives up waiting lets nothing go early.
    async fn run<T: Send + 'static, H: Send + 'static>(
        &self,
        frame: &Arc<ShardedFrame>,
        version: u64,
        hold: H,
        work: impl FnOnce(&ShardedFrame, u64) -> T + Send + 'static,
    ) -> T {
        self.rendered
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        metrics::counter!(crate::meters::RENDERS).increment(1);
        let frame = frame.clone();
        let paces = self.paces.clone();
        let clock = pace::Clock::start();
        on_render_thread(move || {
            let started = std::time::Instant::now();
            let done = work(&frame, version);
            paces.rendered(&frame, version, clock.now(), started.elapsed());
            drop(hold);
            done
        })
        .await
        .expect("a render does not panic")
    }

    /// Drops the oldest finished renders while the kept ones hold more than a quarter of the
    /// working budget: cached bytes are memory too. Renders in flight stay.
    fn trim(&self) {
        let cap = self.budget.capacity() / 4;
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        let held = |slots: &VecDeque<(Key, Arc<Entry>)>| -> u64 {
            slots.iter().map(|(_, e)| e.held()).sum()
        };
        while held(&slots) > cap {
            let idle = |(_, e): &(Key, Arc<Entry>)| e.held() > 0 && e.turn.try_lock().is_ok();
            match slots.iter().position(idle) {
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
    ) -> impl FnOnce(&ShardedFrame, u64, &mut Reservation) -> Result<Bytes, String> + Send + 'static
    {
        let calls = calls.clone();
        move |f: &ShardedFrame, _, _| {
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

    /// While a render of an older version runs, requests for the new one wait for it and then
    /// share one render: however many watch a frame that keeps changing, one render of it runs
    /// at a time, and each request's bytes hold the version it asked at.
    #[tokio::test]
    async fn requests_behind_a_running_render_share_the_next_one() {
        let renders = Arc::new(Renders::new(8, WorkBudget::new(1 << 20, Duration::ZERO)));
        let f = frame();
        let calls = Arc::new(AtomicUsize::new(0));
        let (release, released) = std::sync::mpsc::channel::<()>();
        let (started, has_started) = tokio::sync::oneshot::channel::<()>();
        let first = {
            let (renders, f, calls) = (renders.clone(), f.clone(), calls.clone());
            tokio::spawn(async move {
                renders
                    .get_or_render(&f, "q".into(), 100, move |f: &ShardedFrame, _, _| {
                        calls.fetch_add(1, Ordering::SeqCst);
                        let version = f.version();
                        started.send(()).unwrap();
                        released.recv().unwrap();
                        Ok::<_, String>(Bytes::from(format!("v{version}")))
                    })
                    .await
                    .unwrap()
            })
        };
        has_started.await.unwrap();
        // Two more versions, each asked for by four requests while the first render runs
        // (a current-thread runtime runs the spawned requests up to their wait at each yield).
        let mut waiting = Vec::new();
        for seq in 0..2 {
            let batch = Batch::new("f", 1, seq, vec![Record::new(0, 0, [1.0; 3])]).unwrap();
            f.ingest(&batch).unwrap();
            for _ in 0..4 {
                let (renders, f, render) = (renders.clone(), f.clone(), counting(&calls));
                waiting.push(tokio::spawn(async move {
                    renders.get_or_render(&f, "q".into(), 100, render).await
                }));
            }
            tokio::task::yield_now().await;
            tokio::task::yield_now().await;
        }
        release.send(()).unwrap();
        assert_eq!(
            first.await.unwrap(),
            "v0",
            "the first request asked at version 0"
        );
        for request in waiting {
            assert_eq!(
                request.await.unwrap().unwrap(),
                "v2",
                "the next render read both"
            );
        }
        assert_eq!(calls.load(Ordering::SeqCst), 2, "one render for the eight");
        // An unchanged frame is answered by the latest render.
        let again = renders.get_or_render(&f, "q".into(), 100, counting(&calls));
        assert_eq!(again.await.unwrap(), "v2");
        assert_eq!(calls.load(Ordering::SeqCst), 2);
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
            .get_or_render(&frame(), "q".into(), 1, |_: &ShardedFrame, _, _| {
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
                .get_or_render(&f, format!("q{q}"), 1, |_, _, _| {
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
        let held: u64 = slots.iter().map(|(_, e)| e.held()).sum();
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
