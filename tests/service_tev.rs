//! `splatd serve --tev`: a real server pushes a frame to a tev stand-in as samples arrive; the
//! stand-in decodes tev's protocol independently and the pixels equal the core's resolve.

use std::net::{TcpListener, TcpStream};
use std::time::Instant;

use crate::common;
use crate::common::{parse_metrics, runtime, scrape_metrics, Server, ServerProcess};
use crate::tev_decoder;
use crate::tev_decoder::{assert_planes_equal, read_packet, reassemble, Packet};
use splatd_estimator::{CascadeLayout, FrameState, ResolveParams, Resolved};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Batch, Client, Record};
use splatd_scenes::synth::FireflyScene;

/// Posts the scene's passes `passes` to frame `id` as batches of those numbers, and splats them
/// into `reference` too.
fn post_passes(
    client: &Client,
    id: &str,
    scene: &FireflyScene,
    passes: std::ops::Range<u64>,
    reference: &mut FrameState,
) {
    let rt = runtime();
    for pass in passes {
        let records: Vec<Record> = scene
            .pass(pass)
            .map(|(x, y, rgb)| Record::new(x, y, rgb))
            .collect();
        rt.block_on(client.post_batch(&Batch::new(id, 1, pass, records).unwrap()))
            .unwrap();
        reference.splat_all(scene.pass(pass));
    }
}

/// Reads packets into `packets` until tev's image `id` holds `expected` (the server may first
/// push earlier states of the frame), with a deadline; returns the snapshots of the image
/// (one per update sent whole).
fn read_until(
    stream: &mut TcpStream,
    packets: &mut Vec<(usize, Packet)>,
    id: &str,
    expected: &Resolved,
) -> usize {
    let deadline = Instant::now() + common::PATIENCE;
    let planes_of_expected = tev_decoder::planes_of(expected);
    loop {
        assert!(
            Instant::now() < deadline,
            "tev never received the frame as expected"
        );
        let packet = read_packet(stream).expect("the server keeps the connection open");
        packets.push(packet);
        let images = reassemble(packets);
        if let Some(image) = images.get(id) {
            if image.snapshots.last() == Some(&planes_of_expected) {
                assert_planes_equal("tev image", image.snapshots.last().unwrap(), expected);
                return image.snapshots.len();
            }
        }
    }
}

/// A server pushing to a tev stand-in (every 50 ms) that listens here, and a client of it
/// that created frame `id` of `w` x `h` pixels.
fn serving_tev(id: &str, w: u32, h: u32) -> (TcpListener, ServerProcess, Client) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let tev_addr = listener.local_addr().unwrap().to_string();
    let server = Server::start(&["--tev", &tev_addr, "--tev-interval-ms", "50"]);
    let client = Client::new(&server.url).unwrap();
    runtime()
        .block_on(client.create_frame(&CreateFrame::new(id, w, h)))
        .unwrap();
    (listener, server, client)
}

#[test]
fn served_frames_reach_tev_with_the_resolved_pixels() {
    let (w, h) = (21, 13);
    let (listener, _server, client) = serving_tev("tv", w, h);
    let scene = FireflyScene::new(w, h, 8);
    let mut reference = FrameState::new(w, h, CascadeLayout::with_defaults());
    post_passes(&client, "tv", &scene, 0..6, &mut reference);
    let expected = reference.resolve(&ResolveParams::with_defaults());

    let (mut stream, _) = listener.accept().unwrap();
    stream.set_read_timeout(Some(common::PATIENCE)).unwrap();
    let mut packets = Vec::new();
    read_until(&mut stream, &mut packets, "tv", &expected);
    let created = packets
        .iter()
        .filter(|(_, p)| matches!(p, Packet::Create { .. }))
        .count();
    assert_eq!(created, 1, "the image is created once and then updated");
}

/// tev's updates bring the frame's kept resolve up to date, which images share: the first
/// update resolves the frame whole, the next ones patch it, and an `image.exr` of the version
/// tev shows last resolves nothing. (They resolved every changed frame whole, outside the kept
/// resolve and uncounted: the image then made the only resolve counted, and none was patched.)
#[test]
fn tev_updates_patch_the_kept_resolve_that_images_share() {
    let (w, h) = (40, 24);
    let (listener, server, client) = serving_tev("tk", w, h);
    let scene = FireflyScene::new(w, h, 8);
    let (mut stream, _) = listener.accept().unwrap();
    stream.set_read_timeout(Some(common::PATIENCE)).unwrap();
    let mut packets = Vec::new();
    let mut reference = FrameState::new(w, h, CascadeLayout::with_defaults());
    let params = ResolveParams::with_defaults();
    // Two versions that tev shows, each waited for: two updates at least.
    post_passes(&client, "tk", &scene, 0..2, &mut reference);
    read_until(&mut stream, &mut packets, "tk", &reference.resolve(&params));
    post_passes(&client, "tk", &scene, 2..6, &mut reference);
    let updates = read_until(&mut stream, &mut packets, "tk", &reference.resolve(&params));

    runtime()
        .block_on(client.image("tk", &ImageQuery::default()))
        .unwrap();
    let text = scrape_metrics(&server.url);
    let m = parse_metrics(&text);
    let resolves = |made: &str| {
        let key = format!("splatd_resolves_total{{made=\"{made}\"}}");
        *m.get(&key)
            .unwrap_or_else(|| panic!("no {key} in:\n{text}"))
    };
    let (whole, patched) = (resolves("whole"), resolves("patched"));
    assert_eq!(whole, 1.0, "the first update's resolve only");
    assert!(patched >= 1.0, "tev's later updates patch it: {patched}");
    // An update may take a resolve an earlier one made of a later version than it read.
    assert!(
        whole + patched <= updates as f64,
        "{whole} + {patched} resolves for {updates} updates: the image or the scrape resolved"
    );
}
