//! The real `splatd serve` binary on loopback: concurrent ingest, resolve and every bad input.

use std::collections::BTreeMap;
use std::io::Write;

use crate::common::{read_exr_with_python, runtime, Server};
use bytes::Bytes;
use splatd_estimator::{CascadeLayout, FrameState, ResolveParams, Resolved};
use splatd_formats::exr::{decode_exr_channels, encode_exr, ExtraLayer, Provenance};
use splatd_proto::api::{CascadeParams, CreateFrame, ImageQuery, Variant};
use splatd_proto::{Batch, Client, ClientError, Record};
use splatd_scenes::synth::FireflyScene;

/// Records of one pass of the synthetic scene.
fn pass_records(scene: &FireflyScene, pass: u64) -> Vec<Record> {
    scene
        .pass(pass)
        .map(|(x, y, rgb)| Record::new(x, y, rgb))
        .collect()
}

/// A frame of the test: request, scene and the samples of every pass.
struct TestFrame {
    create: CreateFrame,
    scene: FireflyScene,
    layout: CascadeLayout,
}

fn frames() -> Vec<TestFrame> {
    let a = CreateFrame::new("shot.a", 48, 37);
    let mut b = CreateFrame::new("shot-b", 31, 52);
    b.cascades = CascadeParams {
        base: 4.0,
        cascades: 8,
        lowest_scale: 0.25,
        ..CascadeParams::default()
    };
    let layout_b = CascadeLayout::new(4.0, 8, 0.25, b.cascades.luminance).unwrap();
    vec![
        TestFrame {
            scene: FireflyScene::new(48, 37, 11),
            create: a,
            layout: CascadeLayout::with_defaults(),
        },
        TestFrame {
            scene: FireflyScene::new(31, 52, 12),
            create: b,
            layout: layout_b,
        },
    ]
}

const PASSES: u64 = 24;
const CLIENTS: u64 = 8;

/// Eight concurrent clients post interleaved batches of two frames; each frame's EXR equals the
/// core's resolve of the same samples byte for byte, and an independent reader agrees value by
/// value.
#[test]
fn concurrent_clients_get_the_cores_image_bit_for_bit() {
    let server = Server::start(&[]);
    let frames = frames();
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    rt.block_on(async {
        for f in &frames {
            client.create_frame(&f.create).await.unwrap();
        }
        let mut tasks = Vec::new();
        for c in 0..CLIENTS {
            let client = client.clone();
            // Client c sends passes c, c + 8, ... of both frames, alternating frames, in
            // batches that cut passes at odd places.
            let mut work: Vec<(String, Vec<Record>)> = Vec::new();
            for pass in (c..PASSES).step_by(CLIENTS as usize) {
                for f in &frames {
                    let records = pass_records(&f.scene, pass);
                    for chunk in records.chunks(313) {
                        work.push((f.create.id.clone(), chunk.to_vec()));
                    }
                }
            }
            tasks.push(tokio::spawn(async move {
                for (seq, (frame, records)) in work.into_iter().enumerate() {
                    let batch = Batch::new(frame, 1000 + c, seq as u64, records).unwrap();
                    let ack = client.post_batch(&batch).await.unwrap();
                    assert_eq!(ack.accepted, batch.records.len() as u64);
                    assert!(!ack.duplicate);
                }
            }));
        }
        for t in tasks {
            t.await.unwrap();
        }
    });

    let dir = tempfile::tempdir().unwrap();
    for f in &frames {
        let mut reference = FrameState::new(f.create.width, f.create.height, f.layout.clone());
        for pass in 0..PASSES {
            reference.splat_all(f.scene.pass(pass));
        }
        let params = ResolveParams::with_defaults();
        let resolved = reference.resolve(&params);
        let layers: Vec<ExtraLayer> = reference
            .cascade_means()
            .into_iter()
            .enumerate()
            .map(|(j, rgb)| ExtraLayer {
                name: format!("cascade{j}"),
                rgb,
            })
            .collect();
        let provenance = Provenance {
            layout: &f.layout,
            params: &params,
        };
        let expected = encode_exr(&resolved, &layers, &[], &provenance).unwrap();
        let query = ImageQuery {
            cascades: true,
            ..ImageQuery::default()
        };
        let got = rt.block_on(client.image(&f.create.id, &query)).unwrap();
        assert!(
            got[..] == expected[..],
            "frame {}: served EXR differs from the core's resolve",
            f.create.id
        );
        let info = rt.block_on(client.frame_info(&f.create.id)).unwrap();
        let pixels = (f.create.width * f.create.height) as u64;
        assert_eq!(info.samples, PASSES * pixels);
        assert_eq!((info.spp_min, info.spp_max), (PASSES, PASSES));

        let path = dir.path().join(format!("{}.exr", f.create.id));
        std::fs::write(&path, &got).unwrap();
        check_with_independent_reader(&path, &resolved, &layers);

        // Each variant asked for by name (`?variant=paper`, `?variant=spread`) is the core's
        // resolve with that variant and the frame's other parameters, byte for byte.
        let mut images = Vec::new();
        for variant in [Variant::Paper, Variant::Spread] {
            let params = params.with_variant(variant.to_estimator());
            let resolved = reference.resolve(&params);
            let provenance = Provenance {
                layout: &f.layout,
                params: &params,
            };
            let expected = encode_exr(&resolved, &[], &[], &provenance).unwrap();
            let query = ImageQuery {
                variant: Some(variant),
                ..ImageQuery::default()
            };
            let got = rt.block_on(client.image(&f.create.id, &query)).unwrap();
            assert!(
                got[..] == expected[..],
                "frame {}: served EXR of variant={} differs from the core's resolve",
                f.create.id,
                variant.as_str()
            );
            images.push(resolved.reweighted);
        }
        assert_ne!(
            images[0], images[1],
            "frame {}: spread gives nothing back, so the test cannot tell the variants apart",
            f.create.id
        );
    }
}

