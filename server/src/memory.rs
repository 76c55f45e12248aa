//! How the server asks the kernel for the memory of its large buffers.
//!
//! A frame's cells are hundreds of megabytes touched at random pixels: with 4 KiB pages every
//! sample of a large frame misses the TLB, and every fresh buffer of a state transfer takes a
//! page fault per 4 KiB. Transparent huge pages (2 MiB) cut both by 512; on a box where they are
//! enabled only on request (`/sys/kernel/mm/transparent_hugepage/enabled` = `madvise`, the
//! usual default) a buffer must ask for them with `madvise(MADV_HUGEPAGE)` *before* it is first
//! touched, which is what [`advise_huge_pages`] is for.

/// Asks the kernel to back `buf` with transparent huge pages. Call it on a freshly allocated
/// large buffer before writing to it (`vec![0; n]` of more than the allocator's mmap threshold
/// is not touched yet): pages faulted in afterwards come 2 MiB at a time where the range covers
/// whole ones.
///
/// Only a hint: the contents never change, and a kernel without transparent huge pages (or with
/// them off) refuses it, which is returned and costs nothing but speed. Buffers smaller than a
/// huge page are left alone.
pub fn advise_huge_pages<T>(buf: &[T]) -> std::io::Result<()> {
    if std::mem::size_of_val(buf) < HUGE {
        return Ok(());
    }
    #[cfg(target_os = "linux")]
    if let Some(pages) = whole_pages(buf) {
        // MADV_HUGEPAGE only changes how the kernel backs the pages.
        advise(pages, libc::MADV_HUGEPAGE)?;
    }
    Ok(())
}

/// A huge page: 2 MiB.
const HUGE: usize = 2 << 20;

/// `madvise(advice)` on `pages` (page-aligned addresses inside a buffer this process owns),
/// for advice that never changes the pages' contents (`MADV_HUGEPAGE`, `MADV_POPULATE_WRITE`).
#[cfg(target_os = "linux")]
fn advise(pages: std::ops::Range<usize>, advice: libc::c_int) -> std::io::Result<()> {
    // SAFETY: the callers give page-aligned ranges inside buffers they hold for as long as the
    // call lasts, and advice that changes how the kernel backs the pages, never what they hold.
    let rc = unsafe { libc::madvise(pages.start as *mut libc::c_void, pages.len(), advice) };
    if rc != 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(())
}

/// The addresses of the whole 4 KiB pages inside `buf`, if any.
fn whole_pages<T>(buf: &[T]) -> Option<std::ops::Range<usize>> {
    const PAGE: usize = 4096;
    let start = buf.as_ptr() as usize;
    let first = start.next_multiple_of(PAGE);
    let end = (start + std::mem::size_of_val(buf)) / PAGE * PAGE;
    (first < end).then_some(first..end)
}

/// Readies a frame's fresh cells (or AOV sums) for their first samples: asks for huge pages
/// ([`advise_huge_pages`]), and faults in now, writable, the pages at the ends of `cells` that
/// huge pages cannot cover (before its first 2 MiB boundary and after its last; all of a
/// buffer smaller than a huge page). Contents never change.
///
/// Why: the splat reads a cell before it writes it. A fresh page that is read first is mapped
/// to the kernel's shared zero page and replaced on the first write, which takes a second
/// fault and, in a process whose threads run on several cores, a flush of every such core's
/// TLB (an inter-processor interrupt; on a virtual machine, an exit to the host). Huge pages
/// pay that once per 2 MiB; the ends of a band's buffer paid it once per 4 KiB, and that was
/// 9 % of the server's CPU while a new 1080p frame took its first 32 samples a pixel
/// (`loadgen`; a sixth of its 32 bands' memory is in such ends). Faulted in here, a page costs
/// one fault and no flush. A kernel without `MADV_POPULATE_WRITE` (before Linux 5.14) leaves
/// them to the first samples, as before.
pub fn ready_cells(cells: &[u64]) {
    advise_or_log(cells);
    #[cfg(target_os = "linux")]
    if let Some(pages) = whole_pages(cells) {
        let head = pages.start..pages.start.next_multiple_of(HUGE).min(pages.end);
        let tail = (pages.end / HUGE * HUGE).max(head.end)..pages.end;
        for ends in [head, tail].into_iter().filter(|r| !r.is_empty()) {
            // MADV_POPULATE_WRITE faults the pages in as if they were written, and leaves
            // their contents as they are.
            let bytes = ends.len();
            if let Err(e) = advise(ends, libc::MADV_POPULATE_WRITE) {
                tracing::debug!(bytes, "cells not faulted in ahead: {e}");
                return;
            }
        }
    }
}

