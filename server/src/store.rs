//! The frames a server holds, and the limits on how many and how large.

use std::collections::BTreeMap;
use std::sync::{Arc, RwLock};

use splatd_estimator::ParamError;
use splatd_proto::api::CreateFrame;

use super::frame::{FrameSpec, ShardedFrame};
use super::memory::CellPool;
use super::Limits;

/// What `POST /v1/frames` did.
#[derive(Debug, Clone)]
pub enum Created {
    /// A new, empty frame.
    New(Arc<ShardedFrame>),
    /// A frame with this id and exactly these parameters existed (a retried create).
    Existing(Arc<ShardedFrame>),
}

/// Why the store refused a request. The store says what is wrong; how that is answered (a status,
/// a code) is the caller's business, so the same store can sit behind any interface.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StoreError {
    /// The create request's parameters break their own rules.
    #[error(transparent)]
    InvalidParameters(#[from] ParamError),
    /// The frame would have more pixels than this server allows.
    #[error("a {width}x{height} frame has {pixels} pixels; this server allows at most {max}")]
    TooManyPixels {
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
        /// `width * height`.
        pixels: u64,
        /// The server's limit.
        max: u64,
    },
    /// The frame would have more cascades than this server allows.
    #[error("{requested} cascades requested; this server allows at most {max}")]
    TooManyCascades {
        /// Requested cascades.
        requested: u32,
        /// The server's limit.
        max: u32,
    },
    /// A frame of this id exists with other parameters.
    #[error("frame {id:?} exists with different parameters ({difference})")]
    Exists {
        /// The frame id.
        id: String,
        /// Which parameters differ.
        difference: String,
    },
    /// The store holds as many frames as it may.
    #[error("this server holds {held} frames, its limit; delete one first")]
    TooManyFrames {
        /// Frames held.
        held: usize,
    },
    /// The frame's cascades would not fit in the memory left.
    #[error(
        "frame {id:?} needs {wanted_mib} MiB of cascades; {used_mib} MiB of this server's \
         {max_mib} MiB are in use"
    )]
    MemoryLimit {
        /// The frame id.
        id: String,
        /// MiB the frame needs (rounded up).
        wanted_mib: u64,
        /// MiB in use (rounded up).
        used_mib: u64,
        /// The server's limit in MiB.
        max_mib: u64,
    },
    /// No frame of this id.
    #[error("no frame {id:?} on this server")]
    UnknownFrame {
        /// The frame id asked for.
        id: String,
    },
}

/// All frames of a server, by id.
#[derive(Debug)]
pub struct FrameStore {
    frames: RwLock<BTreeMap<String, Arc<ShardedFrame>>>,
    limits: Limits,
    /// The cells of deleted frames, for new ones ([`CellPool`]); with the frames' cells
    /// within the cascade budget at every create.
    pool: Arc<CellPool>,
}

impl FrameStore {
    /// An empty store enforcing `limits`.
    pub fn new(limits: Limits) -> FrameStore {
        FrameStore {
            frames: RwLock::new(BTreeMap::new()),
            limits,
            pool: Arc::default(),
        }
    }

    /// The cells of deleted frames waiting for new frames.
    pub fn cell_pool(&self) -> &Arc<CellPool> {
        &self.pool
    }

    /// The limits in force.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Checks a create request against the parameters' own rules and this server's limits.
    pub fn check(&self, request: CreateFrame) -> Result<FrameSpec, StoreError> {
        let spec = FrameSpec::new(request)?;
        let r = &spec.request;
        let pixels = r.width as u64 * r.height as u64;
        if pixels > self.limits.max_pixels {
            return Err(StoreError::TooManyPixels {
                width: r.width,
                height: r.height,
                pixels,
                max: self.limits.max_pixels,
            });
        }
        if r.cascades.cascades > self.limits.max_cascades {
            return Err(StoreError::TooManyCascades {
                requested: r.cascades.cascades,
                max: self.limits.max_cascades,
            });
        }
        Ok(spec)
    }

