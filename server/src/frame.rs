//! One frame held by the server: the core's state split into row bands, each behind its own lock.
//!
//! Workers post batches concurrently. A single lock per frame would serialize them, so the state
//! is kept as horizontal bands ([`FrameState::band`]); a batch is bucketed by band and each band is
//! locked only while its own samples are added. A batch is still applied atomically as seen from
//! a reader: writers hold a shared *gate* while they apply, and anything that needs a consistent
//! cut (resolve, export, snapshots) takes the gate exclusively. So a resolve never sees half a
//! batch, and an applied batch is never half-durable.
//!
//! Nothing copies the frame under the gate: at 4K the bands are 1.6 GB, and copying them stopped
//! every writer for a second (and every render did it). Each band (and the AOV sums) is behind
//! an `Arc`; a cut takes the gate only to clone those pointers and copy the small things (the
//! applied set, the counters). A writer about to change a band that a cut still holds copies it
//! first (`Arc::make_mut`, copy on write, under that band's own lock), so the cut keeps the band
//! as it was while the other bands take samples, and with no cut held nothing is copied at all.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};

use splatd_proto::api::{AovSpec, CreateFrame, FrameInfo};
use splatd_proto::{records_digest_of, Applied, Batch, Origin, Record};

use splatd_estimator::{
    self as estimator, aov_words, cell_len, cell_spp, resolve_bands, AovCellsError, AovSums,
    CascadeLayout, FrameState, MergeError, ParamError, Resolved, SampleError, MAX_PIXEL_SAMPLES,
};

use splatd_formats::names::{check_exr_name, describe_aovs, MAX_EXR_NAME_BYTES};
use splatd_formats::state::Importable;

use super::dedup::{BatchId, Seen};

/// Most bands a frame is split into. Contention falls with the number of bands, and 32 is far
/// more than the cores of any one render head; each band costs one lock and one `Vec`.
const MAX_BANDS: u32 = 32;
/// Fewest rows in a band, so tiny frames are not split into pointless slivers.
const MIN_BAND_ROWS: u32 = 8;

/// A frame's parameters, checked and turned into the core's types.
#[derive(Debug, Clone)]
pub struct FrameSpec {
    /// The request as the frame was created (after defaults were filled in).
    pub request: CreateFrame,
    /// The cascade layout.
    pub layout: CascadeLayout,
    /// The default resolve parameters.
    pub resolve: estimator::ResolveParams,
    /// The AOVs that guide its denoised images (see [`crate::denoise::Guides::choose`]).
    pub guides: crate::denoise::Guides,
}

impl FrameSpec {
    /// Checks a create request. Size limits are the store's business, not this one's.
    pub fn new(request: CreateFrame) -> Result<FrameSpec, ParamError> {
        splatd_proto::validate_frame_id(&request.id)
            .map_err(|e| ParamError::new("id", e.to_string()))?;
        if request.width == 0 || request.height == 0 {
            return Err(ParamError::new(
                "width/height",
                format!(
                    "a frame needs at least one pixel, got {}x{}",
                    request.width, request.height
                ),
            ));
        }
        let c = &request.cascades;
        let layout = CascadeLayout::new(c.base, c.cascades, c.lowest_scale, c.luminance)?;
        let resolve = core_resolve_params(&request.resolve)?;
        estimator::check_converged_below(request.converged_below)?;
        check_aovs(&request.aovs)?;
        let guides =
            crate::denoise::Guides::choose(&request.aovs, request.denoise_guides.as_ref())?;
        Ok(FrameSpec {
            request,
            layout,
            resolve,
            guides,
        })
    }

    /// Bytes of cascade and AOV memory a frame of this spec holds.
    pub fn memory_bytes(&self) -> u64 {
        let aovs = match self.aov_channels() {
            0 => 0,
            c => aov_words(c),
        };
        self.request.width as u64
            * self.request.height as u64
            * (cell_len(self.layout.cascades()) + aovs) as u64
            * 8
    }

    /// Channels of all the frame's AOVs together (0: the frame has no AOVs).
    pub fn aov_channels(&self) -> usize {
        self.request.aovs.iter().map(|a| a.channels.len()).sum()
    }

    /// Empty AOV sums for the whole frame, if it has AOVs.
    pub fn empty_aovs(&self) -> Option<AovSums> {
        let c = self.aov_channels();
        (c > 0).then(|| AovSums::new(self.request.width, 0..self.request.height, c))
    }
}

/// Most AOV channels a frame may declare (each costs 16 bytes per pixel).
pub const MAX_AOV_CHANNELS: usize = 64;

/// Layer names of `image.exr` that an AOV may not take.
const RESERVED_LAYERS: [&str; 4] = ["mean", "removed", "spp", crate::denoise::DENOISED_LAYER];

/// Checks a frame's AOV declarations: named, each name once and not one of the served layers'
/// (`mean`, `removed`, `spp`, `cascadeN`, the unnamed beauty), channels named, each once, and
/// every name one that can be written into a valid EXR ([`check_exr_name`]).
fn check_aovs(aovs: &[AovSpec]) -> Result<(), ParamError> {
    let bad = |m: String| Err(ParamError::new("aovs", m));
    let total: usize = aovs.iter().map(|a| a.channels.len()).sum();
    if total > MAX_AOV_CHANNELS {
        return bad(format!(
            "{total} AOV channels declared, at most {MAX_AOV_CHANNELS} are allowed"
        ));
    }
    for (i, aov) in aovs.iter().enumerate() {
        let name = shown(&aov.name);
        // Before anything else quotes it (`{:?}` escapes a NUL or a control character).
        check_exr_name(&aov.name)
            .map_err(|rule| ParamError::new("aovs", format!("AOV name {name}: {rule}")))?;
        let cascade = aov
            .name
            .strip_prefix("cascade")
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if aov.name.is_empty() || RESERVED_LAYERS.contains(&aov.name.as_str()) || cascade {
            return bad(format!(
                "AOV name {name} is empty or taken by a layer image.exr serves (mean, removed, \
                 spp, denoised, cascadeN)"
            ));
        }
        if aovs[..i].iter().any(|a| a.name == aov.name) {
            return bad(format!("AOV {name} is declared twice"));
        }
        if aov.channels.is_empty() {
            return bad(format!("AOV {name} has no channels"));
        }
        for (j, c) in aov.channels.iter().enumerate() {
            check_exr_name(c).map_err(|rule| {
                ParamError::new(
                    "aovs",
                    format!("AOV {name}: channel name {}: {rule}", shown(c)),
                )
            })?;
            if c.is_empty() || c.contains('.') || aov.channels[..j].contains(c) {
                return bad(format!(
                    "AOV {name}: channel {c:?} is empty, has a dot or is named twice"
                ));
            }
            // What image.exr writes: `<name>.<channel>`, with no other prefix.
            let full = aov.name.len() + 1 + c.len();
            if full > MAX_EXR_NAME_BYTES {
                return bad(format!(
                    "AOV {name}: channel {}: length rule: the EXR channel name \
                     \"<name>.<channel>\" would be {full} bytes, and OpenEXR names are at \
                     most {MAX_EXR_NAME_BYTES} bytes",
                    shown(c)
                ));
            }
        }
    }
    Ok(())
}

/// A name quoted for a message, cut short when long (a refused name may be 30,000 bytes).
fn shown(name: &str) -> String {
    const SHOWN: usize = 40;
    if name.chars().count() <= SHOWN {
        return format!("{name:?}");
    }
    let head: String = name.chars().take(SHOWN).collect();
    format!("{head:?}... ({} bytes)", name.len())
}

/// The core's resolve parameters from the API's.
pub fn core_resolve_params(
    p: &splatd_proto::api::ResolveParams,
) -> Result<estimator::ResolveParams, ParamError> {
    estimator::ResolveParams::new(
        p.variant.to_estimator(),
        p.kappa,
        p.kappa_min,
        p.kappa_exponent,
    )
}