/// Compares an EXR read by OpenEXR's Python bindings with the values the core resolved.
fn check_with_independent_reader(
    path: &std::path::Path,
    resolved: &Resolved,
    layers: &[ExtraLayer],
) {
    let (w, h, channels) = read_exr_with_python(path);
    assert_eq!((w, h), (resolved.width, resolved.height));
    let mut expected: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut rgb = |prefix: &str, values: &[[f32; 3]]| {
        for (c, name) in ["R", "G", "B"].iter().enumerate() {
            expected.insert(
                format!("{prefix}{name}"),
                values.iter().map(|p| p[c] as f64).collect(),
            );
        }
    };
    rgb("", &resolved.reweighted);
    rgb("mean.", &resolved.mean);
    rgb("removed.", &resolved.removed);
    for layer in layers {
        rgb(&format!("{}.", layer.name), &layer.rgb);
    }
    expected.insert(
        "spp.Y".into(),
        resolved.spp.iter().map(|&n| n as f64).collect(),
    );
    let names: Vec<&String> = channels.iter().map(|(n, _)| n).collect();
    let expected_names: Vec<&String> = expected.keys().collect();
    assert_eq!(names, expected_names, "channel names");
    for (name, values) in &channels {
        let want = &expected[name];
        for (i, (a, b)) in values.iter().zip(want).enumerate() {
            // Both are f32 values; compare them as such (JSON's decimal text goes through f64).
            assert!(
                (*a as f32).to_bits() == (*b as f32).to_bits(),
                "channel {name} pixel {i}: OpenEXR read {a}, core resolved {b}"
            );
        }
    }
}

/// Raw HTTP for requests the well-behaved client refuses to send.
struct Raw {
    http: reqwest::Client,
    url: String,
}

impl Raw {
    async fn post(
        &self,
        path: &str,
        content_type: &str,
        body: Vec<u8>,
    ) -> (u16, serde_json::Value) {
        let r = self
            .http
            .post(format!("{}{path}", self.url))
            .header("content-type", content_type)
            .body(body)
            .send()
            .await
            .unwrap();
        Self::json(r).await
    }

    async fn get(&self, path: &str) -> (u16, serde_json::Value) {
        let r = self
            .http
            .get(format!("{}{path}", self.url))
            .send()
            .await
            .unwrap();
        Self::json(r).await
    }

