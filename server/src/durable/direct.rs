//! Snapshots written around the page cache (`O_DIRECT`), from a buffer the server keeps.
//!
//! A 1080p frame's snapshot is about 400 MB, written again every second or two while workers
//! post. Through the page cache every byte is first copied into pages the kernel has to find,
//! and on a virtual machine whose host takes back the memory a guest frees, fault in, before
//! writeback sends them to the disk: in a profile of `loadgen --config "--data-dir {tmp}"` that
//! copy (`copy_folio_from_iter_atomic`) took 17.5 % of the machine, more than all the splatting.
//! With `O_DIRECT` the disk takes the bytes straight from one [`BUFFER`]-byte buffer the server
//! keeps warm, and the page cache is not filled with a file nobody reads until a restart.
//!
//! Direct writes must start at an aligned offset, from aligned memory, in whole blocks: the
//! writer sends whole buffers, pads the last block with zeros and cuts the file back to its
//! length. A file system that refuses `O_DIRECT` (at `fcntl`, or with `EINVAL` at the first
//! write) gets ordinary writes of the same bytes instead. Syncing stays the caller's job.

use std::fs::File;
use std::io::{self, Write};

/// Alignment of direct writes: offsets, memory and lengths. 4096 covers both 512-byte and
/// 4 KiB logical blocks.
pub(super) const ALIGN: usize = 4096;
/// Bytes of the buffer snapshots are written from: large enough that each write is one long
/// transfer, small enough to keep for the server's life.
pub(super) const BUFFER: usize = 4 << 20;

/// One aligned block of a [`DirectBuffer`].
#[derive(Clone, Copy)]
#[repr(C, align(4096))]
struct Block([u8; ALIGN]);

/// Memory that direct writes can be sent from: whole [`ALIGN`]ed blocks.
pub(super) struct DirectBuffer {
    blocks: Vec<Block>,
}

impl std::fmt::Debug for DirectBuffer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "DirectBuffer({} bytes)", self.len())
    }
}

impl DirectBuffer {
    /// A buffer of at least `bytes` (at least one block).
    pub(super) fn new(bytes: usize) -> DirectBuffer {
        DirectBuffer {
            blocks: vec![Block([0; ALIGN]); bytes.div_ceil(ALIGN).max(1)],
        }
    }

    fn len(&self) -> usize {
        self.blocks.len() * ALIGN
    }

    fn bytes(&mut self) -> &mut [u8] {
        let len = self.len();
        // SAFETY: `Block` is a plain byte array without padding (`repr(C)`, size == align ==
        // ALIGN), so the vector's blocks are `len` initialized, contiguous bytes, borrowed
        // mutably through `self` for the slice's lifetime.
        unsafe { std::slice::from_raw_parts_mut(self.blocks.as_mut_ptr().cast::<u8>(), len) }
    }
}

/// Writes a new file through a [`DirectBuffer`]; [`DirectWriter::finish`] writes the rest.
pub(super) struct DirectWriter<'a> {
    file: &'a File,
    buffer: &'a mut DirectBuffer,
    filled: usize,
    /// Bytes given to the writer so far: the file's length once finished.
    length: u64,
    direct: bool,
}

impl<'a> DirectWriter<'a> {
    /// A writer of `file`, which must be empty and opened for writing; it writes around the
    /// page cache if the file system lets it.
    pub(super) fn new(file: &'a File, buffer: &'a mut DirectBuffer) -> DirectWriter<'a> {
        let direct = match set_direct(file, true) {
            Ok(()) => true,
            Err(e) => {
                refused(&e);
                false
            }
        };
        DirectWriter {
            file,
            buffer,
            filled: 0,
            length: 0,
            direct,
        }
    }

    /// Whether writes still go around the page cache.
    #[cfg(test)]
    pub(super) fn is_direct(&self) -> bool {
        self.direct
    }

    /// Writes what the buffer holds and gives the file its length. The caller syncs it.
    pub(super) fn finish(mut self) -> io::Result<()> {
        if self.filled == 0 {
            return Ok(());
        }
        let padded = self.direct;
        if padded {
            // Whole blocks only: the tail of the last one is zeros, cut off below (also when the
            // write falls back to the page cache on the way, padding and all).
            let end = self.filled.next_multiple_of(ALIGN);
            self.buffer.bytes()[self.filled..end].fill(0);
            self.filled = end;
        }
        self.drain()?;
        if padded {
            self.file.set_len(self.length)?;
        }
        Ok(())
    }

    /// Sends the buffer's `filled` bytes to the file, falling back to ordinary writes if the
    /// file system refuses a direct one.
    fn drain(&mut self) -> io::Result<()> {
        let DirectWriter {
            file,
            buffer,
            filled,
            direct,
            ..
        } = self;
        let mut pending = &buffer.bytes()[..*filled];
        while !pending.is_empty() {
            let written = match *direct {
                true => crate::failpoint::hit("direct_write").and_then(|()| file.write(pending)),
                false => file.write(pending),
            };
            match written {
                Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
                Ok(n) => pending = &pending[n..],
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) if *direct && e.raw_os_error() == Some(libc::EINVAL) => {
                    refused(&e);
                    set_direct(file, false)?;
                    *direct = false;
                }
                Err(e) => return Err(e),
            }
        }
        *filled = 0;
        Ok(())
    }
}