/// Why a batch was refused. Nothing of a refused batch is applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IngestError {
    /// A record is outside the frame or not a valid radiance value.
    #[error(
        "record {index} (pixel ({}, {}), RGB ({}, {}, {})): {error}",
        record.x, record.y, record.rgb[0], record.rgb[1], record.rgb[2]
    )]
    Sample {
        /// Index of the first bad record in the batch.
        index: usize,
        /// The record.
        record: splatd_proto::Record,
        /// What is wrong with it.
        error: SampleError,
    },
    /// The batch names another frame.
    #[error("batch is for frame {batch:?} but was posted to frame {url:?}")]
    WrongFrame {
        /// Frame id inside the batch.
        batch: String,
        /// Frame id of the URL.
        url: String,
    },
    /// A batch with this `(worker, seq)` but other records was applied before.
    #[error(
        "batch (worker {worker}, seq {seq}) was already applied with other records \
         (digest {applied:016x}, this one {digest:016x}); ids must not be reused for \
         different batches"
    )]
    IdReused {
        /// The worker id.
        worker: u64,
        /// The sequence number.
        seq: u64,
        /// Digest of the records applied under this id.
        applied: u64,
        /// Digest of the records of this batch.
        digest: u64,
    },
    /// A batch with this `(worker, seq)` came in an imported state that recorded no digest of
    /// its records: this one may be it or another batch under a reused id, and dropping it as a
    /// duplicate could lose it.
    #[error(
        "batch (worker {worker}, seq {seq}) is named by a state imported into this frame \
         without a digest of its records, so the server cannot tell whether this is the same \
         batch or another one under a reused id; it is neither applied nor dropped as a \
         duplicate: if the imported state holds it, nothing is missing, otherwise send its \
         samples under a new id"
    )]
    IdUnverified {
        /// The worker id.
        worker: u64,
        /// The sequence number.
        seq: u64,
    },
    /// The frame was deleted while the batch was on its way.
    #[error("frame {frame:?} was deleted")]
    Deleted {
        /// The frame.
        frame: String,
    },
    /// A pixel's AOVs hold 2^32 samples already.
    #[error("the AOVs of pixel ({x}, {y}) hold 2^32 samples already")]
    AovFull {
        /// Column.
        x: u32,
        /// Row.
        y: u32,
    },
}

/// What an applied (or recognised) batch did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ingested {
    /// Samples added (0 for a duplicate).
    pub accepted: u64,
    /// The batch had been applied before; nothing was added this time.
    pub duplicate: bool,
}

/// Why an imported state was refused. Nothing of it is applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ImportRefused {
    /// Size, rows or cascade layout differ from the frame's.
    #[error("state does not fit frame {frame:?}: {error}")]
    Mismatch {
        /// The frame.
        frame: String,
        /// What differs.
        error: MergeError,
    },
    /// The state names another frame.
    #[error("state is of frame {state:?} but was posted to frame {url:?}")]
    WrongFrame {
        /// Frame id inside the state.
        state: String,
        /// Frame id of the URL.
        url: String,
    },
    /// The frame was deleted while the state was on its way.
    #[error("frame {frame:?} was deleted")]
    Deleted {
        /// The frame.
        frame: String,
    },
    /// The state's AOVs are not the frame's, or cannot be added.
    #[error("state's AOVs do not fit frame {frame:?}: {reason}")]
    Aovs {
        /// The frame.
        frame: String,
        /// What differs.
        reason: String,
    },
    /// The state holds batches the frame has applied already: adding it would count them twice.
    #[error(
        "state holds {count} batch(es) that frame {frame:?} has applied already, the first \
         (worker {worker}, seq {seq}); adding it would count them twice (a worker resent them \
         to another node?)"
    )]
    Overlap {
        /// The frame.
        frame: String,
        /// The first such batch's worker.
        worker: u64,
        /// Its sequence number.
        seq: u64,
        /// How many batches of the state the frame has applied.
        count: u64,
    },
}

/// Running totals of a frame (besides what the cascades themselves hold).
#[derive(Debug, Default)]
struct Counters {
    samples: AtomicU64,
    batches: AtomicU64,
    rejected_samples: AtomicU64,
    rejected_batches: AtomicU64,
    imports: AtomicU64,
}

/// Counter values, as saved in snapshots and restored from them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct CounterValues {
    /// Accepted samples (records of applied batches and samples of imported states).
    pub samples: u64,
    /// Applied batches.
    pub batches: u64,
    /// Samples of refused batches.
    pub rejected_samples: u64,
    /// Refused batches.
    pub rejected_batches: u64,
    /// Imported states and pushed deltas.
    pub imports: u64,
}

/// A consistent cut of a frame: what resolve, export and snapshots work from.
///
/// It shares the frame's bands and AOV sums instead of copying them ([`ShardedFrame::cut`]):
/// a writer that changes a band while a cut holds it copies that band first (one band, under
/// that band's own lock), so the cut stays the frame as it was and nobody waits for a copy of
/// the whole frame.
#[derive(Debug, Clone)]
pub struct FrameCut {
    /// The bands, top to bottom.
    pub bands: Vec<Arc<FrameState>>,
    /// Senders seen when the copy was taken.
    pub seen: Seen,
    /// Counters when the copy was taken.
    pub counters: CounterValues,
    /// The frame's version when the copy was taken (see [`ShardedFrame::version`]).
    pub version: u64,
    /// The AOV sums of the whole frame, if it has AOVs.
    pub aovs: Option<Arc<AovSums>>,
}

impl FrameCut {
    /// The bands merged into one whole-frame state.
    pub fn whole(&self) -> FrameState {
        let first = &self.bands[0];
        let mut whole = FrameState::new(first.width(), first.height(), first.layout().clone());
        for band in &self.bands {
            whole
                .merge(band)
                .expect("bands of one frame fit the whole frame");
        }
        whole
    }

    /// The bands, top to bottom, as the estimator takes them.
    pub fn band_refs(&self) -> Vec<&FrameState> {
        self.bands.iter().map(|b| &**b).collect()
    }

    /// Resolves the cut on `threads` threads.
    pub fn resolve(&self, params: &estimator::ResolveParams, threads: usize) -> Resolved {
        resolve_bands(&self.band_refs(), params, threads).expect("a frame's bands tile it")
    }

    /// `B_j / N` per cascade over the whole frame (raw layers for the EXR).
    pub fn cascade_means(&self) -> Vec<Vec<[f32; 3]>> {
        let mut layers: Vec<Vec<[f32; 3]>> = Vec::new();
        for band in &self.bands {
            for (j, layer) in band.cascade_means().into_iter().enumerate() {
                match layers.get_mut(j) {
                    Some(all) => all.extend(layer),
                    None => layers.push(layer),
                }
            }
        }
        layers
    }
}

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
    /// Band index of each row.
    band_of_row: Vec<u16>,
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
    history: Mutex<crate::converge::History>,
    /// The samples-per-pixel figures of [`ShardedFrame::info`] and the version they were
    /// counted at: a frame polled but not changed is not read again.
    spp_figures: Mutex<Option<(u64, SppFigures)>>,
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