/// A zeroed `Vec<u64>` of `len` words, backed by huge pages where the kernel grants them
/// ([`advise_huge_pages`]): for the cells of frames and states.
pub fn zeroed_cells(len: usize) -> Vec<u64> {
    let cells = vec![0u64; len];
    advise_or_log(&cells);
    cells
}

/// [`advise_huge_pages`], logging (at debug level) a kernel that refuses.
pub fn advise_or_log<T>(buf: &[T]) {
    if let Err(e) = advise_huge_pages(buf) {
        tracing::debug!(bytes = std::mem::size_of_val(buf), "no huge pages: {e}");
    }
}

/// Buffers for large request bodies, kept between requests.
///
/// A 1080p EXR pass is 25 MB: read into a fresh buffer each time, it is mapped, grown (copied)
/// as its chunks arrive and unmapped per request, and the page faults of touching it again cost
/// more than reading it. A body read into a kept buffer of its `Content-Length` lands in memory
/// that is already mapped, with no copy. A buffer in use holds exactly the length that the
/// request reserved for its body; at most `keep` idle buffers are kept, and those no request
/// took for [`CELL_POOL_IDLE`] are freed (`AppState::release_idle_until`), so the half a
/// gigabyte of one imported 1080p state is not held for the server's life.
#[derive(Debug)]
pub struct BodyPool {
    free: splatd_formats::scratch::Pool<Vec<u8>>,
}

impl BodyPool {
    /// A pool that keeps at most `keep` idle buffers.
    pub fn new(keep: usize) -> BodyPool {
        BodyPool {
            free: splatd_formats::scratch::Pool::new(keep),
        }
    }

    /// An empty buffer with room for exactly `len` bytes: the largest idle one, shrunk or
    /// grown to `len` (both keep its mapped pages), or a new one.
    pub fn take(&self, len: usize) -> Vec<u8> {
        let mut buffer = self.free.take_largest();
        buffer.clear();
        if buffer.capacity() > len {
            buffer.shrink_to(len);
        } else {
            buffer.reserve_exact(len);
            // Pages not mapped yet (a new buffer, or what growing added) on huge pages.
            advise_or_log(buffer.spare_capacity_mut());
        }
        buffer
    }

    /// Keeps `buffer` for a later body (dropped if `keep` are already idle).
    pub fn give(&self, buffer: Vec<u8>) {
        self.free.give(buffer);
    }

    /// Bytes held by the idle buffers.
    pub fn idle_bytes(&self) -> usize {
        self.free.idle_bytes()
    }

    /// Frees the buffers idle for `idle` or longer at `now`, returning the bytes freed.
    pub fn release_idle(&self, now: std::time::Instant, idle: std::time::Duration) -> usize {
        self.free.release_idle(now, idle)
    }
}

/// Sets the gauge of idle cells: [`CellPool`]'s watcher.
fn set_idle_gauge(bytes: usize) {
    metrics::gauge!(crate::meters::IDLE_CELL_BYTES).set(bytes as f64);
}

