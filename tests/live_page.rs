//! The live page (`GET /`) in a real browser: headless Chromium, driven through chromedriver
//! with plain W3C WebDriver calls, against a real `splatd serve` on loopback.
//!
//! The browser is installed by `tests/setup/chromium.sh` (Debian's `chromium` and
//! `chromium-driver`); a failure to install is a test failure. Set `SPLATD_SKIP_BROWSER=1` to
//! skip this test on machines that cannot have a browser. Every run stores a screenshot of the
//! page beside the test server's log, named after it (the path is printed); with
//! `SPLATD_REFRESH_DOCS=1` it replaces `docs/live_page.png` (the README shows it), so a test run
//! leaves the clone as it was and the README's image changes only on purpose.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::common;
use crate::common::{runtime, Server};
use serde_json::{json, Value};
use splatd_proto::api::{Convergence, CreateFrame, WaitingOn};
use splatd_proto::{Batch, Client, Record};
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
    /// The driver's and the browser's `TMPDIR`, removed after them: Chromium leaves the
    /// directory of its singleton socket (`org.chromium.Chromium.*`) behind in it when its
    /// session ends, two a run in the machine's `/tmp` before.
    _tmp: tempfile::TempDir,
}

/// What chromedriver prints on stdout once it listens (with `--port=0`, on a port it chose).
const DRIVER_READY: &str = "ChromeDriver was started successfully on port ";

