//! An independent decoder of tev's IPC protocol and a tev stand-in, shared by the tests of
//! `splatd_server::viewer::tev` and of `splatd serve --tev` (see `tests/tev_protocol.rs` for the packet layouts).

use std::collections::HashMap;
use std::io::{ErrorKind, Read};
use std::net::{TcpListener, TcpStream};
use std::thread;
use std::time::Duration;

use splatd_estimator::Resolved;

/// How long the stand-in waits for bytes before it calls the test hung: the harness's one cap
/// against hanging, not a deadline (every read ends as soon as its bytes or the close arrive).
pub const READ_TIMEOUT: Duration = splatd_harness::PATIENCE;
/// Most packets one connection may bring (a runaway sender fails the test instead of hanging).
pub const MAX_PACKETS: usize = 10_000;
/// The largest packet the stand-in accepts.
pub const MAX_PACKET_BYTES: usize = 64 << 20;

pub const NAMES: [&str; 9] = [
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

#[derive(Debug, Clone, PartialEq)]
pub enum Packet {
    Create {
        grab_focus: bool,
        name: String,
        width: i32,
        height: i32,
        channels: Vec<String>,
    },
    Update {
        grab_focus: bool,
        name: String,
        channels: Vec<String>,
        x: i32,
        y: i32,
        width: i32,
        height: i32,
        /// `values[c][p]`: channel `c` of pixel `p` of the tile, row-major.
        values: Vec<Vec<f32>>,
    },
    Other(u8),
}

/// Reads little-endian fields off one packet's payload.
pub struct Fields<'a> {
    pub bytes: &'a [u8],
    pub at: usize,
}

impl<'a> Fields<'a> {
    fn take(&mut self, n: usize, what: &str) -> &'a [u8] {
        assert!(
            self.at + n <= self.bytes.len(),
            "packet ends inside {what} (at byte {} of {})",
            self.at,
            self.bytes.len()
        );
        let out = &self.bytes[self.at..self.at + n];
        self.at += n;
        out
    }
    fn u8(&mut self, what: &str) -> u8 {
        self.take(1, what)[0]
    }
    fn bool(&mut self, what: &str) -> bool {
        match self.u8(what) {
            0 => false,
            1 => true,
            other => panic!("{what}: a bool must be 0 or 1, got {other}"),
        }
    }
    fn i32(&mut self, what: &str) -> i32 {
        i32::from_le_bytes(self.take(4, what).try_into().unwrap())
    }
    fn i64(&mut self, what: &str) -> i64 {
        i64::from_le_bytes(self.take(8, what).try_into().unwrap())
    }
    fn string(&mut self, what: &str) -> String {
        let rest = &self.bytes[self.at..];
        let end = rest
            .iter()
            .position(|&b| b == 0)
            .unwrap_or_else(|| panic!("{what}: string without its NUL terminator"));
        let s = String::from_utf8(rest[..end].to_vec()).expect("UTF-8 string");
        self.at += end + 1;
        s
    }
    fn strings(&mut self, n: usize, what: &str) -> Vec<String> {
        (0..n).map(|_| self.string(what)).collect()
    }
    fn rest_f32(&mut self) -> Vec<f32> {
        let rest = &self.bytes[self.at..];
        assert_eq!(rest.len() % 4, 0, "pixel data is not whole f32s");
        self.at = self.bytes.len();
        rest.chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }
}

/// Decodes one packet (its bytes after the length field).
pub fn decode(payload: &[u8]) -> Packet {
    let mut f = Fields {
        bytes: payload,
        at: 0,
    };
    let kind = f.u8("type");
    let packet = match kind {
        4 => {
            let grab_focus = f.bool("grab focus");
            let name = f.string("image name");
            let width = f.i32("width");
            let height = f.i32("height");
            let n = f.i32("channel count");
            assert!((0..=1024).contains(&n), "channel count {n}");
            let channels = f.strings(n as usize, "channel name");
            Packet::Create {
                grab_focus,
                name,
                width,
                height,
                channels,
            }
        }
        3 | 5 | 6 => {
            let grab_focus = f.bool("grab focus");
            let name = f.string("image name");
            let n = if kind == 3 { 1 } else { f.i32("channel count") };
            assert!((1..=1024).contains(&n), "channel count {n}");
            let n = n as usize;
            let channels = f.strings(n, "channel name");
            let (x, y) = (f.i32("x"), f.i32("y"));
            let (width, height) = (f.i32("width"), f.i32("height"));
            assert!(width > 0 && height > 0, "empty update {width}x{height}");
            let pixels = width as usize * height as usize;
            let (offsets, strides): (Vec<i64>, Vec<i64>) = if kind == 6 {
                let offsets = (0..n).map(|_| f.i64("offset")).collect();
                (offsets, (0..n).map(|_| f.i64("stride")).collect())
            } else {
                ((0..n).map(|c| (c * pixels) as i64).collect(), vec![1; n])
            };
            let data = f.rest_f32();
            let used = offsets
                .iter()
                .zip(&strides)
                .map(|(&o, &s)| o + (pixels as i64 - 1) * s + 1)
                .max()
                .unwrap();
            assert_eq!(data.len() as i64, used, "data size of the update");
            let values = offsets
                .iter()
                .zip(&strides)
                .map(|(&o, &s)| {
                    (0..pixels)
                        .map(|p| data[(o + p as i64 * s) as usize])
                        .collect()
                })
                .collect();
            Packet::Update {
                grab_focus,
                name,
                channels,
                x,
                y,
                width,
                height,
                values,
            }
        }
        other => return Packet::Other(other),
    };
    assert_eq!(
        f.at,
        payload.len(),
        "trailing bytes after a type {kind} packet"
    );
    packet
}

