//! Real `splatd serve` processes on loopback ports, for the tests and the benchmarks: one way to
//! start one, learn its address, stop it gently or kill it, and never leave one behind.
//!
//! A server is started on port 0 and reports the port it bound on its first stdout line
//! (`splatd listening on http://ADDR`), so no port is ever guessed. Every wait is bounded by
//! [`PATIENCE`], which only guards against hanging forever.
//!
//! Each server writes its log to a file of its own ([`Log::Own`], the default), never to the
//! test's stderr: what the test's output is (a terminal, a pipe, a file under `ulimit -f`) then
//! cannot change what the server does, and when a test fails while it holds the server, the
//! log's last lines are printed with the failure so that a CI run can be diagnosed. The logs
//! stay for [`LOGS_KEPT_FOR`] (a week) after they were last written.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Lines of a server's log printed when a test fails while holding the server.
const LOG_TAIL_LINES: usize = 60;

/// Where a server's log (its stderr) goes.
#[derive(Debug, Clone, Copy)]
pub enum Log<'a> {
    /// A file of its own under the system's temporary folder (`splatd-logs/`), named after the
    /// program and the server; [`ServerProcess::log_path`] says which.
    Own,
    /// This file, appended to (created if missing).
    File(&'a Path),
    /// The stderr of the program that starts it.
    Inherit,
    /// A pipe whose reading end is closed: every log line the server writes fails (`EPIPE`), as
    /// when an operator's log collector has died.
    Closed,
}

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
    /// Where the server's log (stderr) goes.
    pub log: Log<'a>,
    /// `RUST_LOG` of the server.
    pub log_level: &'a str,
}

