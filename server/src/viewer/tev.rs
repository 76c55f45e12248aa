//! Live view of resolved frames in the [tev](https://github.com/Tom94/tev) image viewer.
//!
//! `splatd serve --tev HOST:PORT` pushes every resolved frame to a running tev over tev's TCP
//! protocol (start tev first; it listens on `127.0.0.1:14158` by default). Each frame becomes
//! one tev image with nine channels: the reweighted estimate as `R`, `G`, `B` (tev shows it
//! first) and the layers `mean.R/G/B` and `removed.R/G/B`, the same names as in the EXRs
//! [`splatd_formats::exr`] writes, so tev's layer list is the same for a live frame and a saved one.
//!
//! The packets are written by the `tev_client` crate: a create-image packet the first time a
//! name is shown (or when its size changed), then update-image packets on every call. Updates
//! go in tiles of at most [`MAX_PIXELS_PER_UPDATE`] pixels, so no packet exceeds about 300 KB
//! whatever the frame size: tev reads packets into a 1 MiB buffer that it grows to fit, and a
//! single packet for a whole 4K frame would be 300 MB held twice, once by each side.
//!
//! This is blocking code (std sockets, with connect and write timeouts). The server calls it
//! from `spawn_blocking` or a dedicated thread, never on an async worker.
//!
//! # Errors and reconnecting
//!
//! tev is a viewer; it may be closed and reopened while splatd runs. A failed write leaves the
//! stream in an unknown place mid-packet, so after any send error the connection is dropped and
//! the error returned; the **next** [`TevSink::show`] reconnects (one attempt, bounded by
//! [`CONNECT_TIMEOUT`]) and creates its image again, since a new tev has none. While tev stays
//! away each call costs one refused or timed-out connection attempt and returns an error;
//! callers log it and carry on.

use std::collections::HashMap;
use std::io;
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::time::Duration;

use tev_client::{PacketCreateImage, PacketUpdateImage, TevClient};

use splatd_estimator::Resolved;

/// How long a connection attempt to tev may take.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(2);

/// How long one write to tev may block (tev busy or hung) before the send fails.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(10);

/// Most pixels in one update packet: 8192 pixels of 9 `f32` channels, 288 KiB of pixel data.
pub const MAX_PIXELS_PER_UPDATE: usize = 8192;

/// The channels of every image, in the order their values are interleaved per pixel.
pub const CHANNELS: [&str; 9] = [
    "R",
    "G",
    "B",
    "mean.R",
    "mean.G",
    "mean.B",
    "removed.R",
    "removed.G",
    "removed.B",
];

const CHANNEL_OFFSETS: [u64; 9] = [0, 1, 2, 3, 4, 5, 6, 7, 8];
const CHANNEL_STRIDES: [u64; 9] = [9; 9];

/// Why a frame could not be shown in tev.
#[derive(Debug, thiserror::Error)]
pub enum TevError {
    /// No connection could be made (tev not running, wrong address, timeout).
    #[error("could not connect to tev at {addr}: {source}")]
    Connect {
        /// The address given.
        addr: String,
        /// What went wrong.
        source: io::Error,
    },
    /// A packet could not be written; the connection was dropped.
    #[error(
        "sending image {image:?} to tev at {addr} failed: {source} \
         (the connection was dropped; the next frame reconnects)"
    )]
    Send {
        /// The address of tev.
        addr: String,
        /// The image being sent.
        image: String,
        /// What went wrong.
        source: io::Error,
    },
    /// The image name cannot travel in tev's protocol.
    #[error("image name {name:?} cannot be shown in tev: {reason}")]
    ImageName {
        /// The name given.
        name: String,
        /// Why it is refused.
        reason: &'static str,
    },
    /// The resolved frame's layers do not have `width * height` pixels.
    #[error("resolved frame {name:?} is {width}x{height} but its {layer} layer has {len} pixels")]
    Inconsistent {
        /// The image name.
        name: String,
        /// Width of the frame.
        width: u32,
        /// Height of the frame.
        height: u32,
        /// The layer of the wrong length.
        layer: &'static str,
        /// Its length.
        len: usize,
    },
}

