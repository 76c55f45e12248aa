//! `splatd::tev` against an independent decoder of tev's IPC protocol.
//!
//! The decoder below is written from tev's own source (`src/Ipc.cpp`, `include/tev/Ipc.h`),
//! not from `tev_client`: every packet is `u32` little-endian length (counting itself), a `u8`
//! type, then fields. Integers are little-endian, booleans one byte, strings NUL-terminated.
//!
//! * create image (4): grab focus, name, `i32` width, `i32` height, `i32` channel count, names;
//! * update image (3): grab focus, name, one channel name, `i32` x, y, width, height, planar
//!   `f32` data;
//! * update image v2 (5): like 3 with an `i32` channel count and that many names;
//! * update image v3 (6): like 5, then `i64` offset and `i64` stride per channel, then `f32`
//!   data where channel `c` of pixel `p` is at `offset[c] + p * stride[c]`.
//!
//! A tev stand-in listens on 127.0.0.1 (port 0) in a thread, decodes every packet and
//! reassembles the images; the tests compare them with the `Resolved` that was shown.

use std::collections::HashMap;
use std::io::{ErrorKind, Read};
use std::net::{TcpListener, TcpStream};
use std::sync::mpsc;
use std::thread;
use std::time::Duration;

use splatd::core::{CascadeLayout, FrameState, ResolveParams, Resolved};
use splatd::tev::{TevError, TevSink, MAX_PIXELS_PER_UPDATE};

/// How long the stand-in waits for bytes before it gives up on a test.
const READ_TIMEOUT: Duration = Duration::from_secs(20);
/// Most packets one connection may bring (a runaway sender fails the test instead of hanging).
const MAX_PACKETS: usize = 10_000;
/// The largest packet the stand-in accepts.
const MAX_PACKET_BYTES: usize = 64 << 20;

