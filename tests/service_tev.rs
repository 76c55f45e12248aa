//! `splatd serve --tev`: a real server pushes a frame to a tev stand-in as samples arrive; the
//! stand-in decodes tev's protocol independently and the pixels equal the core's resolve.

use std::time::Instant;

use crate::common;
use crate::common::{runtime, Server};
use crate::tev_decoder;
use crate::tev_decoder::{assert_planes_equal, read_packet, reassemble, Packet};
use splatd_estimator::{CascadeLayout, FrameState, ResolveParams};
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Client, Record};
use splatd_scenes::synth::FireflyScene;

#[test]
fn served_frames_reach_tev_with_the_resolved_pixels() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let tev_addr = listener.local_addr().unwrap().to_string();
    let server = Server::start(&["--tev", &tev_addr, "--tev-interval-ms", "50"]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    let (w, h) = (21, 13);
    let scene = FireflyScene::new(w, h, 8);
    rt.block_on(client.create_frame(&CreateFrame::new("tv", w, h)))
        .unwrap();
    let mut reference = FrameState::new(w, h, CascadeLayout::with_defaults());
    for pass in 0..6 {
        let records: Vec<Record> = scene
            .pass(pass)
            .map(|(x, y, rgb)| Record::new(x, y, rgb))
            .collect();
        rt.block_on(client.post_batch(&Batch::new("tv", 1, pass, records).unwrap()))
            .unwrap();
        reference.splat_all(scene.pass(pass));
    }
    let expected = reference.resolve(&ResolveParams::with_defaults());

    // Read packets until the image holds the expected pixels (the server may first push an
    // earlier state of the frame), with a deadline.
    let (mut stream, _) = listener.accept().unwrap();
    stream.set_read_timeout(Some(common::PATIENCE)).unwrap();
    let deadline = Instant::now() + common::PATIENCE;
    let mut packets = Vec::new();
    let mut created = 0;
    loop {
        assert!(
            Instant::now() < deadline,
            "tev never received the final frame"
        );
        let packet = read_packet(&mut stream).expect("the server keeps the connection open");
        if matches!(&packet.1, Packet::Create { .. }) {
            created += 1;
        }
        packets.push(packet);
        let images = reassemble(&packets);
        if let Some(image) = images.get("tv") {
            if let Some(last) = image.snapshots.last() {
                let planes_of_expected = tev_decoder::planes_of(&expected);
                if *last == planes_of_expected {
                    assert_planes_equal("tev image", last, &expected);
                    break;
                }
            }
        }
    }
    assert_eq!(created, 1, "the image is created once and then updated");
}
