//! Tests of the data directory: snapshots, old formats, recovery and quarantine.

use std::path::Path;

use splatd_estimator::FrameState;
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Record};

use super::format::{SnapshotMeta, SnapshotMetaV1, SNAPSHOT_MAGIC, SNAPSHOT_VERSION};
use super::*;
use crate::frame::FrameSpec;
use crate::store::FrameStore;
use crate::Limits;

fn open(dir: &Path) -> Arc<Durable> {
    Arc::new(Durable::open(dir, Duration::from_secs(3600)).unwrap())
}

fn frame(id: &str) -> Arc<ShardedFrame> {
    Arc::new(ShardedFrame::new(
        FrameSpec::new(CreateFrame::new(id, 8, 20)).unwrap(),
    ))
}

fn post(frame: &ShardedFrame, worker: u64, seq: u64) {
    let records = (0..20)
        .map(|y| Record::new(3, y, [1.0, 2.0, 3.0]))
        .collect();
    let batch = Batch::new(frame.id(), worker, seq, records).unwrap();
    assert!(!frame.ingest(&batch).unwrap().duplicate);
}

fn recover(dir: &Path) -> FrameStore {
    let store = FrameStore::new(Limits::default());
    open(dir).recover(&store).unwrap();
    store
}

/// The writer of a snapshot of a frame that is deleted, and re-created under the same id,
/// while the snapshot is on its way must not put the old frame's samples and batch ids into
/// the new frame's directory (they came back at the next start, and the new frame's first
/// batch was answered "duplicate").
#[tokio::test]
async fn a_late_snapshot_of_a_deleted_frame_does_not_resurrect_it() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    let old = frame("f");
    durable.frame_created(&old).await.unwrap();
    post(&old, 1, 0);
    // The snapshot task took `old` from the store, then the frame was deleted and created
    // again before the task got to write it.
    old.retire();
    durable.frame_deleted(&old).await.unwrap();
    let new = frame("f");
    durable.frame_created(&new).await.unwrap();
    durable.snapshot(&old).await.unwrap();

    let store = recover(dir.path());
    let back = store.get("f").unwrap();
    assert_eq!(back.info().samples, 0, "the new frame is empty");
    post(&back, 1, 0);
}

/// A create over files that a failed deletion left behind starts from an empty frame.
#[tokio::test]
async fn a_new_frame_ignores_a_stale_snapshot_in_its_directory() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    let old = frame("f");
    durable.frame_created(&old).await.unwrap();
    post(&old, 1, 0);
    durable.snapshot(&old).await.unwrap();
    assert_eq!(recover(dir.path()).get("f").unwrap().info().samples, 20);
    durable.frame_created(&frame("f")).await.unwrap();
    assert_eq!(recover(dir.path()).get("f").unwrap().info().samples, 0);
}

/// Snapshots written before batches had digests are still read; their batches count as
/// applied, and new batches get digests.
#[tokio::test]
async fn version_1_snapshots_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    let f = frame("f");
    durable.frame_created(&f).await.unwrap();
    post(&f, 4, 0);
    durable.snapshot(&f).await.unwrap();

    // Rewrite the snapshot as version 1 wrote it: metadata without digests.
    let path = dir.path().join("frames/f").join(SNAPSHOT_FILE);
    let (meta, _): (SnapshotMeta, usize) =
        bincode::serde::decode_from_slice(&snapshot_meta(&path), bincode::config::legacy())
            .unwrap();
    let v1 = SnapshotMetaV1 {
        frame: meta.frame,
        version: meta.version,
        counters: meta.counters,
        workers: meta.seen.workers,
        nodes: meta.seen.nodes,
    };
    let v1 = bincode::serde::encode_to_vec(&v1, bincode::config::legacy()).unwrap();
    // And its cells as state format version 1 held them.
    let whole = recover(dir.path()).get("f").unwrap().cut().whole();
    fs::write(&path, old_snapshot(1, &v1, &[v1_state(&whole, "f", None)])).unwrap();

    let store = recover(dir.path());
    let back = store.get("f").unwrap();
    assert_eq!(back.info().samples, 20);
    let retry = Batch::new("f", 4, 0, vec![Record::new(0, 0, [9.0; 3])]).unwrap();
    assert!(
        back.ingest(&retry).unwrap().duplicate,
        "old ids stay applied"
    );
    post(&back, 4, 1);
}

