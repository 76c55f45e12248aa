//! States into and out of a frame: imports of other nodes' states and pushed deltas, and the
//! frame's own state in the wire format.

use std::ops::Range;
use std::sync::atomic::Ordering;
use std::sync::{Arc, MutexGuard};

use splatd_proto::api::AovSpec;
use splatd_proto::{Applied, Origin, StateWrite};

use splatd_estimator::{
    cell_len, cell_spp, check_pixels, AovCellsError, AovSums, FrameState, MergeError,
    MAX_PIXEL_SAMPLES,
};

use splatd_formats::names::describe_aovs;
use splatd_formats::state::{Importable, PieceError};

use super::{lock, FrameCut, ImportRefused, ShardedFrame};

impl ShardedFrame {
    pub(super) fn check_fits(&self, state: &FrameState) -> Result<(), MergeError> {
        // Every band has the frame's size and layout.
        lock(&self.bands[0]).check_same_frame(state)
    }

    /// [`ShardedFrame::check_fits`] for any state being imported.
    pub(super) fn check_fits_import(&self, state: &impl Importable) -> Result<(), MergeError> {
        let (width, height, layout) = state.geometry();
        lock(&self.bands[0]).check_same_geometry(width, height, layout)
    }

    /// Refuses a state declaring AOVs (`specs`, not empty) other than the frame's
    /// ([`ImportRefused::Aovs`]).
    pub(super) fn check_state_aovs(&self, specs: &[AovSpec]) -> Result<(), ImportRefused> {
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
    /// frame; returns the samples added. A delta carrying an origin that was applied before is
    /// recognised and not applied again (returns `Ok(None)`); a state holding a batch the frame
    /// has applied is refused ([`ImportRefused::Overlap`]), since adding it would count that
    /// batch twice.
    ///
    /// All or nothing: nothing of a refused state is applied, and the frame is left as it was,
    /// bit for bit. The frame's id, size, layout and AOVs, the origin and the batches are
    /// checked first. The cells of a state not checked already ([`Importable::checked`]) are
    /// checked as they are added, a piece at a time, each piece before it is added, and so is
    /// the room in every pixel: a piece that is refused leaves the additions before it to be
    /// taken back, exactly (cells are integers). So the state is read once, not once to check
    /// it and again to add it; the refusal names the first bad piece's first bad pixel, in
    /// pixel order. The origin and the batches are recorded once all of it is added. The state
    /// may hold any rows of the frame (a band of another node's frame, say): each band adds the
    /// rows it shares with it.
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
    ) -> Result<Option<u64>, ImportRefused> {
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
        // that the room checks and the additions see the same cells; then the applied set, so
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
                return Ok(None);
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
        if let Some((mine, theirs)) = &aov_sums {
            mine.check_room_for(theirs)
                .map_err(|e: AovCellsError| ImportRefused::Aovs {
                    frame: self.id().to_owned(),
                    reason: e.to_string(),
                })?;
        }
        // Copies of the bands cuts hold, made before anything changes.
        let mut bands: Vec<&mut FrameState> = bands.iter_mut().map(|b| self.own(b)).collect();
        let added = self.add_checked(state, &mut bands)?;
        if let Some(o) = origin {
            seen.insert_delta(&o.node, o.seq);
        }
        seen.insert_applied(batches);
        drop(seen);
        if let Some((mine, theirs)) = aov_sums.as_mut() {
            self.own_aovs(mine)
                .merge_overlap(theirs)
                .expect("AOV sums were checked for room above");
        }
        drop(aov_sums);
        drop(bands);
        self.counters.samples.fetch_add(added, Ordering::Relaxed);
        self.counters.imports.fetch_add(1, Ordering::Relaxed);
        self.next_version(self.everywhere());
        Ok(Some(added))
    }