impl ShardedFrame {
    /// An empty frame.
    pub fn new(spec: FrameSpec) -> ShardedFrame {
        let (w, h) = (spec.request.width, spec.request.height);
        let n = (h / MIN_BAND_ROWS).clamp(1, MAX_BANDS);
        let bands = FrameState::bands(w, h, n, &spec.layout);
        // Fresh cells are not touched yet: ask for huge pages before the first sample does.
        for band in &bands {
            crate::memory::advise_or_log(band.cells());
        }
        Self::from_bands(spec, bands, Seen::default(), CounterValues::default())
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
        seen: Seen,
        counters: CounterValues,
    ) -> ShardedFrame {
        let mut band_of_row = vec![0u16; spec.request.height as usize];
        for (i, band) in bands.iter().enumerate() {
            for y in band.rows() {
                band_of_row[y as usize] = i as u16;
            }
        }
        static NEXT_SERIAL: AtomicU64 = AtomicU64::new(1);
        let aovs = spec.empty_aovs().map(|a| Mutex::new(Arc::new(a)));
        let frame = ShardedFrame {
            spec,
            serial: NEXT_SERIAL.fetch_add(1, Ordering::Relaxed),
            bands: bands.into_iter().map(|b| Mutex::new(Arc::new(b))).collect(),
            band_of_row,
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

    /// The frame's convergence over time (see [`crate::converge`]).
    pub fn history(&self) -> MutexGuard<'_, crate::converge::History> {
        lock(&self.history)
    }

    /// Changes whenever samples are added; equal versions mean equal states.
    pub fn version(&self) -> u64 {
        self.version.load(Ordering::Acquire)
    }

    /// Counts a batch refused before it reached [`ShardedFrame::ingest`] (a decode error, say).
    pub fn count_rejected(&self, samples: u64) {
        self.counters
            .rejected_batches
            .fetch_add(1, Ordering::Relaxed);
        self.counters
            .rejected_samples
            .fetch_add(samples, Ordering::Relaxed);
    }

    /// Checks every record of a batch, then applies all of them, or none.
    ///
    /// A batch whose `(worker, seq)` was applied before is recognised and not applied again.
    /// Blocking (it may take tens of milliseconds for a large batch): call from a blocking thread.
    pub fn ingest(&self, batch: &Batch) -> Result<Ingested, IngestError> {
        self.ingest_with_aovs(batch, None)
    }

    /// [`ShardedFrame::ingest`] of a pass's samples with the values of its AOVs (every pixel,
    /// row-major, the frame's AOV channels in order; checked with
    /// [`AovSums::check_values`]), added with the samples or not at all.
    ///
    /// # Panics
    /// If `aovs` is given for a frame without AOVs or has the wrong length.
    pub fn ingest_with_aovs(
        &self,
        batch: &Batch,
        aovs: Option<&[f32]>,
    ) -> Result<Ingested, IngestError> {
        let result = self.ingest_inner(batch, aovs);
        if result.is_err() {
            self.count_rejected(batch.records.len() as u64);
        }
        result
    }

    fn ingest_inner(&self, batch: &Batch, aovs: Option<&[f32]>) -> Result<Ingested, IngestError> {
        if batch.frame != self.id() {
            return Err(IngestError::WrongFrame {
                batch: batch.frame.clone(),
                url: self.id().to_owned(),
            });
        }
        let (w, h) = (self.spec.request.width, self.spec.request.height);
        let mut buckets: Vec<Vec<(u32, u32, [f32; 3])>> = vec![Vec::new(); self.bands.len()];
        let single = self.bands.len() == 1;
        if single {
            buckets[0].reserve_exact(batch.records.len());
        }
        for (index, r) in batch.records.iter().enumerate() {
            if r.x >= w || r.y >= h {
                return Err(IngestError::Sample {
                    index,
                    record: *r,
                    error: SampleError::OutOfFrame {
                        x: r.x,
                        y: r.y,
                        width: w,
                        height: h,
                    },
                });
            }
            self.spec
                .layout
                .check_sample(r.rgb)
                .map_err(|error| IngestError::Sample {
                    index,
                    record: *r,
                    error,
                })?;
            let band = if single {
                0
            } else {
                self.band_of_row[r.y as usize] as usize
            };
            buckets[band].push((r.x, r.y, r.rgb));
        }

        // Outside the gate: a pass over the records, as long as a copy of them.
        let digest = batch.content_digest();
        let parts = Parts::Records { batch, buckets };
        self.apply(batch.worker, batch.seq, digest, parts, aovs)
    }

    /// [`ShardedFrame::ingest_with_aovs`] of a whole pass: `rgb` holds one sample per pixel of
    /// the frame, row-major, top row first; `aovs` as there. The same checks, refusals, digest
    /// and exactly-once as for the batch of the pass's records (pixel `(x, y)` is record
    /// `y * width + x`), without making those records: each band splats its rows straight from
    /// `rgb` ([`FrameState::splat_row`]).
    ///
    /// # Panics
    /// If `rgb` does not have one sample per pixel, or as [`ShardedFrame::ingest_with_aovs`].
    pub fn ingest_pass(
        &self,
        worker: u64,
        seq: u64,
        rgb: &[[f32; 3]],
        aovs: Option<&[f32]>,
    ) -> Result<Ingested, IngestError> {
        let result = self.ingest_pass_inner(worker, seq, rgb, aovs);
        if result.is_err() {
            self.count_rejected(rgb.len() as u64);
        }
        result
    }

    fn ingest_pass_inner(
        &self,
        worker: u64,
        seq: u64,
        rgb: &[[f32; 3]],
        aovs: Option<&[f32]>,
    ) -> Result<Ingested, IngestError> {
        let w = self.spec.request.width as usize;
        assert_eq!(
            rgb.len(),
            w * self.spec.request.height as usize,
            "a pass has one sample per pixel"
        );
        let record = |index: usize| Record::new((index % w) as u32, (index / w) as u32, rgb[index]);
        let valid = rgb
            .iter()
            .fold(true, |ok, &c| ok & self.spec.layout.check_sample(c).is_ok());
        if !valid {
            let (index, error) = rgb
                .iter()
                .enumerate()
                .find_map(|(i, &c)| self.spec.layout.check_sample(c).err().map(|e| (i, e)))
                .expect("an invalid sample");
            return Err(IngestError::Sample {
                index,
                record: record(index),
                error,
            });
        }
        let digest = records_digest_of((0..rgb.len()).map(record));
        self.apply(worker, seq, digest, Parts::Pass { rgb }, aovs)
    }

    /// Applies checked samples as batch `(worker, seq)` with content `digest`: all of them, or
    /// none if the batch was applied before or a pixel cannot take them.
    fn apply(
        &self,
        worker: u64,
        seq: u64,
        digest: u64,
        parts: Parts<'_>,
        aovs: Option<&[f32]>,
    ) -> Result<Ingested, IngestError> {
        // Tests kill the server here, between two acknowledgements (only `abort` applies).
        let _ = crate::failpoint::hit("batch:before_apply");
        let _gate = self.gate.read().unwrap_or_else(|e| e.into_inner());
        if self.retired.load(Ordering::Acquire) {
            return Err(IngestError::Deleted {
                frame: self.id().to_owned(),
            });
        }
        // The bands this batch touches, locked top to bottom (as every holder of several bands
        // locks them), so that the room check below and the additions see the same cells.
        let mut guards: Vec<Option<MutexGuard<'_, Arc<FrameState>>>> = self
            .bands
            .iter()
            .enumerate()
            .map(|(i, band)| parts.touches(i).then(|| lock(band)))
            .collect();
        let mut aov_sums = aovs.map(|_| {
            lock(
                self.aovs
                    .as_ref()
                    .expect("AOV values only for a frame with AOVs"),
            )
        });
        let id = lock(&self.seen).check_batch(worker, seq, digest);
        if id == BatchId::New {
            for (i, guard) in guards.iter().enumerate() {
                if let Some(refusal) = guard.as_deref().and_then(|g| parts.first_full(i, g)) {
                    return Err(refusal);
                }
            }
            if let Some(sums) = &aov_sums {
                if !sums.has_room_for_pass() {
                    let (w, h) = (self.spec.request.width, self.spec.request.height);
                    let (x, y) = (0..h)
                        .flat_map(|y| (0..w).map(move |x| (x, y)))
                        .find(|&(x, y)| sums.count(x, y) >= estimator::MAX_PIXEL_SAMPLES)
                        .unwrap_or((0, 0));
                    return Err(IngestError::AovFull { x, y });
                }
            }
        }
        // Checked again while recording: a batch with the same id may have been applied since.
        let id = match id {
            BatchId::New => lock(&self.seen).insert_batch(worker, seq, digest),
            other => other,
        };
        match id {
            BatchId::New => {}
            BatchId::Retry => {
                return Ok(Ingested {
                    accepted: 0,
                    duplicate: true,
                })
            }
            BatchId::Conflict { applied } => {
                return Err(IngestError::IdReused {
                    worker,
                    seq,
                    applied,
                    digest,
                })
            }
            BatchId::Unverified => return Err(IngestError::IdUnverified { worker, seq }),
        }
        let n = parts.len();
        for (i, guard) in guards.iter_mut().enumerate() {
            if let Some(mut band) = guard.take() {
                // Copies the band first if a cut holds it.
                parts.splat(i, Arc::make_mut(&mut band));
            }
        }
        if let (Some(sums), Some(values)) = (aov_sums.as_mut(), aovs) {
            Arc::make_mut(sums).add_pass(values);
        }
        drop(aov_sums);
        self.counters.samples.fetch_add(n, Ordering::Relaxed);
        self.counters.batches.fetch_add(1, Ordering::Relaxed);
        self.version.fetch_add(1, Ordering::AcqRel);
        Ok(Ingested {
            accepted: n,
            duplicate: false,
        })
    }

    fn check_fits(&self, state: &FrameState) -> Result<(), MergeError> {
        // Every band has the frame's size and layout.
        lock(&self.bands[0]).check_same_frame(state)
    }

    /// [`ShardedFrame::check_fits`] for any state being imported.
    fn check_fits_import(&self, state: &impl Importable) -> Result<(), MergeError> {
        let (width, height, layout) = state.geometry();
        lock(&self.bands[0]).check_same_geometry(width, height, layout)
    }

    /// Refuses a state declaring AOVs (`specs`, not empty) other than the frame's
    /// ([`ImportRefused::Aovs`]).
    fn check_state_aovs(&self, specs: &[AovSpec]) -> Result<(), ImportRefused> {
        if specs != self.spec.request.aovs.as_slice() {
            return Err(ImportRefused::Aovs {
                frame: self.id().to_owned(),
                reason: format!(
                    "the state has AOVs {}, the frame {}",
                    describe_aovs(specs),
                    describe_aovs(&self.spec.request.aovs)
                ),
            });
        }
        Ok(())
    }

    /// What a receiver checks of a state's header before it expands the state's AOV words
    /// (which [`ShardedFrame::import`] checks again, in the same order): the frame's id, the
    /// frame's size, and the frame's AOVs or none (`aovs` empty). So the AOV words of an
    /// accepted state are at most the frame's.
    pub fn check_state_header(
        &self,
        frame: &str,
        width: u32,
        height: u32,
        aovs: &[AovSpec],
    ) -> Result<(), ImportRefused> {
        if frame != self.id() {
            return Err(ImportRefused::WrongFrame {
                state: frame.to_owned(),
                url: self.id().to_owned(),
            });
        }
        let r = &self.spec.request;
        if (width, height) != (r.width, r.height) {
            return Err(ImportRefused::Mismatch {
                frame: self.id().to_owned(),
                error: MergeError::Size {
                    ours_w: r.width,
                    ours_h: r.height,
                    theirs_w: width,
                    theirs_h: height,
                },
            });
        }
        if aovs.is_empty() {
            return Ok(());
        }
        self.check_state_aovs(aovs)
    }

    /// Adds an exported state (or a pushed delta) holding the samples of `batches` to this
    /// frame. A delta carrying an origin that was applied before is recognised and not applied
    /// again (returns `Ok(false)`); a state holding a batch the frame has applied is refused
    /// ([`ImportRefused::Overlap`]), since adding it would count that batch twice.
    ///
    /// All or nothing: everything that can refuse the state is checked before the origin and
    /// the batches are recorded or any band changes. The state may hold any rows of the frame (a
    /// band of another node's frame, say): each band adds the rows it shares with it.
    ///
    /// `aovs` are the state's AOVs: its declarations and sums. A state without AOVs (`None`, or
    /// a version 2 state) adds to the cascades only; a state with AOVs must declare exactly the
    /// frame's.
    pub fn import(
        &self,
        frame: &str,
        state: &impl Importable,
        aovs: Option<(&[AovSpec], &AovSums)>,
        origin: Option<&Origin>,
        batches: &[Applied],
    ) -> Result<bool, ImportRefused> {
        if frame != self.id() {
            return Err(ImportRefused::WrongFrame {
                state: frame.to_owned(),
                url: self.id().to_owned(),
            });
        }
        let mismatch = |error| ImportRefused::Mismatch {
            frame: self.id().to_owned(),
            error,
        };
        self.check_fits_import(state).map_err(mismatch)?;
        if let Some((specs, _)) = aovs {
            self.check_state_aovs(specs)?;
        }
        let _gate = self.gate.read().unwrap_or_else(|e| e.into_inner());
        if self.retired.load(Ordering::Acquire) {
            return Err(ImportRefused::Deleted {
                frame: self.id().to_owned(),
            });
        }
        // Every band, locked top to bottom (as every holder of several bands locks them), so
        // that the room check and the additions see the same cells; then the applied set, so
        // that no batch is recorded between the overlap check and the recording.
        let mut bands: Vec<MutexGuard<'_, Arc<FrameState>>> = self.bands.iter().map(lock).collect();
        // The AOV sums after the bands and before the applied set, as ingest locks them.
        let mut aov_sums = match (aovs, &self.aovs) {
            (Some((_, theirs)), Some(mine)) => Some((lock(mine), theirs)),
            _ => None,
        };
        let mut seen = lock(&self.seen);
        if let Some(o) = origin {
            if seen.nodes.get(&o.node).is_some_and(|s| s.contains(o.seq)) {
                return Ok(false);
            }
        }
        if let Some(o) = seen.overlap(batches) {
            return Err(ImportRefused::Overlap {
                frame: self.id().to_owned(),
                worker: o.worker,
                seq: o.seq,
                count: o.count,
            });
        }
        // No pixel holds more than a whole state: the cells need reading only near the limit.
        let y0 = state.first_row();
        let crowded: Vec<usize> = (0..bands.len())
            .filter(|&i| {
                bands[i].total_samples().saturating_add(state.samples()) > MAX_PIXEL_SAMPLES
            })
            .collect();
        if !crowded.is_empty() {
            state
                .pieces(&mut |first, cells| {
                    crowded
                        .iter()
                        .try_for_each(|&i| bands[i].check_room_for_pixels(y0, first, cells))
                })
                .map_err(mismatch)?;
        }
        if let Some((mine, theirs)) = &aov_sums {
            mine.check_room_for(theirs)
                .map_err(|e: AovCellsError| ImportRefused::Aovs {
                    frame: self.id().to_owned(),
                    reason: e.to_string(),
                })?;
        }
        if let Some(o) = origin {
            seen.insert_delta(&o.node, o.seq);
        }
        seen.insert_applied(batches);
        drop(seen);
        // Every band has the frame's size and layout (checked above for band 0) and room; one
        // pass over the state adds each piece to the bands it falls in.
        // Copies of the bands cuts hold, made before anything changes.
        let mut bands: Vec<&mut FrameState> = bands.iter_mut().map(|b| Arc::make_mut(b)).collect();
        let mut added = 0;
        state
            .pieces(&mut |first, cells| {
                for band in bands.iter_mut() {
                    added += band.add_pixels(y0, first, cells);
                }
                Ok(())
            })
            .expect("adding checked pieces refuses nothing");
        debug_assert_eq!(added, state.samples());
        if let Some((mine, theirs)) = aov_sums.as_mut() {
            Arc::make_mut(mine)
                .merge_overlap(theirs)
                .expect("AOV sums were checked for room above");
        }
        drop(aov_sums);
        drop(bands);
        self.counters
            .samples
            .fetch_add(state.samples(), Ordering::Relaxed);
        self.counters.imports.fetch_add(1, Ordering::Relaxed);
        self.version.fetch_add(1, Ordering::AcqRel);
        Ok(true)
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
        }
    }

