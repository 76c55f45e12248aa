//! AOV names are what OpenEXR can hold (PROTOCOL.md, "AOVs"): printable ASCII, and at most 255
//! bytes for the `<name>.<channel>` that `image.exr` writes. Against real `splatd` processes:
//!
//! * every kind of name that broke frames before (a NUL, 300 and 30,000 characters, a
//!   300-character channel, `été`), and the kinds next to them, is refused by `POST /v1/frames`,
//!   `PUT /v1/frames/{id}` and `splatd post --create --aov` with 400 naming the rule, and no
//!   frame is created. Before the rule each was created (201), its passes were accepted, and
//!   every `image.exr` of the frame answered 500 (or, for `été`, was an EXR OpenEXR could not
//!   open);
//! * the longest and most exotic names the rule accepts go through a pass written by OpenEXR's
//!   own Python package and come back in `image.exr` as OpenEXR's Python reader reads it;
//! * a frame on disk with a name the rule refuses (created before it) does not stop the server:
//!   it is quarantined, naming the rule, and the other frames are served. Before the rule it was
//!   served, and its images failed.
//!
//! `SPLATD_BIN=/path/to/splatd` runs the same checks against another build (how the "before" was
//! seen). Needs `python3` with numpy and OpenEXR (`tests/run.sh` installs them).

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common::read_exr_with_python;
use serde_json::{json, Value};
use splatd_harness::{Options, ServerProcess};

const W: u32 = 4;
const H: u32 = 3;

fn splatd() -> PathBuf {
    std::env::var_os("SPLATD_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_splatd")))
}

fn start(args: &[&str]) -> ServerProcess {
    ServerProcess::launch(&Options::new(splatd(), args)).unwrap_or_else(|e| panic!("{e}"))
}

fn http() -> reqwest::blocking::Client {
    reqwest::blocking::Client::new()
}

/// Status and JSON body of a response.
fn answer(r: reqwest::blocking::Response) -> (u16, Value) {
    let status = r.status().as_u16();
    let text = r.text().unwrap();
    let body = serde_json::from_str(&text).unwrap_or(Value::String(text));
    (status, body)
}

fn frames(server: &ServerProcess) -> Value {
    let (status, body) = answer(
        http()
            .get(format!("{}/v1/frames", server.url))
            .send()
            .unwrap(),
    );
    assert_eq!(status, 200, "{body}");
    body
}

