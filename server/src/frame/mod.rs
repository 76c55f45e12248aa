//! One frame held by the server: the core's state split into row bands, each behind its own lock.
//!
//! Workers post batches concurrently. A single lock per frame would serialize them, so the state
//! is kept as horizontal bands ([`FrameState::band`]); a batch's records are sorted by band (as
//! runs of them) and each band is locked only while its own samples are added. A batch is still
//! applied atomically as seen from a reader: writers hold a shared *gate* while they apply, and
//! anything that needs a consistent cut (resolve, export, snapshots) takes the gate
//! exclusively. So a resolve never sees half a batch, and an applied batch is never
//! half-durable.
//!
//! Nothing copies the frame under the gate: at 4K the bands are 1.6 GB, and copying them stopped
//! every writer for a second (and every render did it). Each band (and the AOV sums) is behind
//! an `Arc`; a cut takes the gate only to clone those pointers and copy the small things (the
//! applied set, the counters). A writer about to change a band that a cut still holds copies it
//! first (`Arc::make_mut`, copy on write, under that band's own lock), so the cut keeps the band
//! as it was while the other bands take samples, and with no cut held nothing is copied at all.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};

use splatd_proto::api::{self, FrameInfo};

use splatd_estimator::{cell_len, cell_spp, AovSums, FrameState, Rect};

use dedup::Seen;

use crate::memory::CellPool;

mod changes;
mod cut;
pub mod dedup;
mod error;
pub mod history;
mod ingest;
mod spec;
mod transfer;

use cut::Counters;
pub use cut::{CounterValues, FrameCut};
pub use error::{ImportRefused, IngestError, Ingested};
pub use spec::{core_resolve_params, FrameSpec, MAX_AOV_CHANNELS};

/// Most bands a frame is split into. Contention falls with the number of bands, and 32 is far
/// more than the cores of any one render head; each band costs one lock and one `Vec`.
const MAX_BANDS: u32 = 32;
/// Fewest rows in a band, so tiny frames are not split into pointless slivers.
const MIN_BAND_ROWS: u32 = 8;

/// Samples per pixel over a frame.
#[derive(Debug, Clone, Copy)]
struct SppFigures {
    min: u64,
    mean: f64,
    max: u64,
}

/// A frame being accumulated by the server.
#[derive(Debug)]
pub struct ShardedFrame {
    spec: FrameSpec,
    /// Unique among the frames of this process, so that a frame deleted and created again
    /// under the same id is never taken for the old one by anything that remembers frames.
    serial: u64,
    /// Shared with the cuts taken since the band last changed ([`ShardedFrame::cut`]).
    bands: Vec<Mutex<Arc<FrameState>>>,
    /// The first row of each band, top to bottom (the first is 0).
    band_starts: Vec<u32>,
    /// Shared while a batch is applied, exclusive while a consistent cut is taken (a handful
    /// of reference counts and the applied set, never the cells).
    gate: RwLock<()>,
    /// Set (under the exclusive gate) when the frame is deleted: nothing is applied after.
    retired: AtomicBool,
    /// Held shared by every request that changes the frame, from before it looks at the frame
    /// until its answer is ready ([`ShardedFrame::lease`]); a deletion takes it exclusively, so
    /// it is answered only after every such answer.
    requests: Arc<tokio::sync::RwLock<()>>,
    seen: Mutex<Seen>,
    /// The AOV sums of the whole frame (if it has AOVs), locked after the bands; shared with
    /// cuts like the bands.
    aovs: Option<Mutex<Arc<AovSums>>>,
    counters: Counters,
    /// Bumped after every change, so watchers (previews, tev, snapshots) can tell if anything
    /// happened since they last looked.
    version: AtomicU64,
    /// The version of the latest snapshot on disk (durable servers only).
    durable_version: AtomicU64,
    /// Per worker, the sequence number below which every batch is in that snapshot.
    durable_floors: Mutex<std::collections::HashMap<u64, u64>>,
    /// Convergence figures of the frame's renders over time.
    history: Mutex<history::History>,
    /// The samples-per-pixel figures of [`ShardedFrame::info`] and the version they were
    /// counted at: a frame polled but not changed is not read again.
    spp_figures: Mutex<Option<(u64, SppFigures)>>,
    /// Where each recent version changed the frame, written with the version under the shared
    /// gate (so a cut sees every change up to its version).
    changes: Mutex<changes::Changes>,
    /// Where the cells go when the frame is dropped (frames of the store), for the next frame.
    pool: Option<Arc<CellPool>>,
}