/// The body of `state` as state format version 1 wrote it: 2^-32 units (64 times finer,
/// plus a remainder that rounds away), `4K` cells per pixel, no high word; pixel `saturate`
/// gets a top-cascade sum saturated at `u64::MAX`.
fn v1_state(state: &FrameState, id: &str, saturate: Option<usize>) -> Vec<u8> {
    let k = state.layout().cascades();
    let mut cells = Vec::new();
    for cell in state.cells().chunks_exact(splatd_estimator::cell_len(k)) {
        assert_eq!(cell[4 * k], 0, "no high word in an old state");
        for (i, &v) in cell[..4 * k].iter().enumerate() {
            cells.push(if i % 4 == 3 { v * 64 } else { v * 64 + 17 });
        }
    }
    if let Some(pixel) = saturate {
        cells[pixel * 4 * k + 4 * (k - 1)] = u64::MAX;
    }
    let mut dump = splatd_formats::state::dump(state, None, id, None, vec![]);
    dump.frac_bits = 32;
    dump.cells = cells;
    dump.encode_v1()
}

/// The metadata bytes of the snapshot file at `path` (after magic, version and their
/// length), as [`old_snapshot`] takes them.
fn snapshot_meta(path: &Path) -> Vec<u8> {
    let bytes = fs::read(path).unwrap();
    let meta_len = u64::from_le_bytes(bytes[6..14].try_into().unwrap()) as usize;
    bytes[14..14 + meta_len].to_vec()
}

/// A snapshot of `version` with metadata `meta` and `states` as its bands.
fn old_snapshot(version: u16, meta: &[u8], states: &[Vec<u8>]) -> Vec<u8> {
    let mut old = Vec::new();
    old.extend_from_slice(&SNAPSHOT_MAGIC);
    old.extend_from_slice(&version.to_le_bytes());
    old.extend_from_slice(&(meta.len() as u64).to_le_bytes());
    old.extend_from_slice(meta);
    old.extend_from_slice(&(states.len() as u32).to_le_bytes());
    for state in states {
        old.extend_from_slice(&(state.len() as u64).to_le_bytes());
        old.extend_from_slice(state);
    }
    let crc = crc32fast::hash(&old);
    old.extend_from_slice(&crc.to_le_bytes());
    old
}

/// Snapshots of version 3 hold states of format version 2 (no AOV section): read as frames
/// without AOV samples.
#[tokio::test]
async fn version_3_snapshots_with_version_2_states_are_read_without_aovs() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    let f = frame("f");
    durable.frame_created(&f).await.unwrap();
    post(&f, 4, 0);
    durable.snapshot(&f).await.unwrap();
    let path = dir.path().join("frames/f").join(SNAPSHOT_FILE);
    // The snapshot a server of state format version 2 wrote: version 3, one band of a
    // version 2 state.
    let whole = f.cut().whole();
    let v2 = splatd_formats::state::dump(&whole, None, "f", None, vec![]).encode_v2();
    fs::write(&path, old_snapshot(3, &snapshot_meta(&path), &[v2])).unwrap();

    let back = recover(dir.path()).get("f").unwrap();
    assert_eq!(back.info().samples, 20);
    assert!(back.cut().whole() == whole);
    assert!(back.cut().aovs.is_none());
    post(&back, 4, 1);
}

/// A frame with AOVs keeps them through a snapshot and a restart, bit for bit.
#[tokio::test]
async fn aov_sums_survive_a_snapshot() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    let request = CreateFrame {
        aovs: vec![splatd_proto::api::AovSpec::new("depth", &["Z"])],
        ..CreateFrame::new("f", 8, 20)
    };
    let f = Arc::new(ShardedFrame::new(FrameSpec::new(request).unwrap()));
    durable.frame_created(&f).await.unwrap();
    for seq in 0..3 {
        let records = (0..160)
            .map(|i| Record::new(i % 8, i / 8, [1.0, 2.0, 3.0]))
            .collect();
        let batch = Batch::new("f", 1, seq, records).unwrap();
        let depth: Vec<f32> = (0..160).map(|i| i as f32 * -0.37 + seq as f32).collect();
        f.ingest_with_aovs(&batch, Some(&depth)).unwrap();
    }
    durable.snapshot(&f).await.unwrap();
    let back = recover(dir.path()).get("f").unwrap();
    let (before, after) = (
        f.cut().aovs.clone().unwrap(),
        back.cut().aovs.clone().unwrap(),
    );
    assert_eq!(after.count(7, 19), 3);
    assert_eq!(before, after);
}