    /// Creates a frame, or returns the existing one if it has exactly the same parameters.
    /// Blocking: a new frame's memory is zeroed here (call from a blocking thread).
    ///
    /// The frame is built without the store's lock held: cells taken from the pool are zeroed
    /// first, a `memset` of the whole frame that faults in whatever memory the frame before
    /// never touched (1.2 s for a 1080p frame with an albedo and a normal after an empty one,
    /// on the 2-core VM), and every request that looks a frame up waits for that lock. So the
    /// request is settled first (a retry, a clash of ids, a refusal), the frame built, and the
    /// same checks made again when it is put in (another create may have come in between; a
    /// frame built for nothing gives its memory back to the pool).
    pub fn create(&self, spec: FrameSpec) -> Result<Created, StoreError> {
        {
            let frames = self.frames.read().unwrap_or_else(|e| e.into_inner());
            if let Some(existing) = self.existing(&frames, &spec)? {
                return Ok(existing);
            }
            self.admit(&frames, &spec)?;
        }
        // Tests pause here to show that nothing else waits for the frame's memory.
        let _ = crate::failpoint::hit("frame:building");
        let frame = Arc::new(ShardedFrame::new_in(spec, &self.pool));
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        if let Some(existing) = self.existing(&frames, frame.spec())? {
            return Ok(existing);
        }
        self.admit(&frames, frame.spec())?;
        frames.insert(frame.id().to_owned(), frame.clone());
        Ok(Created::New(frame))
    }

    /// The frame of `spec`'s id if it has exactly `spec`'s parameters (a retried create), an
    /// error if it has others, `None` if there is none.
    fn existing(
        &self,
        frames: &BTreeMap<String, Arc<ShardedFrame>>,
        spec: &FrameSpec,
    ) -> Result<Option<Created>, StoreError> {
        let Some(existing) = frames.get(&spec.request.id) else {
            return Ok(None);
        };
        if existing.spec().request == spec.request {
            return Ok(Some(Created::Existing(existing.clone())));
        }
        Err(StoreError::Exists {
            id: spec.request.id.clone(),
            difference: describe_difference(&existing.spec().request, &spec.request),
        })
    }

    /// Removes `frame` (this very frame, not another of the same id).
    pub fn remove_frame(&self, frame: &Arc<ShardedFrame>) {
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        if frames
            .get(frame.id())
            .is_some_and(|f| Arc::ptr_eq(f, frame))
        {
            frames.remove(frame.id());
        }
    }

    /// Puts back a frame whose deletion failed; false if its id was taken meanwhile.
    pub fn reinsert(&self, frame: Arc<ShardedFrame>) -> bool {
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        if frames.contains_key(frame.id()) {
            return false;
        }
        frames.insert(frame.id().to_owned(), frame);
        true
    }

    /// Puts a frame restored from disk back (no limits: it was admitted before).
    pub fn insert_restored(&self, mut frame: ShardedFrame) {
        frame.give_cells_to(&self.pool);
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        frames.insert(frame.id().to_owned(), Arc::new(frame));
    }

    fn admit(
        &self,
        frames: &BTreeMap<String, Arc<ShardedFrame>>,
        spec: &FrameSpec,
    ) -> Result<(), StoreError> {
        if frames.len() >= self.limits.max_frames {
            return Err(StoreError::TooManyFrames { held: frames.len() });
        }
        let used: u64 = frames.values().map(|f| f.spec().memory_bytes()).sum();
        let wanted = spec.memory_bytes();
        if used + wanted > self.limits.max_memory_bytes {
            return Err(StoreError::MemoryLimit {
                id: spec.request.id.clone(),
                wanted_mib: wanted.div_ceil(1 << 20),
                used_mib: used.div_ceil(1 << 20),
                max_mib: self.limits.max_memory_bytes >> 20,
            });
        }
        // The pool's cells count against the budget too: if the new frame cannot fit beside
        // them, they go (it takes what fits its bands first, the rest is garbage then).
        if used + wanted + self.pool.idle_bytes() > self.limits.max_memory_bytes {
            self.pool
                .release_idle(std::time::Instant::now(), std::time::Duration::ZERO);
        }
        Ok(())
    }