/// A pass of `W`x`H` pixels written by OpenEXR's Python package: beauty `R`, `G`, `B` and a
/// constant channel per entry of `channels` (full channel name to value).
fn write_pass(path: &Path, channels: &Value) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/write_named_pass.py");
    let mut child = Command::new("python3")
        .arg(script)
        .arg(path)
        .args([W.to_string(), H.to_string()])
        .stdin(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("running python3 (tests/run.sh installs its packages)");
    use std::io::Write;
    child
        .stdin
        .take()
        .unwrap()
        .write_all(channels.to_string().as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "write_named_pass.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// One AOV as `CreateFrame` takes it.
fn aov(name: &str, channels: &[&str]) -> Value {
    json!({"name": name, "channels": channels})
}

#[test]
fn names_openexr_cannot_hold_are_refused_at_creation_and_nothing_is_created() {
    let long = |c: char, n: usize| std::iter::repeat_n(c, n).collect::<String>();
    // (what, the AOV, the rule the answer must name)
    let cases: Vec<(&str, Value, &str)> = vec![
        (
            "a NUL in a name",
            aov("Diff\0Col", &["R"]),
            "characters rule",
        ),
        (
            "a NUL in a channel",
            aov("DiffCol", &["R\0"]),
            "characters rule",
        ),
        (
            "a tab in a channel",
            aov("DiffCol", &["R\tG"]),
            "characters rule",
        ),
        (
            "a newline in a name",
            aov("Diff\nCol", &["R"]),
            "characters rule",
        ),
        (
            "DEL in a name",
            aov("Diff\u{7f}", &["R"]),
            "characters rule",
        ),
        (
            "a 300-character name",
            aov(&long('a', 300), &["R"]),
            "length rule",
        ),
        (
            "a 30,000-character name",
            aov(&long('b', 30_000), &["R"]),
            "length rule",
        ),
        (
            "a 300-character channel",
            aov("DiffCol", &[&long('c', 300)]),
            "length rule",
        ),
        // Each part fits, the channel name image.exr writes (250 + 1 + 5 bytes) does not.
        (
            "a 256-byte <name>.<channel>",
            aov(&long('n', 250), &["RGBAX"]),
            "length rule",
        ),
        ("a Latin-1 name", aov("été", &["R"]), "encoding rule"),
        ("a non-Latin-1 name", aov("深度", &["Z"]), "encoding rule"),
        ("a non-ASCII channel", aov("Depth", &["Ž"]), "encoding rule"),
    ];
    let server = start(&[]);
    for (what, bad, rule) in &cases {
        let good = aov("ViewLayer.Depth", &["Z"]);
        let body = json!({"width": W, "height": H, "aovs": [good, bad]});
        let mut post = body.clone();
        post["id"] = json!("bad");
        let answers = [
            (
                "POST /v1/frames",
                http()
                    .post(format!("{}/v1/frames", server.url))
                    .json(&post)
                    .send()
                    .unwrap(),
            ),
            (
                "PUT /v1/frames/bad",
                http()
                    .put(format!("{}/v1/frames/bad", server.url))
                    .json(&body)
                    .send()
                    .unwrap(),
            ),
        ];
        for (request, response) in answers {
            let (status, body) = answer(response);
            assert_eq!(status, 400, "{what}: {request} answered {body}");
            assert_eq!(body["error"], "invalid_parameters", "{what}: {body}");
            let message = body["message"].as_str().unwrap();
            assert!(message.contains(rule), "{what}: {request}: {message}");
            assert!(
                message.len() < 1000,
                "{what}: the message quotes a long name cut short: {} bytes",
                message.len()
            );
        }
        let (status, _) = answer(
            http()
                .get(format!("{}/v1/frames/bad", server.url))
                .send()
                .unwrap(),
        );
        assert_eq!(status, 404, "{what}: no frame was created");
    }
    assert_eq!(frames(&server)["frames"], json!([]));

    // `splatd post --create --aov` creates with PUT: refused the same way, nothing posted.
    let dir = tempfile::tempdir().unwrap();
    let pass = dir.path().join("pass.exr");
    write_pass(&pass, &json!({}));
    for (aov, rule) in [
        ("été=R".to_string(), "encoding rule"),
        (format!("{}=R", long('a', 300)), "length rule"),
        ("Diff\tCol=R".to_string(), "characters rule"),
    ] {
        let out = Command::new(splatd())
            .args([
                "post",
                "--url",
                &server.url,
                "--frame",
                "posted",
                "--create",
            ])
            .args(["--aov", &aov])
            .arg(&pass)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "post --aov {aov:.20} succeeded");
        assert!(stderr.contains("400") && stderr.contains(rule), "{stderr}");
    }
    assert_eq!(frames(&server)["frames"], json!([]));
}

#[test]
fn the_longest_and_most_exotic_names_accepted_read_back_with_openexr() {
    let long = |c: char, n: usize| std::iter::repeat_n(c, n).collect::<String>();
    // (AOV name, channel, value): the name image.exr writes is `name.channel`.
    let longest_name = long('L', 253); // + ".R": 255 bytes, the limit
    let longest_channel = long('c', 253); // "x." + it: 255 bytes
    let exotic = r#"View Layer #1 (key) ~!@$%^&*[]{}<>|\/?;:'",+=-_`.Diff Col"#;
    let aovs: Vec<(&str, &str, f64)> = vec![
        (&longest_name, "R", 0.25),
        ("x", &longest_channel, 0.5),
        (exotic, "r g!", 0.75),
        // 32 bytes: just over the short names of files without the long-names flag.
        ("ViewLayer.DenoisingAlbedo", "Xyzwvu", 1.5),
    ];
    let full = |(n, c, _): &(&str, &str, f64)| format!("{n}.{c}");
    assert_eq!(full(&aovs[0]).len(), 255);
    assert_eq!(full(&aovs[1]).len(), 255);
    assert_eq!(full(&aovs[3]).len(), 32);

    let server = start(&[]);
    let spec: Vec<Value> = aovs.iter().map(|(n, c, _)| aov(n, &[c])).collect();
    let (status, info) = answer(
        http()
            .put(format!("{}/v1/frames/names", server.url))
            .json(&json!({"width": W, "height": H, "aovs": spec}))
            .send()
            .unwrap(),
    );
    assert_eq!(status, 201, "{info}");
    assert_eq!(info["aovs"], json!(spec), "the names are kept as given");

    let dir = tempfile::tempdir().unwrap();
    let pass = dir.path().join("pass.exr");
    let channels: serde_json::Map<String, Value> =
        aovs.iter().map(|a| (full(a), json!(a.2))).collect();
    write_pass(&pass, &Value::Object(channels));
    for seq in 0..2 {
        let (status, ack) = answer(
            http()
                .post(format!(
                    "{}/v1/frames/names/passes?worker=1&seq={seq}",
                    server.url
                ))
                .header("content-type", "image/x-exr")
                .body(std::fs::read(&pass).unwrap())
                .send()
                .unwrap(),
        );
        assert_eq!(status, 200, "{ack}");
        assert_eq!(ack["accepted"], (W * H) as u64);
    }

    let response = http()
        .get(format!("{}/v1/frames/names/image.exr", server.url))
        .send()
        .unwrap();
    assert_eq!(response.status().as_u16(), 200);
    let exr = dir.path().join("image.exr");
    let bytes = response.bytes().unwrap();
    // OpenEXR sets the long-names flag (bit 10 of the version field) for names over 31 bytes.
    assert_ne!(bytes[5] & 0b100, 0, "long-names flag");
    std::fs::write(&exr, &bytes).unwrap();
    let (w, h, read) = read_exr_with_python(&exr);
    assert_eq!((w, h), (W, H));
    for a in &aovs {
        let name = full(a);
        let values = read
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, v)| v)
            .unwrap_or_else(|| {
                let names: Vec<&String> = read.iter().map(|(n, _)| n).collect();
                panic!("OpenEXR reads no channel {name:?}; it reads {names:?}")
            });
        // Two passes of a constant: their mean, exact in the AOVs' 2^-20 steps.
        assert!(values.iter().all(|&v| v == a.2), "{name:?}: {values:?}");
    }
    let r = &read.iter().find(|(n, _)| n == "mean.R").unwrap().1;
    assert!(r.iter().all(|&v| v == 1.0), "the beauty's mean: {r:?}");
}

