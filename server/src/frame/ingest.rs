//! Batches and passes into a frame: every record checked, then all applied or none.

use std::sync::atomic::Ordering;
use std::sync::{Arc, MutexGuard};

use splatd_proto::{pass_digest, Batch, Record, RecordsDigest};

use splatd_estimator::{
    self as estimator, component_bits_accepted, FrameState, Kernel, Rect, SampleError,
    MAX_PIXEL_SAMPLES,
};

use super::dedup::BatchId;
use super::{lock, IngestError, Ingested, ShardedFrame};

impl ShardedFrame {
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
    /// [`AovSums::check_values`](splatd_estimator::AovSums::check_values)), added with the samples or not at all.
    ///
    /// # Panics
    /// If `aovs` is given for a frame without AOVs or has the wrong length.
    pub fn ingest_with_aovs(
        &self,
        batch: &Batch,
        aovs: Option<&[f32]>,
    ) -> Result<Ingested, IngestError> {
        let mut check = self.record_check();
        check.add(&batch.records);
        self.ingest_checked_with_aovs(batch, check, aovs)
    }

    /// A check of records for this frame, to fill as a batch is decoded
    /// ([`Batch::decode_visiting`]) and give to [`ShardedFrame::ingest_checked`].
    pub fn record_check(&self) -> RecordCheck {
        let (w, h) = (self.spec.request.width, self.spec.request.height);
        RecordCheck::new((w, h), self.spec.layout.component_limit_bits())
    }

    /// [`ShardedFrame::ingest`] of a batch whose records `check` has seen, all of them and
    /// only them, in order (as [`Batch::decode_visiting`] decoded them): the records are not
    /// read again for the check and the digest, and their samples are splatted without being
    /// checked again.
    ///
    /// # Panics
    /// If `check` saw another number of records than the batch has.
    pub fn ingest_checked(
        &self,
        batch: &Batch,
        check: RecordCheck,
    ) -> Result<Ingested, IngestError> {
        self.ingest_checked_with_aovs(batch, check, None)
    }

    fn ingest_checked_with_aovs(
        &self,
        batch: &Batch,
        check: RecordCheck,
        aovs: Option<&[f32]>,
    ) -> Result<Ingested, IngestError> {
        assert_eq!(
            check.count,
            batch.records.len(),
            "a check of the batch's records"
        );
        let result = self.ingest_inner(batch, check, aovs);
        if result.is_err() {
            self.count_rejected(batch.records.len() as u64);
        }
        result
    }

    fn ingest_inner(
        &self,
        batch: &Batch,
        check: RecordCheck,
        aovs: Option<&[f32]>,
    ) -> Result<Ingested, IngestError> {
        if batch.frame != self.id() {
            return Err(IngestError::WrongFrame {
                batch: batch.frame.clone(),
                url: self.id().to_owned(),
            });
        }
        let records = &batch.records;
        let (bounds, digest) = check.finish();
        let Some(bounds) = bounds else {
            return Err(self.first_refused(records));
        };
        let runs = self.runs_by_band(records);
        let parts = Parts::Records {
            batch,
            runs,
            bounds,
        };
        self.apply(batch.worker, batch.seq, digest, parts, aovs)
    }

    /// The records sorted into runs per band: consecutive records in one band are one run.
    fn runs_by_band(&self, records: &[Record]) -> Vec<Runs> {
        let mut runs: Vec<Runs> = vec![Runs::default(); self.bands.len()];
        let Some(first) = records.first() else {
            return runs;
        };
        let mut band = self.band_of_row(first.y);
        let mut rows = self.band_rows(band);
        let mut start = 0;
        for (i, r) in records.iter().enumerate() {
            // Two comparisons a record; the band is looked up only where it changes.
            if !rows.contains(&r.y) {
                runs[band].push(start..i as u32);
                (band, start) = (self.band_of_row(r.y), i as u32);
                rows = self.band_rows(band);
            }
        }
        runs[band].push(start..records.len() as u32);
        runs
    }

