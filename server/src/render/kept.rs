//! The latest resolve of each recently rendered frame, kept so that the next render of the
//! frame patches it where the frame changed instead of resolving it all again.
//!
//! A dashboard, the live page and a farm's final fetches all render the same frame at its
//! default parameters over and over while workers add samples a tile at a time. Each of those
//! renders used to resolve the whole frame; with the resolve kept, a render after a batch that
//! touched 1 % of the frame costs about 2 % of a full one (`bench speed`), bit for bit the same
//! ([`splatd_estimator::resolve_region_into`], which widens the changed pixels by the margin
//! the resolve reads). The frame says which pixels each version changed
//! ([`ShardedFrame::changes_between`]).
//!
//! Only renders at the frame's own resolve parameters are kept (queries that vary `kappa`
//! resolve afresh), for at most [`MAX_KEPT`] frames, the most recently rendered: a kept resolve
//! holds the resolved layers of the frame (44 bytes per pixel, 91 MB at 1080p) beyond the
//! working budget, so their number is small and fixed.
//!
//! The buffers of a resolve no longer kept (its frame deleted, or pushed out by a fifth) are
//! held as one *spare*, which the next frame resolved whole for the first time resolves into.
//! A farm fetches each frame's final, deletes the frame and starts the next one of the same
//! size: a first resolve into fresh buffers faults in its layers' new pages (91 MB at 1080p;
//! some 500 MB when the spread stage also kept its support planes and lists), about a third of
//! an `image.exr`'s time on a virtual machine whose host hands out freed memory lazily
//! (`passbench`, measured with the planes and lists). So at
//! most `MAX_KEPT + 1` resolves are held, and the spare goes as soon as a frame takes it.
//!
//! With a kept resolve can go the frame's need map at the default tile size, made from the same
//! cut when figures are asked for, whose figures are filed in the frame's history. It is
//! patched like the resolve: when figures are asked for, only the map's tiles that the frame's
//! changes since the map reach are made again (`reached_by`, `NeedMap::update`), so figures
//! after a batch in one worker's tile cost about what the patch did, not a read of the whole
//! state. The renders of a changing frame that start together when its pace ends (an
//! image, the live page's previews, a dashboard's figures) share one resolve instead of each
//! patching the changes the one before it left: while a request for figures waits, whichever
//! of them resolves the frame makes the need map from the same cut
//! ([`KeptResolves::want_figures`]). Figures asked for after an image of the same version cost
//! a need map, not a resolve.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};

use splatd_estimator::{
    reached_by, resolve_bands_into, resolve_region_into, NeedMap, Rect, ResolveParams, Resolved,
    DEFAULT_NEED_TILE,
};

use crate::frame::{FrameCut, ShardedFrame};

/// Most frames whose latest resolve is kept.
pub const MAX_KEPT: usize = 4;
/// Most rectangles a patch is cut into (the estimator merges the frame's changes down to them).
const MAX_PATCHES: usize = 16;

/// One frame's kept resolve: of which version, the layers and the need map made with them.
#[derive(Debug, Default)]
struct Kept {
    version: u64,
    resolved: Option<Resolved>,
    /// The need map at the default tile, of the frame at `need_version` (renders of images
    /// bring it up to date only while figures are wanted, [`KeptResolves::want_figures`];
    /// otherwise the next figures render makes again the tiles that the frame's changes since
    /// reach).
    need: Option<NeedMap>,
    need_version: u64,
}

type Slot = Arc<Mutex<Kept>>;

/// The kept resolves, newest last.
#[derive(Debug, Default)]
pub struct KeptResolves {
    slots: Mutex<VecDeque<(u64, Slot)>>,
    /// Renders that patched a kept resolve.
    patched: std::sync::atomic::AtomicU64,
    /// Renders that resolved the whole frame at its own parameters.
    whole: std::sync::atomic::AtomicU64,
    /// Need-map tiles made (every tile of a map built whole, the stale ones of a map brought
    /// up to date).
    need_tiles: std::sync::atomic::AtomicU64,
    /// The buffers of the last resolve that stopped being kept, for the next first resolve.
    spare: Mutex<Option<Resolved>>,
    /// Requests for figures waiting for a render, by frame serial ([`FiguresWanted`]).
    figures_wanted: Mutex<HashMap<u64, usize>>,
}

