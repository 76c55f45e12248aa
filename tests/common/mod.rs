//! Shared by the integration tests: real `splatd` processes on loopback ports, and small helpers.
#![allow(dead_code)] // each test binary uses a different subset

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// A `splatd serve` process on an ephemeral 127.0.0.1 port, stopped (SIGTERM, then SIGKILL)
/// when dropped.
pub struct Server {
    child: Option<Child>,
    /// `http://127.0.0.1:PORT`
    pub url: String,
    /// `127.0.0.1:PORT`
    pub addr: String,
}

impl Server {
    /// Starts `splatd serve --addr 127.0.0.1:0 <args>` and waits for its "listening" line.
    pub fn start(args: &[&str]) -> Server {
        Self::start_with_env(args, &[])
    }

    /// Like [`Server::start`], with extra environment variables.
    pub fn start_with_env(args: &[&str], env: &[(&str, &str)]) -> Server {
        Self::start_at("127.0.0.1:0", args, env)
    }

    /// Starts a server on a given address (to restart one on the port it had).
    pub fn start_at(addr: &str, args: &[&str], env: &[(&str, &str)]) -> Server {
        Self::start_logged(addr, args, env, None)
    }

    /// Like [`Server::start_at`], with the server's log (stderr) written to `log`.
    pub fn start_logged(
        addr: &str,
        args: &[&str],
        env: &[(&str, &str)],
        log: Option<&Path>,
    ) -> Server {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_splatd"));
        let stderr = match log {
            Some(path) => Stdio::from(std::fs::File::create(path).expect("log file")),
            None => Stdio::inherit(),
        };
        cmd.args(["serve", "--addr", addr])
            .args(args)
            .env("RUST_LOG", "error")
            .stdout(Stdio::piped())
            .stderr(stderr);
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().expect("starting splatd");
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut lines = BufReader::new(stdout).lines();
            if let Some(Ok(line)) = lines.next() {
                let _ = tx.send(line);
            }
            // Keep draining so the server never blocks on a full pipe.
            for _ in lines {}
        });
        let line = match rx.recv_timeout(PATIENCE) {
            Ok(line) => line,
            Err(_) => {
                let _ = child.kill();
                panic!("splatd did not report its address within {PATIENCE:?}");
            }
        };
        let url = line
            .strip_prefix("splatd listening on ")
            .unwrap_or_else(|| panic!("unexpected first line from splatd: {line:?}"))
            .to_owned();
        let addr = url.trim_start_matches("http://").to_owned();
        Server {
            child: Some(child),
            url,
            addr,
        }
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("running").id()
    }

    /// Sends SIGTERM and waits (bounded) for a clean exit; returns the exit status code.
    pub fn terminate(mut self) -> Option<i32> {
        let mut child = self.child.take().expect("running");
        signal(child.id(), "TERM");
        wait_bounded(&mut child, PATIENCE)
    }

    /// Waits for the process to end by itself (a failpoint aborted it, say); its exit code, or
    /// `None` for a signal. Bounded by [`PATIENCE`] against a test that would hang.
    pub fn wait_exit(mut self) -> Option<i32> {
        let mut child = self.child.take().expect("running");
        let start = Instant::now();
        loop {
            if let Some(status) = child.try_wait().expect("waiting for splatd") {
                return status.code();
            }
            assert!(
                start.elapsed() < PATIENCE,
                "splatd did not exit within {PATIENCE:?}"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// SIGKILLs the process (no chance to flush anything) and reaps it.
    pub fn kill(mut self) {
        let mut child = self.child.take().expect("running");
        let _ = child.kill();
        let _ = child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            signal(child.id(), "TERM");
            if wait_bounded(&mut child, Duration::from_secs(5)).is_none() {
                let _ = child.kill();
                let _ = child.wait();
            }
        }
    }
}

fn signal(pid: u32, sig: &str) {
    let _ = Command::new("kill")
        .args([&format!("-{sig}"), &pid.to_string()])
        .status();
}

fn wait_bounded(child: &mut Child, limit: Duration) -> Option<i32> {
    let start = Instant::now();
    while start.elapsed() < limit {
        if let Ok(Some(status)) = child.try_wait() {
            return status.code();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = child.kill();
    let _ = child.wait();
    None
}

/// Channels of an EXR as read by the OpenEXR project's Python bindings (an independent reader).
pub fn read_exr_with_python(path: &Path) -> (u32, u32, Vec<(String, Vec<f64>)>) {
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
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("reader prints JSON");
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

/// A multi-threaded runtime for tests that drive servers with async clients.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(4)
        .enable_all()
        .build()
        .expect("runtime")
}

/// How long any wait in a test may last before the test gives up as hung. It guards against
/// hanging forever; it is never what a test asserts, so it is generous for loaded machines.
pub const PATIENCE: Duration = Duration::from_secs(120);

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

/// A loopback port that was free a moment ago.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("binding 127.0.0.1:0")
        .port()
}