#[test]
fn a_frame_on_disk_with_a_name_now_refused_is_quarantined_and_the_rest_served() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().to_str().unwrap();
    let server = start(&["--data-dir", data]);
    for id in ["old", "good"] {
        let (status, body) = answer(
            http()
                .put(format!("{}/v1/frames/{id}", server.url))
                .json(&json!({"width": W, "height": H, "aovs": [aov("Depth", &["Z"])]}))
                .send()
                .unwrap(),
        );
        assert_eq!(status, 201, "{body}");
    }
    assert_eq!(server.terminate(), Some(0));

    // As a server before the rule would have written it.
    let meta = dir.path().join("frames/old/frame.json");
    let json = std::fs::read_to_string(&meta).unwrap();
    assert!(json.contains(r#""Depth""#), "{json}");
    std::fs::write(&meta, json.replace(r#""Depth""#, r#""De\u0000pth""#)).unwrap();

    let server = start(&["--data-dir", data]);
    let listed = frames(&server);
    let ids: Vec<&str> = listed["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["id"].as_str().unwrap())
        .collect();
    assert_eq!(ids, ["good"], "{listed}");
    let quarantined = listed["quarantined"].as_array().unwrap();
    assert_eq!(quarantined.len(), 1, "{listed}");
    assert_eq!(quarantined[0]["id"], "old");
    let reason = quarantined[0]["reason"].as_str().unwrap();
    assert!(reason.contains("characters rule"), "{reason}");
    let moved_to = Path::new(quarantined[0]["moved_to"].as_str().unwrap());
    let kept = std::fs::read_to_string(moved_to.join("frame.json")).unwrap();
    assert!(kept.contains(r#""De\u0000pth""#), "kept as it was: {kept}");
    let (status, health) = answer(
        http()
            .get(format!("{}/healthz", server.url))
            .send()
            .unwrap(),
    );
    assert_eq!((status, health["status"].as_str()), (200, Some("degraded")));
    let (status, _) = answer(
        http()
            .get(format!("{}/v1/frames/good/image.exr", server.url))
            .send()
            .unwrap(),
    );
    assert_eq!(status, 200);
}