/// The cells and AOV sums of deleted frames (and of copies of bands and sums no longer
/// needed), kept for the frames created after them.
///
/// A farm fetches a frame's final, deletes the frame and creates the next one, usually of the
/// same size. Freed, a frame's hundreds of megabytes go back to the kernel, and the next frame
/// faults in as many fresh pages, each zeroed by the kernel; on a virtual machine whose host
/// takes back memory its guest frees, every one of those faults also waits for the host
/// (measured on the 2-core test box: a 1080p frame's first 16 passes took 1.5 s of posting
/// when the memory had been free for 8 s, 1.05 s when it came straight from a deleted frame).
/// Kept here, the next frame's bands take the same memory, zeroed by a `memset` of pages
/// already mapped.
///
/// The same holds for the copies a frame's writers make of bands a snapshot still holds
/// (copy on write, see `frame`): the snapshot gives each band it is done with back here once
/// the frame has moved on to a copy, and the next copy fills it, so a frame written through
/// snapshot after snapshot stops asking the kernel for memory.
///
/// The store keeps what it holds within the cascade budget (`--max-memory-mib`): what the
/// frames hold plus what is kept here never exceeds it at a create (see `FrameStore`), and
/// buffers idle for [`CELL_POOL_IDLE`] go back to the kernel.
#[derive(Debug)]
pub struct CellPool {
    free: splatd_formats::scratch::Pool<Vec<u64>>,
}

/// How long a deleted frame's cells wait for a new frame before they are freed (and, likewise,
/// pass and image scratches and body buffers for their next request: see
/// `AppState::release_idle_until`).
pub const CELL_POOL_IDLE: std::time::Duration = std::time::Duration::from_secs(30);

impl Default for CellPool {
    /// An empty pool that keeps any number of idle buffers (the store bounds what it holds)
    /// and keeps the idle-cells gauge.
    fn default() -> CellPool {
        CellPool {
            free: splatd_formats::scratch::Pool::watched(usize::MAX, set_idle_gauge),
        }
    }
}

impl CellPool {
    /// Idle cells with room for `len` words (the smallest that has) and at most twice that, or
    /// an empty buffer. Either way the contents are garbage until a band is made in them:
    /// [`FrameState::band_in`](splatd_estimator::FrameState::band_in) zeroes them (replacing an
    /// empty buffer with zeroed memory), `clone_in` copies a band into them (growing an empty
    /// one once, to the copy's length). A far larger buffer (a frame's AOV sums, a larger
    /// frame's band) is left for a request of its size, not held by a band that would use a
    /// fraction of it.
    pub fn take(&self, len: usize) -> Vec<u64> {
        self.free.take_fitting(len * 8, len * 16)
    }

    /// Keeps `cells` for a later frame.
    pub fn give(&self, cells: Vec<u64>) {
        if cells.capacity() > 0 {
            self.free.give(cells);
        }
    }

    /// Keeps the cells of `band` if nothing else holds it; a band still shared is left to its
    /// other holders. Its last two holders are a cut that ended and the frame that moved on to
    /// a copy of it, each giving it here, in either order (a snapshot may finish while the
    /// frame's writer is still copying the band): with
    /// [`Arc::into_inner`](std::sync::Arc::into_inner) exactly one of them gets the cells, even
    /// when both let go at the same moment. (Given only by the cut, as
    /// first written, they were freed whenever the copy took longer than the rest of the
    /// snapshot, and the next copy faulted in fresh memory: with a 216 MB copy of AOV sums,
    /// every snapshot's under `loadgen --kind passes --aovs`.)
    pub fn give_band(&self, band: std::sync::Arc<splatd_estimator::FrameState>) {
        if let Some(state) = std::sync::Arc::into_inner(band) {
            self.give(state.into_cells());
        }
    }

    /// Keeps the words of AOV sums nothing else holds, as [`CellPool::give_band`] keeps a
    /// band's cells: a frame's AOV sums are copied on write like its bands.
    pub fn give_aovs(&self, sums: std::sync::Arc<splatd_estimator::AovSums>) {
        if let Some(sums) = std::sync::Arc::into_inner(sums) {
            self.give(sums.into_words());
        }
    }

    /// Frees the cells idle for `idle` or longer at `now` (all of them with zero), returning
    /// the bytes freed.
    pub fn release_idle(&self, now: std::time::Instant, idle: std::time::Duration) -> u64 {
        self.free.release_idle(now, idle) as u64
    }

