//! Shared by the integration tests: real `splatd` processes on loopback ports, and small helpers.

use std::path::Path;
use std::process::Command;

pub use splatd_harness::{Log, Options, ServerProcess, PATIENCE};

/// A `splatd serve` process of this build (see `splatd-harness`), with the constructors the
/// tests use.
pub struct Server;

#[allow(clippy::new_ret_no_self)]
impl Server {
    /// Starts `splatd serve --addr 127.0.0.1:0 <args>` and waits for its "listening" line.
    pub fn start(args: &[&str]) -> ServerProcess {
        Self::start_with_env(args, &[])
    }

    /// Like [`Server::start`], with extra environment variables.
    pub fn start_with_env(args: &[&str], env: &[(&str, &str)]) -> ServerProcess {
        Self::launch(Options {
            env,
            ..Options::new(env!("CARGO_BIN_EXE_splatd"), args)
        })
    }

    /// Like [`Server::start_with_env`], with the server's log (stderr) written to `log`.
    pub fn start_logged(args: &[&str], env: &[(&str, &str)], log: &Path) -> ServerProcess {
        Self::launch(Options {
            env,
            log: Log::File(log),
            ..Options::new(env!("CARGO_BIN_EXE_splatd"), args)
        })
    }

    fn launch(options: Options<'_>) -> ServerProcess {
        ServerProcess::launch(&options).unwrap_or_else(|e| panic!("{e}"))
    }
}

/// Channels of an EXR as read by the OpenEXR project's Python bindings (an independent reader).
pub fn read_exr_with_python(path: &Path) -> (u32, u32, Vec<(String, Vec<f64>)>) {
    let v = read_exr_json(path);
    let width = v["width"].as_u64().expect("width") as u32;
    let height = v["height"].as_u64().expect("height") as u32;
    let mut channels: Vec<(String, Vec<f64>)> = v["channels"]
        .as_object()
        .expect("channels")
        .iter()
        .map(|(k, vals)| {
            let vals = vals
                .as_array()
                .expect("values")
                .iter()
                .map(|x| x.as_f64().expect("number"))
                .collect();
            (k.clone(), vals)
        })
        .collect();
    channels.sort_by(|a, b| a.0.cmp(&b.0));
    (width, height, channels)
}

/// The `software` and `splatd:` header attributes of an EXR as OpenEXR's Python bindings read
/// them: strings, numbers, and lists for vectors.
pub fn read_exr_attributes_with_python(path: &Path) -> serde_json::Value {
    read_exr_json(path)["attributes"].clone()
}

/// What `tests/py/read_exr.py` prints for `path`.
fn read_exr_json(path: &Path) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/read_exr.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(path)
        .output()
        .expect("running python3 (tests/run.sh installs its packages)");
    assert!(
        out.status.success(),
        "python EXR reader failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("reader prints JSON")
}

/// A multi-threaded runtime for tests that drive servers with async clients.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(4)
        .enable_all()
        .build()
        .expect("runtime")
}

/// A TCP forwarder on a loopback port the test owns for its whole life, relaying each
/// connection to whichever server is current: clients keep one URL while the server behind it
/// is killed and restarted on a new ephemeral port (no port can be taken by another test in
/// between). While no server is set, connections are closed at once, as a dead server's are.
pub struct Forwarder {
    /// `http://127.0.0.1:PORT`
    pub url: String,
    target: std::sync::Arc<std::sync::Mutex<Option<String>>>,
}

impl Forwarder {
    /// Starts forwarding to `target` (`127.0.0.1:PORT`).
    pub fn start(target: &str) -> Forwarder {
        use std::net::{TcpListener, TcpStream};
        let listener = TcpListener::bind("127.0.0.1:0").expect("binding a forwarder");
        let url = format!("http://{}", listener.local_addr().unwrap());
        let current = std::sync::Arc::new(std::sync::Mutex::new(Some(target.to_owned())));
        let shared = current.clone();
        // Plain threads: the forwarder lives as long as the test process, which is short.
        std::thread::spawn(move || {
            for conn in listener.incoming() {
                let Ok(client) = conn else { return };
                let target = shared.lock().unwrap().clone();
                let Some(server) = target.and_then(|t| TcpStream::connect(t).ok()) else {
                    drop(client);
                    continue;
                };
                let pipe = |mut from: TcpStream, mut to: TcpStream| {
                    std::thread::spawn(move || {
                        let _ = std::io::copy(&mut from, &mut to);
                        let _ = to.shutdown(std::net::Shutdown::Write);
                    });
                };
                let (c2, s2) = (client.try_clone().unwrap(), server.try_clone().unwrap());
                pipe(client, server);
                pipe(s2, c2);
            }
        });
        Forwarder {
            url,
            target: current,
        }
    }

    /// Relays new connections to `target`, or refuses them with `None`.
    pub fn point_at(&self, target: Option<&str>) {
        *self.target.lock().unwrap() = target.map(str::to_owned);
    }
}