    /// The frame `id`.
    pub fn get(&self, id: &str) -> Result<Arc<ShardedFrame>, StoreError> {
        let frames = self.frames.read().unwrap_or_else(|e| e.into_inner());
        frames.get(id).cloned().ok_or_else(|| unknown(id))
    }

    /// Every frame, ordered by id.
    pub fn list(&self) -> Vec<Arc<ShardedFrame>> {
        let frames = self.frames.read().unwrap_or_else(|e| e.into_inner());
        frames.values().cloned().collect()
    }

    /// Removes frame `id`.
    pub fn remove(&self, id: &str) -> Result<Arc<ShardedFrame>, StoreError> {
        let mut frames = self.frames.write().unwrap_or_else(|e| e.into_inner());
        frames.remove(id).ok_or_else(|| unknown(id))
    }
}

fn unknown(id: &str) -> StoreError {
    StoreError::UnknownFrame { id: id.to_owned() }
}

/// Names the first parameters that differ between two create requests.
fn describe_difference(ours: &CreateFrame, theirs: &CreateFrame) -> String {
    let mut diffs = Vec::new();
    if (ours.width, ours.height) != (theirs.width, theirs.height) {
        diffs.push(format!(
            "size {}x{} here, {}x{} requested",
            ours.width, ours.height, theirs.width, theirs.height
        ));
    }
    if ours.cascades != theirs.cascades {
        diffs.push(format!(
            "cascades {:?} here, {:?} requested",
            ours.cascades, theirs.cascades
        ));
    }
    if ours.resolve != theirs.resolve {
        diffs.push(format!(
            "resolve {:?} here, {:?} requested",
            ours.resolve, theirs.resolve
        ));
    }
    if ours.aovs != theirs.aovs {
        diffs.push(format!(
            "aovs {} here, {} requested",
            splatd_formats::names::describe_aovs(&ours.aovs),
            splatd_formats::names::describe_aovs(&theirs.aovs)
        ));
    }
    if ours.denoise != theirs.denoise {
        diffs.push(format!(
            "denoise {} here, {} requested",
            ours.denoise.as_str(),
            theirs.denoise.as_str()
        ));
    }
    if ours.denoise_guides != theirs.denoise_guides {
        diffs.push(format!(
            "denoise_guides {:?} here, {:?} requested",
            ours.denoise_guides, theirs.denoise_guides
        ));
    }
    if ours.converged_below != theirs.converged_below {
        diffs.push(format!(
            "converged_below {} here, {} requested",
            ours.converged_below, theirs.converged_below
        ));
    }
    diffs.join("; ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use splatd_proto::{Batch, Record};

    fn spec(id: &str, w: u32, h: u32) -> FrameSpec {
        FrameSpec::new(CreateFrame::new(id, w, h)).unwrap()
    }

    /// A deleted frame's cells wait in the pool, and the next frame of the same size takes
    /// them all and starts empty; the pool frees what waits longer than its idle time.
    #[test]
    fn a_deleted_frames_cells_serve_the_next_frame() {
        let store = FrameStore::new(Limits::default());
        let Created::New(first) = store.create(spec("a", 64, 48)).unwrap() else {
            panic!("a new frame")
        };
        let records = (0..48)
            .map(|y| Record::new(y, y, [40.0, 1.0, 0.5]))
            .collect();
        first
            .ingest(&Batch::new("a", 1, 0, records).unwrap())
            .unwrap();
        let bytes = first.spec().memory_bytes();
        let pool = store.cell_pool().clone();
        assert_eq!(pool.idle_bytes(), 0);
        drop(store.remove("a").unwrap());
        drop(first);
        assert_eq!(pool.idle_bytes(), bytes, "every band's cells are kept");

        let Created::New(second) = store.create(spec("b", 64, 48)).unwrap() else {
            panic!("a new frame")
        };
        assert_eq!(pool.idle_bytes(), 0, "the new frame took them all");
        let cut = second.cut();
        assert!(
            cut.band_refs()
                .iter()
                .all(|b| b.cells().iter().all(|&c| c == 0)),
            "and starts empty"
        );
        assert_eq!(second.info().samples, 0);
        drop(cut);

        drop(store.remove("b").unwrap());
        drop(second);
        let now = std::time::Instant::now();
        assert_eq!(pool.release_idle(now, crate::memory::CELL_POOL_IDLE), 0);
        let later = now + crate::memory::CELL_POOL_IDLE;
        assert_eq!(
            pool.release_idle(later, crate::memory::CELL_POOL_IDLE),
            bytes
        );
        assert_eq!(pool.idle_bytes(), 0);
    }

    /// A writer that changes bands a cut holds copies them into cells the pool has, and the
    /// bands the last cut holding them (a render's, a snapshot's) is done with go back to the
    /// pool once the frame has moved on to copies; the frame holds exactly what it was sent
    /// all along.
    #[test]
    fn copies_on_write_take_the_cells_cuts_gave_back() {
        let store = FrameStore::new(Limits::default());
        let Created::New(frame) = store.create(spec("a", 64, 48)).unwrap() else {
            panic!("a new frame")
        };
        let pool = store.cell_pool().clone();
        let batch = |seq: u64| {
            let records = (0..48).map(|y| Record::new(y, y, [seq as f32 + 0.5, 1.0, 9.0]));
            Batch::new("a", 1, seq, records.collect()).unwrap()
        };
        let mut oracle = splatd_estimator::FrameState::new(64, 48, frame.spec().layout.clone());
        let mut send = |seq: u64| {
            let b = batch(seq);
            frame.ingest(&b).unwrap();
            for r in &b.records {
                oracle.splat(r.x, r.y, r.rgb).unwrap();
            }
        };
        send(0);
        let first = frame.cut();
        send(1); // copies every band: the pool has nothing yet
        assert_eq!(pool.idle_bytes(), 0);
        let bytes = frame.spec().memory_bytes();
        let snapshot = first.clone();
        drop(first);
        assert_eq!(
            pool.idle_bytes(),
            0,
            "another cut still holds the old bands"
        );
        for band in snapshot.bands.iter().cloned() {
            frame.recycle(band); // as a snapshot does with each band it has written
        }
        assert_eq!(pool.idle_bytes(), 0, "the cut itself still holds them");
        drop(snapshot);
        assert_eq!(pool.idle_bytes(), bytes, "the last cut's bands, given back");
        let second = frame.cut();
        send(2); // copies every band again, into the cells given back
        assert_eq!(pool.idle_bytes(), 0, "the copies took them");
        drop(second);
        assert_eq!(pool.idle_bytes(), bytes);
        let held = frame.cut().whole();
        assert!(held == oracle, "the frame holds the three batches");
        assert_eq!(frame.info().samples, 3 * 48);
        // Bands the frame still shares are not given back.
        let before = pool.idle_bytes();
        drop(frame.cut());
        assert_eq!(pool.idle_bytes(), before);
    }

    /// A frame's AOV sums are copied on write like its bands: a pass that changes sums a cut
    /// holds copies them into memory the pool has, and the sums a cut is done with go back to
    /// the pool, so a frame snapshotted or rendered while it takes passes stops asking the
    /// kernel for memory; the frame holds exactly what it was sent all along.
    #[test]
    fn aov_sums_are_copied_on_write_into_the_memory_cuts_gave_back() {
        let store = FrameStore::new(Limits::default());
        let (w, h) = (64, 48);
        let request = CreateFrame {
            aovs: vec![
                splatd_proto::api::AovSpec::new("albedo", &["R", "G", "B"]),
                splatd_proto::api::AovSpec::new("depth", &["Z"]),
            ],
            ..CreateFrame::new("a", w, h)
        };
        let Created::New(frame) = store
            .create(FrameSpec::new(request.clone()).unwrap())
            .unwrap()
        else {
            panic!("a new frame")
        };
        let pool = store.cell_pool().clone();
        let pixels = (w * h) as usize;
        let mut oracle = splatd_estimator::AovSums::new(w, 0..h, 4);
        let mut send = |seq: u64| {
            let rgb = vec![[seq as f32 + 0.5, 1.0, 9.0]; pixels];
            let values: Vec<f32> = (0..4 * pixels)
                .map(|i| (i % 7) as f32 * 0.25 - seq as f32)
                .collect();
            frame.ingest_pass(1, seq, &rgb, Some(&values)).unwrap();
            oracle.add_pass(&values);
        };
        send(0);
        let first = frame.cut();
        send(1); // copies every band and the sums: the pool has nothing yet
        assert_eq!(pool.idle_bytes(), 0);
        drop(first);
        let bytes = frame.spec().memory_bytes();
        assert_eq!(
            pool.idle_bytes(),
            bytes,
            "the cut's bands and sums, given back"
        );
        let second = frame.cut();
        let held = second.aovs.as_deref().map(|sums| sums.words().as_ptr());
        send(2); // copies them again, into the memory given back
        assert_eq!(pool.idle_bytes(), 0, "the copies took it");
        let snapshot = second.clone();
        drop(second);
        assert_eq!(pool.idle_bytes(), 0, "another cut still holds them");
        let aovs = snapshot.aovs.clone().expect("a frame with AOVs");
        frame.recycle_aovs(aovs); // as a snapshot does once it has written them
        drop(snapshot);
        assert_eq!(pool.idle_bytes(), bytes);
        let now = frame.cut().aovs.clone().expect("a frame with AOVs");
        assert_eq!(*now, oracle, "the frame holds the three passes' AOV values");
        assert_ne!(
            held,
            Some(now.words().as_ptr()),
            "the cut's sums were not changed"
        );
        drop(now);

        // A deleted frame's sums serve the next frame's, which start empty.
        drop(store.remove("a").unwrap());
        drop(frame);
        assert_eq!(
            pool.idle_bytes(),
            2 * bytes,
            "its memory and the cuts' copies"
        );
        let next = CreateFrame {
            id: "b".into(),
            ..request
        };
        let Created::New(frame) = store.create(FrameSpec::new(next).unwrap()).unwrap() else {
            panic!("a new frame")
        };
        assert_eq!(
            pool.idle_bytes(),
            bytes,
            "the new frame took one frame's worth"
        );
        let sums = frame.cut().aovs.clone().expect("a frame with AOVs");
        assert_eq!(*sums, splatd_estimator::AovSums::new(w, 0..h, 4), "empty");
    }

    /// A frame still held by a cut when it is deleted keeps those bands out of the pool (the
    /// cut frees them); a new frame that cannot fit in the budget beside the pool frees it.
    #[test]
    fn the_pool_stays_within_the_budget() {
        let one = spec("a", 64, 48).memory_bytes();
        let store = FrameStore::new(Limits {
            max_memory_bytes: 2 * one + one / 2,
            ..Limits::default()
        });
        let Created::New(a) = store.create(spec("a", 64, 48)).unwrap() else {
            panic!("a new frame")
        };
        let cut = a.cut();
        drop(store.remove("a").unwrap());
        drop(a);
        assert_eq!(
            store.cell_pool().idle_bytes(),
            0,
            "the cut holds every band"
        );
        drop(cut);

        let Created::New(b) = store.create(spec("b", 64, 48)).unwrap() else {
            panic!("a new frame")
        };
        drop(store.remove("b").unwrap());
        drop(b);
        assert_eq!(store.cell_pool().idle_bytes(), one);
        // Twice the rows: it does not fit beside the kept cells (1 + 2 > 2.5 frames).
        store.create(spec("c", 64, 96)).unwrap();
        assert_eq!(store.cell_pool().idle_bytes(), 0, "the kept cells went");
    }
}
