//! How often a frame that keeps changing is rendered: at most a set share of the time.
//!
//! Sharing renders (see [`crate::render`]) makes a frame cost one render at a time however many
//! watch it, but while workers keep adding samples every request sees a new version, so a
//! dashboard, the live page and an `image.exr` fetched now and then kept one render of the frame
//! running back to back. On a head whose cores ingest uses, that cost a quarter of the ingest
//! rate (`watchbench`), and a client fetching images in a loop cost the same.
//!
//! So after a render that took `d`, the next one of that frame, of whatever kind, starts no
//! sooner than `d * (1 / share - 1)` after it ended, **while the frame keeps changing**; the
//! renders that waited for that moment start together, so a request waits for one pace, not
//! for a queue of them. A frame rendered at most `share` of the wall time costs ingest at most
//! about that share of what rendering it without pause did. Answers never get older for it: a request that
//! waits is answered by a render that starts after the wait and so holds every sample
//! acknowledged before the request came; watchers of a busy frame only see new figures and
//! images less often. A frame that has not changed since its last render is not held back (a
//! new query of it, say the final `image.exr` after a dashboard's figures, renders at once), and
//! neither is one that goes quiet: the wait ends as soon as [`QUIET`] passes with nothing new,
//! so the final fetched when the workers are done is rendered within that time.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Duration;

use tokio::time::Instant;

use crate::frame::ShardedFrame;

/// A wait for a frame's pace ends once this passes with no new samples in the frame.
pub const QUIET: Duration = Duration::from_millis(100);

/// The share of the wall time a changing frame's renders may take unless set.
pub const DEFAULT_SHARE: f64 = 0.2;

/// Tokio's clock where a thread outside the runtime can read it: tokio's instant when made
/// (in the runtime, paused in tests) plus the real time since.
#[derive(Debug, Clone, Copy)]
pub struct Clock {
    tokio: Instant,
    real: std::time::Instant,
}

impl Clock {
    /// Tokio's clock from now on; made in the runtime.
    pub fn start() -> Clock {
        Clock {
            tokio: Instant::now(),
            real: std::time::Instant::now(),
        }
    }

    /// The time on tokio's clock.
    pub fn now(&self) -> Instant {
        self.tokio + self.real.elapsed()
    }
}

/// The latest renders of one frame.
#[derive(Debug, Default, Clone, Copy)]
struct Gate {
    /// The newest version of the frame a render read before it began.
    version: u64,
    /// When the next render of the frame may start if the frame changed since.
    next: Option<Instant>,
}

/// The pace of every frame rendered so far.
#[derive(Debug)]
pub struct Paces {
    /// In `(0, 1]`; 1 renders a changing frame back to back.
    share: f64,
    frames: Mutex<HashMap<u64, Gate>>,
}

impl Paces {
    /// Renders of a changing frame take at most `share` of the wall time (clamped to
    /// `[0.01, 1]`).
    pub fn new(share: f64) -> Paces {
        Paces {
            share: if share.is_nan() {
                1.0
            } else {
                share.clamp(0.01, 1.0)
            },
            frames: Mutex::default(),
        }
    }

    /// The share set.
    pub fn share(&self) -> f64 {
        self.share
    }

    /// When the next render of `frame` may start if that is later than now: `None` if the
    /// frame was never rendered, has not changed since its last render, or its pace is over.
    fn held_until(&self, frame: &ShardedFrame) -> Option<Instant> {
        let gate = {
            let frames = self.frames.lock().unwrap_or_else(|e| e.into_inner());
            frames.get(&frame.serial()).copied().unwrap_or_default()
        };
        gate.next
            .filter(|&next| frame.version() != gate.version && Instant::now() < next)
    }

