//! Hostile clients against a real server: ten thousand malformed bodies, slow senders, and
//! requests past every limit. The server neither crashes nor grows, and frames change only by
//! what was valid.

use std::io::{Read, Write};
use std::net::TcpStream;

use crate::common;
use crate::common::{runtime, Server};
use splatd_estimator::{CascadeLayout, FrameState, ResolveParams};
use splatd_formats::exr::{encode_exr, Provenance};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Batch, Client, DecodeLimits, Record, StateDump};
use splatd_scenes::synth::{FireflyScene, SplitMix64};

const W: u32 = 16;
const H: u32 = 12;

fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS in /proc/PID/status")
}

/// One malformed variant of a valid body.
fn mutate(rng: &mut SplitMix64, valid: &[u8]) -> Vec<u8> {
    let mut b = valid.to_vec();
    match rng.next_u64() % 7 {
        // Truncated anywhere.
        0 => b.truncate((rng.next_u64() % b.len() as u64) as usize),
        // A few bit flips anywhere.
        1 => {
            for _ in 0..1 + rng.next_u64() % 4 {
                let i = (rng.next_u64() % b.len() as u64) as usize;
                b[i] ^= 1 << (rng.next_u64() % 8);
            }
        }
        // A wrong frame id length.
        2 => b[6..14].copy_from_slice(&(rng.next_u64() % 4096).to_le_bytes()),
        // A huge or wrong record count.
        3 => {
            let at = 6 + 8 + 1 + 8 + 8;
            let n = match rng.next_u64() % 3 {
                0 => u64::MAX - rng.next_u64() % 16,
                1 => 1 << (20 + rng.next_u64() % 40),
                _ => rng.next_u64() % 64,
            };
            b[at..at + 8].copy_from_slice(&n.to_le_bytes());
        }
        // Garbage appended.
        4 => b.extend((0..1 + rng.next_u64() % 64).map(|_| rng.next_u64() as u8)),
        // Pure garbage.
        5 => {
            let n = rng.next_u64() % 256;
            b = (0..n).map(|_| rng.next_u64() as u8).collect();
        }
        // A record's float made NaN, infinite or negative, or its pixel pushed out.
        _ => {
            let records = (b.len() - 39) / 20;
            let r = 39 + 20 * (rng.next_u64() % records as u64) as usize;
            match rng.next_u64() % 4 {
                0 => b[r + 8..r + 12].copy_from_slice(&f32::NAN.to_le_bytes()),
                1 => b[r + 12..r + 16].copy_from_slice(&f32::INFINITY.to_le_bytes()),
                2 => b[r + 19] |= 0x80,
                _ => b[r..r + 4].copy_from_slice(&(W + rng.next_u64() as u32 % 1000).to_le_bytes()),
            }
        }
    }
    b
}