    /// Appends the frame's state with the batches it holds, in the state wire format, to `out`
    /// (`GET .../state`), encoded from a [`ShardedFrame::cut`]: writers go on meanwhile.
    pub fn write_state(&self, out: &mut Vec<u8>) {
        let cut = self.cut();
        let bands: Vec<&FrameState> = cut.bands.iter().map(|b| &**b).collect();
        let aovs = cut
            .aovs
            .as_deref()
            .map(|sums| (self.spec.request.aovs.as_slice(), sums));
        splatd_formats::state::write_bands(&bands, aovs, self.id(), None, cut.seen.applied(), out)
            .expect("writing into a Vec<u8> is infallible");
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

    /// What the frame looks like now, for `GET /v1/frames/{id}`.
    pub fn info(&self) -> FrameInfo {
        let spp = self.spp_figures();
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

/// The checked samples of one ingest.
enum Parts<'a> {
    /// A batch's records, sorted into one bucket per band.
    Records {
        batch: &'a Batch,
        buckets: Vec<Vec<(u32, u32, [f32; 3])>>,
    },
    /// A whole pass: one sample per pixel of the frame, row-major.
    Pass { rgb: &'a [[f32; 3]] },
}

impl Parts<'_> {
    /// Samples in all.
    fn len(&self) -> u64 {
        match self {
            Parts::Records { batch, .. } => batch.records.len() as u64,
            Parts::Pass { rgb } => rgb.len() as u64,
        }
    }

    /// Whether band `i` receives samples.
    fn touches(&self, i: usize) -> bool {
        match self {
            Parts::Records { buckets, .. } => !buckets[i].is_empty(),
            Parts::Pass { .. } => true,
        }
    }

    /// The refusal for the first sample band `i` (`band`) cannot take, if any.
    fn first_full(&self, i: usize, band: &FrameState) -> Option<IngestError> {
        match self {
            Parts::Records { batch, buckets } => first_full(band, &buckets[i]).map(|(x, y)| {
                let spp = band.spp(x, y);
                pixel_full(batch, x, y, spp)
            }),
            Parts::Pass { rgb } => {
                // One sample per pixel of the band's rows.
                let w = band.width();
                let pixels = w as u64 * band.rows().len() as u64;
                if band.total_samples().saturating_add(pixels) <= MAX_PIXEL_SAMPLES {
                    return None;
                }
                let (x, y) = band
                    .rows()
                    .flat_map(|y| (0..w).map(move |x| (x, y)))
                    .find(|&(x, y)| !band.has_room(x, y, 1))?;
                let index = y as usize * w as usize + x as usize;
                Some(IngestError::Sample {
                    index,
                    record: Record::new(x, y, rgb[index]),
                    error: SampleError::PixelFull { x, y },
                })
            }
        }
    }

    /// Adds band `i`'s samples to `band`.
    fn splat(&self, i: usize, band: &mut FrameState) {
        let report = match self {
            Parts::Records { buckets, .. } => band.splat_records(&buckets[i]),
            Parts::Pass { rgb } => {
                let w = band.width() as usize;
                let mut report = estimator::SplatReport::default();
                for y in band.rows() {
                    let row = &rgb[y as usize * w..(y as usize + 1) * w];
                    let r = band.splat_row(0, y, row);
                    report.accepted += r.accepted;
                    report.pixel_full += r.rejected();
                }
                report
            }
        };
        debug_assert_eq!(report.rejected(), 0, "samples were checked before");
    }
}

/// The first pixel of `samples` (of one band) that cannot take all of its samples in `band`.
fn first_full(band: &FrameState, samples: &[(u32, u32, [f32; 3])]) -> Option<(u32, u32)> {
    let n = samples.len() as u64;
    if band.total_samples().saturating_add(n) <= MAX_PIXEL_SAMPLES {
        return None;
    }
    // Near the limit: count the samples of the pixels that could not take the whole batch.
    let mut near: std::collections::HashMap<(u32, u32), u64> = Default::default();
    for &(x, y, _) in samples {
        if !band.has_room(x, y, n) {
            *near.entry((x, y)).or_default() += 1;
        }
    }
    samples
        .iter()
        .map(|&(x, y, _)| (x, y))
        .find(|&(x, y)| near.get(&(x, y)).is_some_and(|&k| !band.has_room(x, y, k)))
}

/// The refusal of `batch` because pixel `(x, y)`, holding `spp` samples, cannot take them all:
/// names the record that would go past the limit.
#[cold]
fn pixel_full(batch: &Batch, x: u32, y: u32, spp: u64) -> IngestError {
    let mut held = spp;
    let (index, record) = batch
        .records
        .iter()
        .enumerate()
        .filter(|(_, r)| (r.x, r.y) == (x, y))
        .find(|_| {
            held += 1;
            held > MAX_PIXEL_SAMPLES
        })
        .expect("the pixel cannot take its records");
    IngestError::Sample {
        index,
        record: *record,
        error: SampleError::PixelFull { x, y },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use splatd_proto::Record;
    use splatd_scenes::synth::FireflyScene;

    fn spec(w: u32, h: u32) -> FrameSpec {
        FrameSpec::new(CreateFrame::new("f", w, h)).expect("valid")
    }

    fn batch(worker: u64, seq: u64, records: Vec<Record>) -> Batch {
        Batch::new("f", worker, seq, records).expect("valid frame id")
    }

    fn records(scene: &FireflyScene, pass: u64) -> Vec<Record> {
        scene
            .pass(pass)
            .map(|(x, y, rgb)| Record { x, y, rgb })
            .collect()
    }

    /// Names are printable ASCII and `<name>.<channel>` at most 255 bytes; each refusal names
    /// its rule, and quotes a long name cut short.
    #[test]
    fn aov_names_are_what_openexr_holds() {
        let spec = |name: &str, channel: &str| {
            FrameSpec::new(CreateFrame {
                aovs: vec![AovSpec::new(name, &[channel])],
                ..CreateFrame::new("f", 2, 2)
            })
        };
        let refused = |name: &str, channel: &str| spec(name, channel).unwrap_err().to_string();
        let long = |n: usize| "a".repeat(n);
        assert!(spec(&long(253), "R").is_ok());
        assert!(spec("x", &long(253)).is_ok());
        assert!(spec(r#"View Layer #1 ~!@$%^&*()[]{}<>|\/?;:'",+=-_`"#, "r g").is_ok());
        for (name, channel, rule) in [
            ("a\0b", "R", "characters rule"),
            ("ab", "\u{1b}", "characters rule"),
            ("été", "R", "encoding rule"),
            ("ab", "深", "encoding rule"),
            (long(254).as_str(), "R", "length rule"),
            ("x", long(254).as_str(), "length rule"),
            (long(30_000).as_str(), "R", "length rule"),
        ] {
            let e = refused(name, channel);
            assert!(e.contains(rule), "{e}");
            assert!(e.len() < 400, "{e}");
        }
        assert!(refused("a\0b", "R").contains("byte 1 is the control character 0x00"));
    }

    #[test]
    fn banded_frame_resolves_like_one_state() {
        let scene = FireflyScene::new(13, 70, 5);
        let frame = ShardedFrame::new(spec(13, 70));
        assert!(frame.bands.len() > 1, "the test needs several bands");
        let mut reference = FrameState::new(13, 70, CascadeLayout::with_defaults());
        for pass in 0..24 {
            reference.splat_all(scene.pass(pass));
            let got = frame
                .ingest(&batch(1, pass, records(&scene, pass)))
                .unwrap();
            assert_eq!(got.accepted, 13 * 70);
        }
        let params = estimator::ResolveParams::with_defaults();
        assert_eq!(frame.cut().resolve(&params, 2), reference.resolve(&params));
        assert_eq!(frame.cut().whole(), reference);
        let info = frame.info();
        assert_eq!(
            (info.spp_min, info.spp_max, info.samples),
            (24, 24, 24 * 910)
        );
    }

    #[test]
    fn a_bad_record_anywhere_leaves_the_frame_untouched() {
        let frame = ShardedFrame::new(spec(4, 40));
        let mut recs: Vec<Record> = (0..40)
            .map(|y| Record {
                x: 1,
                y,
                rgb: [1.0; 3],
            })
            .collect();
        recs[39].rgb[1] = f32::NAN;
        let err = frame.ingest(&batch(1, 0, recs.clone())).unwrap_err();
        assert!(
            matches!(err, IngestError::Sample { index: 39, .. }),
            "{err}"
        );
        recs[39].rgb[1] = 1.0;
        recs[20].x = 4;
        let err = frame.ingest(&batch(1, 0, recs)).unwrap_err();
        assert!(
            err.to_string().starts_with("record 20 (pixel (4, 20)")
                && err.to_string().contains("outside the 4x40 frame"),
            "{err}"
        );
        assert_eq!(frame.cut().whole().total_samples(), 0);
        let info = frame.info();
        assert_eq!((info.rejected_batches, info.rejected_samples), (2, 80));
        assert_eq!(frame.version(), 0);
    }

    #[test]
    fn a_retried_batch_counts_once() {
        let frame = ShardedFrame::new(spec(4, 4));
        let recs = vec![Record {
            x: 0,
            y: 0,
            rgb: [2.0; 3],
        }];
        let first = frame.ingest(&batch(9, 0, recs.clone())).unwrap();
        let again = frame.ingest(&batch(9, 0, recs.clone())).unwrap();
        assert_eq!(
            first,
            Ingested {
                accepted: 1,
                duplicate: false
            }
        );
        assert_eq!(
            again,
            Ingested {
                accepted: 0,
                duplicate: true
            }
        );
        assert!(!frame.ingest(&batch(8, 0, recs)).unwrap().duplicate);
        assert_eq!(frame.info().samples, 2);
    }

    #[test]
    fn imports_add_exactly_and_deltas_count_once() {
        let scene = FireflyScene::new(9, 30, 2);
        let frame = ShardedFrame::new(spec(9, 30));
        let mut other = FrameState::new(9, 30, CascadeLayout::with_defaults());
        for pass in 0..5 {
            other.splat_all(scene.pass(pass));
            frame
                .ingest(&batch(1, pass, records(&scene, pass)))
                .unwrap();
        }
        let origin = Origin {
            node: "n1".into(),
            seq: 0,
        };
        assert!(frame.import("f", &other, None, Some(&origin), &[]).unwrap());
        assert!(!frame.import("f", &other, None, Some(&origin), &[]).unwrap());
        let mut expected = other.clone();
        expected.merge(&other).unwrap();
        assert_eq!(frame.cut().whole(), expected);

        let wrong = FrameState::new(9, 31, CascadeLayout::with_defaults());
        let err = frame.import("f", &wrong, None, None, &[]).unwrap_err();
        assert!(err.to_string().contains("9x30"), "{err}");
        assert_eq!(frame.cut().whole(), expected);
    }

    /// A cut holds every band as it was at the cut, whatever is applied while it is held
    /// (a batch over every band, an import), and the frame itself loses nothing; only bands
    /// changed while a cut holds them are copied.
    #[test]
    fn a_cut_is_the_frame_at_the_cut() {
        let scene = FireflyScene::new(9, 70, 3);
        let frame = ShardedFrame::new(spec(9, 70));
        assert!(frame.bands.len() >= 4, "the test needs several bands");
        for pass in 0..3 {
            frame
                .ingest(&batch(1, pass, records(&scene, pass)))
                .unwrap();
        }
        let cut = frame.cut();
        let at_cut: Vec<FrameState> = cut.bands.iter().map(|b| (**b).clone()).collect();
        let at_cut_seen = cut.seen.clone();
        let mut other = FrameState::new(9, 70, CascadeLayout::with_defaults());
        other.splat_all(scene.pass(7));

        // The cut shares the bands: taking it copied nothing.
        for (band, held) in frame.bands.iter().zip(&cut.bands) {
            assert!(Arc::ptr_eq(&lock(band), held));
        }
        frame.ingest(&batch(1, 3, records(&scene, 3))).unwrap();
        frame.import("f", &other, None, None, &[]).unwrap();
        let held: Vec<FrameState> = cut.bands.iter().map(|b| (**b).clone()).collect();
        assert_eq!(held, at_cut, "the cut is the frame as it was");
        assert_eq!(cut.seen, at_cut_seen);
        for (band, held) in frame.bands.iter().zip(&cut.bands) {
            assert!(!Arc::ptr_eq(&lock(band), held), "changed bands were copied");
        }

        let mut expected = cut.whole();
        expected.splat_all(scene.pass(3));
        expected.merge(&other).unwrap();
        drop(cut);
        assert_eq!(frame.cut().whole(), expected);

        // With no cut held, a writer changes its band in place.
        let before: Vec<*const FrameState> =
            frame.bands.iter().map(|b| Arc::as_ptr(&lock(b))).collect();
        frame.ingest(&batch(1, 4, records(&scene, 4))).unwrap();
        let after: Vec<*const FrameState> =
            frame.bands.iter().map(|b| Arc::as_ptr(&lock(b))).collect();
        assert_eq!(before, after, "no copy without a cut");
    }

    #[test]
    fn nonsense_parameters_are_refused_by_name() {
        let mut req = CreateFrame::new("f", 4, 4);
        req.cascades.base = 1.0;
        let err = FrameSpec::new(req).unwrap_err();
        assert!(err.to_string().contains("base"), "{err}");
        let err = FrameSpec::new(CreateFrame::new("f", 0, 4)).unwrap_err();
        assert!(err.to_string().contains("0x4"), "{err}");
        let mut req = CreateFrame::new("f", 4, 4);
        req.resolve.kappa = -1.0;
        assert!(FrameSpec::new(req)
            .unwrap_err()
            .to_string()
            .contains("kappa"));
    }

    /// A batch id reused for other records is refused by name, applies nothing and is counted;
    /// the original batch's retry is still a plain duplicate.
    #[test]
    fn an_id_reused_for_other_records_is_refused() {
        let frame = ShardedFrame::new(spec(4, 4));
        let first = vec![Record::new(0, 0, [2.0; 3])];
        let other = vec![Record::new(1, 1, [3.0; 3])];
        frame.ingest(&batch(9, 0, first.clone())).unwrap();
        let before = frame.cut().whole();
        let err = frame.ingest(&batch(9, 0, other)).unwrap_err();
        assert!(
            matches!(
                err,
                IngestError::IdReused {
                    worker: 9,
                    seq: 0,
                    ..
                }
            ),
            "{err}"
        );
        assert!(
            err.to_string()
                .contains("already applied with other records"),
            "{err}"
        );
        assert_eq!(
            frame.cut().whole(),
            before,
            "nothing of the refused batch applied"
        );
        let info = frame.info();
        assert_eq!(
            (info.samples, info.rejected_batches, info.rejected_samples),
            (1, 1, 1)
        );
        assert!(frame.ingest(&batch(9, 0, first)).unwrap().duplicate);
    }

    /// A state holding only some rows of the frame (legal in the state format) is added whole,
    /// into whichever bands its rows fall in; a state that does not fit changes nothing: not the
    /// cells, not the origins seen, not the version.
    #[test]
    fn imports_are_all_or_nothing() {
        let scene = FireflyScene::new(16, 64, 8);
        let frame = ShardedFrame::new(spec(16, 64));
        assert!(frame.bands.len() >= 8, "the test needs several bands");
        let layout = CascadeLayout::with_defaults();
        // Rows 4..20 straddle band boundaries.
        let mut part = FrameState::band(16, 64, 4..20, layout.clone());
        let mut whole = FrameState::new(16, 64, layout.clone());
        for pass in 0..6 {
            let rows = part.rows();
            part.splat_all(scene.pass(pass).filter(|s| rows.contains(&s.1)));
        }
        whole.merge(&part).unwrap();
        let origin = Origin {
            node: "n".into(),
            seq: 0,
        };
        assert!(frame.import("f", &part, None, Some(&origin), &[]).unwrap());
        assert_eq!(frame.cut().whole(), whole);
        assert_eq!(frame.version(), 1);

        let other_layout = CascadeLayout::new(
            layout.base(),
            5,
            layout.lowest_scale(),
            layout.luminance_weights(),
        )
        .unwrap();
        let misfit = FrameState::band(16, 64, 0..8, other_layout);
        let retry = Origin {
            node: "m".into(),
            seq: 0,
        };
        let err = frame
            .import("f", &misfit, None, Some(&retry), &[])
            .unwrap_err();
        assert!(matches!(err, ImportRefused::Mismatch { .. }), "{err}");
        assert_eq!(frame.cut().whole(), whole);
        assert_eq!(frame.version(), 1);
        assert!(
            !frame.cut().seen.nodes.contains_key("m"),
            "a refused import's origin is not recorded"
        );
    }

    /// A batch with a sample brighter than the layout represents, or one that would put more
    /// than 2^32 samples in a pixel, is refused whole and counted; so is an import that would.
    #[test]
    fn too_bright_samples_and_full_pixels_are_refused_whole() {
        let frame = ShardedFrame::new(spec(4, 40));
        let max = frame.spec().layout.max_component() as f32;
        let mut recs: Vec<Record> = (0..40).map(|y| Record::new(1, y, [max; 3])).collect();
        recs[30].rgb[2] = 1e14;
        let err = frame.ingest(&batch(1, 0, recs.clone())).unwrap_err();
        assert!(
            matches!(
                err,
                IngestError::Sample {
                    index: 30,
                    error: SampleError::TooBright { .. },
                    ..
                }
            ),
            "{err}"
        );
        assert!(err.to_string().contains("largest representable"), "{err}");
        assert_eq!(frame.version(), 0);
        recs[30].rgb[2] = max;
        assert_eq!(frame.ingest(&batch(1, 0, recs)).unwrap().accepted, 40);

        // Fill pixel (2, 3) to 2^32 samples, by an import.
        let mut full = FrameState::new(4, 40, frame.spec().layout.clone());
        full.splat(2, 3, [1.0; 3]).unwrap();
        for _ in 0..32 {
            let copy = full.clone();
            full.merge(&copy).unwrap();
        }
        assert!(frame.import("f", &full, None, None, &[]).unwrap());
        let before = frame.cut().whole();
        let recs = vec![
            Record::new(0, 0, [1.0; 3]),
            Record::new(2, 3, [1.0; 3]),
            Record::new(3, 3, [1.0; 3]),
        ];
        let err = frame.ingest(&batch(1, 1, recs)).unwrap_err();
        assert!(
            matches!(
                err,
                IngestError::Sample {
                    index: 1,
                    error: SampleError::PixelFull { x: 2, y: 3 },
                    ..
                }
            ),
            "{err}"
        );
        let mut one = FrameState::new(4, 40, frame.spec().layout.clone());
        one.splat(2, 3, [1.0; 3]).unwrap();
        one.splat(0, 39, [1.0; 3]).unwrap();
        let err = frame.import("f", &one, None, None, &[]).unwrap_err();
        assert_eq!(
            err,
            ImportRefused::Mismatch {
                frame: "f".into(),
                error: MergeError::TooManySamples { x: 2, y: 3 }
            }
        );
        assert_eq!(frame.cut().whole(), before, "nothing of either applied");
        let info = frame.info();
        assert_eq!(info.samples, 40 + (1 << 32));
        assert_eq!(info.spp_max, 1 << 32);
        assert_eq!((info.rejected_batches, info.rejected_samples), (2, 43));
        // Other pixels still take samples.
        let ok = vec![Record::new(0, 0, [1.0; 3]), Record::new(3, 39, [2.0; 3])];
        assert_eq!(frame.ingest(&batch(1, 2, ok)).unwrap().accepted, 2);
    }

    /// A pass ingested whole (rows straight into the bands) against the batch of its records:
    /// the same cells over several bands, the same digest (a pass retried as records is a
    /// duplicate, other records under its id a conflict), the same refusals with the same
    /// index and record for a bad sample and for a full pixel, and nothing applied by them.
    #[test]
    fn a_pass_is_ingested_as_the_batch_of_its_records() {
        let (w, h) = (13, 70);
        let scene = FireflyScene::new(w, h, 5);
        let by_pass = ShardedFrame::new(spec(w, h));
        let by_records = ShardedFrame::new(spec(w, h));
        assert!(by_pass.bands.len() > 1, "the test needs several bands");
        for pass in 0..6 {
            let recs = records(&scene, pass);
            let rgb: Vec<[f32; 3]> = recs.iter().map(|r| r.rgb).collect();
            let got = by_pass.ingest_pass(1, pass, &rgb, None).unwrap();
            assert_eq!(got.accepted, (w * h) as u64);
            by_records.ingest(&batch(1, pass, recs)).unwrap();
        }
        assert_eq!(by_pass.cut().whole(), by_records.cut().whole());
        let again = by_pass.ingest(&batch(1, 5, records(&scene, 5))).unwrap();
        assert!(again.duplicate, "the records of pass 5 are its retry");
        let err = by_pass
            .ingest(&batch(1, 5, records(&scene, 6)))
            .unwrap_err();
        assert!(matches!(err, IngestError::IdReused { .. }), "{err}");

        // A bad sample: refused naming the same record as the batch refusal does.
        let mut recs = records(&scene, 6);
        recs[200].rgb[1] = -1.0;
        let rgb: Vec<[f32; 3]> = recs.iter().map(|r| r.rgb).collect();
        let version = by_pass.version();
        let err = by_pass.ingest_pass(1, 6, &rgb, None).unwrap_err();
        assert_eq!(err, by_records.ingest(&batch(1, 6, recs)).unwrap_err());
        assert!(
            matches!(err, IngestError::Sample { index: 200, .. }),
            "{err}"
        );
        assert_eq!(by_pass.version(), version);

        // A full pixel: pixel (2, 3), holding 6 samples, to 2^32 by an import into both frames
        // of 2^32 samples less 6.
        let layout = by_pass.spec().layout.clone();
        let mut full = FrameState::new(w, h, layout.clone());
        full.splat(2, 3, [1.0; 3]).unwrap();
        for _ in 0..32 {
            let copy = full.clone();
            full.merge(&copy).unwrap();
        }
        let mut six = FrameState::new(w, h, layout);
        for _ in 0..6 {
            six.splat(2, 3, [1.0; 3]).unwrap();
        }
        let top = full.delta_since(&six).unwrap();
        for frame in [&by_pass, &by_records] {
            assert!(frame.import("f", &top, None, None, &[]).unwrap());
            assert_eq!(frame.cut().whole().spp(2, 3), MAX_PIXEL_SAMPLES);
        }
        let before = by_pass.cut().whole();
        let recs = records(&scene, 7);
        let rgb: Vec<[f32; 3]> = recs.iter().map(|r| r.rgb).collect();
        let err = by_pass.ingest_pass(1, 7, &rgb, None).unwrap_err();
        assert_eq!(err, by_records.ingest(&batch(1, 7, recs)).unwrap_err());
        assert!(
            matches!(
                err,
                IngestError::Sample {
                    index: 41,
                    error: SampleError::PixelFull { x: 2, y: 3 },
                    ..
                }
            ),
            "{err}"
        );
        assert_eq!(by_pass.cut().whole(), before, "nothing of it applied");
        let info = by_pass.info();
        // The conflicting id, the bad sample and the full pixel.
        assert_eq!((info.rejected_batches, info.rejected_samples), (3, 3 * 910));
    }

    /// A state body imported from its runs (checked and added piece by piece, straight from the
    /// bytes) gives the frame the same cells as the decoded state, with the same refusals.
    #[test]
    fn imports_from_runs_match_imports_of_states() {
        let import_runs = |frame: &ShardedFrame, state: &FrameState| {
            let bytes = splatd_formats::state::dump(state, None, "f", None, vec![]).encode();
            let (dump, runs, aov_runs) =
                splatd_proto::StateDump::decode_runs(&bytes, u64::MAX).unwrap();
            let decoded = splatd_formats::state::load_runs(dump, runs, aov_runs).unwrap();
            assert_eq!(decoded.samples(), state.total_samples());
            frame.import("f", &decoded, decoded.aovs(), None, &[])
        };
        let scene = FireflyScene::new(16, 64, 9);
        let layout = CascadeLayout::with_defaults();
        // Rows 4..20 straddle band boundaries; every other pixel of a row is empty, so the
        // state is many short runs.
        let mut part = FrameState::band(16, 64, 4..20, layout.clone());
        for pass in 0..5 {
            let rows = part.rows();
            part.splat_all(
                scene
                    .pass(pass)
                    .filter(|s| rows.contains(&s.1) && (s.0 + s.1) % 2 == 0),
            );
        }
        let (states, runs) = (
            ShardedFrame::new(spec(16, 64)),
            ShardedFrame::new(spec(16, 64)),
        );
        assert!(runs.bands.len() >= 8, "the test needs several bands");
        for _ in 0..2 {
            assert!(states.import("f", &part, None, None, &[]).unwrap());
            assert!(import_runs(&runs, &part).unwrap());
        }
        assert_eq!(runs.cut().whole(), states.cut().whole());
        assert_eq!(runs.info().samples, 2 * part.total_samples());

        // A pixel at 2^32 samples refuses a state adding one more, whole.
        let small = ShardedFrame::new(spec(4, 40));
        let mut full = FrameState::new(4, 40, small.spec().layout.clone());
        full.splat(2, 3, [1.0; 3]).unwrap();
        for _ in 0..32 {
            let copy = full.clone();
            full.merge(&copy).unwrap();
        }
        assert!(import_runs(&small, &full).unwrap());
        let before = small.cut().whole();
        let mut one = FrameState::new(4, 40, small.spec().layout.clone());
        one.splat(0, 0, [1.0; 3]).unwrap();
        one.splat(2, 3, [1.0; 3]).unwrap();
        assert_eq!(
            import_runs(&small, &one).unwrap_err(),
            ImportRefused::Mismatch {
                frame: "f".into(),
                error: MergeError::TooManySamples { x: 2, y: 3 }
            }
        );
        assert_eq!(small.cut().whole(), before, "nothing of it applied");
    }

    /// A state's header is checked before its AOV words are expanded, with the refusals that
    /// `import` gives: another frame's id, another size, AOVs other than the frame's (a state
    /// without AOVs is fine). Nothing is applied by a check.
    #[test]
    fn state_headers_are_checked_before_aov_words_are_expanded() {
        let albedo = vec![AovSpec::new("albedo", &["R", "G", "B"])];
        let mut request = CreateFrame::new("f", 8, 4);
        request.aovs = albedo.clone();
        let frame = ShardedFrame::new(FrameSpec::new(request).unwrap());
        assert_eq!(frame.check_state_header("f", 8, 4, &albedo), Ok(()));
        assert_eq!(frame.check_state_header("f", 8, 4, &[]), Ok(()));
        assert!(matches!(
            frame.check_state_header("g", 9, 4, &albedo),
            Err(ImportRefused::WrongFrame { state, .. }) if state == "g"
        ));
        assert_eq!(
            frame.check_state_header("f", 9, 4, &albedo),
            Err(ImportRefused::Mismatch {
                frame: "f".into(),
                error: MergeError::Size {
                    ours_w: 8,
                    ours_h: 4,
                    theirs_w: 9,
                    theirs_h: 4
                }
            })
        );
        let depth = [AovSpec::new("depth", &["Z"])];
        match frame.check_state_header("f", 8, 4, &depth) {
            Err(ImportRefused::Aovs { reason, .. }) => {
                assert!(reason.contains("\"depth\" (Z)"), "{reason}");
                assert!(reason.contains("\"albedo\" (R, G, B)"), "{reason}");
            }
            other => panic!("{other:?}"),
        }
        // A frame without AOVs takes no state with AOVs.
        let plain = ShardedFrame::new(spec(8, 4));
        assert!(matches!(
            plain.check_state_header("f", 8, 4, &albedo),
            Err(ImportRefused::Aovs { .. })
        ));
        assert_eq!(frame.info().samples, 0);
    }

    /// After `retire` returns, nothing is applied: batches and imports are refused by name.
    #[test]
    fn a_retired_frame_takes_nothing() {
        let frame = ShardedFrame::new(spec(4, 4));
        frame
            .ingest(&batch(1, 0, vec![Record::new(0, 0, [1.0; 3])]))
            .unwrap();
        frame.retire();
        let err = frame
            .ingest(&batch(1, 1, vec![Record::new(0, 0, [1.0; 3])]))
            .unwrap_err();
        assert!(matches!(err, IngestError::Deleted { .. }), "{err}");
        let state = frame.cut().whole();
        assert!(matches!(
            frame.import("f", &state, None, None, &[]),
            Err(ImportRefused::Deleted { .. })
        ));
        assert_eq!(frame.info().samples, 1);
        frame.unretire();
        assert!(frame
            .ingest(&batch(1, 1, vec![Record::new(0, 0, [1.0; 3])]))
            .is_ok());
    }

    /// A deletion waits for the answers of requests that hold a lease, and no lease is given
    /// after it began.
    #[tokio::test]
    async fn a_deletion_drains_leased_requests_first() {
        let frame = Arc::new(ShardedFrame::new(spec(4, 4)));
        let lease = frame.lease().await.expect("a live frame leases");
        let deleting = tokio::spawn({
            let frame = frame.clone();
            async move { frame.retire_and_drain().await }
        });
        // Retiring runs on a blocking thread that a loaded machine may start late: wait for it
        // as an event, bounded only against a hang.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
        while !frame.is_retired() && std::time::Instant::now() < deadline {
            tokio::time::sleep(std::time::Duration::from_millis(1)).await;
        }
        assert!(frame.is_retired());
        assert!(frame.lease().await.is_none(), "no lease after retiring");
        tokio::task::yield_now().await;
        assert!(
            !deleting.is_finished(),
            "the deletion waits for the leased request"
        );
        drop(lease);
        deleting.await.unwrap();
    }
}