impl<'a> Options<'a> {
    /// `binary serve --addr 127.0.0.1:0 args`, logging errors to a file of its own.
    pub fn new(binary: impl Into<PathBuf>, args: &'a [&'a str]) -> Options<'a> {
        Options {
            binary: binary.into(),
            addr: "127.0.0.1:0",
            args,
            env: &[],
            log: Log::Own,
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

/// A `splatd serve` process, stopped (SIGTERM, then SIGKILL) when dropped; dropped while its
/// thread panics (a failed assertion), it prints its log's tail first.
pub struct ServerProcess {
    child: Option<Child>,
    log: Option<PathBuf>,
    /// `http://127.0.0.1:PORT`
    pub url: String,
    /// `127.0.0.1:PORT`
    pub addr: String,
}

impl ServerProcess {
    /// Starts a server and waits for its address.
    pub fn launch(options: &Options<'_>) -> Result<ServerProcess, String> {
        let mut cmd = Command::new(&options.binary);
        let log = match options.log {
            Log::Own => Some(own_log_path()?),
            Log::File(path) => Some(path.to_owned()),
            Log::Inherit | Log::Closed => None,
        };
        let stderr = match (&log, options.log) {
            (Some(path), _) => Stdio::from(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(path)
                    .map_err(|e| format!("{}: {e}", path.display()))?,
            ),
            (None, Log::Closed) => Stdio::piped(),
            (None, _) => Stdio::inherit(),
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
        // Log::Closed: the reading end goes now, before the server writes its first line.
        drop(child.stderr.take());
        let tail = |log: &Option<PathBuf>| {
            log.as_deref()
                .map(|p| format!("\n{}", log_tail(p, LOG_TAIL_LINES)))
                .unwrap_or_default()
        };
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
                    "splatd exited or did not report its address within {PATIENCE:?}{}",
                    tail(&log)
                ));
            }
        };
        let Some(url) = line.strip_prefix("splatd listening on ") else {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!(
                "unexpected first line from splatd: {line:?}{}",
                tail(&log)
            ));
        };
        Ok(ServerProcess {
            child: Some(child),
            log,
            url: url.to_owned(),
            addr: url.trim_start_matches("http://").to_owned(),
        })
    }

    /// The file the server logs to, unless it logs to an inherited or closed stderr.
    pub fn log_path(&self) -> Option<&Path> {
        self.log.as_deref()
    }

    /// The last `lines` lines of the server's log, for a failure message.
    pub fn log_tail(&self, lines: usize) -> String {
        match &self.log {
            Some(path) => log_tail(path, lines),
            None => "(the server's log is not in a file)".to_owned(),
        }
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
        if std::thread::panicking() {
            if let Some(path) = &self.log {
                eprintln!("{}", log_tail(path, LOG_TAIL_LINES));
            }
        }
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

/// How long the servers' own logs (and what tests keep beside them) stay in `splatd-logs/`.
pub const LOGS_KEPT_FOR: Duration = Duration::from_secs(7 * 24 * 3600);

/// A fresh log file name for a server of this program: `TMP/splatd-logs/PROGRAM-PID-N.log`.
/// The first one a process asks for also removes the files there older than [`LOGS_KEPT_FOR`]:
/// a run of the test suite leaves about a hundred logs, which are worth reading after a failure
/// but would otherwise pile up on a machine that runs the suite every day.
fn own_log_path() -> Result<PathBuf, String> {
    static NEXT: AtomicUsize = AtomicUsize::new(0);
    static PRUNED: std::sync::Once = std::sync::Once::new();
    let dir = std::env::temp_dir().join("splatd-logs");
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    PRUNED.call_once(|| remove_older(&dir, LOGS_KEPT_FOR));
    let program = std::env::current_exe()
        .ok()
        .and_then(|p| p.file_stem().map(|s| s.to_string_lossy().into_owned()))
        .unwrap_or_else(|| "splatd".into());
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    Ok(dir.join(format!("{program}-{}-{n}.log", std::process::id())))
}

/// Removes the files directly in `dir` last modified more than `age` ago. Best effort: another
/// process may be removing the same files, and what cannot be removed stays.
fn remove_older(dir: &Path, age: Duration) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let now = std::time::SystemTime::now();
    for entry in entries.flatten() {
        let old = entry.metadata().is_ok_and(|m| {
            m.is_file()
                && m.modified()
                    .is_ok_and(|t| now.duration_since(t).is_ok_and(|d| d > age))
        });
        if old {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// The last `lines` lines of the log at `path`, under a heading that names the file.
pub fn log_tail(path: &Path, lines: usize) -> String {
    match std::fs::read(path) {
        Ok(bytes) => {
            let text = String::from_utf8_lossy(&bytes);
            let all: Vec<&str> = text.lines().collect();
            let from = all.len().saturating_sub(lines);
            format!(
                "--- last {} of {} lines of the server's log {} ---\n{}\n--- end of log ---",
                all.len() - from,
                all.len(),
                path.display(),
                all[from..].join("\n")
            )
        }
        Err(e) => format!("(the server's log {} cannot be read: {e})", path.display()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Files older than the age go, newer ones and directories stay.
    #[test]
    fn only_files_older_than_the_age_are_removed() {
        let dir = tempfile::tempdir().expect("temp dir");
        let now = std::time::SystemTime::now();
        let file = |name: &str, age: Duration| {
            let path = dir.path().join(name);
            let f = std::fs::File::create(&path).expect("create");
            f.set_modified(now - age).expect("set mtime");
            path
        };
        let week = LOGS_KEPT_FOR;
        let old = file("suite-1-0.log", week + Duration::from_secs(60));
        let old_png = file("suite-1-0.png", week * 3);
        let recent = file("suite-2-0.log", week - Duration::from_secs(60));
        let fresh = file("suite-3-0.log", Duration::ZERO);
        let sub = dir.path().join("a-directory");
        std::fs::create_dir(&sub).expect("mkdir");

        remove_older(dir.path(), week);

        assert!(
            !old.exists() && !old_png.exists(),
            "older than a week: removed"
        );
        assert!(recent.exists() && fresh.exists(), "newer: kept");
        assert!(sub.is_dir(), "directories are not touched");
        // A folder that does not exist is no error.
        remove_older(&dir.path().join("missing"), week);
    }
}