/// A connection to tev that resolved frames are shown through.
///
/// ```no_run
/// # fn demo(resolved: &splatd_estimator::Resolved) -> Result<(), splatd_server::viewer::tev::TevError> {
/// let mut tev = splatd_server::viewer::tev::TevSink::connect("127.0.0.1:14158")?;
/// tev.show("shot010.beauty", resolved)?; // creates the image
/// tev.show("shot010.beauty", resolved)?; // updates it
/// # Ok(()) }
/// ```
#[derive(Debug)]
pub struct TevSink {
    addr: String,
    client: Option<TevClient>,
    /// Images created over the current connection, with their size.
    created: HashMap<String, (u32, u32)>,
    /// Interleaved pixel data of one tile, reused between packets.
    tile: Vec<f32>,
}

impl TevSink {
    /// Connects to tev at `addr` (`host:port`), waiting at most [`CONNECT_TIMEOUT`] per address
    /// the name resolves to.
    ///
    /// # Errors
    /// [`TevError::Connect`] if no address accepts the connection.
    pub fn connect(addr: &str) -> Result<TevSink, TevError> {
        let client = open(addr)?;
        Ok(TevSink {
            addr: addr.to_string(),
            client: Some(client),
            created: HashMap::new(),
            tile: Vec::new(),
        })
    }

    /// The address of tev.
    pub fn addr(&self) -> &str {
        &self.addr
    }

    /// Whether the sink holds a connection (false after a failed send, until the next `show`
    /// reconnects).
    pub fn is_connected(&self) -> bool {
        self.client.is_some()
    }

    /// Shows a resolved frame as the tev image `name`: creates the image the first time the
    /// name is shown over this connection (or when the frame's size changed), then sends all
    /// its pixels as updates. A frame with no pixels sends nothing.
    ///
    /// Reconnects first if an earlier call failed (see the module docs).
    ///
    /// # Errors
    /// [`TevError::ImageName`] for an empty name or one containing a NUL byte (tev's strings
    /// are NUL-terminated), [`TevError::Inconsistent`] for a malformed [`Resolved`] (both
    /// checked before anything is sent), [`TevError::Connect`] if reconnecting failed and
    /// [`TevError::Send`] if a packet could not be written.
    pub fn show(&mut self, name: &str, resolved: &Resolved) -> Result<(), TevError> {
        check_name(name)?;
        check_resolved(name, resolved)?;
        let (width, height) = (resolved.width, resolved.height);
        if width == 0 || height == 0 {
            return Ok(());
        }
        let mut client = match self.client.take() {
            Some(client) => client,
            None => {
                // A new connection may be a new tev: it has none of the images.
                self.created.clear();
                open(&self.addr)?
            }
        };
        match self.send_frame(&mut client, name, resolved) {
            Ok(()) => {
                self.client = Some(client);
                Ok(())
            }
            Err(source) => Err(TevError::Send {
                addr: self.addr.clone(),
                image: name.to_string(),
                source,
            }),
        }
    }

    fn send_frame(
        &mut self,
        client: &mut TevClient,
        name: &str,
        resolved: &Resolved,
    ) -> io::Result<()> {
        let (width, height) = (resolved.width, resolved.height);
        if self.created.get(name) != Some(&(width, height)) {
            // Creating an image with a name tev already shows replaces it.
            client.send(PacketCreateImage {
                image_name: name,
                grab_focus: false,
                width,
                height,
                channel_names: &CHANNELS,
            })?;
            self.created.insert(name.to_string(), (width, height));
        }
        for (x, y, w, h) in tiles(width, height) {
            self.tile.clear();
            for row in y..y + h {
                let start = row as usize * width as usize + x as usize;
                for i in start..start + w as usize {
                    self.tile.extend_from_slice(&resolved.reweighted[i]);
                    self.tile.extend_from_slice(&resolved.mean[i]);
                    self.tile.extend_from_slice(&resolved.removed[i]);
                }
            }
            client.send(PacketUpdateImage {
                image_name: name,
                grab_focus: false,
                channel_names: &CHANNELS,
                channel_offsets: &CHANNEL_OFFSETS,
                channel_strides: &CHANNEL_STRIDES,
                x,
                y,
                width: w,
                height: h,
                data: &self.tile,
            })?;
        }
        Ok(())
    }
}