    /// Adds `state` to `bands` (all the frame's bands, locked; the state fits their size and
    /// layout), checking each piece before it is added: its cells (unless the state is
    /// [`Importable::checked`]) and the room in each pixel it adds to. Returns the samples
    /// added; if a piece is refused, everything added is taken back first, so the bands are as
    /// they were, bit for bit.
    ///
    /// A large state is added by a few threads, each to its own bands from the pixels they
    /// hold (the locks are all held already, so they hold them for less time); a refusal names
    /// the first one in pixel order.
    fn add_checked(
        &self,
        state: &impl Importable,
        bands: &mut [&mut FrameState],
    ) -> Result<u64, ImportRefused> {
        let y0 = state.first_row();
        let (width, _, layout) = state.geometry();
        let cascades = layout.cascades();
        let stride = cell_len(cascades);
        let checked = state.checked();
        // The state's pixels that `group` (consecutive bands) holds.
        let within = |group: &[&mut FrameState]| {
            let (start, end) = (group[0].rows().start, group[group.len() - 1].rows().end);
            start.saturating_sub(y0) as u64 * width as u64
                ..end.saturating_sub(y0) as u64 * width as u64
        };
        let add = |group: &mut [&mut FrameState]| -> Result<u64, PieceError> {
            let within = within(group);
            let mut added = 0;
            // The pieces before this pixel are added.
            let mut done = within.start;
            let visit = state.pieces_in(within.clone(), &mut |first, cells| {
                let samples = if checked {
                    cells.chunks_exact(stride).map(cell_spp).sum()
                } else {
                    check_pixels(width, y0, cascades, first, cells)?
                };
                // A pixel holds at most its band's samples, and a piece's pixel at most the
                // piece's: the band's cells need reading only near the limit.
                for band in group.iter() {
                    if band.total_samples().saturating_add(samples) > MAX_PIXEL_SAMPLES {
                        band.check_room_for_pixels(y0, first, cells)?;
                    }
                }
                for band in group.iter_mut() {
                    added += band.add_pixels(y0, first, cells);
                }
                done = first + (cells.len() / stride) as u64;
                Ok(())
            });
            match visit {
                Ok(()) => Ok(added),
                Err(refused) => {
                    take_back(state, group, within.start..done);
                    Err(refused)
                }
            }
        };
        let threads = splatd_formats::state::shares(state.pixels(), super::cores()).len();
        let added = super::on_groups(bands, threads, |group| (group[0].rows().start, add(group)));
        let Some(refused) = added.iter().find_map(|(_, a)| a.clone().err()) else {
            return Ok(added.into_iter().map(|(_, a)| a.unwrap_or(0)).sum());
        };
        // The groups that added all their share take it back too (the same groups: the same
        // bands cut into as many).
        super::on_groups(bands, threads, |group| {
            let start = group[0].rows().start;
            if added.iter().any(|(s, a)| *s == start && a.is_ok()) {
                let within = within(group);
                take_back(state, group, within);
            }
        });
        Err(match refused {
            PieceError::Invalid(e) => ImportRefused::Invalid(e),
            PieceError::Merge(error) => ImportRefused::Mismatch {
                frame: self.id().to_owned(),
                error,
            },
        })
    }

    /// Writes the frame's state with the batches it holds, in the state wire format, to `out`
    /// (`GET .../state`), encoded from `cut` (a [`ShardedFrame::cut`] of this frame): writers
    /// go on meanwhile, and no copy of the whole encoding is made. `out` is handed the long
    /// stretches of cells by the number of their band in `cut.bands`
    /// ([`StateWrite::write_cells`]), so it may send them from the cut itself.
    pub fn write_state(&self, cut: &FrameCut, out: &mut impl StateWrite) -> std::io::Result<()> {
        let bands: Vec<&FrameState> = cut.bands.iter().map(|b| &**b).collect();
        let aovs = cut
            .aovs
            .as_deref()
            .map(|sums| (self.spec.request.aovs.as_slice(), sums));
        splatd_formats::state::write_bands(&bands, aovs, self.id(), None, cut.seen.applied(), out)?;
        out.flush()
    }
}

/// Takes back the addition of `state`'s pixels numbered in `within` to `group` (all of them
/// added, piece by piece, by [`ShardedFrame::import`]): the bands are again as they were.
fn take_back(state: &impl Importable, group: &mut [&mut FrameState], within: Range<u64>) {
    let y0 = state.first_row();
    state
        .pieces_in(within, &mut |first, cells| {
            for band in group.iter_mut() {
                band.sub_pixels(y0, first, cells);
            }
            Ok(())
        })
        .expect("pieces that were added are handed out again as they were");
}