/// `splatd serve` arguments for a durable server in `dir` that snapshots only when asked
/// (`POST .../sync`; the periodic snapshots are an hour apart), so a test knows exactly what
/// is on disk.
pub fn durable_args(dir: &Path) -> Vec<String> {
    vec![
        "--data-dir".into(),
        dir.display().to_string(),
        "--snapshot-interval-ms".into(),
        "3600000".into(),
    ]
}

/// A loopback port that was free a moment ago (a tiny race with other processes is possible; a
/// server then fails loudly to bind it).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("binding 127.0.0.1:0")
        .port()
}

/// The site-packages directory of a virtual environment's `python`, for a `PYTHONPATH` that lets
/// an interpreter outside the environment (Blender's, or `python3` with Mitsuba) import the
/// client package installed there.
pub fn venv_site_packages(python: &Path) -> String {
    let out = Command::new(python)
        .args([
            "-c",
            "import sysconfig; print(sysconfig.get_paths()['purelib'])",
        ])
        .output()
        .unwrap_or_else(|e| panic!("{}: {e}", python.display()));
    assert!(
        out.status.success(),
        "{} found no site-packages",
        python.display()
    );
    String::from_utf8_lossy(&out.stdout).trim().to_owned()
}

/// Whether this run is on CI (`CI=true`), where every tool the tests need is installed by
/// `tests/run.sh` and a test that cannot run is a failure.
pub fn on_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v == "true")
}

/// What a test does when `why` keeps it from checking what it is for (a tool could not be
/// installed): on CI it fails; elsewhere it goes on to skip, after a `SKIP` line on standard
/// error written past the test harness's capture (which never shows a passing test's output),
/// so that a skipped test cannot pass for one that ran.
pub fn skip_unless_ci(test: &str, why: &str) {
    use std::io::Write;
    assert!(
        !on_ci(),
        "{test}: {why}; CI must run this test, so there it fails instead of skipping"
    );
    let line = format!("\n!!!!!!!!!! SKIP {test}: {why}\n!!!!!!!!!! THIS TEST CHECKED NOTHING\n\n");
    let _ = std::io::stderr().write_all(line.as_bytes());
}

/// Runs `tests/setup/{script}`, which installs what a test needs (idempotently), and returns
/// what it printed (trimmed: the scripts print the path of what they installed), or what it
/// said on standard error when it failed.
pub fn run_setup(script: &str) -> Result<String, String> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/setup")
        .join(script);
    let out = Command::new("bash")
        .arg(&path)
        .output()
        .unwrap_or_else(|e| panic!("running {}: {e}", path.display()));
    if out.status.success() {
        Ok(String::from_utf8_lossy(&out.stdout).trim().to_owned())
    } else {
        Err(String::from_utf8_lossy(&out.stderr).trim().to_owned())
    }
}

/// A fresh Python virtual environment in `dir` with the client package installed by pip from a
/// copy of `proto/python` (so no build files land in the checkout); returns its `python`.
///
/// Needs `python3 -m venv` (`tests/setup/python_venv.sh` installs it) and pip's index or cache
/// for numpy, the package's one dependency.
pub fn python_package_venv(dir: &Path) -> std::path::PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    if let Err(e) = run_setup("python_venv.sh") {
        panic!("tests/setup/python_venv.sh failed: {e}");
    }
    let source = dir.join("splatd-client-src");
    let package = source.join("splatd_client");
    std::fs::create_dir_all(&package).unwrap();
    for file in ["pyproject.toml", "README.md"] {
        std::fs::copy(root.join("proto/python").join(file), source.join(file)).unwrap();
    }
    for entry in std::fs::read_dir(root.join("proto/python/splatd_client")).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            std::fs::copy(&path, package.join(path.file_name().unwrap())).unwrap();
        }
    }
    let venv = dir.join("venv");
    let run = |cmd: &mut Command, what: &str| {
        let out = cmd.output().unwrap_or_else(|e| panic!("{what}: {e}"));
        assert!(
            out.status.success(),
            "{what} failed:\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    };
    run(
        Command::new("python3").args(["-m", "venv"]).arg(&venv),
        "python3 -m venv",
    );
    let python = venv.join("bin/python");
    run(
        Command::new(&python)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
            ])
            .arg(&source),
        "pip install ./proto/python into a fresh venv",
    );
    python
}

/// `name{labels} value` lines into a map (comments skipped).
pub fn parse_metrics(text: &str) -> std::collections::HashMap<String, f64> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let (name, value) = l.rsplit_once(' ').expect("name and value");
            (name.to_owned(), value.parse().expect("a number"))
        })
        .collect()
}

/// `GET /metrics`: the text, checked to be Prometheus text.
pub fn scrape_metrics(url: &str) -> String {
    let response = reqwest::blocking::get(format!("{url}/metrics")).unwrap();
    assert_eq!(response.status(), 200);
    let content_type = response.headers()["content-type"]
        .to_str()
        .unwrap()
        .to_owned();
    assert!(content_type.starts_with("text/plain"), "{content_type}");
    response.text().unwrap()
}