    /// Waits for `frame`'s pace if the frame changed since its last render and keeps changing:
    /// until the next render may start, or until [`QUIET`] passes with no new samples,
    /// whichever comes first. Returns the time waited.
    ///
    /// The moment is read again at every step of the wait, so a render of the frame that ends
    /// meanwhile moves it for every request waiting: renders of any kind that wait for the
    /// frame start together when its pace ends, and share one resolve
    /// ([`KeptResolves`](crate::render::KeptResolves)). A wait that kept the moment it read
    /// first ended before those that began after the next render had ended, so the live page's
    /// previews, a dashboard's figures and an image each started at a moment of their own and
    /// each resolved a frame that the writers had changed all over. That also let a changing
    /// frame's renders take more than their share: `watchbench` (2 rounds) ran 36-39 renders
    /// with 16 resolves; reading the moment again, 29-30 with 11-12.
    pub async fn wait(&self, frame: &ShardedFrame) -> Duration {
        let start = Instant::now();
        while let Some(next) = self.held_until(frame) {
            let seen = frame.version();
            tokio::time::sleep(next.saturating_duration_since(Instant::now()).min(QUIET)).await;
            if frame.version() == seen {
                break;
            }
        }
        start.elapsed()
    }

    /// Whether a render of `frame` may start now: the frame never rendered, unchanged since its
    /// last render, or its pace over. For work that no request waits for (the tev feed), which
    /// skips a frame until then instead of waiting in [`Paces::wait`].
    pub fn due(&self, frame: &ShardedFrame) -> bool {
        self.held_until(frame).is_none()
    }

    /// Files a render of `frame` at `version` that took `took` and ended at `ended`.
    ///
    /// The moments are on tokio's clock, which tests pause, so that a wait ends by its own
    /// deadline there too; a render thread, outside the runtime, reads it through
    /// [`Clock`].
    pub fn rendered(&self, frame: &ShardedFrame, version: u64, ended: Instant, took: Duration) {
        let next = ended + took.mul_f64(1.0 / self.share - 1.0);
        let mut frames = self.frames.lock().unwrap_or_else(|e| e.into_inner());
        let gate = frames.entry(frame.serial()).or_default();
        gate.version = gate.version.max(version);
        gate.next = Some(gate.next.map_or(next, |n| n.max(next)));
    }