impl Write for DirectWriter<'_> {
    fn write(&mut self, data: &[u8]) -> io::Result<usize> {
        let room = self.buffer.len() - self.filled;
        let n = data.len().min(room);
        let filled = self.filled;
        self.buffer.bytes()[filled..filled + n].copy_from_slice(&data[..n]);
        self.filled += n;
        self.length += n as u64;
        if self.filled == self.buffer.len() {
            self.drain()?;
        }
        Ok(n)
    }

    /// A no-op: direct writes go in whole blocks, so a partial one waits for
    /// [`DirectWriter::finish`].
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// Says (at debug level: on such a file system it is every snapshot, and nothing is wrong) that
/// a file is written through the page cache after all.
fn refused(e: &io::Error) {
    tracing::debug!(error = %e, "direct writes refused; this file goes through the page cache");
}

/// Turns `O_DIRECT` on or off for `file`.
fn set_direct(file: &File, on: bool) -> io::Result<()> {
    use std::os::fd::AsRawFd;
    let fd = file.as_raw_fd();
    // SAFETY: fcntl with F_GETFL/F_SETFL only reads and sets the flags of a descriptor this
    // function borrows for the call.
    let flags = unsafe { libc::fcntl(fd, libc::F_GETFL) };
    if flags < 0 {
        return Err(io::Error::last_os_error());
    }
    let flags = match on {
        true => flags | libc::O_DIRECT,
        false => flags & !libc::O_DIRECT,
    };
    // SAFETY: as above.
    if unsafe { libc::fcntl(fd, libc::F_SETFL, flags) } < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    /// Bytes of `len` that differ from block to block and from their zero padding.
    fn pattern(len: usize) -> Vec<u8> {
        (0..len).map(|i| (i % 251) as u8 + 1).collect()
    }

    /// Writes `data` in pieces of `piece` bytes and reads the file back with a plain read.
    fn round_trip(data: &[u8], piece: usize, buffer: &mut DirectBuffer) -> (Vec<u8>, bool) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out");
        let file = File::create(&path).unwrap();
        let mut w = DirectWriter::new(&file, buffer);
        for chunk in data.chunks(piece.max(1)) {
            w.write_all(chunk).unwrap();
        }
        let direct = w.is_direct();
        w.finish().unwrap();
        drop(file);
        let mut back = Vec::new();
        File::open(&path).unwrap().read_to_end(&mut back).unwrap();
        (back, direct)
    }

    #[test]
    fn every_length_reads_back_exactly() {
        let mut buffer = DirectBuffer::new(3 * ALIGN);
        let mut direct = false;
        for len in [0, 1, ALIGN - 1, ALIGN, ALIGN + 1, 3 * ALIGN, 7 * ALIGN + 5] {
            for piece in [1, 7, ALIGN, 5 * ALIGN] {
                let data = pattern(len);
                let (back, d) = round_trip(&data, piece, &mut buffer);
                assert_eq!(back.len(), len, "length {len} in pieces of {piece}");
                assert!(back == data, "bytes of length {len} in pieces of {piece}");
                direct |= d;
            }
        }
        if !direct {
            eprintln!("SKIP (part): the temporary directory's file system refuses O_DIRECT");
        }
    }

    #[test]
    fn a_buffer_is_aligned_for_direct_writes() {
        let mut buffer = DirectBuffer::new(1);
        assert_eq!(buffer.len(), ALIGN);
        assert_eq!(buffer.bytes().as_ptr() as usize % ALIGN, 0);
    }
}