/// Ten thousand malformed batch bodies and a thousand malformed states from four connections:
/// every one gets a 4xx JSON error or, when the mutation happened to leave a valid batch, a 200;
/// the server's memory stays bounded, and the frame ends exactly as the valid batches make it.
#[test]
fn ten_thousand_malformed_bodies_leave_the_server_well_and_the_frame_exact() {
    let server = Server::start(&["--max-records", "256"]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    rt.block_on(client.create_frame(&CreateFrame::new("f", W, H)))
        .unwrap();
    let scene = FireflyScene::new(W, H, 9);
    let pass = |p: u64| -> Vec<Record> {
        scene
            .pass(p)
            .map(|(x, y, rgb)| Record::new(x, y, rgb))
            .collect()
    };
    // Seed the frame, so "unchanged" is about a frame with content.
    let mut reference = FrameState::new(W, H, CascadeLayout::with_defaults());
    for p in 0..4 {
        let batch = Batch::new("f", 1, p, pass(p)).unwrap();
        rt.block_on(client.post_batch(&batch)).unwrap();
        reference.splat_all(scene.pass(p));
    }
    let state = rt.block_on(client.export_state("f")).unwrap();
    let rss_before = rss_kib(server.pid());

    // Bodies: mutations of valid batches (each from its own worker id and sequence number, so a
    // mutation that stays valid is a new batch, not a duplicate).
    let mut rng = SplitMix64::new(2026);
    let mut bodies = Vec::new();
    for i in 0..10_000u64 {
        let valid = Batch::new("f", 1000 + i, 0, pass(4 + i % 8))
            .unwrap()
            .encode();
        bodies.push(mutate(&mut rng, &valid));
    }
    let mut states = Vec::new();
    for _ in 0..1000 {
        states.push(mutate_state(&mut rng, &state));
    }

    let url = server.url.clone();
    let outcomes = rt.block_on(async move {
        let http = reqwest::Client::new();
        let mut tasks = Vec::new();
        let chunk = bodies.len().div_ceil(4);
        let bodies: Vec<Vec<Vec<u8>>> = bodies.chunks(chunk).map(|c| c.to_vec()).collect();
        for (k, part) in bodies.into_iter().enumerate() {
            let http = http.clone();
            let url = url.clone();
            let states: Vec<Vec<u8>> = states.iter().skip(k).step_by(4).cloned().collect();
            tasks.push(tokio::spawn(async move {
                let mut accepted = Vec::new();
                let mut refused = 0u32;
                for body in part {
                    let r = http
                        .post(format!("{url}/v1/frames/f/samples"))
                        .header("content-type", "application/x-splatd-batch")
                        .body(body.clone())
                        .send()
                        .await
                        .expect("the server answers every request");
                    let status = r.status().as_u16();
                    let json: serde_json::Value = r.json().await.expect("a JSON body");
                    match status {
                        200 => accepted.push(body),
                        400..=499 => {
                            assert!(json["error"].is_string() && json["message"].is_string());
                            refused += 1;
                        }
                        _ => panic!("HTTP {status} for a malformed body: {json}"),
                    }
                }
                for body in states {
                    let r = http
                        .post(format!("{url}/v1/frames/f/state"))
                        .header("content-type", "application/x-splatd-state")
                        .body(body)
                        .send()
                        .await
                        .expect("the server answers every request");
                    let status = r.status().as_u16();
                    assert!(
                        (400..500).contains(&status),
                        "a malformed state got HTTP {status}: {:?}",
                        r.text().await
                    );
                }
                (accepted, refused)
            }));
        }
        let mut all = Vec::new();
        for t in tasks {
            all.push(t.await.unwrap());
        }
        all
    });
    let mut refused = 0;
    let limits = DecodeLimits {
        max_records: 256,
        ..DecodeLimits::default()
    };
    for (accepted, r) in outcomes {
        refused += r;
        // Independently: an accepted body must be a valid batch; it then counts in the reference.
        for body in accepted {
            let batch = Batch::decode(&body, &limits).expect("the server accepted a valid batch");
            let report = reference.splat_all(batch.records.iter().map(|r| (r.x, r.y, r.rgb)));
            assert_eq!(
                report.rejected(),
                0,
                "the server accepted an invalid sample"
            );
        }
    }
    assert!(
        refused > 9_000,
        "only {refused} of 10000 mutations were refused"
    );
    let rss_after = rss_kib(server.pid());
    println!(
        "10000 malformed batches ({refused} refused) and 1000 malformed states; server RSS \
         {rss_before} KiB before, {rss_after} KiB after"
    );
    assert!(
        rss_after < rss_before + 64 * 1024,
        "server memory grew from {rss_before} KiB to {rss_after} KiB"
    );
    let image = rt
        .block_on(client.image("f", &ImageQuery::default()))
        .unwrap();
    let params = ResolveParams::with_defaults();
    let provenance = Provenance {
        layout: reference.layout(),
        params: &params,
    };
    let expected = encode_exr(&reference.resolve(&params), &[], &[], &provenance).unwrap();
    assert!(
        image[..] == expected[..],
        "the frame is not what the valid batches make it"
    );
}

fn mutate_state(rng: &mut SplitMix64, valid: &[u8]) -> Vec<u8> {
    let mut b = valid.to_vec();
    match rng.next_u64() % 4 {
        0 => b.truncate((rng.next_u64() % b.len() as u64) as usize),
        1 => {
            // Bit flips in the first 39 bytes, all header: magic, version, the frame id "f",
            // width, height, rows and base (a flip among the cells would be a valid, different
            // state).
            for _ in 0..1 + rng.next_u64() % 3 {
                let i = (rng.next_u64() % 39) as usize;
                b[i] ^= 1 << (rng.next_u64() % 8);
            }
            // Keep it invalid for sure if the flips cancelled out or hit padding. (Decoded with
            // the frame's size as the limit: a flipped size must not allocate in the test.)
            if StateDump::decode(&b, (W * H * 25) as u64).is_ok() {
                b.push(0);
            }
        }
        2 => b.extend_from_slice(&[0; 8]),
        _ => {
            b = (0..rng.next_u64() % 512)
                .map(|_| rng.next_u64() as u8)
                .collect()
        }
    }
    b
}

/// A client that trickles its headers, or stalls in its body, is cut off by the server's
/// timeouts instead of holding a connection forever.
#[test]
fn slow_senders_are_cut_off() {
    let server = Server::start(&["--head-timeout", "1", "--request-timeout", "2"]);
    let rt = runtime();
    rt.block_on(
        Client::new(&server.url)
            .unwrap()
            .create_frame(&CreateFrame::new("f", 4, 4)),
    )
    .unwrap();

    // Half a request line, then silence: the server closes the connection (end of stream),
    // rather than the client's read giving up. The client's read limit only guards against a
    // hang; it is far longer than the server's timeouts and is not what is checked.
    let mut s = TcpStream::connect(&server.addr).unwrap();
    s.set_read_timeout(Some(common::PATIENCE)).unwrap();
    s.write_all(b"POST /v1/frames/f/samples HTTP/1.1\r\nHost: x\r\n")
        .unwrap();
    let mut buf = Vec::new();
    let closed = s.read_to_end(&mut buf);
    assert!(
        closed.is_ok(),
        "a connection with unfinished headers was not closed by the server: {closed:?}"
    );

    // Complete headers promising a body that never comes.
    let mut s = TcpStream::connect(&server.addr).unwrap();
    s.set_read_timeout(Some(common::PATIENCE)).unwrap();
    s.write_all(
        b"POST /v1/frames/f/samples HTTP/1.1\r\nHost: x\r\n\
          Content-Type: application/x-splatd-batch\r\nContent-Length: 100000\r\n\r\nSPLB",
    )
    .unwrap();
    let mut buf = Vec::new();
    let closed = s.read_to_end(&mut buf);
    let text = String::from_utf8_lossy(&buf);
    assert!(
        closed.is_ok(),
        "a stalled body's connection was not closed: {closed:?}"
    );
    assert!(text.starts_with("HTTP/1.1 408"), "{text}");
    assert!(text.contains("request_timeout"), "{text}");
}

/// Frames past the count, size and memory limits are refused with a message naming the limit.
#[test]
fn frame_limits_are_enforced_by_name() {
    let server = Server::start(&[
        "--max-frames",
        "2",
        "--max-memory-mib",
        "1",
        "--max-pixels",
        "5000",
        "--max-records",
        "100",
    ]);
    let http = reqwest::blocking::Client::new();
    let create = |body: &str| {
        let r = http
            .post(format!("{}/v1/frames", server.url))
            .header("content-type", "application/json")
            .body(body.to_owned())
            .send()
            .unwrap();
        (r.status().as_u16(), r.json::<serde_json::Value>().unwrap())
    };
    // 64x64 at 6 cascades is 768 KiB of cascades; a second one would pass the 1 MiB budget.
    assert_eq!(create(r#"{"id":"a","width":64,"height":64}"#).0, 201);
    let (status, err) = create(r#"{"id":"b","width":64,"height":64}"#);
    assert_eq!(
        (status, err["error"].as_str()),
        (409, Some("memory_limit")),
        "{err}"
    );
    assert!(err["message"].as_str().unwrap().contains("MiB"), "{err}");
    let (status, err) = create(r#"{"id":"c","width":100,"height":100}"#);
    assert_eq!(
        (status, err["error"].as_str()),
        (413, Some("frame_too_large")),
        "{err}"
    );
    assert_eq!(create(r#"{"id":"d","width":8,"height":8}"#).0, 201);
    let (status, err) = create(r#"{"id":"e","width":8,"height":8}"#);
    assert_eq!(
        (status, err["error"].as_str()),
        (409, Some("too_many_frames")),
        "{err}"
    );

    // A body far past the batch limit is refused without being read whole.
    let big = Batch::new("d", 1, 0, vec![Record::new(0, 0, [1.0; 3]); 5000])
        .unwrap()
        .encode();
    let r = http
        .post(format!("{}/v1/frames/d/samples", server.url))
        .header("content-type", "application/x-splatd-batch")
        .body(big)
        .send()
        .unwrap();
    assert_eq!(r.status().as_u16(), 413);
    let err: serde_json::Value = r.json().unwrap();
    assert_eq!(err["error"], "body_too_large", "{err}");
}