    /// Why a batch is refused: its first record outside the frame or with a value the layout
    /// does not accept. At least one record is one of those.
    fn first_refused(&self, records: &[Record]) -> IngestError {
        let (w, h) = (self.spec.request.width, self.spec.request.height);
        records
            .iter()
            .enumerate()
            .find_map(|(index, r)| {
                let error = if r.x >= w || r.y >= h {
                    SampleError::OutOfFrame {
                        x: r.x,
                        y: r.y,
                        width: w,
                        height: h,
                    }
                } else {
                    self.spec.layout.check_sample(r.rgb).err()?
                };
                Some(IngestError::Sample {
                    index,
                    record: *r,
                    error,
                })
            })
            .expect("a refused batch has a record to refuse")
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

    pub(super) fn ingest_pass_inner(
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
        if !estimator::samples_accepted(rgb, self.spec.layout.component_limit_bits()) {
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
        let digest = pass_digest(w, rgb);
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
        // Copies a band first if a cut holds it.
        let mut touched: Vec<(usize, &mut FrameState)> = guards
            .iter_mut()
            .enumerate()
            .filter_map(|(i, g)| g.as_mut().map(|band| (i, self.own(band))))
            .collect();
        splat_bands(&parts, &mut touched);
        drop(touched);
        drop(guards);
        if let (Some(sums), Some(values)) = (aov_sums.as_mut(), aovs) {
            self.own_aovs(sums).add_pass(values);
        }
        drop(aov_sums);
        self.counters.samples.fetch_add(n, Ordering::Relaxed);
        self.counters.batches.fetch_add(1, Ordering::Relaxed);
        self.next_version(parts.bounds(self));
        Ok(Ingested {
            accepted: n,
            duplicate: false,
        })
    }
}

/// Samples in one ingest from which its bands are splatted on several threads: below it a
/// thread costs more than it saves (a pass of 1920x1080 is 2 M samples, a batch 64 Ki).
const PARALLEL_SAMPLES: u64 = 1 << 19;

/// Splats each band of `touched` (index, state) with its samples of `parts`: on the calling
/// thread, or for a large ingest in groups of bands on as many threads as the machine has
/// cores, so that a pass is not splatted on one core while the others wait for its bands. The
/// bands are disjoint rows: the result is the same bit for bit whichever thread splats which
/// band.
fn splat_bands(parts: &Parts<'_>, touched: &mut [(usize, &mut FrameState)]) {
    let threads = if parts.len() < PARALLEL_SAMPLES {
        1
    } else {
        super::cores()
    };
    super::on_groups(touched, threads, |group| {
        for (i, band) in group.iter_mut() {
            parts.splat(*i, band);
        }
    });
}

/// Records checked as they come, a slice at a time: whether every one is inside the frame
/// with a value its layout accepts, the box of their pixels, and their content digest
/// ([`Batch::content_digest`]). Filled while a batch is decoded
/// ([`Batch::decode_visiting`]), it reads each record while the decoder's run of them is still in
/// the cache (a batch of 65536 records, 1.3 MB, does not fit a 1 MiB L2).
///
/// Records are `repr(C)` words (x, y and the bits of r, g, b), checked eight at a time as 40
/// words (five AVX2 vectors) in loops over those words that become vector instructions: each
/// word against its limit (x and y pass there; [`component_bits_accepted`] for the colour) and
/// each word's running least and greatest; x and y are then checked by their greatest. (A
/// check per record that returned its reason, then appended the record to its band's runs,
/// took 12.1 % of the server's CPU under `loadgen`'s record ingest; this check as a pass of its
/// own after decoding, 10.7 %, most of it reading the records back from L3.)
#[derive(Debug)]
pub struct RecordCheck {
    size: (u32, u32),
    lanes: Lanes,
    kernel: Kernel,
    count: usize,
    digest: RecordsDigest,
}

/// Records checked at once by [`RecordCheck`], and their words. (Four records, 20 words,
/// took 1.7 times as long per record: the compiler ran them in 128-bit halves.)
const CHECK_GROUP: usize = 8;
const CHECK_WORDS: usize = CHECK_GROUP * 5;

/// A [`RecordCheck`]'s running figures, per word of a group of records.
#[derive(Debug)]
struct Lanes {
    limits: [u32; CHECK_WORDS],
    /// All ones while every word passed its limit, else 0 (a mask, not a `bool`: bytes made
    /// the vector loop pack and unpack each comparison's lanes).
    good: [u32; CHECK_WORDS],
    least: [u32; CHECK_WORDS],
    most: [u32; CHECK_WORDS],
}

impl Lanes {
    /// Checks groups of [`CHECK_GROUP`] records' words, lane by lane (the loop indexes several
    /// arrays by lane, as the vector code it becomes does).
    #[inline(always)]
    #[allow(clippy::needless_range_loop)]
    fn groups(&mut self, groups: &[[u32; CHECK_WORDS]]) {
        for words in groups {
            for i in 0..CHECK_WORDS {
                let accepted = component_bits_accepted(words[i], self.limits[i]);
                self.good[i] &= 0u32.wrapping_sub(accepted.into());
                self.least[i] = self.least[i].min(words[i]);
                self.most[i] = self.most[i].max(words[i]);
            }
        }
    }

    /// [`Lanes::groups`] as compiled for this CPU: with AVX2 where it has it, under the AVX-512
    /// kernel too (the baseline's SSE2 has no unsigned comparison or minimum of 32-bit lanes,
    /// and emulating them made the check 7 % of the server's CPU under `loadgen`'s record
    /// ingest).
    fn groups_with(&mut self, kernel: Kernel, groups: &[[u32; CHECK_WORDS]]) {
        match kernel {
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 | Kernel::Avx512 => {
                assert!(kernel.available(), "AVX2 kernel on a CPU without AVX2");
                // SAFETY: the CPU has AVX2, checked just above (a cached feature test).
                unsafe { self.groups_avx2(groups) }
            }
            _ => self.groups(groups),
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn groups_avx2(&mut self, groups: &[[u32; CHECK_WORDS]]) {
        self.groups(groups)
    }
}

impl RecordCheck {
    /// A check for a `w` x `h` frame whose layout accepts components up to the `f32` bits
    /// `limit` ([`CascadeLayout::component_limit_bits`]), on the fastest kernel this CPU runs.
    ///
    /// [`CascadeLayout::component_limit_bits`]: splatd_estimator::CascadeLayout::component_limit_bits
    fn new(size: (u32, u32), limit: u32) -> RecordCheck {
        RecordCheck::with_kernel(size, limit, Kernel::detect())
    }

    fn with_kernel(size: (u32, u32), limit: u32, kernel: Kernel) -> RecordCheck {
        RecordCheck {
            size,
            lanes: Lanes {
                limits: std::array::from_fn(|i| if i % 5 < 2 { u32::MAX } else { limit }),
                good: [u32::MAX; CHECK_WORDS],
                least: [u32::MAX; CHECK_WORDS],
                most: [0; CHECK_WORDS],
            },
            kernel,
            count: 0,
            digest: RecordsDigest::new(),
        }
    }

    /// Checks `records`, which come after every record checked before.
    pub fn add(&mut self, records: &[Record]) {
        let (groups, rest) = records.split_at(records.len() - records.len() % CHECK_GROUP);
        self.lanes
            .groups_with(self.kernel, bytemuck::cast_slice(groups));
        if let Some(&first) = rest.first() {
            // The last records, and the first of them again in the lanes left over (which
            // changes neither the verdict nor the box).
            let mut group = [first; CHECK_GROUP];
            group[..rest.len()].copy_from_slice(rest);
            let words: [u32; CHECK_WORDS] = bytemuck::cast(group);
            self.lanes.groups(&[words]);
        }
        self.digest.update(records);
        self.count += records.len();
    }

    /// The box of the records' pixels (empty for no records), or `None` if a record is outside
    /// the frame or has a value the layout refuses; and their content digest.
    fn finish(self) -> (Option<Rect>, u64) {
        let digest = self.digest.finish();
        if self.count == 0 {
            return (Some(Rect::new(0, 0, 0, 0)), digest);
        }
        // Word `word` of each record of a group: x is word 0, y word 1.
        let l = &self.lanes;
        let lanes = |word: usize| (word..CHECK_WORDS).step_by(5);
        let least_of = |word| lanes(word).map(|i| l.least[i]).fold(u32::MAX, u32::min);
        let most_of = |word| lanes(word).map(|i| l.most[i]).fold(0, u32::max);
        let (w, h) = self.size;
        let (x1, y1) = (most_of(0), most_of(1));
        let good = l.good.iter().all(|&g| g == u32::MAX) && x1 < w && y1 < h;
        let bounds = good.then(|| Rect::new(least_of(0), least_of(1), x1 + 1, y1 + 1));
        (bounds, digest)
    }
}

/// The records of a batch that fall in one band: runs of consecutive records, in order (a
/// worker's scan-line runs make a few long ones). Indices, not copies: copying every record
/// into its band's bucket, in memory that grew with each batch, was a sixth of the server's
/// CPU time while ingesting batches (measured under `loadgen`).
#[derive(Debug, Clone, Default)]
struct Runs(Vec<std::ops::Range<u32>>);

impl Runs {
    /// Adds records `run` (not empty), which come after every record added before and not
    /// right after them: another band's run lies between.
    fn push(&mut self, run: std::ops::Range<u32>) {
        debug_assert!(!run.is_empty(), "a run holds records");
        debug_assert!(
            self.0.last().is_none_or(|last| last.end < run.start),
            "runs of one band are apart"
        );
        self.0.push(run);
    }

    fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Records in all.
    fn len(&self) -> u64 {
        self.0.iter().map(|run| (run.end - run.start) as u64).sum()
    }

    /// The samples of these records of `batch`, in order.
    fn samples<'b>(&'b self, batch: &'b Batch) -> impl Iterator<Item = (u32, u32, [f32; 3])> + 'b {
        self.0.iter().flat_map(move |run| {
            batch.records[run.start as usize..run.end as usize]
                .iter()
                .map(|r| (r.x, r.y, r.rgb))
        })
    }
}

/// The checked samples of one ingest.
enum Parts<'a> {
    /// A batch's records, sorted into runs per band.
    Records {
        batch: &'a Batch,
        runs: Vec<Runs>,
        /// The bounding box of the records' pixels (empty for no records).
        bounds: Rect,
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

    /// The pixels the samples fall in (a bounding box: cheap to keep, and for a worker's tile
    /// or a few rows it is the tile or the rows).
    fn bounds(&self, frame: &ShardedFrame) -> Rect {
        match self {
            Parts::Records { bounds, .. } => *bounds,
            Parts::Pass { .. } => frame.everywhere(),
        }
    }

    /// Whether band `i` receives samples.
    fn touches(&self, i: usize) -> bool {
        match self {
            Parts::Records { runs, .. } => !runs[i].is_empty(),
            Parts::Pass { .. } => true,
        }
    }

    /// The refusal for the first sample band `i` (`band`) cannot take, if any.
    fn first_full(&self, i: usize, band: &FrameState) -> Option<IngestError> {
        match self {
            Parts::Records { batch, runs, .. } => {
                first_full(band, runs[i].len(), || runs[i].samples(batch)).map(|(x, y)| {
                    let spp = band.spp(x, y);
                    pixel_full(batch, x, y, spp)
                })
            }
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
            Parts::Records { batch, runs, .. } => {
                band.splat_valid_records_from(runs[i].samples(batch))
            }
            Parts::Pass { rgb } => {
                let w = band.width() as usize;
                let mut report = estimator::SplatReport::default();
                for y in band.rows() {
                    let row = &rgb[y as usize * w..(y as usize + 1) * w];
                    let r = band.splat_valid_row(0, y, row);
                    report.accepted += r.accepted;
                    report.pixel_full += r.rejected();
                }
                report
            }
        };
        debug_assert_eq!(report.rejected(), 0, "samples were checked before");
    }
}

/// The first pixel of the `n` samples (of one band, as many times as asked) that cannot take
/// all of its samples in `band`.
fn first_full<I>(band: &FrameState, n: u64, samples: impl Fn() -> I) -> Option<(u32, u32)>
where
    I: Iterator<Item = (u32, u32, [f32; 3])>,
{
    if band.total_samples().saturating_add(n) <= MAX_PIXEL_SAMPLES {
        return None;
    }
    // Near the limit: count the samples of the pixels that could not take the whole batch.
    let mut near: std::collections::HashMap<(u32, u32), u64> = Default::default();
    for (x, y, _) in samples() {
        if !band.has_room(x, y, n) {
            *near.entry((x, y)).or_default() += 1;
        }
    }
    samples()
        .map(|(x, y, _)| (x, y))
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

// Every kernel this CPU runs, said loudly, as the estimator's tests choose them.
#[cfg(test)]
#[path = "../../../estimator/tests/common/kernels.rs"]
mod kernels;

#[cfg(test)]
mod tests {
    use super::kernels::kernels;
    use super::*;
    use crate::frame::FrameSpec;
    use splatd_proto::api::CreateFrame;
    use splatd_scenes::synth::SplitMix64;

    /// `n` records of a `w` x `h` frame: about one coordinate in 13 outside it, and one
    /// component in 8 an edge value (zeros, the largest `max`, beyond it, negative, NaN,
    /// infinite), the rest in `[0, 1)`.
    fn records(rng: &mut SplitMix64, n: usize, (w, h): (u32, u32), max: f32) -> Vec<Record> {
        let values = [0.0, -0.0, 0.5, max, f32::MAX, -1.0, f32::NAN, f32::INFINITY];
        let pick = |rng: &mut SplitMix64| {
            if rng.next_u64().is_multiple_of(8) {
                values[(rng.next_u64() % values.len() as u64) as usize]
            } else {
                rng.next_f64() as f32
            }
        };
        (0..n)
            .map(|_| {
                let coordinate = |rng: &mut SplitMix64, size: u32| match rng.next_u64() % 40 {
                    0 => size,
                    1 => u32::MAX,
                    2 => 1 << 31,
                    _ => (rng.next_u64() % u64::from(size)) as u32,
                };
                let (x, y) = (coordinate(rng, w), coordinate(rng, h));
                Record::new(x, y, [pick(rng), pick(rng), pick(rng)])
            })
            .collect()
    }

    #[test]
    fn records_are_checked_boxed_and_hashed_as_one_by_one() {
        let frame = ShardedFrame::new(FrameSpec::new(CreateFrame::new("f", 13, 70)).unwrap());
        let layout = &frame.spec.layout;
        let limit = layout.component_limit_bits();
        assert_eq!(frame.record_check().kernel, Kernel::detect());
        let mut rng = SplitMix64::new(3);
        for n in (0..=9).chain([64, 65, 1000]) {
            for _ in 0..200 {
                let mut records = records(&mut rng, n, (13, 70), layout.max_component() as f32);
                if rng.next_u64().is_multiple_of(2) {
                    // Half the batches good, so that boxes are compared too.
                    records.retain(|r| r.x < 13 && r.y < 70 && layout.check_sample(r.rgb).is_ok());
                }
                let good = records
                    .iter()
                    .all(|r| r.x < 13 && r.y < 70 && layout.check_sample(r.rgb).is_ok());
                let expected = good.then(|| {
                    let fold = |f: fn(u32, u32) -> u32, at: fn(&Record) -> u32, from| {
                        records.iter().map(at).fold(from, f)
                    };
                    if records.is_empty() {
                        Rect::new(0, 0, 0, 0)
                    } else {
                        Rect::new(
                            fold(u32::min, |r| r.x, u32::MAX),
                            fold(u32::min, |r| r.y, u32::MAX),
                            fold(u32::max, |r| r.x, 0) + 1,
                            fold(u32::max, |r| r.y, 0) + 1,
                        )
                    }
                });
                // On each kernel this CPU runs, in one slice, and a few records at a time as a
                // decoder hands them over.
                let digest = splatd_proto::records_digest_of(records.iter().copied());
                for kernel in kernels() {
                    let check = || RecordCheck::with_kernel((13, 70), limit, kernel);
                    let mut whole = check();
                    whole.add(&records);
                    assert_eq!(whole.finish(), (expected, digest), "{kernel:?} {records:?}");
                    let mut pieces = check();
                    for piece in records.chunks(7) {
                        pieces.add(piece);
                    }
                    assert_eq!(
                        pieces.finish(),
                        (expected, digest),
                        "{kernel:?} {records:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn runs_cut_where_the_band_changes() {
        let frame = ShardedFrame::new(FrameSpec::new(CreateFrame::new("f", 13, 70)).unwrap());
        assert!(frame.bands.len() > 4, "several bands");
        // Each row's band by its rows, and the runs one record at a time, as a reference.
        let band = |y: u32| {
            (0..frame.bands.len())
                .find(|&b| frame.band_rows(b).contains(&y))
                .unwrap()
        };
        let mut rng = SplitMix64::new(5);
        for n in [0, 1, 2, 3, 50, 500] {
            for scan in [false, true] {
                let rows: Vec<u32> = (0..n as u32)
                    .map(|i| {
                        if scan {
                            (i / 7) % 70
                        } else {
                            (rng.next_u64() % 70) as u32
                        }
                    })
                    .collect();
                let records: Vec<Record> =
                    rows.iter().map(|&y| Record::new(0, y, [0.5; 3])).collect();
                let mut expected = vec![Vec::<std::ops::Range<u32>>::new(); frame.bands.len()];
                for (i, &y) in rows.iter().enumerate() {
                    let list = &mut expected[band(y)];
                    match list.last_mut() {
                        Some(run) if run.end == i as u32 => run.end += 1,
                        _ => list.push(i as u32..i as u32 + 1),
                    }
                }
                let runs: Vec<_> = frame
                    .runs_by_band(&records)
                    .into_iter()
                    .map(|r| r.0)
                    .collect();
                assert_eq!(runs, expected, "{rows:?}");
            }
        }
    }
}