    /// Bytes held by the idle cells.
    pub fn idle_bytes(&self) -> u64 {
        self.free.idle_bytes() as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The advice leaves the contents alone, and a buffer advised before it is written reads
    /// back what was written (the hint changes the backing, never the values).
    #[test]
    fn advice_keeps_contents() {
        let mut cells = zeroed_cells(3 << 20);
        assert!(cells.iter().all(|&c| c == 0));
        for (i, c) in cells.iter_mut().enumerate() {
            *c = i as u64 * 7;
        }
        advise_huge_pages(&cells).expect("THP is available on Linux test machines");
        assert!(cells.iter().enumerate().all(|(i, &c)| c == i as u64 * 7));
        // Small and empty buffers are left alone.
        advise_huge_pages(&[1u8; 100]).unwrap();
        advise_huge_pages::<u64>(&[]).unwrap();
    }

    /// A band's copy on write (`FrameState::clone_in` of cells from the pool, as
    /// `ShardedFrame::own` makes it) lands in idle cells where the pool has them, else in new
    /// memory with room for the whole copy.
    #[test]
    fn cells_for_a_copy_come_from_the_pool_or_hold_it_whole() {
        let layout = splatd_estimator::CascadeLayout::with_defaults();
        let band = splatd_estimator::FrameState::new(512, 256, layout);
        let len = band.cells().len();
        let pool = CellPool::default();
        let fresh = band.clone_in(pool.take(len)).into_cells();
        assert!(fresh.capacity() >= len);
        assert_eq!(fresh, band.cells());
        let idle = vec![5u64; len + len / 2];
        let at = idle.as_ptr();
        pool.give(idle);
        let copy = band.clone_in(pool.take(len));
        assert_eq!(copy.cells().as_ptr(), at, "the idle cells, not new memory");
        assert_eq!(copy.cells(), band.cells());
        assert_eq!(pool.idle_bytes(), 0);
    }

    /// Readied cells keep their contents; the pages at their ends that no huge page covers are
    /// in memory afterwards, and the pages between them are not touched.
    #[cfg(target_os = "linux")]
    #[test]
    fn readied_cells_have_their_ends_in_memory_and_nothing_else() {
        const PAGE: usize = 4096;
        // Mapped here, not allocated, so that the pages are surely fresh (an allocator may
        // hand back memory an earlier test touched). 13 MiB, as a 1080p frame's band, from
        // 12 KiB past the mapping's start: both ends are partial huge pages wherever the
        // kernel maps it.
        let len = 13 << 20;
        // SAFETY: a new private anonymous mapping; nothing else refers to it.
        let map = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                len,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                -1,
                0,
            )
        };
        assert_ne!(map, libc::MAP_FAILED, "{}", std::io::Error::last_os_error());
        let start = map as usize + 3 * PAGE;
        let words = (len - 3 * PAGE) / 8;
        // SAFETY: inside the mapping, zero-filled by the kernel, aligned for u64, and only read
        // through this slice until it is unmapped below.
        let cells = unsafe { std::slice::from_raw_parts(start as *const u64, words) };
        let resident = |at: usize| {
            let page = at / PAGE * PAGE;
            let mut v = 0u8;
            // SAFETY: `page` is a page-aligned address inside the mapping; one byte out.
            let rc = unsafe { libc::mincore(page as *mut libc::c_void, PAGE, &mut v) };
            assert_eq!(rc, 0, "{}", std::io::Error::last_os_error());
            v & 1 == 1
        };
        let end = start + words * 8;
        let head = start.next_multiple_of(HUGE);
        let tail = end / HUGE * HUGE;
        assert!(!resident(start) && !resident(end - 1), "a fresh mapping");

        ready_cells(cells);

        for at in (start..head).chain(tail..end).step_by(PAGE) {
            assert!(resident(at), "page at {:#x} of the ends", at - start);
        }
        let middle = (head + tail) / 2;
        assert!(
            !resident(head) && !resident(middle),
            "pages between the ends stay untouched"
        );
        assert!(cells.iter().all(|&c| c == 0), "contents unchanged");
        // SAFETY: the mapping made above; `cells` is not used after this.
        assert_eq!(unsafe { libc::munmap(map, len) }, 0);
    }
}