/// Snapshots of versions 1 and 2 hold states of format version 1 (32 fractional bits, `4K`
/// cells per pixel): they are converted when read, and a saturated sum, which cannot be
/// converted honestly, quarantines the frame, naming the pixel.
#[tokio::test]
async fn version_2_snapshots_with_old_states_are_converted() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    for id in ["f", "sat"] {
        let f = frame(id);
        durable.frame_created(&f).await.unwrap();
        post(&f, 4, 0);
        let bright = vec![
            Record::new(5, 7, [1e5, 2.0, 3e4]),
            Record::new(0, 0, [0.3; 3]),
        ];
        let batch = Batch::new(id, 4, 1, bright).unwrap();
        f.ingest(&batch).unwrap();
        durable.snapshot(&f).await.unwrap();
    }
    let expected = recover(dir.path()).get("f").unwrap().cut().whole();

    for (id, saturate) in [("f", false), ("sat", true)] {
        let path = dir.path().join("frames").join(id).join(SNAPSHOT_FILE);
        let meta = snapshot_meta(&path);
        let state = v1_state(&expected, id, saturate.then_some(7 * 8 + 5));
        fs::write(&path, old_snapshot(2, &meta, &[state])).unwrap();
    }

    let store = FrameStore::new(Limits::default());
    let durable = open(dir.path());
    assert_eq!(durable.recover(&store).unwrap(), 1);
    let back = store.get("f").unwrap();
    assert_eq!(back.cut().whole(), expected, "converted exactly");
    assert_eq!(back.info().samples, 22);
    let q = durable.quarantined();
    assert_eq!(q.len(), 1);
    assert_eq!(q[0].frame, "sat");
    assert!(
        q[0].reason.contains("pixel (5, 7)") && q[0].reason.contains("saturated"),
        "{}",
        q[0].reason
    );
    // The next snapshot is written in the current versions and read back as it is.
    post(&back, 4, 2);
    durable.snapshot(&back).await.unwrap();
    let bytes = fs::read(dir.path().join("frames/f").join(SNAPSHOT_FILE)).unwrap();
    assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), SNAPSHOT_VERSION);
    assert_eq!(recover(dir.path()).get("f").unwrap().info().samples, 42);
}

/// A damaged or missing file never reads as an empty frame: the frame is moved aside and
/// listed, and every other frame is served.
#[tokio::test]
async fn damaged_frames_are_quarantined_and_the_rest_recovered() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    for id in ["good", "lost", "torn", "garbled"] {
        let f = frame(id);
        durable.frame_created(&f).await.unwrap();
        post(&f, 1, 0);
        durable.snapshot(&f).await.unwrap();
    }
    let frames = dir.path().join("frames");
    fs::remove_file(frames.join("lost").join(SNAPSHOT_FILE)).unwrap();
    let torn = frames.join("torn").join(SNAPSHOT_FILE);
    let len = fs::metadata(&torn).unwrap().len();
    File::options()
        .write(true)
        .open(&torn)
        .unwrap()
        .set_len(len / 2)
        .unwrap();
    fs::write(frames.join("garbled").join(FRAME_FILE), b"{not json").unwrap();

    let store = FrameStore::new(Limits::default());
    let durable = open(dir.path());
    assert_eq!(durable.recover(&store).unwrap(), 1);
    assert_eq!(store.get("good").unwrap().info().samples, 20);
    let mut q = durable.quarantined();
    q.sort_by(|a, b| a.frame.cmp(&b.frame));
    let names: Vec<&str> = q.iter().map(|q| q.frame.as_str()).collect();
    assert_eq!(names, ["garbled", "lost", "torn"]);
    assert!(q[1].reason.contains("missing"), "{}", q[1].reason);
    for entry in &q {
        assert!(entry.moved_to.join(FRAME_FILE).exists(), "{entry:?}");
        assert!(
            store.get(&entry.frame).is_err(),
            "{} is not served",
            entry.frame
        );
    }
    // The next start serves what is left, and the quarantined files stay put.
    let again = open(dir.path());
    assert_eq!(
        again.recover(&FrameStore::new(Limits::default())).unwrap(),
        1
    );
    assert!(again.quarantined().is_empty());
}

/// A frame created but never snapshotted is legitimately empty after a restart.
#[tokio::test]
async fn a_frame_never_snapshotted_recovers_empty() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    durable.frame_created(&frame("f")).await.unwrap();
    let store = recover(dir.path());
    assert_eq!(store.get("f").unwrap().info().samples, 0);
}