const NAMES: [&str; 9] = [
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
enum Packet {
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
struct Fields<'a> {
    bytes: &'a [u8],
    at: usize,
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
fn decode(payload: &[u8]) -> Packet {
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
fn read_packet(stream: &mut TcpStream) -> Option<(usize, Packet)> {
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
type Packets = Vec<(usize, Packet)>;

/// Every packet of a connection until the peer closes it.
fn read_all(mut stream: TcpStream) -> Packets {
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
struct Image {
    width: usize,
    height: usize,
    channels: Vec<String>,
    planes: Vec<Vec<f32>>,
    /// How often each pixel was written by updates.
    writes: Vec<u32>,
    /// The whole image each time every pixel had been written once more.
    snapshots: Vec<Vec<Vec<f32>>>,
}

fn reassemble(packets: &[(usize, Packet)]) -> HashMap<String, Image> {
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
fn planes_of(r: &Resolved) -> Vec<Vec<f32>> {
    let mut planes = Vec::new();
    for layer in [&r.reweighted, &r.mean, &r.removed] {
        for c in 0..3 {
            planes.push(layer.iter().map(|p| p[c]).collect());
        }
    }
    planes
}

fn assert_planes_equal(what: &str, got: &[Vec<f32>], r: &Resolved) {
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

/// A frame with dim samples everywhere and a few fireflies, so every layer has content.
fn splat_some(state: &mut FrameState, seed: u64, per_pixel: u32) {
    let mut s = seed | 1;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f32 / (1u64 << 53) as f32
    };
    for y in 0..state.height() {
        for x in 0..state.width() {
            for _ in 0..per_pixel {
                let v = next();
                let scale = if next() < 0.02 { 5000.0 } else { 1.0 };
                state
                    .splat(x, y, [v * scale, v * 0.5 * scale, next() * scale])
                    .expect("valid sample");
            }
        }
    }
}

/// A tev stand-in: accepts `connections` connections in turn and sends each one's packets back.
fn stand_in(connections: usize) -> (String, thread::JoinHandle<Vec<Packets>>) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("a loopback port");
    let addr = listener.local_addr().unwrap().to_string();
    let handle = thread::spawn(move || {
        (0..connections)
            .map(|_| read_all(listener.accept().expect("a connection").0))
            .collect()
    });
    (addr, handle)
}

#[test]
fn a_frame_is_created_once_then_updated_with_the_resolved_values() {
    let (addr, tev) = stand_in(1);
    let (w, h) = (37, 23);
    let mut state = FrameState::new(w, h, CascadeLayout::with_defaults());
    let params = ResolveParams::with_defaults();
    splat_some(&mut state, 1, 4);
    let first = state.resolve(&params);
    splat_some(&mut state, 2, 12);
    let second = state.resolve(&params);
    assert_ne!(first, second);
    assert!(
        second.removed.iter().any(|p| p[0] > 0.0),
        "fireflies removed"
    );

    let mut sink = TevSink::connect(&addr).expect("connect to the stand-in");
    sink.show("shot010.beauty", &first).expect("first show");
    sink.show("shot010.beauty", &second).expect("second show");
    sink.show("other", &first).expect("a second image");
    drop(sink);
    let packets = tev.join().expect("the stand-in").remove(0);

    let creates: Vec<&Packet> = packets
        .iter()
        .map(|(_, p)| p)
        .filter(|p| matches!(p, Packet::Create { .. }))
        .collect();
    assert_eq!(creates.len(), 2, "one create per image name");
    assert_eq!(
        packets[0].1,
        Packet::Create {
            grab_focus: false,
            name: "shot010.beauty".into(),
            width: w as i32,
            height: h as i32,
            channels: NAMES.iter().map(|s| s.to_string()).collect(),
        }
    );
    let images = reassemble(&packets);
    let beauty = &images["shot010.beauty"];
    assert_eq!(beauty.snapshots.len(), 2, "every pixel sent once per show");
    assert_planes_equal("first show", &beauty.snapshots[0], &first);
    assert_planes_equal("second show", &beauty.snapshots[1], &second);
    assert_planes_equal("other image", &images["other"].planes, &first);
}

#[test]
fn wide_frames_travel_in_packets_of_bounded_size() {
    let (addr, tev) = stand_in(1);
    let (w, h) = (MAX_PIXELS_PER_UPDATE as u32 + 5, 3);
    let mut state = FrameState::new(w, h, CascadeLayout::with_defaults());
    splat_some(&mut state, 3, 1);
    let resolved = state.resolve(&ResolveParams::with_defaults());

    let mut sink = TevSink::connect(&addr).expect("connect to the stand-in");
    sink.show("wide", &resolved).expect("show");
    drop(sink);
    let packets = tev.join().expect("the stand-in").remove(0);

    let bound = MAX_PIXELS_PER_UPDATE * NAMES.len() * 4 + 1024;
    for (len, _) in &packets {
        assert!(*len <= bound, "a {len}-byte packet, more than {bound}");
    }
    assert_eq!(
        packets.len(),
        1 + 2 * h as usize,
        "a create, then every row in two pieces"
    );
    assert_planes_equal("wide", &reassemble(&packets)["wide"].planes, &resolved);
}

#[test]
fn after_tev_goes_away_the_next_show_reconnects_and_recreates() {
    let listener = TcpListener::bind("127.0.0.1:0").expect("a loopback port");
    let addr = listener.local_addr().unwrap().to_string();
    let (closed_tx, closed_rx) = mpsc::channel();
    let tev = thread::spawn(move || {
        // The first tev reads one packet and quits.
        let (mut first, _) = listener.accept().expect("the first connection");
        first.set_read_timeout(Some(READ_TIMEOUT)).unwrap();
        assert!(matches!(
            read_packet(&mut first),
            Some((_, Packet::Create { .. }))
        ));
        drop(first);
        closed_tx.send(()).unwrap();
        // The second one stays.
        read_all(listener.accept().expect("the second connection").0)
    });

    let mut state = FrameState::new(16, 8, CascadeLayout::with_defaults());
    splat_some(&mut state, 4, 2);
    let resolved = state.resolve(&ResolveParams::with_defaults());
    let mut sink = TevSink::connect(&addr).expect("connect to the stand-in");
    let _ = sink.show("frame", &resolved); // may or may not see the close
    closed_rx
        .recv_timeout(READ_TIMEOUT)
        .expect("the first tev closed");

    // Writes into a closed connection fail within a few packets; the error drops it.
    let mut failure = None;
    for _ in 0..200 {
        match sink.show("frame", &resolved) {
            Ok(()) => thread::sleep(Duration::from_millis(5)),
            Err(e) => {
                failure = Some(e);
                break;
            }
        }
    }
    let failure = failure.expect("a send error after tev went away");
    assert!(matches!(failure, TevError::Send { .. }), "{failure:?}");
    assert!(
        failure.to_string().contains("next frame reconnects"),
        "{failure}"
    );
    assert!(!sink.is_connected());

    sink.show("frame", &resolved)
        .expect("the reconnecting show");
    assert!(sink.is_connected());
    drop(sink);
    let packets = tev.join().expect("the stand-in");
    assert!(
        matches!(&packets[0].1, Packet::Create { name, .. } if name == "frame"),
        "a new tev gets the image created again, got {:?}",
        packets.first().map(|p| &p.1)
    );
    assert_planes_equal(
        "after reconnect",
        &reassemble(&packets)["frame"].planes,
        &resolved,
    );
}

#[test]
fn an_unreachable_tev_is_a_connect_error_naming_the_address() {
    // A port that was free a moment ago: nothing listens there.
    let addr = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .to_string();
    let err = TevSink::connect(&addr).unwrap_err();
    assert!(matches!(err, TevError::Connect { .. }), "{err:?}");
    assert!(
        err.to_string()
            .starts_with(&format!("could not connect to tev at {addr}: ")),
        "{err}"
    );
    let err = TevSink::connect("not an address").unwrap_err();
    assert!(err.to_string().contains("not an address"), "{err}");
}

#[test]
fn bad_names_and_malformed_frames_are_refused_before_sending() {
    let (addr, tev) = stand_in(1);
    let mut state = FrameState::new(4, 4, CascadeLayout::with_defaults());
    splat_some(&mut state, 5, 1);
    let mut resolved = state.resolve(&ResolveParams::with_defaults());
    let mut sink = TevSink::connect(&addr).expect("connect to the stand-in");

    let err = sink.show("a\0b", &resolved).unwrap_err();
    assert!(matches!(err, TevError::ImageName { .. }), "{err:?}");
    resolved.mean.pop();
    let err = sink.show("frame", &resolved).unwrap_err();
    assert_eq!(
        err.to_string(),
        "resolved frame \"frame\" is 4x4 but its mean layer has 15 pixels"
    );
    assert!(sink.is_connected(), "refusals keep the connection");
    drop(sink);
    assert!(
        tev.join().expect("the stand-in")[0].is_empty(),
        "nothing sent"
    );
}
