//! Every write and admin endpoint of a real server refuses missing, wrong and insufficient
//! tokens, changes nothing when it does, and never writes a token to its log.

use crate::common::{runtime, Server};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Batch, Client, Record};
use splatd_scenes::synth::FireflyScene;

const WRITE: &str = "w-0123456789abcdef-secret";
const READ: &str = "r-0123456789abcdef-secret";
const ADMIN: &str = "a-0123456789abcdef-secret";

fn batch(seq: u64) -> Vec<u8> {
    let scene = FireflyScene::new(8, 8, 1);
    let records = scene
        .pass(seq)
        .map(|(x, y, rgb)| Record::new(x, y, rgb))
        .collect();
    Batch::new("f", 1, seq, records).unwrap().encode()
}

#[test]
fn write_and_admin_endpoints_refuse_missing_wrong_and_insufficient_tokens() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::write(
        &tokens,
        format!("# roles token\nwrite {WRITE}\nread {READ}\n"),
    )
    .unwrap();
    let log = dir.path().join("server.log");
    let server = Server::start_logged(
        &["--tokens-file", tokens.to_str().unwrap()],
        &[
            ("SPLATD_TOKENS", &format!("admin {ADMIN}")),
            ("RUST_LOG", "debug"),
        ],
        &log,
    );
    let rt = runtime();
    let admin = Client::new(&server.url).unwrap().with_token(ADMIN);
    rt.block_on(admin.create_frame(&CreateFrame::new("f", 8, 8)))
        .unwrap();
    let state = rt.block_on(admin.export_state("f")).unwrap();

    let http = reqwest::blocking::Client::new();
    let url = |p: &str| format!("{}{p}", server.url);
    let create = br#"{"id":"g","width":4,"height":4}"#.to_vec();
    // (method, path, content type, body, the role it needs)
    let requests: Vec<(&str, String, &str, Vec<u8>, &str)> = vec![
        (
            "POST",
            url("/v1/frames/f/samples"),
            "application/x-splatd-batch",
            batch(0),
            "write",
        ),
        (
            "POST",
            url("/v1/frames/f/passes?worker=1&seq=0"),
            "image/x-exr",
            vec![0; 16],
            "write",
        ),
        (
            "POST",
            url("/v1/frames/f/sync"),
            "application/json",
            vec![],
            "write",
        ),
        (
            "POST",
            url("/v1/frames"),
            "application/json",
            create,
            "admin",
        ),
        ("DELETE", url("/v1/frames/f"), "", vec![], "admin"),
        (
            "POST",
            url("/v1/frames/f/state"),
            "application/x-splatd-state",
            state.to_vec(),
            "admin",
        ),
        ("GET", url("/v1/frames/f/image.exr"), "", vec![], "read"),
        ("GET", url("/v1/frames"), "", vec![], "read"),
        ("GET", url("/metrics"), "", vec![], "read"),
    ];
    let send = |method: &str, u: &str, ct: &str, body: &[u8], token: Option<&str>| {
        let mut r = http.request(method.parse().unwrap(), u);
        if !ct.is_empty() {
            r = r.header("content-type", ct);
        }
        if let Some(t) = token {
            r = r.header("authorization", format!("Bearer {t}"));
        }
        let r = r.body(body.to_vec()).send().unwrap();
        let status = r.status().as_u16();
        let body: serde_json::Value = if status >= 400 {
            r.json().unwrap()
        } else {
            serde_json::Value::Null
        };
        (status, body)
    };
    for (method, u, ct, body, role) in &requests {
        let (status, err) = send(method, u, ct, body, None);
        assert_eq!(status, 401, "{method} {u} without a token: {err}");
        assert_eq!(err["error"], "unauthorized");
        let (status, _) = send(method, u, ct, body, Some("not-a-token-at-all-really"));
        assert_eq!(status, 401, "{method} {u} with a wrong token");
        let weaker: &[&str] = match *role {
            "write" => &[READ],
            "admin" => &[READ, WRITE],
            _ => &[WRITE],
        };
        for token in weaker {
            let (status, err) = send(method, u, ct, body, Some(token));
            assert_eq!(status, 403, "{method} {u} needs {role}: {err}");
            assert!(err["message"].as_str().unwrap().contains(role), "{err}");
        }
    }
    // Nothing changed: the frame exists, has no samples, and "g" was never created.
    let info = rt.block_on(admin.frame_info("f")).unwrap();
    assert_eq!(
        (info.samples, info.batches, info.rejected_batches),
        (0, 0, 0)
    );
    assert_eq!(rt.block_on(admin.list_frames()).unwrap().len(), 1);

    // The right roles work, and health and the page need none.
    let writer = Client::new(&server.url).unwrap().with_token(WRITE);
    let ack = rt
        .block_on(writer.post_encoded("f", batch(0).into()))
        .unwrap();
    assert_eq!(ack.accepted, 64);
    let reader = Client::new(&server.url).unwrap().with_token(READ);
    rt.block_on(reader.image("f", &ImageQuery::default()))
        .unwrap();
    assert_eq!(send("GET", &url("/healthz"), "", &[], None).0, 200);
    assert_eq!(send("GET", &url("/"), "", &[], None).0, 200);

    drop(server);
    let log = std::fs::read_to_string(&log).unwrap();
    assert!(
        log.contains("bearer tokens required"),
        "debug log was written"
    );
    for t in [WRITE, READ, ADMIN] {
        assert!(!log.contains(t), "a token appears in the server log");
    }
}

#[test]
fn public_read_opens_reads_only() {
    let server = Server::start_with_env(
        &["--public-read"],
        &[("SPLATD_TOKENS", &format!("admin {ADMIN}"))],
    );
    let rt = runtime();
    let anonymous = Client::new(&server.url).unwrap();
    assert!(rt.block_on(anonymous.list_frames()).unwrap().is_empty());
    assert!(rt
        .block_on(anonymous.create_frame(&CreateFrame::new("x", 4, 4)))
        .is_err());
}