/// A write that fails part way leaves no temporary file behind to hold the space.
#[test]
fn a_failed_write_removes_its_temporary_file() {
    let dir = tempfile::tempdir().unwrap();
    let mut buffer = direct::DirectBuffer::new(direct::BUFFER);
    let err = write_atomically(dir.path(), "out", "out.tmp", &mut buffer, |w| {
        w.write_all(&[7u8; 4 << 20])?;
        Err(io::Error::new(
            io::ErrorKind::StorageFull,
            "no space left on device",
        ))
    })
    .unwrap_err();
    assert!(err.to_string().contains("no space left"), "{err}");
    assert!(!dir.path().join("out.tmp").exists());
    assert!(!dir.path().join("out").exists());
}

/// A snapshot lets go of each band of its cut once the band is written, before the file is
/// synced: a writer changing a band the snapshot has written no longer copies it first, and
/// none copies anything while the disk syncs. (It used to hold the whole cut until the sync was
/// done: a 1080p frame's 400 MB took longer to sync than to encode, and every pass arriving
/// meanwhile copied every band.)
#[test]
fn a_snapshot_lets_go_of_each_band_once_written() {
    struct Watch<'a> {
        frame: &'a ShardedFrame,
        held: Vec<usize>,
    }
    impl Write for Watch<'_> {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            self.held.push(self.frame.bands_held_by_cuts());
            Ok(buf.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }
    let frame = frame("bands");
    post(&frame, 1, 0);
    let cut = frame.cut();
    assert_eq!(frame.bands_held_by_cuts(), 2, "an 8x20 frame has two bands");
    let (snapshot, seen) = format::Snapshot::new(&frame, cut);
    assert!(
        seen.workers[&1].contains(0),
        "the applied set goes back for marking durable"
    );
    let mut watch = Watch {
        frame: &frame,
        held: Vec::new(),
    };
    snapshot.write_to(&mut watch).unwrap();
    assert_eq!(
        frame.bands_held_by_cuts(),
        0,
        "all let go of once written, before anything syncs"
    );
    // Both held while the first band is written, one while the second is, none for the CRC.
    assert_eq!(watch.held.first(), Some(&2), "{:?}", watch.held);
    assert!(watch.held.contains(&1), "{:?}", watch.held);
    assert_eq!(watch.held.last(), Some(&0), "{:?}", watch.held);
    assert!(
        watch.held.windows(2).all(|w| w[0] >= w[1]),
        "{:?}",
        watch.held
    );
}

/// A snapshot call that waited for its turn while another snapshot wrote everything it needs
/// returns without writing again, although the frame changed since: calls waiting together
/// share a snapshot (a farm's workers syncing as they finish). One whose changes came after
/// that snapshot's cut still writes its own.
#[tokio::test]
async fn waiting_snapshots_share_the_one_written_meanwhile() {
    let dir = tempfile::tempdir().unwrap();
    let durable = open(dir.path());
    let f = frame("f");
    durable.frame_created(&f).await.unwrap();
    post(&f, 1, 0);
    let covered = f.version();

    // A sync of batch 0 waits for its turn while another snapshot, of batch 0, is written.
    let turn = durable.lock_for("f");
    let guard = turn.lock().await;
    let waiting = tokio::spawn({
        let (durable, f) = (durable.clone(), f.clone());
        async move { durable.snapshot(&f).await }
    });
    // The test's runtime has one thread: the task runs until it waits for the turn.
    tokio::task::yield_now().await;
    let cut = f.cut();
    let version = cut.version;
    let seen = durable.write_snapshot(&f, cut).unwrap();
    f.mark_durable(&seen, version);
    assert_eq!(f.durable_version(), covered);
    // Batch 1 arrives after that snapshot's cut, before the waiting sync gets its turn.
    post(&f, 1, 1);
    drop(guard);
    waiting.await.unwrap().unwrap();
    assert_eq!(
        f.durable_version(),
        covered,
        "the waiting sync needed nothing more, so it wrote nothing"
    );
    assert_eq!(recover(dir.path()).get("f").unwrap().info().samples, 20);

    // A sync called after batch 1 writes it.
    durable.snapshot(&f).await.unwrap();
    assert_eq!(f.durable_version(), f.version());
    assert_eq!(recover(dir.path()).get("f").unwrap().info().samples, 40);
}