    /// Forgets `frame`'s pace (when it is deleted).
    pub fn forget(&self, frame: &ShardedFrame) {
        let mut frames = self.frames.lock().unwrap_or_else(|e| e.into_inner());
        frames.remove(&frame.serial());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::FrameSpec;
    use splatd_proto::api::CreateFrame;
    use splatd_proto::{Batch, Record};
    use std::sync::Arc;

    fn frame() -> Arc<ShardedFrame> {
        Arc::new(ShardedFrame::new(
            FrameSpec::new(CreateFrame::new("f", 4, 4)).unwrap(),
        ))
    }

    fn add(frame: &ShardedFrame, seq: u64) {
        let batch = Batch::new("f", 1, seq, vec![Record::new(0, 0, [1.0; 3])]).unwrap();
        frame.ingest(&batch).unwrap();
    }

    /// A writer adding `batches` samples to `frame`, the first now, then one every 10 ms.
    fn writing(frame: &Arc<ShardedFrame>, batches: u64) -> tokio::task::JoinHandle<()> {
        add(frame, 0);
        let f = frame.clone();
        tokio::spawn(async move {
            for seq in 1..batches {
                tokio::time::sleep(Duration::from_millis(10)).await;
                add(&f, seq);
            }
        })
    }

    /// After a render of 1 s at a share of 0.2, the next render of a frame that keeps changing
    /// waits 4 s; of a frame that went quiet, one quiet spell; of an unchanged frame, nothing.
    /// On tokio's paused clock, so the waits are exact.
    #[tokio::test(start_paused = true)]
    async fn a_changing_frame_waits_its_pace_and_a_quiet_one_does_not() {
        let paces = Paces::new(0.2);
        let f = frame();
        assert_eq!(
            paces.wait(&f).await,
            Duration::ZERO,
            "a frame never rendered"
        );
        paces.rendered(&f, f.version(), Instant::now(), Duration::from_secs(1));
        assert_eq!(paces.wait(&f).await, Duration::ZERO, "an unchanged frame");

        // A writer adds a sample every 10 ms for 10 s: two renders wait out one pace together.
        let writer = writing(&f, 1000);
        let (a, b) = tokio::join!(paces.wait(&f), paces.wait(&f));
        // Tokio's timers round up to the millisecond: 4 s, or up to 1 ms more.
        let ms = Duration::from_millis(1);
        for waited in [a, b] {
            assert!(
                waited >= Duration::from_secs(4) && waited <= Duration::from_secs(4) + ms,
                "waited {waited:?}"
            );
        }
        paces.rendered(&f, f.version(), Instant::now(), Duration::from_secs(1));
        writer.abort();

        // One more sample, then nothing: the wait ends after one quiet spell.
        add(&f, 5000);
        let waited = paces.wait(&f).await;
        assert!(
            waited >= QUIET && waited <= QUIET + ms,
            "a frame that went quiet waited {waited:?}"
        );
    }

    /// A render that ends while requests wait for the frame's pace moves the moment for all of
    /// them, those already waiting too: they start together, when the pace it set ends.
    #[tokio::test(start_paused = true)]
    async fn a_render_that_ends_meanwhile_moves_every_wait_to_its_pace() {
        let paces = Arc::new(Paces::new(0.2));
        let f = frame();
        paces.rendered(&f, f.version(), Instant::now(), Duration::from_secs(1));
        let writer = writing(&f, 2000);
        let start = Instant::now();
        let waiting = |after: Duration| {
            let (paces, f) = (paces.clone(), f.clone());
            tokio::spawn(async move {
                tokio::time::sleep(after).await;
                paces.wait(&f).await;
                Instant::now() - start
            })
        };
        // One request waits from the start for the pace of the 1 s render (4 s).
        let first = waiting(Duration::ZERO);
        // A render of another kind, which read the frame at the start, ends at 1 s after 2 s:
        // the next may start 8 s after it, 9 s after the start.
        let read = f.version();
        tokio::time::sleep(Duration::from_secs(1)).await;
        paces.rendered(&f, read, Instant::now(), Duration::from_secs(2));
        // Another request comes at 2 s.
        let second = waiting(Duration::from_secs(1));
        let (first, second) = (first.await.unwrap(), second.await.unwrap());
        writer.abort();
        let ms = Duration::from_millis(1);
        for ended in [first, second] {
            assert!(
                ended >= Duration::from_secs(9) && ended <= Duration::from_secs(9) + ms,
                "a wait ended {ended:?} after the start, not with the latest render's pace"
            );
        }
    }

    /// `due` says without waiting what `wait` waits for: a changed frame is due once its pace
    /// is over, an unchanged one at once.
    #[tokio::test(start_paused = true)]
    async fn a_changed_frame_is_due_when_its_pace_ends() {
        let paces = Paces::new(0.2);
        let f = frame();
        assert!(paces.due(&f), "a frame never rendered");
        paces.rendered(&f, f.version(), Instant::now(), Duration::from_secs(1));
        assert!(paces.due(&f), "an unchanged frame");
        add(&f, 1);
        assert!(
            !paces.due(&f),
            "a frame changed right after a render of 1 s"
        );
        tokio::time::sleep(Duration::from_millis(3999)).await;
        assert!(!paces.due(&f), "the pace of a 1 s render at 0.2 is 4 s");
        tokio::time::sleep(Duration::from_millis(1)).await;
        assert!(paces.due(&f), "the pace is over");
    }

    /// A share of 1 renders a changing frame back to back; the share is clamped.
    #[tokio::test(start_paused = true)]
    async fn a_share_of_one_never_waits() {
        let paces = Paces::new(1.0);
        let f = frame();
        paces.rendered(&f, 0, Instant::now(), Duration::from_secs(3));
        add(&f, 0);
        assert_eq!(paces.wait(&f).await, Duration::ZERO);
        assert_eq!(Paces::new(f64::NAN).share(), 1.0);
        assert_eq!(Paces::new(0.0).share(), 0.01);
    }
}
