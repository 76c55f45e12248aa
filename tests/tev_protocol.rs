//! `splatd_server::viewer::tev` against an independent decoder of tev's IPC protocol.
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

use std::net::TcpListener;
use std::sync::mpsc;
use std::thread;
use std::time::Instant;

use splatd_estimator::{CascadeLayout, FrameState, ResolveParams};
use splatd_server::viewer::tev::{TevError, TevSink, MAX_PIXELS_PER_UPDATE};

use crate::tev_decoder::*;

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

    // The stand-in has closed its end. A write into the connection fails once the close (and
    // the reset answering the first write after it) reached this side, which TCP does not
    // time: show until one fails. The loop ends by itself at that event; the cap only stops a
    // hung test. The error drops the connection.
    let deadline = Instant::now() + READ_TIMEOUT;
    let failure = loop {
        match sink.show("frame", &resolved) {
            Ok(()) => {
                assert!(
                    Instant::now() < deadline,
                    "no send error after tev went away (hung?)"
                );
                thread::yield_now();
            }
            Err(e) => break e,
        }
    };
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
