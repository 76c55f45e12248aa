//! The live page (`GET /`) in a real browser: headless Chromium, driven through chromedriver
//! with plain W3C WebDriver calls, against a real `splatd serve` on loopback.
//!
//! The browser is installed by `tests/setup/chromium.sh` (Debian's `chromium` and
//! `chromium-driver`); a failure to install is a test failure. Set `SPLATD_SKIP_BROWSER=1` to
//! skip this test on machines that cannot have a browser. Set `SPLATD_SCREENSHOT=1` to save a
//! screenshot of the page to `docs/live.png`.

mod common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{runtime, Server};
use serde_json::{json, Value};
use splatd_proto::api::CreateFrame;
use splatd_proto::{Batch, Client};
use splatd_scenes::tracer::Tracer;

const FRAME: &str = "live-shot";
const WIDTH: u32 = 200;
const HEIGHT: u32 = 150;
const SEED: u64 = 7;

/// How long any one thing the page does may take to show.
const PAGE_DEADLINE: Duration = common::PATIENCE;

/// The W3C element reference key.
const ELEMENT_KEY: &str = "element-6066-11e4-a52e-4f735466cecf";

/// Installs (if needed) Chromium and chromedriver; returns their paths, or `None` when the
/// test is to be skipped.
fn browser() -> Option<(PathBuf, PathBuf)> {
    if std::env::var("SPLATD_SKIP_BROWSER").as_deref() == Ok("1") {
        eprintln!(
            "SPLATD_SKIP_BROWSER=1: skipping the live page test (it needs headless Chromium)"
        );
        return None;
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/setup/chromium.sh");
    let out = Command::new("bash")
        .arg(&script)
        .stderr(Stdio::inherit())
        .output()
        .expect("running tests/setup/chromium.sh");
    assert!(
        out.status.success(),
        "tests/setup/chromium.sh could not install chromium and chromedriver ({}); \
         set SPLATD_SKIP_BROWSER=1 to skip this test",
        out.status
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let lines: Vec<&str> = stdout.lines().filter(|l| !l.trim().is_empty()).collect();
    assert!(
        lines.len() >= 2,
        "chromium.sh should print the chromium and chromedriver paths, printed {stdout:?}"
    );
    let n = lines.len();
    Some((PathBuf::from(lines[n - 2]), PathBuf::from(lines[n - 1])))
}

/// A `chromedriver` process on a loopback port, killed when dropped.
struct Driver {
    child: Child,
    port: u16,
}

/// What chromedriver prints on stdout once it listens (with `--port=0`, on a port it chose).
const DRIVER_READY: &str = "ChromeDriver was started successfully on port ";

impl Driver {
    /// Starts chromedriver on a port of its choosing and waits for the line naming it: ready is
    /// that event, and no other program can take the port in between.
    fn start(path: &Path) -> Driver {
        let mut child = Command::new(path)
            .arg("--port=0")
            .arg("--allowed-ips=127.0.0.1")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", path.display()));
        let stdout = child.stdout.take().expect("stdout is piped");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut port = None;
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if port.is_none() {
                    port = line
                        .strip_prefix(DRIVER_READY)
                        .and_then(|rest| rest.trim_end_matches('.').trim().parse::<u16>().ok());
                    if let Some(p) = port {
                        let _ = tx.send(p);
                    }
                }
                // Keeps draining, so chromedriver never blocks on a full pipe.
            }
        });
        let mut driver = Driver { child, port: 0 };
        match rx.recv_timeout(PAGE_DEADLINE) {
            Ok(port) => driver.port = port,
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                let status = driver.child.wait();
                panic!("chromedriver exited ({status:?}) without saying it listens");
            }
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                panic!("chromedriver never said it listens (hung?)")
            }
        }
        driver
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One WebDriver session (one browser); the browser is closed when dropped, even after a panic.
struct Session {
    http: reqwest::Client,
    port: u16,
    id: String,
}