/// A request for a frame's figures waiting for its render, from
/// [`KeptResolves::want_figures`] until dropped.
#[derive(Debug)]
pub struct FiguresWanted {
    kept: Arc<KeptResolves>,
    serial: u64,
}

impl Drop for FiguresWanted {
    fn drop(&mut self) {
        let mut wanted = self.kept.wanted();
        if let Some(n) = wanted.get_mut(&self.serial) {
            *n -= 1;
            if *n == 0 {
                wanted.remove(&self.serial);
            }
        }
    }
}

/// How a render got its resolve.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Made {
    /// The kept resolve was of this very version.
    Kept,
    /// The kept resolve was patched where the frame changed.
    Patched,
    /// The whole frame was resolved.
    Whole,
}

impl Made {
    /// Counts a resolve made so in the server's metrics (`splatd_resolves_total{made}`).
    fn count(self) {
        let made = match self {
            Made::Kept => return,
            Made::Patched => "patched",
            Made::Whole => "whole",
        };
        metrics::counter!(crate::meters::RESOLVES, "made" => made).increment(1);
    }
}

impl KeptResolves {
    /// How many renders patched a kept resolve so far.
    pub fn patched(&self) -> u64 {
        self.patched.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// How many renders resolved a whole frame at its own parameters so far.
    pub fn whole(&self) -> u64 {
        self.whole.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// How many need-map tiles renders made so far (all of a map built whole, the stale ones
    /// of a map brought up to date).
    pub fn need_tiles(&self) -> u64 {
        self.need_tiles.load(std::sync::atomic::Ordering::Relaxed)
    }

    fn wanted(&self) -> std::sync::MutexGuard<'_, HashMap<u64, usize>> {
        self.figures_wanted
            .lock()
            .unwrap_or_else(|e| e.into_inner())
    }

    /// Marks `frame`'s figures as wanted until the guard is dropped: a request for them holds
    /// it while it waits for its render. Meanwhile, a render of another kind that brings the
    /// kept resolve up to date brings the need map with it, from the same cut, so the figures
    /// render that starts beside it (at the frame's pace) finds both made and resolves
    /// nothing. Without it, an image or preview that took the kept resolve first left the
    /// figures render to resolve the frame again from a cut of its own, a few batches newer.
    pub fn want_figures(self: &Arc<Self>, frame: &ShardedFrame) -> FiguresWanted {
        *self.wanted().entry(frame.serial()).or_default() += 1;
        FiguresWanted {
            kept: self.clone(),
            serial: frame.serial(),
        }
    }

    fn slot(&self, frame: &ShardedFrame) -> Slot {
        let serial = frame.serial();
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        let slot = match slots.iter().position(|(s, _)| *s == serial) {
            Some(i) => slots.remove(i).expect("found").1,
            None => Slot::default(),
        };
        slots.push_back((serial, slot.clone()));
        while slots.len() > MAX_KEPT {
            let (_, old) = slots.pop_front().expect("more than MAX_KEPT");
            self.keep_spare(&old);
        }
        slot
    }

    /// Forgets the kept resolve of `frame` (when it is deleted); its buffers become the spare.
    pub fn forget(&self, frame: &ShardedFrame) {
        let serial = frame.serial();
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(i) = slots.iter().position(|(s, _)| *s == serial) {
            let (_, old) = slots.remove(i).expect("found");
            self.keep_spare(&old);
        }
    }

    /// Takes the buffers of a slot no longer kept as the spare, unless a render is using the
    /// slot right now (then they go with it).
    fn keep_spare(&self, old: &Slot) {
        let Ok(mut kept) = old.try_lock() else {
            return;
        };
        if let Some(resolved) = kept.resolved.take() {
            kept.need = None;
            *self.spare.lock().unwrap_or_else(|e| e.into_inner()) = Some(resolved);
        }
    }

    /// Whether a spare is held (for tests).
    #[cfg(test)]
    fn has_spare(&self) -> bool {
        self.spare
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .is_some()
    }

    /// Calls `use_it` with a cut of `frame` taken now and its resolve at `params` on `threads`:
    /// the kept one, patched or made whole as needed, when `params` are the frame's own;
    /// otherwise a resolve of its own. Renders of one frame take turns here, and each takes its
    /// cut in its turn: a render waiting behind another holds no cut (while a cut is held,
    /// writers copy each band they change), and its cut is of the version its turn came at, so
    /// the patch covers only what changed since the render before.
    ///
    /// `use_it` gets the cut to drop as soon as it is done with it: an encoding that no longer
    /// needs the state should not hold it.
    pub fn with_resolved<T>(
        &self,
        frame: &ShardedFrame,
        params: &ResolveParams,
        threads: usize,
        use_it: impl FnOnce(&Resolved, FrameCut, Made) -> T,
    ) -> T {
        if *params != frame.spec().resolve {
            let cut = frame.cut();
            let resolved = cut.resolve(params, threads);
            Made::Whole.count();
            return use_it(&resolved, cut, Made::Whole);
        }
        self.bring_up_to_date(frame, threads, false, |kept, cut, made| {
            use_it(kept.resolved.as_ref().expect("kept above"), cut, made)
        })
    }

    /// Brings `frame`'s kept resolve (at the frame's own parameters) up to a cut taken now, and
    /// with `need` its need map too, whose figures it files in the frame's history; calls
    /// `use_it` with them and the cut while the slot is still locked.
    fn bring_up_to_date<T>(
        &self,
        frame: &ShardedFrame,
        threads: usize,
        need: bool,
        use_it: impl FnOnce(&Kept, FrameCut, Made) -> T,
    ) -> T {
        let params = &frame.spec().resolve;
        let slot = self.slot(frame);
        let mut guard = slot.lock().unwrap_or_else(|e| e.into_inner());
        let kept = &mut *guard;
        let cut = frame.cut();
        let need = need || self.wanted().contains_key(&frame.serial());
        let bands = cut.band_refs();
        let made = match kept.resolved.as_mut() {
            Some(_) if kept.version == cut.version => Made::Kept,
            Some(resolved) => {
                // Cuts are taken in turn under this slot's lock, so each is at least as new as
                // the one the kept resolve came from.
                debug_assert!(
                    kept.version < cut.version,
                    "a cut older than the kept resolve"
                );
                match frame.changes_between(kept.version, cut.version) {
                    Some(changed) => {
                        let changed = Rect::merge(&changed, MAX_PATCHES);
                        resolve_region_into(&bands, params, threads, &changed, resolved)
                            .expect("a frame's bands tile it");
                        Made::Patched
                    }
                    None => {
                        resolve_bands_into(&bands, params, threads, resolved)
                            .expect("a frame's bands tile it");
                        Made::Whole
                    }
                }
            }
            None => {
                let spare = self.spare.lock().unwrap_or_else(|e| e.into_inner()).take();
                let mut resolved = spare.unwrap_or_default();
                resolve_bands_into(&bands, params, threads, &mut resolved)
                    .expect("a frame's bands tile it");
                kept.resolved = Some(resolved);
                Made::Whole
            }
        };
        let counter = match made {
            Made::Kept => None,
            Made::Patched => Some(&self.patched),
            Made::Whole => Some(&self.whole),
        };
        if let Some(counter) = counter {
            counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        made.count();
        if need && (kept.need.is_none() || kept.need_version != cut.version) {
            let resolved = kept.resolved.as_ref().expect("kept above");
            // The map's tiles that the changes since it was made reach are made again (however
            // the resolve was brought up to date, the outputs elsewhere are the same bits); all
            // of them when there is no map or those changes are no longer known.
            let stale = kept.need.take().and_then(|map| {
                let changed = frame.changes_between(kept.need_version, cut.version)?;
                Some((map, changed))
            });
            let (map, tiles) = match stale {
                Some((mut map, changed)) => {
                    let (w, h) = (resolved.width, resolved.height);
                    let areas = reached_by(params, &Rect::merge(&changed, MAX_PATCHES), w, h);
                    let tiles = map
                        .update(&bands, resolved, params, &areas, threads)
                        .expect("a frame's bands tile it");
                    (map, tiles)
                }
                None => {
                    let map =
                        NeedMap::build_on(&bands, resolved, params, DEFAULT_NEED_TILE, threads)
                            .expect("a frame's bands tile it");
                    let tiles = map.tiles.len();
                    (map, tiles)
                }
            };
            self.need_tiles
                .fetch_add(tiles as u64, std::sync::atomic::Ordering::Relaxed);
            let mut history = frame.history();
            let seconds = history.seconds();
            history.record(cut.version, seconds, map.convergence(params));
            kept.need = Some(map);
            kept.need_version = cut.version;
        }
        kept.version = cut.version;
        drop(bands);
        use_it(kept, cut, made)
    }

    /// The need map at the default tile size of `frame` at its own parameters, and the version
    /// it is of: the kept one if it is of version `wanted` or later (a render that started with
    /// this one just made it), else one made from a cut taken now and the kept resolve brought
    /// up to it (a frame unchanged since an image costs the need map only).
    pub fn with_need_since<T>(
        &self,
        frame: &ShardedFrame,
        threads: usize,
        wanted: u64,
        use_it: impl FnOnce(&NeedMap, u64) -> T,
    ) -> T {
        {
            let slot = self.slot(frame);
            let guard = slot.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(need) = guard.need.as_ref().filter(|_| guard.need_version >= wanted) {
                return use_it(need, guard.need_version);
            }
        }
        self.bring_up_to_date(frame, threads, true, |kept, cut, _| {
            drop(cut);
            use_it(kept.need.as_ref().expect("made above"), kept.need_version)
        })
    }

    /// [`with_resolved`](Self::with_resolved) for a render that needs the resolved layers only,
    /// not the state: the kept resolve as it is if it is of version `wanted` or later (a render
    /// of another kind, say the other layer of the live page's preview, just made it), else one
    /// made as `with_resolved` makes it, its cut dropped before `use_it` runs.
    pub fn with_resolved_since<T>(
        &self,
        frame: &ShardedFrame,
        params: &ResolveParams,
        threads: usize,
        wanted: u64,
        use_it: impl FnOnce(&Resolved, Made) -> T,
    ) -> T {
        if *params == frame.spec().resolve {
            let slot = self.slot(frame);
            let guard = slot.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(resolved) = guard.resolved.as_ref().filter(|_| guard.version >= wanted) {
                return use_it(resolved, Made::Kept);
            }
        }
        self.with_resolved(frame, params, threads, |resolved, cut, made| {
            drop(cut);
            use_it(resolved, made)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::FrameSpec;
    use splatd_proto::api::CreateFrame;
    use splatd_proto::{Batch, Record};
    use splatd_scenes::synth::FireflyScene;

    /// A frame "f" of `w` x `h` pixels with the default settings.
    fn new_frame(w: u32, h: u32) -> ShardedFrame {
        ShardedFrame::new(FrameSpec::new(CreateFrame::new("f", w, h)).unwrap())
    }

    /// Ingests the scene's pass `seq` whole as batch `seq`; the frame's version after it.
    fn ingest_pass(frame: &ShardedFrame, scene: &FireflyScene, seq: u64) -> u64 {
        let records = scene.pass(seq).map(|(x, y, rgb)| Record::new(x, y, rgb));
        let batch = Batch::new("f", 1, seq, records.collect()).unwrap();
        frame.ingest(&batch).unwrap();
        frame.version()
    }

    /// Ingests batch `seq`: a worker's tile, the square of `side` pixels at `(x0, y0)` of the
    /// scene's pass `seq + 10` (fireflies included).
    fn ingest_tile(
        frame: &ShardedFrame,
        scene: &FireflyScene,
        seq: u64,
        (x0, y0): (u32, u32),
        side: u32,
    ) {
        let records: Vec<Record> = scene
            .pass(seq + 10)
            .filter(|&(x, y, _)| (x0..x0 + side).contains(&x) && (y0..y0 + side).contains(&y))
            .map(|(x, y, rgb)| Record::new(x, y, rgb))
            .collect();
        frame
            .ingest(&Batch::new("f", 1, seq, records).unwrap())
            .unwrap();
    }

    /// Renders after batches in one tile patch the kept resolve, and every patched resolve is
    /// bit for bit a fresh resolve of the same cut (the oracle); a pass, which changes every
    /// pixel, and other parameters are resolved whole.
    #[test]
    fn a_patched_resolve_is_the_whole_resolve() {
        let (w, h) = (96, 80);
        let frame = new_frame(w, h);
        let params = frame.spec().resolve;
        let scene = FireflyScene::new(w, h, 5);
        let all: Vec<Record> = (0..4)
            .flat_map(|p| scene.pass(p))
            .map(|(x, y, rgb)| Record::new(x, y, rgb))
            .collect();
        frame.ingest(&Batch::new("f", 1, 0, all).unwrap()).unwrap();
        let kept = KeptResolves::default();
        let bits = |r: &Resolved| -> Vec<u32> {
            let rgb = r.reweighted.iter().chain(&r.mean).chain(&r.removed);
            rgb.flat_map(|p| p.map(f32::to_bits))
                .chain(r.spp.iter().map(|&n| n as u32))
                .collect()
        };
        let check = |want: Made| {
            kept.with_resolved(&frame, &params, 2, |r, cut, made| {
                let oracle = bits(&cut.resolve(&params, 1));
                assert_eq!(made, want);
                assert!(bits(r) == oracle, "{made:?} differs from a fresh resolve");
            });
        };
        check(Made::Whole);
        check(Made::Kept);
        for seq in 1..6u64 {
            ingest_tile(&frame, &scene, seq, ((seq as u32 * 13) % (w - 12), 20), 12);
            check(Made::Patched);
        }
        assert_eq!(kept.patched(), 5);
        let pass: Vec<[f32; 3]> = vec![[0.5, 0.25, 2.0]; (w * h) as usize];
        frame.ingest_pass(1, 99, &pass, None).unwrap();
        // The estimator resolves the whole frame when the change covers most of it.
        check(Made::Patched);
        let other = ResolveParams::new(params.variant(), 3.0, 1.0, 0.0).unwrap();
        kept.with_resolved(&frame, &other, 1, |_, _, made| {
            assert_eq!(made, Made::Whole)
        });
    }

    /// A deleted frame's resolve buffers are the spare that the next frame's first resolve
    /// fills (no fresh pages), and what it fills them with is that frame's own fresh resolve,
    /// nothing left of the frame before; a frame pushed out of the kept set leaves its buffers
    /// to the frame that pushed it out.
    #[test]
    fn a_deleted_frames_buffers_serve_the_next_frames_first_resolve() {
        let (w, h) = (48, 40);
        let make = |seed: u64| {
            let frame = new_frame(w, h);
            let scene = FireflyScene::new(w, h, seed);
            let records = (0..3)
                .flat_map(|p| scene.pass(p))
                .map(|(x, y, rgb)| Record::new(x, y, rgb));
            frame
                .ingest(&Batch::new("f", 1, 0, records.collect()).unwrap())
                .unwrap();
            frame
        };
        let kept = KeptResolves::default();
        let first = make(1);
        let params = first.spec().resolve;
        let pointer = kept.with_resolved(&first, &params, 1, |r, _, _| r.reweighted.as_ptr());
        assert!(!kept.has_spare());
        kept.forget(&first);
        assert!(kept.has_spare(), "the deleted frame's buffers are kept");

        let second = make(2);
        let pointer = kept.with_resolved(&second, &params, 2, |r, cut, made| {
            assert_eq!(made, Made::Whole);
            assert_eq!(r.reweighted.as_ptr(), pointer, "resolved into the spare");
            assert_eq!(
                *r,
                cut.resolve(&params, 1),
                "the second frame's own resolve"
            );
            r.reweighted.as_ptr()
        });
        assert!(!kept.has_spare(), "the spare went to the second frame");

        // The fifth frame after it pushes it out and resolves into its buffers.
        let others: Vec<ShardedFrame> = (3..7).map(make).collect();
        let pointers: Vec<_> = others
            .iter()
            .map(|frame| kept.with_resolved(frame, &params, 1, |r, _, _| r.reweighted.as_ptr()))
            .collect();
        assert_eq!(
            pointers[3], pointer,
            "the frame pushed out left its buffers"
        );
        assert!(!pointers[..3].contains(&pointer));
    }

    /// A render that needs only the resolved layers takes the kept resolve when it is of the
    /// version the render asks for or later, and patches it otherwise.
    #[test]
    fn a_layer_of_a_version_already_resolved_is_not_resolved_again() {
        let frame = new_frame(40, 30);
        let params = frame.spec().resolve;
        let one = |seq: u64| Batch::new("f", 1, seq, vec![Record::new(3, 4, [2.0; 3])]).unwrap();
        frame.ingest(&one(0)).unwrap();
        let kept = KeptResolves::default();
        let asked = frame.version();
        kept.with_resolved(&frame, &params, 1, |_, _, made| {
            assert_eq!(made, Made::Whole)
        });
        frame.ingest(&one(1)).unwrap();
        let spp_at = |wanted: u64| {
            kept.with_resolved_since(&frame, &params, 1, wanted, |r, made| {
                (r.spp[4 * 40 + 3], made)
            })
        };
        assert_eq!(
            spp_at(asked),
            (1, Made::Kept),
            "the kept resolve answers its version"
        );
        assert_eq!(
            spp_at(frame.version()),
            (2, Made::Patched),
            "a later version is patched"
        );
        assert_eq!(spp_at(frame.version()), (2, Made::Kept));
    }

    /// Figures asked for after an image of the same version cost a need map, made from a cut
    /// of that version and the kept resolve (no resolve); the need map goes with the kept
    /// resolve, so asking at that version or an older one makes nothing, and it is the need map
    /// of a fresh resolve of the same cut.
    #[test]
    fn the_need_map_goes_with_the_kept_resolve() {
        let (w, h) = (40, 30);
        let frame = new_frame(w, h);
        let params = frame.spec().resolve;
        let scene = FireflyScene::new(w, h, 3);
        let kept = KeptResolves::default();
        let asked = ingest_pass(&frame, &scene, 0);
        kept.with_resolved(&frame, &params, 1, |_, _, made| {
            assert_eq!(made, Made::Whole)
        });
        assert_eq!(
            frame.history().latest_version(),
            None,
            "an image files no figures"
        );
        let oracle = {
            let cut = frame.cut();
            let resolved = cut.resolve(&params, 1);
            NeedMap::build(&cut.band_refs(), &resolved, &params, DEFAULT_NEED_TILE).unwrap()
        };
        let tiles = kept.with_need_since(&frame, 1, asked, |m, _| m.tiles.clone());
        assert_eq!(tiles, oracle.tiles);
        assert_eq!(frame.history().latest_version(), Some(asked));
        assert_eq!(
            (kept.whole(), kept.patched()),
            (1, 0),
            "no resolve for the figures"
        );

        // A writer adds a pass; a render that started before it still gets the kept map.
        ingest_pass(&frame, &scene, 1);
        let (tiles, version) = kept.with_need_since(&frame, 1, asked, |m, v| (m.tiles.clone(), v));
        assert_eq!(version, asked);
        assert_eq!(tiles, oracle.tiles);
        assert_eq!(
            (kept.whole(), kept.patched()),
            (1, 0),
            "nothing resolved again"
        );

        // Asked at the new version, it is brought up to date, and the figures are filed.
        let now = frame.version();
        let samples = kept.with_need_since(&frame, 1, now, |m, v| {
            assert_eq!(v, now);
            m.convergence(&ResolveParams::with_defaults()).samples
        });
        assert_eq!(samples, u64::from(2 * w * h));
        assert_eq!(frame.history().latest_version(), Some(now));
        assert_eq!(kept.patched(), 1);
    }

    /// While a request for figures waits, a render of the layers that resolves the frame makes
    /// the need map from the same cut, so the figures render beside it resolves nothing and
    /// files the figures of that cut (the map of a fresh resolve of it, the oracle); with no
    /// request waiting, renders of layers leave the map alone.
    #[test]
    fn a_layer_render_makes_the_map_while_figures_are_wanted() {
        let (w, h) = (40, 30);
        let frame = new_frame(w, h);
        let params = frame.spec().resolve;
        let scene = FireflyScene::new(w, h, 4);
        let pass = |seq: u64| ingest_pass(&frame, &scene, seq);
        let layers = |kept: &KeptResolves, asked: u64| {
            kept.with_resolved_since(&frame, &params, 1, asked, |_, made| {
                assert_ne!(made, Made::Kept, "the frame changed since")
            });
        };
        let kept = Arc::new(KeptResolves::default());
        kept.with_need_since(&frame, 1, pass(0), |_, _| ());
        let tiles = kept.need_tiles();

        layers(&kept, pass(1));
        assert_eq!(kept.need_tiles(), tiles, "no figures wanted: no map made");

        let asked = pass(2);
        let wanted = kept.want_figures(&frame);
        layers(&kept, asked);
        assert!(
            kept.need_tiles() > tiles,
            "figures wanted: the map made too"
        );
        let resolves = (kept.whole(), kept.patched());
        let oracle = {
            let cut = frame.cut();
            let resolved = cut.resolve(&params, 1);
            NeedMap::build(&cut.band_refs(), &resolved, &params, DEFAULT_NEED_TILE).unwrap()
        };
        let (map, version) = kept.with_need_since(&frame, 1, asked, |m, v| (m.tiles.clone(), v));
        assert_eq!(version, asked);
        assert_eq!(map, oracle.tiles);
        assert_eq!(frame.history().latest_version(), Some(asked));
        assert_eq!(
            (kept.whole(), kept.patched()),
            resolves,
            "the figures render resolved nothing"
        );

        drop(wanted);
        let tiles = kept.need_tiles();
        layers(&kept, pass(3));
        assert_eq!(kept.need_tiles(), tiles, "the request went: no map made");
    }

    /// After batches in one worker's tile, figures renders make again only the need map's
    /// tiles that the frame's changes since the map reach, also when an image render patched
    /// the resolve in between (the changes it patched are still the map's to catch up on), and
    /// each map is the map built afresh from a fresh resolve of the same cut (the oracle).
    #[test]
    fn figures_after_a_tile_make_only_the_tiles_near_it_again() {
        let (w, h) = (320, 240);
        let frame = new_frame(w, h);
        let params = frame.spec().resolve;
        let scene = FireflyScene::new(w, h, 9);
        let records = (0..2)
            .flat_map(|p| scene.pass(p))
            .map(|(x, y, rgb)| Record::new(x, y, rgb));
        frame
            .ingest(&Batch::new("f", 1, 0, records.collect()).unwrap())
            .unwrap();
        let kept = KeptResolves::default();
        let all = u64::from(w.div_ceil(DEFAULT_NEED_TILE) * h.div_ceil(DEFAULT_NEED_TILE));
        let figures = |kept: &KeptResolves| {
            let (tiles, version) =
                kept.with_need_since(&frame, 2, frame.version(), |m, v| (m.tiles.clone(), v));
            let cut = frame.cut();
            assert_eq!(version, cut.version);
            let resolved = cut.resolve(&params, 1);
            let oracle =
                NeedMap::build(&cut.band_refs(), &resolved, &params, DEFAULT_NEED_TILE).unwrap();
            assert!(tiles == oracle.tiles, "the map of a fresh resolve");
        };
        figures(&kept);
        assert_eq!(kept.need_tiles(), all, "the first map is built whole");
        for seq in 1..5u64 {
            ingest_tile(&frame, &scene, seq, ((seq as u32 * 29) % (w - 16), 40), 16);
            if seq % 2 == 0 {
                // An image first: it patches the resolve and leaves the map stale.
                kept.with_resolved(&frame, &params, 1, |_, _, made| {
                    assert_eq!(made, Made::Patched)
                });
            }
            let before = kept.need_tiles();
            figures(&kept);
            let made = kept.need_tiles() - before;
            assert!(
                made > 0 && made < all / 2,
                "batch {seq}: {made} of {all} tiles"
            );
        }
        assert_eq!(kept.whole(), 1, "only the first resolve was whole");
    }
}
