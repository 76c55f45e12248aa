//! Real `splatd serve` processes on loopback ports, for the tests and the benchmarks: one way to
//! start one, learn its address, stop it gently or kill it, and never leave one behind.
//!
//! A server is started on port 0 and reports the port it bound on its first stdout line
//! (`splatd listening on http://ADDR`), so no port is ever guessed. Every wait is bounded by
//! [`PATIENCE`], which only guards against hanging forever.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// How long any wait may last before it is taken for a hang. Generous, for loaded machines.
pub const PATIENCE: Duration = Duration::from_secs(120);

/// How to start a server.
#[derive(Debug, Clone)]
pub struct Options<'a> {
    /// The `splatd` binary.
    pub binary: PathBuf,
    /// Address to listen on (default `127.0.0.1:0`).
    pub addr: &'a str,
    /// Arguments after `serve --addr ADDR`.
    pub args: &'a [&'a str],
    /// Extra environment variables.
    pub env: &'a [(&'a str, &'a str)],
    /// Where the server's log (stderr) goes; inherited when `None`.
    pub log: Option<&'a Path>,
    /// `RUST_LOG` of the server.
    pub log_level: &'a str,
}

impl<'a> Options<'a> {
    /// `binary serve --addr 127.0.0.1:0 args`, logging errors to the inherited stderr.
    pub fn new(binary: impl Into<PathBuf>, args: &'a [&'a str]) -> Options<'a> {
        Options {
            binary: binary.into(),
            addr: "127.0.0.1:0",
            args,
            env: &[],
            log: None,
            log_level: "error",
        }
    }
}

/// The `splatd` binary beside the running executable: how benchmarks built by the same
/// `cargo build` find the server.
pub fn sibling_binary() -> Result<PathBuf, String> {
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let splatd = exe.with_file_name("splatd");
    if splatd.exists() {
        Ok(splatd)
    } else {
        Err(format!(
            "{} not found: build the server beside this program (cargo build --release --bins)",
            splatd.display()
        ))
    }
}

/// A `splatd serve` process, stopped (SIGTERM, then SIGKILL) when dropped.
pub struct ServerProcess {
    child: Option<Child>,
    /// `http://127.0.0.1:PORT`
    pub url: String,
    /// `127.0.0.1:PORT`
    pub addr: String,
}

impl ServerProcess {
    /// Starts a server and waits for its address.
    pub fn launch(options: &Options<'_>) -> Result<ServerProcess, String> {
        let mut cmd = Command::new(&options.binary);
        let stderr = match options.log {
            Some(path) => Stdio::from(
                std::fs::File::create(path).map_err(|e| format!("{}: {e}", path.display()))?,
            ),
            None => Stdio::inherit(),
        };
        cmd.args(["serve", "--addr", options.addr])
            .args(options.args)
            .env("RUST_LOG", options.log_level)
            .stdout(Stdio::piped())
            .stderr(stderr);
        for (k, v) in options.env {
            cmd.env(k, v);
        }
        let mut child = cmd
            .spawn()
            .map_err(|e| format!("starting {}: {e}", options.binary.display()))?;
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
                let _ = child.wait();
                return Err(format!(
                    "splatd exited or did not report its address within {PATIENCE:?}"
                ));
            }
        };
        let Some(url) = line.strip_prefix("splatd listening on ") else {
            let _ = child.kill();
            return Err(format!("unexpected first line from splatd: {line:?}"));
        };
        Ok(ServerProcess {
            child: Some(child),
            url: url.to_owned(),
            addr: url.trim_start_matches("http://").to_owned(),
        })
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("running").id()
    }

    /// Sends SIGTERM and waits (bounded) for the exit; its code, `None` if killed.
    pub fn terminate(mut self) -> Option<i32> {
        let mut child = self.child.take().expect("running");
        signal(child.id(), "TERM");
        wait_bounded(&mut child, PATIENCE)
    }

    /// Waits for the process to end by itself (a failpoint aborted it, say); its exit code,
    /// `None` for a signal.
    ///
    /// # Panics
    /// When it has not ended within [`PATIENCE`].
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

impl Drop for ServerProcess {
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

/// Waits up to `limit` for the child to exit; kills it after that.
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