    async fn json(r: reqwest::Response) -> (u16, serde_json::Value) {
        let status = r.status().as_u16();
        let ct = r
            .headers()
            .get("content-type")
            .map(|v| v.to_str().unwrap().to_owned());
        let bytes = r.bytes().await.unwrap();
        let body = serde_json::from_slice(&bytes)
            .unwrap_or_else(|_| panic!("HTTP {status} ({ct:?}) body is not JSON: {bytes:?}"));
        (status, body)
    }
}

fn batch_bytes(frame: &str, seq: u64, records: Vec<Record>) -> Vec<u8> {
    Batch::new(frame, 5, seq, records).unwrap().encode()
}

fn good_records() -> Vec<Record> {
    (0..10)
        .map(|i| Record::new(i, i, [1.0, 2.0, 0.5]))
        .collect()
}

/// Every kind of bad input gets its status and a JSON error naming the problem, and leaves the
/// frame exactly as it was.
#[test]
fn bad_input_is_refused_by_name_and_changes_nothing() {
    let server = Server::start(&["--max-records", "1000", "--max-cascades", "10"]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    let raw = Raw {
        http: reqwest::Client::new(),
        url: server.url.clone(),
    };
    rt.block_on(async {
        client
            .create_frame(&CreateFrame::new("f", 16, 16))
            .await
            .unwrap();
        let ok = client
            .post_batch(&Batch::new("f", 1, 0, good_records()).unwrap())
            .await
            .unwrap();
        assert_eq!(ok.accepted, 10);
        let before_image = client.image("f", &ImageQuery::default()).await.unwrap();
        let before = client.frame_info("f").await.unwrap();

        let mut cases: Vec<(&str, u16, &str, &str, Vec<u8>)> = Vec::new();
        let samples = "/v1/frames/f/samples";
        let ct = "application/x-splatd-batch";
        let with = |i: usize, r: Record| {
            let mut recs = good_records();
            recs[i] = r;
            recs
        };
        let out_x = batch_bytes("f", 1, with(3, Record::new(16, 0, [1.0; 3])));
        cases.push((
            samples,
            422,
            "pixel_out_of_range",
            "record 3 (pixel (16, 0)",
            out_x,
        ));
        let out_y = batch_bytes("f", 1, with(9, Record::new(0, 99, [1.0; 3])));
        cases.push((
            samples,
            422,
            "pixel_out_of_range",
            "outside the 16x16 frame",
            out_y,
        ));
        let nan = batch_bytes("f", 1, with(4, Record::new(1, 1, [1.0, f32::NAN, 0.0])));
        cases.push((samples, 422, "non_finite_sample", "record 4", nan));
        let inf = batch_bytes(
            "f",
            1,
            with(0, Record::new(1, 1, [f32::INFINITY, 0.0, 0.0])),
        );
        cases.push((samples, 422, "non_finite_sample", "record 0", inf));
        let neg = batch_bytes("f", 1, with(7, Record::new(1, 1, [0.0, 0.0, -1.0])));
        cases.push((samples, 422, "negative_sample", "record 7", neg));
        let mut magic = batch_bytes("f", 1, good_records());
        magic[0] = b'X';
        cases.push((samples, 400, "bad_magic", "SPLB", magic));
        let mut version = batch_bytes("f", 1, good_records());
        version[4] = 9;
        cases.push((samples, 400, "unsupported_version", "9", version));
        let full = batch_bytes("f", 1, good_records());
        cases.push((
            samples,
            400,
            "truncated_batch",
            "",
            full[..full.len() - 7].to_vec(),
        ));
        cases.push((samples, 400, "truncated_batch", "", full[..20].to_vec()));
        let mut trailing = full.clone();
        trailing.extend_from_slice(&[0; 5]);
        cases.push((samples, 400, "trailing_bytes", "5", trailing));
        let mut huge_count = full.clone();
        let at = 6 + 8 + 1 + 8 + 8; // record count of frame id "f"
        huge_count[at..at + 8].copy_from_slice(&(1u64 << 60).to_le_bytes());
        cases.push((samples, 400, "truncated_batch", "", huge_count));
        cases.push((
            samples,
            400,
            "bad_magic",
            "",
            b"garbage, not a batch".to_vec(),
        ));
        let too_many: Vec<Record> = (0..1001)
            .map(|i| Record::new(i % 16, 0, [1.0; 3]))
            .collect();
        cases.push((samples, 413, "", "", batch_bytes("f", 1, too_many)));
        let other = batch_bytes("g", 1, good_records());
        cases.push((samples, 400, "frame_mismatch", "\"g\"", other));
        cases.push((
            "/v1/frames/nope/samples",
            404,
            "unknown_frame",
            "nope",
            batch_bytes("nope", 1, good_records()),
        ));

        for (path, status, code, needle, body) in cases {
            let (got, err) = raw.post(path, ct, body).await;
            assert_eq!(got, status, "{path} expected {status} {code}: {err}");
            if !code.is_empty() {
                assert_eq!(err["error"], code, "{err}");
            }
            let message = err["message"].as_str().expect("message");
            assert!(
                message.contains(needle),
                "{code}: {message:?} lacks {needle:?}"
            );
        }

        // Wrong content type; wrong encoding.
        let (got, err) = raw
            .post(
                samples,
                "application/json",
                batch_bytes("f", 1, good_records()),
            )
            .await;
        assert_eq!(
            (got, err["error"].as_str()),
            (415, Some("unsupported_content_type"))
        );
        let r = raw
            .http
            .post(format!("{}{samples}", server.url))
            .header("content-type", ct)
            .header("content-encoding", "br")
            .body(batch_bytes("f", 1, good_records()))
            .send()
            .await
            .unwrap();
        let (got, err) = Raw::json(r).await;
        assert_eq!(got, 415, "{err}");
        let r = raw
            .http
            .post(format!("{}{samples}", server.url))
            .header("content-type", ct)
            .header("content-encoding", "gzip")
            .body(b"not gzip at all".to_vec())
            .send()
            .await
            .unwrap();
        let (got, err) = Raw::json(r).await;
        assert_eq!(got, 400, "{err}");

        // Frames that make no sense, and JSON that is not a frame.
        let frames = "/v1/frames";
        let js = "application/json";
        for (body, status, needle) in [
            (r#"{"id":"x","width":0,"height":4}"#, 400, "0x4"),
            (
                r#"{"id":"x","width":4,"height":4,"cascades":{"base":0.5}}"#,
                400,
                "base",
            ),
            (
                r#"{"id":"x","width":4,"height":4,"cascades":{"cascades":1}}"#,
                400,
                "cascades",
            ),
            (
                r#"{"id":"x","width":4,"height":4,"cascades":{"cascades":99}}"#,
                400,
                "99",
            ),
            (
                r#"{"id":"x","width":4,"height":4,"cascades":{"cascades":12}}"#,
                413,
                "at most 10",
            ),
            (
                r#"{"id":"x","width":4,"height":4,"resolve":{"kappa":-2}}"#,
                400,
                "kappa",
            ),
            (r#"{"id":"x","width":4,"height":4,"widht":3}"#, 400, "widht"),
            (r#"{"id":"../x","width":4,"height":4}"#, 400, "id"),
            (
                r#"{"id":"x","width":100000,"height":100000}"#,
                413,
                "100000x100000",
            ),
            (
                r#"{"id":"f","width":8,"height":16}"#,
                409,
                "16x16 here, 8x16",
            ),
            (r#"{"id": "x", "#, 400, "JSON"),
        ] {
            let (got, err) = raw.post(frames, js, body.as_bytes().to_vec()).await;
            assert_eq!(got, status, "{body}: {err}");
            let message = err["message"].as_str().unwrap();
            assert!(
                message.contains(needle),
                "{body}: {message:?} lacks {needle:?}"
            );
        }

        // Bad image queries.
        for q in ["variant=median", "kapa=2", "kappa=-1", "cascades=maybe"] {
            let (got, err) = raw.get(&format!("/v1/frames/f/image.exr?{q}")).await;
            assert_eq!(got, 400, "{q}: {err}");
        }
        let (got, err) = raw.get("/v1/frames/nope/image.exr").await;
        assert_eq!((got, err["error"].as_str()), (404, Some("unknown_frame")));
        let (got, err) = raw.get("/v2/whatever").await;
        assert_eq!((got, err["error"].as_str()), (404, Some("unknown_route")));

        // After all that, the frame is what it was, and still takes good batches.
        let after = client.frame_info("f").await.unwrap();
        assert_eq!(after.samples, before.samples);
        assert_eq!(after.batches, before.batches);
        assert_eq!(
            (after.spp_min, after.spp_max),
            (before.spp_min, before.spp_max)
        );
        assert!(after.rejected_batches >= 14, "{after:?}");
        let after_image = client.image("f", &ImageQuery::default()).await.unwrap();
        assert!(
            after_image == before_image,
            "a refused request changed the image"
        );
        let ack = client
            .post_batch(&Batch::new("f", 1, 1, good_records()).unwrap())
            .await
            .unwrap();
        assert_eq!(ack.accepted, 10);
    });
}

/// Compressed bodies are accepted; a retried batch counts once; frames list and delete.
#[test]
fn gzip_and_zstd_bodies_retries_and_frame_lifecycle() {
    let server = Server::start(&[]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    rt.block_on(async {
        let info = client
            .create_frame(&CreateFrame::new("z", 16, 16))
            .await
            .unwrap();
        assert_eq!(info.samples, 0);
        // A retried create with identical parameters is fine.
        client
            .create_frame(&CreateFrame::new("z", 16, 16))
            .await
            .unwrap();
        let body = batch_bytes("z", 0, good_records());
        let mut gz = flate2_like_gzip(&body);
        let http = reqwest::Client::new();
        let url = format!("{}/v1/frames/z/samples", server.url);
        for (encoding, bytes) in [
            ("gzip", std::mem::take(&mut gz)),
            ("zstd", splatd_scenes::hostile::zstd_frame(&body)),
        ] {
            let r = http
                .post(&url)
                .header("content-type", "application/x-splatd-batch")
                .header("content-encoding", encoding)
                .body(bytes)
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200, "{encoding}: {:?}", r.text().await);
        }
        // The second post (zstd) carried the same (worker, seq): a duplicate.
        let info = client.frame_info("z").await.unwrap();
        assert_eq!((info.samples, info.batches), (10, 1));
        let ack = client.post_encoded("z", Bytes::from(body)).await.unwrap();
        assert!(ack.duplicate && ack.accepted == 0);

        let list = client.list_frames().await.unwrap();
        assert_eq!(
            list.iter().map(|f| f.id.as_str()).collect::<Vec<_>>(),
            ["z"]
        );
        client.delete_frame("z").await.unwrap();
        assert!(matches!(
            client.frame_info("z").await,
            Err(ClientError::Rejected { status: 404, .. })
        ));
        assert!(client.list_frames().await.unwrap().is_empty());
    });
}

/// A gzip member with stored (uncompressed) deflate blocks: enough to exercise the server's
/// decompression without a compression crate in the tests.
fn flate2_like_gzip(data: &[u8]) -> Vec<u8> {
    let mut out = vec![0x1f, 0x8b, 8, 0, 0, 0, 0, 0, 0, 255];
    let mut chunks = data.chunks(65535).peekable();
    if chunks.peek().is_none() {
        out.extend_from_slice(&[1, 0, 0, 0xff, 0xff]);
    }
    while let Some(chunk) = chunks.next() {
        out.push(u8::from(chunks.peek().is_none()));
        let len = chunk.len() as u16;
        out.extend_from_slice(&len.to_le_bytes());
        out.extend_from_slice(&(!len).to_le_bytes());
        out.extend_from_slice(chunk);
    }
    out.extend_from_slice(&crc32fast::hash(data).to_le_bytes());
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    out
}

/// A frame being created holds up no other request: while its memory is taken and zeroed
/// (paused there by a failpoint), batches to another frame are acknowledged, frames are listed
/// and `/healthz` answers; a retry of the same create is answered once the frame exists, and
/// the frame is created once.
#[test]
fn a_frame_being_created_holds_up_no_other_request() {
    let dir = tempfile::tempdir().unwrap();
    let points = dir.path().to_str().unwrap();
    let server = Server::start_with_env(
        &[],
        &[
            ("SPLATD_FAILPOINTS", "frame:building=pause@2"),
            ("SPLATD_FAILPOINT_DIR", points),
        ],
    );
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    rt.block_on(client.create_frame(&CreateFrame::new("a", 64, 48)))
        .unwrap();
    let url = server.url.clone();
    let create = move || {
        reqwest::blocking::Client::builder()
            .timeout(std::time::Duration::from_secs(120))
            .build()
            .unwrap()
            .post(format!("{url}/v1/frames"))
            .json(&CreateFrame::new("b", 1920, 1080))
            .send()
            .map(|r| r.status().as_u16())
    };
    let first = std::thread::spawn(create.clone());
    let reached = dir.path().join("frame:building.reached");
    for waited in 0.. {
        if reached.exists() {
            break;
        }
        assert!(waited < 6000, "the create never reached its building");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    for seq in 0..3 {
        let records = (0..48).map(|y| Record::new(y, y, [1.0; 3])).collect();
        let ack = rt
            .block_on(client.post_batch(&Batch::new("a", 1, seq, records).unwrap()))
            .unwrap();
        assert_eq!(ack.accepted, 48);
    }
    let http = reqwest::blocking::Client::builder()
        .timeout(std::time::Duration::from_secs(20))
        .build()
        .unwrap();
    let healthz = http.get(format!("{}/healthz", server.url)).send().unwrap();
    assert_eq!(healthz.status(), 200, "/healthz while a frame is built");
    let listed = || -> serde_json::Value {
        let response = http
            .get(format!("{}/v1/frames", server.url))
            .send()
            .unwrap();
        assert_eq!(response.status(), 200);
        response.json().unwrap()
    };
    let frames = listed();
    assert_eq!(
        frames["frames"].as_array().map(Vec::len),
        Some(1),
        "{frames}"
    );
    // The same create again, while the first is built: both end with the one frame.
    let retry = std::thread::spawn(create);
    std::fs::write(dir.path().join("frame:building.release"), b"").unwrap();
    let mut statuses = [
        first.join().unwrap().unwrap(),
        retry.join().unwrap().unwrap(),
    ];
    statuses.sort();
    assert_eq!(statuses, [200, 201], "one created, one answered with it");
    let info = rt.block_on(client.frame_counts("a")).unwrap();
    assert_eq!(info.samples, 3 * 48);
    let frames = listed();
    assert_eq!(
        frames["frames"].as_array().map(Vec::len),
        Some(2),
        "{frames}"
    );
}

/// SIGTERM stops the server cleanly (exit code 0).
#[test]
fn sigterm_shuts_down_cleanly() {
    let server = Server::start(&[]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    rt.block_on(async {
        client
            .create_frame(&CreateFrame::new("s", 8, 8))
            .await
            .unwrap();
    });
    assert_eq!(server.terminate(), Some(0));
}

/// The offline resolve of a batch file equals the server's image of the same batches.
#[test]
fn offline_resolve_matches_the_server() {
    let scene = FireflyScene::new(20, 12, 4);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("samples.splb");
    let mut file = std::fs::File::create(&path).unwrap();
    let mut batches = Vec::new();
    for pass in 0..16 {
        let batch = Batch::new("off", 3, pass, pass_records(&scene, pass)).unwrap();
        splatd_proto::batchfile::write_batch(&mut file, &batch).unwrap();
        batches.push(batch);
    }
    file.flush().unwrap();
    let exr = dir.path().join("frame.exr");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_splatd"))
        .args(["resolve", "--width", "20", "--height", "12", "-o"])
        .arg(&exr)
        .arg(&path)
        .status()
        .unwrap();
    assert!(status.success());
    let offline = std::fs::read(&exr).unwrap();

    let server = Server::start(&[]);
    let rt = runtime();
    let client = Client::new(&server.url).unwrap();
    let served = rt.block_on(async {
        client
            .create_frame(&CreateFrame::new("off", 20, 12))
            .await
            .unwrap();
        for b in &batches {
            client.post_batch(b).await.unwrap();
        }
        client.image("off", &ImageQuery::default()).await.unwrap()
    });
    assert!(served[..] == offline[..], "offline and served EXRs differ");
    let channels = decode_exr_channels(&offline).unwrap();
    assert!(channels.iter().any(|(n, _)| n == "spp.Y"));
}