impl Drop for ShardedFrame {
    /// Gives the bands' cells to the frame's pool, those no cut still holds (a cut frees its
    /// bands when it ends).
    fn drop(&mut self) {
        for band in std::mem::take(&mut self.bands) {
            self.recycle(band.into_inner().unwrap_or_else(|e| e.into_inner()));
        }
        if let Some(sums) = self.aovs.take() {
            self.recycle_aovs(sums.into_inner().unwrap_or_else(|e| e.into_inner()));
        }
    }
}

/// Held by a request that changes a frame until its answer is ready (see
/// [`ShardedFrame::lease`]).
#[derive(Debug)]
pub struct Lease {
    _guard: tokio::sync::OwnedRwLockReadGuard<()>,
}

/// Locks a mutex, ignoring poisoning: every mutation of the guarded values is a sequence of
/// additions that cannot panic half-way, so a panic elsewhere leaves them consistent.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The machine's cores: the threads a large ingest or import (and a resolve) works on.
pub fn cores() -> usize {
    static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *CORES.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// `work` on `items` cut into at most `threads` consecutive groups of equal length, each group
/// on a thread of its own (the first on the calling thread); the groups' results in order.
/// For work on disjoint bands, whose locks the caller holds.
fn on_groups<T: Send, R: Send>(
    items: &mut [T],
    threads: usize,
    work: impl Fn(&mut [T]) -> R + Sync,
) -> Vec<R> {
    let per = items.len().div_ceil(threads.max(1)).max(1);
    if items.is_empty() {
        return Vec::new();
    }
    if per >= items.len() {
        // One group: no thread to start.
        return vec![work(items)];
    }
    let mut groups = items.chunks_mut(per);
    let mine = groups.next().expect("two groups or more");
    let work = &work;
    std::thread::scope(|scope| {
        let others: Vec<_> = groups.map(|g| scope.spawn(move || work(g))).collect();
        let mut results = vec![work(mine)];
        results.extend(
            others
                .into_iter()
                .map(|t| t.join().expect("work on bands does not panic")),
        );
        results
    })
}

impl ShardedFrame {
    /// An empty frame.
    pub fn new(spec: FrameSpec) -> ShardedFrame {
        Self::new_with(spec, None)
    }

    /// An empty frame whose cells come from `pool` where it has them, and go back to it when
    /// the frame is dropped.
    pub fn new_in(spec: FrameSpec, pool: &Arc<CellPool>) -> ShardedFrame {
        Self::new_with(spec, Some(pool.clone()))
    }

    /// The band that holds row `y` (a row of the frame).
    fn band_of_row(&self, y: u32) -> usize {
        self.band_starts.partition_point(|&start| start <= y) - 1
    }

    /// The rows of `band`.
    fn band_rows(&self, band: usize) -> std::ops::Range<u32> {
        let end = self.band_starts.get(band + 1);
        self.band_starts[band]..end.copied().unwrap_or(self.spec.request.height)
    }

    /// The state of `band` to change: copied first if a cut still holds it (copy on write),
    /// into cells from the frame's pool where it has them, so that a frame written while
    /// snapshots or renders hold its bands does not fault in fresh memory for every copy.
    ///
    /// The band it leaves goes to the pool as well, if the cut let go of it while the copy was
    /// made (see [`CellPool::give_band`]).
    ///
    /// With no idle cells that fit, the copy grows new memory on 4 KiB pages, not advised for
    /// huge ones: it runs under the band's lock, and new huge pages can be slow to fault in. On
    /// the 2-core test box (a virtual machine whose balloon device reports the memory its guest
    /// frees to the host) filling 12 MB of new memory took 75-119 ms on huge pages and 5.0-5.5
    /// ms on 4 KiB pages (a C loop, nothing else running); in `watchbench` the writers' copies
    /// into new huge pages took 73-173 ms a band on average (from the pool: 1.2 ms), every
    /// writer of the band waiting behind them, and on 4 KiB pages the writers' posts with
    /// watchers took 15.5 ms at the 99.9th percentile against 119-139 ms, 39-41 ms at most
    /// against 534-567 ms. The price: such cells stay on 4 KiB pages as they go round the
    /// pool, and there a band takes random pixels up to a tenth slower (`bench speed --pages
    /// 4k`: 57-63 against 66-69 M samples/s; scan-line runs and passes the same).
    fn own<'a>(&self, band: &'a mut Arc<FrameState>) -> &'a mut FrameState {
        if Arc::get_mut(band).is_none() {
            // Tests hold the copy here while the cut that holds the band ends (`pause`).
            let _ = crate::failpoint::hit("frame:copying_band");
            if let Some(pool) = &self.pool {
                let copy = band.clone_in(pool.take(band.cells().len()));
                pool.give_band(std::mem::replace(band, Arc::new(copy)));
            }
        }
        Arc::make_mut(band)
    }

    /// The AOV sums to change, copied first if a cut still holds them, into memory from the
    /// frame's pool as [`ShardedFrame::own`] copies a band: a frame of 6 AOV channels at 1080p
    /// holds 216 MB of sums, and a fresh copy of them for every snapshot or render that held
    /// them took 75 ms of page faults.
    fn own_aovs<'a>(&self, sums: &'a mut Arc<AovSums>) -> &'a mut AovSums {
        if Arc::get_mut(sums).is_none() {
            // Tests hold the copy here while the cut that holds the sums ends (`pause`).
            let _ = crate::failpoint::hit("frame:copying_aovs");
            if let Some(pool) = &self.pool {
                let copy = sums.clone_in(pool.take(sums.words().len()));
                pool.give_aovs(std::mem::replace(sums, Arc::new(copy)));
            }
        }
        Arc::make_mut(sums)
    }

    /// Takes back AOV sums a cut is done with, as [`ShardedFrame::recycle`] takes a band.
    pub fn recycle_aovs(&self, sums: Arc<AovSums>) {
        if let Some(pool) = &self.pool {
            pool.give_aovs(sums);
        }
    }

    /// Takes back a band of a cut that is done with it: its cells go to the frame's pool for
    /// the next copy on write if nothing else holds it (the frame has moved on to a copy).
    pub fn recycle(&self, band: Arc<FrameState>) {
        if let Some(pool) = &self.pool {
            pool.give_band(band);
        }
    }

    /// Gives the frame's cells to `pool` when it is dropped (a frame restored from disk).
    pub fn give_cells_to(&mut self, pool: &Arc<CellPool>) {
        self.pool = Some(pool.clone());
    }

    fn new_with(spec: FrameSpec, pool: Option<Arc<CellPool>>) -> ShardedFrame {
        let (w, h) = (spec.request.width, spec.request.height);
        let n = (h / MIN_BAND_ROWS).clamp(1, MAX_BANDS);
        let bands = FrameState::bands_in(w, h, n, &spec.layout, |len| {
            pool.as_ref().map_or_else(Vec::new, |p| p.take(len))
        });
        // The AOV sums from the pool too (a deleted frame's go there with its cells).
        let aovs = spec.empty_aovs_in(|len| pool.as_ref().map_or_else(Vec::new, |p| p.take(len)));
        // Fresh cells and sums are not touched yet: ask for huge pages before the first sample
        // does, and fault in the ends they cannot cover (memory from the pool was readied when
        // it was fresh; readying it again is harmless).
        for cells in bands
            .iter()
            .map(|b| b.cells())
            .chain(aovs.iter().map(|a| a.words()))
        {
            crate::memory::ready_cells(cells);
        }
        let mut frame =
            Self::from_bands(spec, bands, aovs, Seen::default(), CounterValues::default());
        frame.pool = pool;
        frame
    }

    /// A frame restored from a snapshot: its spec, a whole-frame state, its AOV sums (`None`:
    /// empty) and what it had seen.
    pub fn restore(
        spec: FrameSpec,
        state: &FrameState,
        aovs: Option<&AovSums>,
        seen: Seen,
        counters: CounterValues,
        version: u64,
    ) -> Result<ShardedFrame, String> {
        let frame = ShardedFrame::new(spec);
        frame.check_fits(state).map_err(|e| e.to_string())?;
        for band in &frame.bands {
            Arc::make_mut(&mut lock(band))
                .merge(state)
                .map_err(|e| e.to_string())?;
        }
        if let Some(restored) = aovs {
            let Some(mine) = &frame.aovs else {
                return Err("AOV sums for a frame that declares no AOVs".into());
            };
            Arc::make_mut(&mut lock(mine))
                .merge_overlap(restored)
                .map_err(|e| e.to_string())?;
        }
        *lock(&frame.seen) = seen;
        frame.set_counters(counters);
        frame.version.store(version, Ordering::Release);
        *lock(&frame.changes) = changes::Changes::starting_at(version);
        Ok(frame)
    }

    /// Records that a snapshot holding everything up to `version`, and the batches in `seen`,
    /// is on disk.
    pub fn mark_durable(&self, seen: &Seen, version: u64) {
        let mut floors = lock(&self.durable_floors);
        for (&worker, set) in &seen.workers {
            floors.insert(worker, set.floor());
        }
        self.durable_version.fetch_max(version, Ordering::AcqRel);
    }

    /// The version of the latest snapshot on disk.
    pub fn durable_version(&self) -> u64 {
        self.durable_version.load(Ordering::Acquire)
    }

    /// Every batch of `worker` numbered below this is on disk.
    pub fn durable_floor(&self, worker: u64) -> u64 {
        lock(&self.durable_floors)
            .get(&worker)
            .copied()
            .unwrap_or(0)
    }

    fn from_bands(
        spec: FrameSpec,
        bands: Vec<FrameState>,
        aovs: Option<AovSums>,
        seen: Seen,
        counters: CounterValues,
    ) -> ShardedFrame {
        let band_starts = bands.iter().map(|band| band.rows().start).collect();
        static NEXT_SERIAL: AtomicU64 = AtomicU64::new(1);
        let aovs = aovs.map(|a| Mutex::new(Arc::new(a)));
        let frame = ShardedFrame {
            spec,
            serial: NEXT_SERIAL.fetch_add(1, Ordering::Relaxed),
            bands: bands.into_iter().map(|b| Mutex::new(Arc::new(b))).collect(),
            band_starts,
            gate: RwLock::new(()),
            retired: AtomicBool::new(false),
            requests: Arc::new(tokio::sync::RwLock::new(())),
            seen: Mutex::new(seen),
            aovs,
            counters: Counters::default(),
            version: AtomicU64::new(0),
            durable_version: AtomicU64::new(0),
            durable_floors: Mutex::new(Default::default()),
            history: Mutex::new(Default::default()),
            spp_figures: Mutex::new(None),
            changes: Mutex::new(changes::Changes::starting_at(0)),
            pool: None,
        };
        frame.set_counters(counters);
        frame
    }

    fn set_counters(&self, v: CounterValues) {
        let c = &self.counters;
        c.samples.store(v.samples, Ordering::Relaxed);
        c.batches.store(v.batches, Ordering::Relaxed);
        c.rejected_samples
            .store(v.rejected_samples, Ordering::Relaxed);
        c.rejected_batches
            .store(v.rejected_batches, Ordering::Relaxed);
        c.imports.store(v.imports, Ordering::Relaxed);
    }

    fn counter_values(&self) -> CounterValues {
        let c = &self.counters;
        CounterValues {
            samples: c.samples.load(Ordering::Relaxed),
            batches: c.batches.load(Ordering::Relaxed),
            rejected_samples: c.rejected_samples.load(Ordering::Relaxed),
            rejected_batches: c.rejected_batches.load(Ordering::Relaxed),
            imports: c.imports.load(Ordering::Relaxed),
        }
    }

    /// The frame id.
    pub fn id(&self) -> &str {
        &self.spec.request.id
    }

    /// This frame's serial number, unique in the process.
    pub fn serial(&self) -> u64 {
        self.serial
    }

    /// The frame's parameters.
    pub fn spec(&self) -> &FrameSpec {
        &self.spec
    }

    /// Samples accepted so far (records of applied batches and samples of imported states).
    pub fn samples(&self) -> u64 {
        self.counters.samples.load(Ordering::Relaxed)
    }

    /// The frame's convergence over time (see [`crate::render::figures`]).
    pub fn history(&self) -> MutexGuard<'_, history::History> {
        lock(&self.history)
    }

    /// Changes whenever samples are added; equal versions mean equal states.
    pub fn version(&self) -> u64 {
        self.version.load(Ordering::Acquire)
    }

    /// Makes the next version, which changed the pixels in `rect`. Called with the gate held
    /// shared, after the change is in the bands.
    fn next_version(&self, rect: Rect) {
        let mut changes = lock(&self.changes);
        let version = self.version.fetch_add(1, Ordering::AcqRel) + 1;
        changes.record(version, rect);
    }

    /// The pixels the versions after `from` up to `to` changed, or `None` when they are not
    /// all remembered (then anything kept of version `from` must be made again whole).
    pub fn changes_between(&self, from: u64, to: u64) -> Option<Vec<Rect>> {
        lock(&self.changes).between(from, to)
    }

    /// The whole frame, as a change.
    fn everywhere(&self) -> Rect {
        Rect::new(0, 0, self.spec.request.width, self.spec.request.height)
    }
    /// A lease for a request that will change the frame and answer for it; `None` once the frame
    /// is retired. Hold it until the answer is ready.
    pub async fn lease(&self) -> Option<Lease> {
        // Checked first as well: a deletion queues for the lock only after retiring the frame,
        // so this never waits behind one.
        if self.is_retired() {
            return None;
        }
        let lease = Lease {
            _guard: self.requests.clone().read_owned().await,
        };
        (!self.is_retired()).then_some(lease)
    }

    /// Marks the frame deleted. Returns once no batch or import is being applied, and from then
    /// on none is: whatever was acknowledged before is in the frame, and nothing is acknowledged
    /// after.
    pub fn retire(&self) {
        let _gate = self.gate.write().unwrap_or_else(|e| e.into_inner());
        self.retired.store(true, Ordering::Release);
    }

    /// [`ShardedFrame::retire`], then waits until every request holding a [`Lease`] has its
    /// answer: after this returns, no request that changed the frame is still to be answered.
    pub async fn retire_and_drain(self: &Arc<Self>) {
        let frame = self.clone();
        // The gate is a blocking lock, held by batches while they are applied.
        let _ = tokio::task::spawn_blocking(move || frame.retire()).await;
        drop(self.requests.write().await);
    }

    /// Undoes [`ShardedFrame::retire`], for a deletion that failed.
    pub fn unretire(&self) {
        self.retired.store(false, Ordering::Release);
    }

    /// Whether [`ShardedFrame::retire`] was called (and not undone).
    pub fn is_retired(&self) -> bool {
        self.retired.load(Ordering::Acquire)
    }

    /// A consistent cut of the whole frame, taken under the exclusive gate (so no batch is
    /// half in it) in the time of a few reference counts and a copy of the applied set: the
    /// cut shares the bands and AOV sums; writers that change them afterwards copy what they
    /// change first (see [`FrameCut`]).
    pub fn cut(&self) -> FrameCut {
        let _gate = self.gate.write().unwrap_or_else(|e| e.into_inner());
        FrameCut {
            bands: self.bands.iter().map(|b| lock(b).clone()).collect(),
            seen: lock(&self.seen).clone(),
            counters: self.counter_values(),
            version: self.version(),
            aovs: self.aovs.as_ref().map(|a| lock(a).clone()),
            pool: self.pool.clone(),
        }
    }

    /// Fewest, mean and most samples of any pixel now: counted from the cells once per
    /// version (a read of the whole state), then remembered.
    fn spp_figures(&self) -> SppFigures {
        let version = self.version();
        if let Some((v, figures)) = *lock(&self.spp_figures) {
            if v == version {
                return figures;
            }
        }
        let k = self.spec.layout.cascades();
        let (mut min, mut max, mut sum, mut pixels) = (u64::MAX, 0u64, 0u128, 0u64);
        for band in &self.bands {
            // Under the band's lock: its writers wait for the scan of one band (cheaper for
            // them than copying it, which a cut would make them do).
            let band = lock(band);
            for cell in band.cells().chunks_exact(cell_len(k)) {
                let n = cell_spp(cell);
                min = min.min(n);
                max = max.max(n);
                sum += n as u128;
                pixels += 1;
            }
        }
        let figures = SppFigures {
            min: if pixels == 0 { 0 } else { min },
            mean: if pixels == 0 {
                0.0
            } else {
                sum as f64 / pixels as f64
            },
            max,
        };
        // Counted at `version` or later: filed under `version`, it is never taken for a
        // newer state than it saw.
        *lock(&self.spp_figures) = Some((version, figures));
        figures
    }

    /// What the frame looks like now, its samples per pixel counted over its cells (counted
    /// once per version).
    pub fn info(&self) -> FrameInfo {
        self.info_with(self.spp_figures())
    }

    /// [`info`](Self::info) with the samples per pixel of `c`, the figures of a render that read
    /// the frame at the version asked about or later (`GET /v1/frames/{id}`): counting them
    /// again reads the whole state under the bands' locks, and while workers keep changing the
    /// frame every count was a new one, writers waiting on each.
    pub fn info_rendered(&self, c: &api::Convergence) -> FrameInfo {
        self.info_with(SppFigures {
            min: c.spp_min,
            mean: c.spp_mean,
            max: c.spp_max,
        })
    }

    /// [`info`](Self::info) for the frame list: the newest samples per pixel the frame has,
    /// those of its latest render or of its latest count, whichever read the later version
    /// (counted only if it has neither). A list never counts the cells of a frame again while
    /// workers change it: the live page lists the frames every second, and each count read a
    /// busy 1080p frame's whole state (35 ms, writers waiting on each band's lock in turn) for
    /// every open page. A frame's counts (`samples`) are always its own now.
    pub fn listed(&self) -> FrameInfo {
        let rendered = self.history().latest().map(|(version, c)| {
            let spp = SppFigures {
                min: c.spp_min,
                mean: c.spp_mean,
                max: c.spp_max,
            };
            (version, spp)
        });
        let counted = *lock(&self.spp_figures);
        let newest = match (rendered, counted) {
            (Some(r), Some(c)) => Some(if r.0 >= c.0 { r } else { c }),
            (r, c) => r.or(c),
        };
        match newest {
            Some((_, spp)) => self.info_with(spp),
            None => self.info(),
        }
    }

    fn info_with(&self, spp: SppFigures) -> FrameInfo {
        let c = self.counter_values();
        let r = &self.spec.request;
        FrameInfo {
            id: r.id.clone(),
            width: r.width,
            height: r.height,
            cascades: r.cascades.clone(),
            resolve: r.resolve.clone(),
            samples: c.samples,
            batches: c.batches,
            spp_min: spp.min,
            spp_mean: spp.mean,
            spp_max: spp.max,
            rejected_samples: c.rejected_samples,
            rejected_batches: c.rejected_batches,
            memory_bytes: self.spec.memory_bytes(),
            aovs: r.aovs.clone(),
            denoise: r.denoise,
            denoise_guides: self.spec.guides.to_api(),
            convergence: None,
        }
    }
}

#[cfg(test)]
impl ShardedFrame {
    /// Bands a cut still holds (which a writer changing them would copy first).
    pub(crate) fn bands_held_by_cuts(&self) -> usize {
        self.bands
            .iter()
            .filter(|b| Arc::strong_count(&lock(b)) > 1)
            .count()
    }
}

#[cfg(test)]
mod tests;