/// Opens a connection with the timeouts set.
fn open(addr: &str) -> Result<TevClient, TevError> {
    let fail = |source| TevError::Connect {
        addr: addr.to_string(),
        source,
    };
    let candidates: Vec<SocketAddr> = addr.to_socket_addrs().map_err(fail)?.collect();
    let mut last = io::Error::new(
        io::ErrorKind::InvalidInput,
        "the address resolved to no socket address",
    );
    for candidate in candidates {
        match TcpStream::connect_timeout(&candidate, CONNECT_TIMEOUT) {
            Ok(stream) => {
                stream
                    .set_write_timeout(Some(WRITE_TIMEOUT))
                    .map_err(fail)?;
                // Packets are written whole; do not hold back the last segment of one.
                stream.set_nodelay(true).map_err(fail)?;
                return Ok(TevClient::wrap(stream));
            }
            Err(e) => last = e,
        }
    }
    Err(fail(last))
}

/// Refuses what `tev_client` would panic on and tev could not parse.
fn check_name(name: &str) -> Result<(), TevError> {
    let reason = if name.is_empty() {
        "it is empty"
    } else if name.contains('\0') {
        "it contains a NUL byte, which ends strings in tev's protocol"
    } else {
        return Ok(());
    };
    Err(TevError::ImageName {
        name: name.to_string(),
        reason,
    })
}

/// Every layer must have `width * height` pixels: the tiles index them without checks.
fn check_resolved(name: &str, r: &Resolved) -> Result<(), TevError> {
    let pixels = r.width as usize * r.height as usize;
    for (layer, len) in [
        ("reweighted", r.reweighted.len()),
        ("mean", r.mean.len()),
        ("removed", r.removed.len()),
    ] {
        if len != pixels {
            return Err(TevError::Inconsistent {
                name: name.to_string(),
                width: r.width,
                height: r.height,
                layer,
                len,
            });
        }
    }
    Ok(())
}

/// `(x, y, width, height)` tiles covering a non-empty frame row-major, each of at most
/// [`MAX_PIXELS_PER_UPDATE`] pixels: whole rows, or pieces of one row for very wide frames.
fn tiles(width: u32, height: u32) -> impl Iterator<Item = (u32, u32, u32, u32)> {
    let max = MAX_PIXELS_PER_UPDATE as u32;
    let tile_w = width.min(max);
    let tile_h = (max / tile_w).max(1);
    (0..height).step_by(tile_h as usize).flat_map(move |y| {
        (0..width)
            .step_by(tile_w as usize)
            .map(move |x| (x, y, tile_w.min(width - x), tile_h.min(height - y)))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn covered(width: u32, height: u32) -> Vec<u32> {
        let mut hits = vec![0u32; (width * height) as usize];
        for (x, y, w, h) in tiles(width, height) {
            assert!(w >= 1 && h >= 1 && (w * h) as usize <= MAX_PIXELS_PER_UPDATE);
            for row in y..y + h {
                for col in x..x + w {
                    hits[(row * width + col) as usize] += 1;
                }
            }
        }
        hits
    }

    #[test]
    fn tiles_cover_every_pixel_once_and_stay_small() {
        for (w, h) in [
            (1, 1),
            (37, 23),
            (8192, 3),
            (8193, 2),
            (20000, 2),
            (3, 9000),
        ] {
            assert!(covered(w, h).iter().all(|&n| n == 1), "{w}x{h}");
        }
    }

    #[test]
    fn names_tev_cannot_carry_are_refused() {
        assert!(check_name("shot010.beauty").is_ok());
        let err = check_name("a\0b").unwrap_err();
        assert!(err.to_string().contains("NUL"), "{err}");
        assert!(check_name("").is_err());
    }
}