impl Session {
    /// Waits for chromedriver to be ready, then opens headless Chromium.
    async fn open(driver: &Driver, chromium: &Path) -> Session {
        let http = reqwest::Client::builder()
            // A cap against a hung browser only, like every wait here.
            .timeout(PAGE_DEADLINE)
            .build()
            .expect("HTTP client");
        let base = format!("http://127.0.0.1:{}", driver.port);
        // chromedriver said it listens; it must also say it is ready.
        let status = call(&http, "GET", &format!("{base}/status"), None).await;
        assert_eq!(
            status["ready"],
            json!(true),
            "chromedriver status: {status}"
        );
        let capabilities = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {
                "binary": chromium,
                "args": ["--headless=new", "--no-sandbox", "--disable-gpu",
                         "--disable-dev-shm-usage", "--window-size=1280,800"],
            },
        }}});
        let value = call(
            &http,
            "POST",
            &format!("{base}/session"),
            Some(capabilities),
        )
        .await;
        let id = value["sessionId"]
            .as_str()
            .unwrap_or_else(|| panic!("new session answered without a sessionId: {value}"))
            .to_owned();
        Session {
            http,
            port: driver.port,
            id,
        }
    }

    async fn cmd(&self, method: &str, path: &str, body: Option<Value>) -> Value {
        let url = format!("http://127.0.0.1:{}/session/{}{path}", self.port, self.id);
        call(&self.http, method, &url, body).await
    }

    async fn goto(&self, url: &str) {
        self.cmd("POST", "/url", Some(json!({ "url": url }))).await;
    }

    /// Runs `script` (a function body) in the page and returns its result.
    async fn execute(&self, script: &str) -> Value {
        self.cmd(
            "POST",
            "/execute/sync",
            Some(json!({"script": script, "args": []})),
        )
        .await
    }

    /// Waits until `probe` returns `Some`, polling every 100 ms up to [`PAGE_DEADLINE`]; the
    /// panic message names `what` and the last state seen.
    async fn wait_for<T>(
        &self,
        what: &str,
        script: &str,
        probe: impl Fn(&Value) -> Option<T>,
    ) -> T {
        let deadline = Instant::now() + PAGE_DEADLINE;
        loop {
            let value = self.execute(script).await;
            if let Some(t) = probe(&value) {
                return t;
            }
            assert!(
                Instant::now() < deadline,
                "the page did not show {what} within {PAGE_DEADLINE:?}; last seen: {value}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    async fn click(&self, css: &str) {
        let found = self
            .cmd(
                "POST",
                "/element",
                Some(json!({"using": "css selector", "value": css})),
            )
            .await;
        let element = found[ELEMENT_KEY]
            .as_str()
            .unwrap_or_else(|| panic!("no element reference for {css:?}: {found}"))
            .to_owned();
        self.cmd(
            "POST",
            &format!("/element/{element}/click"),
            Some(json!({})),
        )
        .await;
    }

    async fn screenshot(&self) -> Vec<u8> {
        let value = self.cmd("GET", "/screenshot", None).await;
        base64_decode(value.as_str().expect("screenshot is a base64 string"))
    }
}

impl Drop for Session {
    /// Closes the browser with a plain, bounded HTTP request (no runtime is needed in `drop`).
    fn drop(&mut self) {
        let Ok(mut stream) = TcpStream::connect(("127.0.0.1", self.port)) else {
            return;
        };
        let _ = stream.set_read_timeout(Some(Duration::from_secs(10)));
        let _ = stream.set_write_timeout(Some(Duration::from_secs(10)));
        let request = format!(
            "DELETE /session/{} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nConnection: close\r\n\r\n",
            self.id, self.port
        );
        if stream.write_all(request.as_bytes()).is_ok() {
            let _ = stream.read_to_end(&mut Vec::new());
        }
    }
}

/// One WebDriver command; returns its `value`, panicking with the driver's error otherwise.
async fn call(http: &reqwest::Client, method: &str, url: &str, body: Option<Value>) -> Value {
    let method = reqwest::Method::from_bytes(method.as_bytes()).expect("HTTP method");
    let mut request = http.request(method.clone(), url);
    if let Some(body) = body {
        request = request
            .header("Content-Type", "application/json")
            .body(serde_json::to_vec(&body).expect("JSON"));
    }
    let response = request
        .send()
        .await
        .unwrap_or_else(|e| panic!("WebDriver {method} {url}: {e}"));
    let status = response.status();
    let bytes = response.bytes().await.expect("WebDriver response body");
    let value: Value = serde_json::from_slice(&bytes).unwrap_or_else(|e| {
        panic!(
            "WebDriver {method} {url}: HTTP {status}, not JSON ({e}): {}",
            String::from_utf8_lossy(&bytes)
        )
    });
    assert!(
        status.is_success(),
        "WebDriver {method} {url} failed with HTTP {status}: {value}"
    );
    value["value"].clone()
}

/// Standard base64 (with padding, whitespace ignored), for the screenshot.
fn base64_decode(text: &str) -> Vec<u8> {
    let digit = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => u32::from(c - b'A'),
            b'a'..=b'z' => u32::from(c - b'a') + 26,
            b'0'..=b'9' => u32::from(c - b'0') + 52,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("invalid base64 character {:?}", c as char),
        }
    };
    let clean: Vec<u8> = text
        .bytes()
        .filter(|c| !c.is_ascii_whitespace() && *c != b'=')
        .collect();
    let mut out = Vec::with_capacity(clean.len() * 3 / 4);
    for chunk in clean.chunks(4) {
        let mut bits = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            bits |= digit(c) << (18 - 6 * i);
        }
        let bytes = bits.to_be_bytes();
        out.extend_from_slice(&bytes[1..chunk.len()]);
    }
    out
}

/// Sends passes `passes` of the path tracer to the frame, one batch per pass.
async fn post_passes(client: &Client, tracer: &Tracer, passes: std::ops::Range<u64>) {
    for pass in passes {
        let mut records = Vec::new();
        tracer.render_rows(0..HEIGHT, pass, SEED, &mut records);
        let batch = Batch {
            frame: FRAME.to_owned(),
            worker: 1,
            seq: pass,
            records,
        };
        let ack = client.post_batch(&batch).await.expect("batch accepted");
        assert_eq!(ack.accepted, u64::from(WIDTH * HEIGHT));
    }
}