/// Reads one packet: `None` at a clean end of stream.
pub fn read_packet(stream: &mut TcpStream) -> Option<(usize, Packet)> {
    let mut len = [0u8; 4];
    match stream.read_exact(&mut len) {
        Ok(()) => {}
        Err(e) if e.kind() == ErrorKind::UnexpectedEof => return None,
        Err(e) => panic!("reading a packet length: {e}"),
    }
    let len = u32::from_le_bytes(len) as usize;
    assert!((5..=MAX_PACKET_BYTES).contains(&len), "packet length {len}");
    let mut payload = vec![0u8; len - 4];
    stream
        .read_exact(&mut payload)
        .unwrap_or_else(|e| panic!("reading a {len}-byte packet: {e}"));
    Some((len, decode(&payload)))
}

/// The packets of one connection, each with its length in bytes.
pub type Packets = Vec<(usize, Packet)>;

/// Every packet of a connection until the peer closes it.
pub fn read_all(mut stream: TcpStream) -> Packets {
    stream.set_read_timeout(Some(READ_TIMEOUT)).unwrap();
    let mut packets = Vec::new();
    while let Some(p) = read_packet(&mut stream) {
        packets.push(p);
        assert!(packets.len() <= MAX_PACKETS, "too many packets");
    }
    packets
}

/// An image as tev would hold it after the packets.
#[derive(Debug)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub channels: Vec<String>,
    pub planes: Vec<Vec<f32>>,
    /// How often each pixel was written by updates.
    pub writes: Vec<u32>,
    /// The whole image each time every pixel had been written once more.
    pub snapshots: Vec<Vec<Vec<f32>>>,
}

pub fn reassemble(packets: &[(usize, Packet)]) -> HashMap<String, Image> {
    let mut images: HashMap<String, Image> = HashMap::new();
    for (_, packet) in packets {
        match packet {
            Packet::Create {
                name,
                width,
                height,
                channels,
                ..
            } => {
                let (w, h) = (*width as usize, *height as usize);
                images.insert(
                    name.clone(),
                    Image {
                        width: w,
                        height: h,
                        channels: channels.clone(),
                        planes: vec![vec![f32::NAN; w * h]; channels.len()],
                        writes: vec![0; w * h],
                        snapshots: Vec::new(),
                    },
                );
            }
            Packet::Update {
                name,
                channels,
                x,
                y,
                width,
                height,
                values,
                ..
            } => {
                let image = images
                    .get_mut(name)
                    .unwrap_or_else(|| panic!("update of image {name:?} before its creation"));
                let (x, y, w, h) = (*x as usize, *y as usize, *width as usize, *height as usize);
                assert!(
                    x + w <= image.width && y + h <= image.height,
                    "tile ({x}, {y}) {w}x{h} outside the {}x{} image",
                    image.width,
                    image.height
                );
                for (c, channel) in channels.iter().enumerate() {
                    let plane = image
                        .channels
                        .iter()
                        .position(|n| n == channel)
                        .unwrap_or_else(|| panic!("update of unknown channel {channel:?}"));
                    for row in 0..h {
                        for col in 0..w {
                            let at = (y + row) * image.width + x + col;
                            image.planes[plane][at] = values[c][row * w + col];
                        }
                    }
                }
                for row in 0..h {
                    for col in 0..w {
                        image.writes[(y + row) * image.width + x + col] += 1;
                    }
                }
                let k = image.writes[0];
                if image.writes.iter().all(|&n| n == k) && k as usize > image.snapshots.len() {
                    image.snapshots.push(image.planes.clone());
                }
            }
            Packet::Other(kind) => panic!("unexpected packet type {kind}"),
        }
    }
    images
}

/// The planes a `Resolved` should arrive as, in [`NAMES`] order.
pub fn planes_of(r: &Resolved) -> Vec<Vec<f32>> {
    let mut planes = Vec::new();
    for layer in [&r.reweighted, &r.mean, &r.removed] {
        for c in 0..3 {
            planes.push(layer.iter().map(|p| p[c]).collect());
        }
    }
    planes
}

pub fn assert_planes_equal(what: &str, got: &[Vec<f32>], r: &Resolved) {
    let want = planes_of(r);
    assert_eq!(got.len(), want.len(), "{what}: channel count");
    for (c, (g, w)) in got.iter().zip(&want).enumerate() {
        for (i, (a, b)) in g.iter().zip(w).enumerate() {
            assert!(
                a.to_bits() == b.to_bits(),
                "{what}: channel {} of pixel ({}, {}) arrived as {a} but was {b}",
                NAMES[c],
                i % r.width as usize,
                i / r.width as usize
            );
        }
    }
}

/// A tev stand-in: accepts `connections` connections in turn and sends each one's packets back.
pub fn stand_in(connections: usize) -> (String, thread::JoinHandle<Vec<Packets>>) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("a loopback port");
    let addr = listener.local_addr().unwrap().to_string();
    let handle = thread::spawn(move || {
        (0..connections)
            .map(|_| read_all(listener.accept().expect("a connection").0))
            .collect()
    });
    (addr, handle)
}