impl Driver {
    /// Starts chromedriver on a port of its choosing and waits for the line naming it: ready is
    /// that event, and no other program can take the port in between.
    fn start(path: &Path) -> Driver {
        let tmp = tempfile::tempdir().expect("temp dir");
        let mut child = Command::new(path)
            .env("TMPDIR", tmp.path())
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
        let mut driver = Driver {
            child,
            port: 0,
            _tmp: tmp,
        };
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

    /// Clicks frame `id` in the page's frame list, once the list shows it (it is fetched again
    /// every second).
    async fn open_frame(&self, id: &str) {
        let link = format!("nav a[data-frame=\"{id}\"]");
        self.wait_for(
            &format!("frame {id} in the frame list"),
            &format!("return document.querySelector('{link}') !== null;"),
            |v| v.as_bool().filter(|&b| b),
        )
        .await;
        self.click(&link).await;
    }

    async fn click(&self, css: &str) {
        let element = self.element(css).await;
        self.cmd(
            "POST",
            &format!("/element/{element}/click"),
            Some(json!({})),
        )
        .await;
    }

    /// The element matching `css`; panics naming it when there is none.
    async fn element(&self, css: &str) -> String {
        let found = self
            .cmd(
                "POST",
                "/element",
                Some(json!({"using": "css selector", "value": css})),
            )
            .await;
        found[ELEMENT_KEY]
            .as_str()
            .unwrap_or_else(|| panic!("no element reference for {css:?}: {found}"))
            .to_owned()
    }

    /// Types `text` into the element matching `css`, as a user would.
    async fn type_into(&self, css: &str, text: &str) {
        let element = self.element(css).await;
        self.cmd(
            "POST",
            &format!("/element/{element}/value"),
            Some(json!({ "text": text })),
        )
        .await;
    }

    /// Drags the mouse from `from` to `to` (viewport pixels) with the left button held, in a
    /// few steps, then releases it.
    async fn drag(&self, from: (f64, f64), to: (f64, f64)) {
        let at = |(x, y): (f64, f64)| {
            json!({"type": "pointerMove", "duration": 0, "origin": "viewport",
                   "x": x.round() as i64, "y": y.round() as i64})
        };
        let mut steps = vec![at(from), json!({"type": "pointerDown", "button": 0})];
        for i in 1..=4 {
            let t = f64::from(i) / 4.0;
            steps.push(at((
                from.0 + (to.0 - from.0) * t,
                from.1 + (to.1 - from.1) * t,
            )));
        }
        steps.push(json!({"type": "pointerUp", "button": 0}));
        let actions = json!({"actions": [{"type": "pointer", "id": "mouse",
            "parameters": {"pointerType": "mouse"}, "actions": steps}]});
        self.cmd("POST", "/actions", Some(actions)).await;
        self.cmd("DELETE", "/actions", None).await;
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

/// The server's latest convergence figures of `frame`.
async fn verdict_of(client: &Client, frame: &str) -> Convergence {
    client
        .frame_info(frame)
        .await
        .expect("frame info")
        .convergence
        .expect("figures of a frame with samples")
}

/// What the page's verdict says for these figures: the server's verdict, and what it waits on
/// in the page's words.
fn page_verdict(c: &Convergence) -> String {
    match c.waiting_on {
        None => "yes".to_owned(),
        Some(WaitingOn::PixelsWithoutSamples) => "no: pixels without samples".to_owned(),
        Some(WaitingOn::RemovedEnergy) => "no".to_owned(),
        Some(WaitingOn::OwnSamples) => format!(
            "no: {:.1} % short of own samples",
            100.0 * c.deficit_fraction
        ),
    }
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

/// What the page shows: both images (which request they show, size, pixel sum), their
/// on-screen box, the divider's, the split, the stats and the plot's points. `null` while an
/// image has not loaded.
const PAGE_PROBE: &str = r##"
const shot = (id) => {
  const img = document.getElementById(id);
  if (!img || !img.dataset.src || !img.complete || img.naturalWidth === 0) return null;
  const canvas = document.createElement("canvas");
  canvas.width = img.naturalWidth;
  canvas.height = img.naturalHeight;
  const ctx = canvas.getContext("2d");
  ctx.drawImage(img, 0, 0);
  const data = ctx.getImageData(0, 0, canvas.width, canvas.height).data;
  let sum = 0;
  for (let i = 0; i < data.length; i += 4) sum += data[i] + data[i + 1] + data[i + 2];
  return { src: img.dataset.src, width: img.naturalWidth, height: img.naturalHeight, sum };
};
const mean = shot("mean"), reweighted = shot("reweighted");
if (!mean || !reweighted) return null;
const box = (id) => {
  const r = document.getElementById(id).getBoundingClientRect();
  return { left: r.left, top: r.top, width: r.width, height: r.height };
};
const points = [...document.querySelectorAll("#plot circle")].map(
  (c) => [Number(c.dataset.spp), Number(c.dataset.removed)]);
const heat = document.getElementById("heat");
return { mean, reweighted, image: box("reweighted"), viewport: box("viewport"),
         divider: box("divider"), clip: document.getElementById("reweighted").style.clipPath,
         spp: document.getElementById("spp").textContent,
         nav: document.querySelector("#frames a small")?.textContent,
         converged: document.getElementById("converged").textContent,
         points, heat_tiles: Number(heat.dataset.tiles || 0),
         heat_samples: Number(heat.dataset.samples || 0), heat_hidden: heat.hidden };
"##;

fn num(v: &Value, path: &[&str]) -> f64 {
    let mut v = v;
    for key in path {
        v = &v[*key];
    }
    v.as_f64()
        .unwrap_or_else(|| panic!("{path:?} is not a number in {v}"))
}

fn close(a: f64, b: f64, what: &str) {
    assert!((a - b).abs() <= 1.0, "{what}: {a} vs {b}");
}

/// The page lists the frame and shows it split between mean and reweighted, fit to the
/// window; 1:1 and panning move the image as asked, the divider follows a drag, the exposure
/// slider brightens the images, the convergence plot gains a point as samples arrive (and falls),
/// and the heat map shows the need map's tiles. Stores a screenshot for README.
#[test]
fn live_page_zooms_pans_splits_exposes_and_plots_convergence() {
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
        session.open_frame(FRAME).await;

        // Fit to the window: both layers at the frame's size, scaled to fill the viewport.
        let at4 = session
            .wait_for("both images of 4 spp and a plot point", PAGE_PROBE, |v| {
                (v["spp"] == "4 / 4.0 / 4" && v["points"].as_array()?.len() == 1).then(|| v.clone())
            })
            .await;
        for layer in ["mean", "reweighted"] {
            assert_eq!(
                (num(&at4, &[layer, "width"]), num(&at4, &[layer, "height"])),
                (f64::from(WIDTH), f64::from(HEIGHT)),
                "{layer} has the frame's size"
            );
            let src = at4[layer]["src"].as_str().unwrap();
            assert!(
                src.contains(&format!("/v1/frames/{FRAME}/preview.png?layer={layer}")),
                "{src}"
            );
            assert!(num(&at4, &[layer, "sum"]) > 0.0, "{layer} is not black");
        }
        // The verdict is the server's (here the caustic's removed energy holds it back).
        let c = verdict_of(&client, FRAME).await;
        assert_eq!(c.waiting_on, Some(WaitingOn::RemovedEnergy), "{c:?}");
        assert_eq!(at4["converged"], page_verdict(&c).as_str(), "{c:?}");
        let (vw, vh) = (
            num(&at4, &["viewport", "width"]),
            num(&at4, &["viewport", "height"]),
        );
        let fit = ((vw - 2.0) / f64::from(WIDTH)).min((vh - 2.0) / f64::from(HEIGHT));
        assert!(
            fit > 1.5,
            "the viewport is larger than the frame: {vw}x{vh}"
        );
        close(
            num(&at4, &["image", "width"]),
            f64::from(WIDTH) * fit,
            "fit width",
        );
        close(
            num(&at4, &["image", "height"]),
            f64::from(HEIGHT) * fit,
            "fit height",
        );
        // The divider starts in the middle of the image.
        let middle = num(&at4, &["image", "left"]) + num(&at4, &["image", "width"]) / 2.0;
        let divider =
            |v: &Value| num(v, &["divider", "left"]) + num(v, &["divider", "width"]) / 2.0;
        close(divider(&at4), middle, "divider in the middle");

        // 1:1: one screen pixel per frame pixel, centred.
        session.click("#one").await;
        let one = session
            .wait_for("the image at 1:1", PAGE_PROBE, |v| {
                let w = v["image"]["width"].as_f64()?;
                ((w - f64::from(WIDTH)).abs() < 0.5).then(|| v.clone())
            })
            .await;
        close(
            num(&one, &["image", "height"]),
            f64::from(HEIGHT),
            "1:1 height",
        );
        let (left, top) = (num(&one, &["image", "left"]), num(&one, &["image", "top"]));
        close(
            left + f64::from(WIDTH) / 2.0,
            num(&one, &["viewport", "left"]) + vw / 2.0,
            "1:1 is centred",
        );

        // Pan: dragging the picture (away from the divider) moves it by the drag.
        let grab = (left + 20.0, top + 20.0);
        session.drag(grab, (grab.0 + 60.0, grab.1 + 40.0)).await;
        let panned = session
            .wait_for("the image panned", PAGE_PROBE, |v| {
                let l = v["image"]["left"].as_f64()?;
                ((l - left - 60.0).abs() <= 1.0).then(|| v.clone())
            })
            .await;
        close(num(&panned, &["image", "top"]), top + 40.0, "panned down");
        close(
            num(&panned, &["image", "width"]),
            f64::from(WIDTH),
            "panning keeps 1:1",
        );

        // Split: dragging the divider 50 px left puts it at a quarter of the 200 px image.
        let (left, top) = (
            num(&panned, &["image", "left"]),
            num(&panned, &["image", "top"]),
        );
        let from = (divider(&panned), top + 75.0);
        close(from.0, left + 100.0, "divider in the middle at 1:1");
        session.drag(from, (from.0 - 50.0, from.1)).await;
        let split = session
            .wait_for("the divider moved", PAGE_PROBE, |v| {
                (v["clip"] == "inset(0px 0px 0px 25%)").then(|| v.clone())
            })
            .await;
        close(divider(&split), left + 50.0, "divider at a quarter");
        close(
            num(&split, &["image", "left"]),
            left,
            "dragging the divider does not pan",
        );

        // Exposure: +2 EV makes both images brighter.
        let before = num(&split, &["reweighted", "sum"]);
        session
            .execute(
                "const s = document.getElementById('exposure'); s.value = '2'; \
                 s.dispatchEvent(new Event('input'));",
            )
            .await;
        let brighter = session
            .wait_for("the images at +2 EV", PAGE_PROBE, |v| {
                let ok = v["reweighted"]["src"].as_str()?.contains("stops=2")
                    && v["mean"]["src"].as_str()?.contains("stops=2");
                ok.then(|| v.clone())
            })
            .await;
        assert!(
            num(&brighter, &["reweighted", "sum"]) > before * 1.2,
            "+2 EV brightens: {before} then {}",
            brighter["reweighted"]["sum"]
        );

        // The plot gains points as samples arrive, and the removed energy falls.
        post_passes(&client, &tracer, 4..16).await;
        let at16 = session
            .wait_for(
                "the frame at 16 spp in the stats and the plot",
                PAGE_PROBE,
                |v| {
                    let points = v["points"].as_array()?;
                    let last = points.last()?.as_array()?;
                    (v["spp"] == "16 / 16.0 / 16"
                        && v["nav"] == format!("{WIDTH}x{HEIGHT}, 16.0 spp")
                        && last[0].as_f64()? == 16.0
                        && v["reweighted"]["src"].as_str()?.contains("samples=480000"))
                    .then(|| v.clone())
                },
            )
            .await;
        let points = at16["points"].as_array().unwrap();
        assert!(points.len() >= 2, "a point per version seen: {points:?}");
        let removed = |p: &Value| p[1].as_f64().unwrap();
        assert!(
            removed(points.last().unwrap()) < removed(&points[0]),
            "removed energy falls from 4 to 16 spp: {points:?}"
        );
        assert_eq!(
            at16["converged"], "no",
            "16 spp of a caustic is not converged"
        );

        // The heat map: the need map's 13 x 10 tiles of 16 px, for all the samples.
        session.click("#heat-toggle").await;
        session
            .wait_for("the heat map", PAGE_PROBE, |v| {
                (v["heat_tiles"] == 130
                    && v["heat_samples"] == 480_000
                    && v["heat_hidden"] == false)
                    .then_some(())
            })
            .await;

        // For the screenshot: back to the automatic exposure, fit to the window.
        session
            .execute(
                "const s = document.getElementById('exposure'); s.value = '0'; \
                 s.dispatchEvent(new Event('input'));",
            )
            .await;
        session
            .wait_for("the images at +0 EV", PAGE_PROBE, |v| {
                v["reweighted"]["src"]
                    .as_str()?
                    .contains("stops=0&")
                    .then_some(())
            })
            .await;
        session.click("#fit").await;
        session
            .wait_for("the image fit again", PAGE_PROBE, |v| {
                let w = v["image"]["width"].as_f64()?;
                ((w - f64::from(WIDTH) * fit).abs() <= 1.0).then_some(())
            })
            .await;
        let png = session.screenshot().await;
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n", "the screenshot is a PNG");
        let path = if std::env::var_os("SPLATD_REFRESH_DOCS").is_some_and(|v| v == "1") {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/live_page.png")
        } else {
            // Beside the server's log, named after it.
            let log = server.log_path().map(|log| log.with_extension("png"));
            log.unwrap_or_else(|| std::env::temp_dir().join("splatd-live-page.png"))
        };
        std::fs::write(&path, png).unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
        eprintln!("saved the screenshot in {}", path.display());
        drop(session);
        drop(driver);
    });
}

/// On a server with tokens the page asks for one; typed into the token field it is kept for
/// the tab only (sessionStorage, not localStorage) and every request, images included, carries
/// it.
#[test]
fn live_page_reads_with_a_token_kept_in_the_session_only() {
    let Some((chromium, chromedriver)) = browser() else {
        return;
    };
    const READ: &str = "read-token-for-the-live-page";
    const ADMIN: &str = "admin-token-for-the-live-page";
    let dir = tempfile::tempdir().expect("temp dir");
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, format!("read {READ}\nadmin {ADMIN}\n")).expect("tokens file");
    let server = Server::start(&["--tokens-file", tokens.to_str().unwrap()]);
    let rt = runtime();
    rt.block_on(async {
        let client = Client::new(&server.url).expect("client").with_token(ADMIN);
        client
            .create_frame(&CreateFrame::new(FRAME, WIDTH, HEIGHT))
            .await
            .expect("frame created");
        post_passes(&client, &Tracer::new(WIDTH, HEIGHT), 0..2).await;

        let driver = Driver::start(&chromedriver);
        let session = Session::open(&driver, &chromium).await;
        session.goto(&format!("{}/#{FRAME}", server.url)).await;
        let asks = "const a = document.getElementById('auth'); \
                    return a.hidden ? null : a.textContent;";
        let said = session
            .wait_for("the page asking for a token", asks, |v| {
                v.as_str().map(str::to_owned)
            })
            .await;
        assert_eq!(said, "token needed");
        let listed =
            format!("return document.querySelector('nav a[data-frame=\"{FRAME}\"]') !== null;");
        assert_eq!(
            session.execute(&listed).await,
            json!(false),
            "no frames without a token"
        );

        session.type_into("#token", READ).await;
        session
            .wait_for("both images loaded with the token", PAGE_PROBE, |v| {
                (v["spp"] == "2 / 2.0 / 2").then_some(())
            })
            .await;
        let stored = session
            .execute("return [sessionStorage.getItem('splatd.token'), localStorage.length];")
            .await;
        assert_eq!(stored, json!([READ, 0]), "kept in sessionStorage only");

        // A reload in the same tab keeps it; the field shows it (masked).
        session.goto(&format!("{}/#{FRAME}", server.url)).await;
        session
            .wait_for("the frame after a reload", PAGE_PROBE, |v| {
                (v["spp"] == "2 / 2.0 / 2").then_some(())
            })
            .await;
        let field = session
            .execute("const t = document.getElementById('token'); return [t.value, t.type];")
            .await;
        assert_eq!(field, json!([READ, "password"]));

        // A smooth frame of two samples a pixel removes nothing, yet is not converged: each
        // pixel's own samples are short of full support, and the page says so.
        client
            .create_frame(&CreateFrame::new("grey", WIDTH, HEIGHT))
            .await
            .expect("frame created");
        for seq in 0..2 {
            let records = (0..WIDTH * HEIGHT)
                .map(|p| Record::new(p % WIDTH, p / WIDTH, [0.5; 3]))
                .collect();
            let batch = Batch::new("grey", 1, seq, records).expect("a batch");
            client.post_batch(&batch).await.expect("batch accepted");
        }
        session.open_frame("grey").await;
        // `-` until the figures of the grey frame's first render are in.
        let probe = "return [document.getElementById('title').textContent, \
                     document.getElementById('converged').textContent];";
        let title = format!("grey ({WIDTH}x{HEIGHT})");
        let shown = session
            .wait_for("the grey frame's verdict", probe, |v| {
                (v[0] == title.as_str() && v[1] != "-").then(|| v[1].clone())
            })
            .await;
        let c = verdict_of(&client, "grey").await;
        assert_eq!(c.waiting_on, Some(WaitingOn::OwnSamples), "{c:?}");
        assert_eq!(shown, page_verdict(&c).as_str(), "{c:?}");
        drop(session);
        drop(driver);
    });
}