/// What the page shows of the preview: its `src`, size, a hash of its pixels and the spp text;
/// `null` while the current `src` has not loaded.
const PREVIEW_PROBE: &str = r#"
const img = document.getElementById("preview");
if (!img || !img.src || !img.complete || img.naturalWidth === 0) return null;
const canvas = document.createElement("canvas");
canvas.width = img.naturalWidth;
canvas.height = img.naturalHeight;
const ctx = canvas.getContext("2d");
ctx.drawImage(img, 0, 0);
const data = ctx.getImageData(0, 0, canvas.width, canvas.height).data;
let hash = 2166136261 >>> 0, sum = 0;
for (let i = 0; i < data.length; i++) {
  hash = Math.imul(hash ^ data[i], 16777619) >>> 0;
  sum += data[i];
}
return { src: img.src, width: img.naturalWidth, height: img.naturalHeight, hash, sum,
         spp: document.getElementById("spp").textContent };
"#;

/// The preview as the probe reported it.
#[derive(Debug, Clone, PartialEq)]
struct Preview {
    src: String,
    width: u64,
    height: u64,
    hash: u64,
    sum: u64,
    spp: String,
}

fn preview(v: &Value) -> Option<Preview> {
    Some(Preview {
        src: v["src"].as_str()?.to_owned(),
        width: v["width"].as_u64()?,
        height: v["height"].as_u64()?,
        hash: v["hash"].as_u64()?,
        sum: v["sum"].as_u64()?,
        spp: v["spp"].as_str()?.to_owned(),
    })
}

/// The page lists the frame, shows its preview when clicked, and follows new samples: the
/// preview's `src`, its pixels and the spp figures all change after more samples are posted.
#[test]
fn live_page_shows_a_frame_and_follows_new_samples() {
    let Some((chromium, chromedriver)) = browser() else {
        return;
    };
    let server = Server::start(&[]);
    let rt = runtime();
    rt.block_on(async {
        let client = Client::new(&server.url).expect("client");
        client
            .create_frame(&CreateFrame::new(FRAME, WIDTH, HEIGHT))
            .await
            .expect("frame created");
        let tracer = Tracer::new(WIDTH, HEIGHT);
        post_passes(&client, &tracer, 0..4).await;

        let driver = Driver::start(&chromedriver);
        let session = Session::open(&driver, &chromium).await;
        session.goto(&format!("{}/", server.url)).await;
        let link = format!("nav a[data-frame=\"{FRAME}\"]");
        session
            .wait_for(
                "the frame in the frame list",
                &format!("return document.querySelector('{link}') !== null;"),
                |v| v.as_bool().filter(|&b| b),
            )
            .await;
        session.click(&link).await;

        let before = session
            .wait_for("the loaded preview of 4 spp", PREVIEW_PROBE, |v| {
                preview(v).filter(|p| p.spp.starts_with("4 / "))
            })
            .await;
        assert_eq!(
            (before.width, before.height),
            (u64::from(WIDTH), u64::from(HEIGHT)),
            "the preview has the frame's size"
        );
        assert_eq!(before.spp, "4 / 4.0 / 4", "spp min / mean / max");
        assert!(
            before
                .src
                .contains(&format!("/v1/frames/{FRAME}/preview.png")),
            "preview src {}",
            before.src
        );
        assert!(before.sum > 0, "the preview of 4 spp is not all black");
        let hash = session.execute("return location.hash;").await;
        assert_eq!(
            hash,
            json!(format!("#{FRAME}")),
            "clicking selects the frame"
        );

        post_passes(&client, &tracer, 4..16).await;
        // The page may catch the frame between batches; wait for the final state.
        let final_src = format!("samples={}", 16 * u64::from(WIDTH * HEIGHT));
        let after = session
            .wait_for("the preview of 16 spp", PREVIEW_PROBE, |v| {
                preview(v).filter(|p| p.spp == "16 / 16.0 / 16" && p.src.contains(&final_src))
            })
            .await;
        assert_ne!(after.src, before.src, "the preview's src changed");
        assert_ne!(
            after.hash, before.hash,
            "the preview's pixels changed after 12 more passes"
        );
        assert_eq!(
            (after.width, after.height),
            (u64::from(WIDTH), u64::from(HEIGHT))
        );

        if std::env::var("SPLATD_SCREENSHOT").as_deref() == Ok("1") {
            let png = session.screenshot().await;
            assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n", "the screenshot is a PNG");
            let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/live.png");
            std::fs::create_dir_all(path.parent().unwrap()).expect("docs/");
            std::fs::write(&path, png).expect("writing docs/live.png");
            eprintln!("saved {}", path.display());
        }
        drop(session);
        drop(driver);
    });
}
