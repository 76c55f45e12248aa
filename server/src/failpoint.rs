//! Fault injection for tests: crash or fail at a named point, on a chosen hit.
//!
//! Crash tests used to kill the server at random moments and hope a kill landed where it
//! mattered. A failpoint makes the moment certain: `SPLATD_FAILPOINTS` (read once, at the first
//! hit) lists `point=action[@n]` entries separated by `,` or `;`:
//!
//! * `abort`: the process aborts on the spot, with no unwinding and no flushing, as a SIGKILL
//!   would leave it;
//! * `error`: the operation fails with an injected I/O error, as a failing disk would make it;
//! * `full`: the operation fails as on a full disk (`StorageFull`, what `ENOSPC` reads as).
//! * `refuse`: the operation fails with `EINVAL`, as from a file system that does not take the
//!   request (a direct write, say);
//! * `pause`: the thread stops there until the test lets it go: it creates `POINT.reached` in
//!   the directory [`PAUSE_DIR_ENV`] names, then waits for `POINT.release` to appear there (at
//!   most [`PAUSE_LIMIT`], so a test that never releases it does not hang the server).
//!
//! With `@n` the action happens on the `n`-th hit only (counting from 1), otherwise on every hit.
//! Points: `snapshot.bin:before_rename` (a snapshot is written to `snapshot.tmp` and synced, not
//! yet renamed over the previous one), `snapshot.bin:before_write` and the same for
//! `frame.json`; `direct_write` (a write around the page cache, which falls back to an ordinary
//! one when refused); `batch:before_apply` (a batch or pass is about to be applied; only `abort`
//! has an effect there: the server dies between two acknowledgements); `denoise:before_oidn`
//! (a denoise's input is made and OIDN is about to run; for `pause`); `frame:building` (a
//! create is settled and its frame's memory is about to be taken and zeroed; for `pause`);
//! `frame:copying_band` and `frame:copying_aovs` (a writer is about to copy a band or AOV sums
//! that a cut holds; for `pause`).
//! Unset (in production), a hit costs one check of an initialized `OnceLock`.

use std::collections::HashMap;
use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::OnceLock;

/// The environment variable that configures failpoints.
pub const ENV: &str = "SPLATD_FAILPOINTS";

/// The environment variable naming the directory of `pause`'s files.
pub const PAUSE_DIR_ENV: &str = "SPLATD_FAILPOINT_DIR";

/// The longest a `pause` waits for its release.
pub const PAUSE_LIMIT: std::time::Duration = std::time::Duration::from_secs(60);

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Action {
    Abort,
    Error,
    Full,
    Refuse,
    Pause,
}

#[derive(Debug)]
struct Point {
    action: Action,
    /// The hit that triggers the action; `None` for every hit.
    on_hit: Option<u64>,
    hits: AtomicU64,
}

/// Parses a `SPLATD_FAILPOINTS` value.
fn parse(spec: &str) -> Result<HashMap<String, Point>, String> {
    let mut points = HashMap::new();
    for entry in spec
        .split([',', ';'])
        .map(str::trim)
        .filter(|e| !e.is_empty())
    {
        let (name, rest) = entry
            .split_once('=')
            .ok_or_else(|| format!("{entry:?}: expected point=action[@n]"))?;
        let (action, on_hit) = match rest.split_once('@') {
            Some((action, n)) => {
                let n: u64 = n
                    .parse()
                    .ok()
                    .filter(|&n| n > 0)
                    .ok_or_else(|| format!("{entry:?}: @n needs a positive number"))?;
                (action, Some(n))
            }
            None => (rest, None),
        };
        let action = match action {
            "abort" => Action::Abort,
            "error" => Action::Error,
            "full" => Action::Full,
            "refuse" => Action::Refuse,
            "pause" => Action::Pause,
            other => return Err(format!("{entry:?}: unknown action {other:?}")),
        };
        points.insert(
            name.to_owned(),
            Point {
                action,
                on_hit,
                hits: AtomicU64::new(0),
            },
        );
    }
    Ok(points)
}

fn points() -> &'static HashMap<String, Point> {
    static POINTS: OnceLock<HashMap<String, Point>> = OnceLock::new();
    POINTS.get_or_init(|| match std::env::var(ENV) {
        Ok(spec) => parse(&spec).unwrap_or_else(|e| panic!("{ENV}: {e}")),
        Err(_) => HashMap::new(),
    })
}

/// Passes point `name`: aborts the process or returns an injected error when it is configured
/// to on this hit, otherwise returns `Ok`.
pub fn hit(name: &str) -> io::Result<()> {
    let Some(point) = points().get(name) else {
        return Ok(());
    };
    act(name, point)
}

fn act(name: &str, point: &Point) -> io::Result<()> {
    let n = point.hits.fetch_add(1, Ordering::SeqCst) + 1;
    if point.on_hit.is_some_and(|on| on != n) {
        return Ok(());
    }
    match point.action {
        Action::Abort => {
            use std::io::Write;
            let _ = writeln!(std::io::stderr(), "failpoint {name}: aborting (hit {n})");
            std::process::abort();
        }
        Action::Error => Err(io::Error::other(format!(
            "injected fault at failpoint {name} (hit {n})"
        ))),
        Action::Full => Err(io::Error::new(
            io::ErrorKind::StorageFull,
            format!("injected full disk at failpoint {name} (hit {n})"),
        )),
        Action::Refuse => Err(io::Error::from_raw_os_error(libc::EINVAL)),
        Action::Pause => {
            pause(name);
            Ok(())
        }
    }
}

/// `pause` at point `name`: says so with `name.reached`, then waits for `name.release`.
fn pause(name: &str) {
    let dir = std::path::PathBuf::from(std::env::var_os(PAUSE_DIR_ENV).unwrap_or_else(|| {
        panic!("failpoint {name}: pause needs {PAUSE_DIR_ENV}");
    }));
    std::fs::write(dir.join(format!("{name}.reached")), b"")
        .unwrap_or_else(|e| panic!("failpoint {name}: {e}"));
    let release = dir.join(format!("{name}.release"));
    let started = std::time::Instant::now();
    while !release.exists() && started.elapsed() < PAUSE_LIMIT {
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_parse_and_errors_fire_on_their_hit() {
        let points = parse("a=error@2; b=abort ,c=error").unwrap();
        assert_eq!(points["a"].on_hit, Some(2));
        assert_eq!(points["b"].action, Action::Abort);
        let a = &points["a"];
        assert!(act("a", a).is_ok());
        let err = act("a", a).unwrap_err();
        assert!(err.to_string().contains("failpoint a (hit 2)"), "{err}");
        assert!(act("a", a).is_ok(), "only the second hit");
        let c = &points["c"];
        assert!(act("c", c).is_err() && act("c", c).is_err(), "every hit");
        assert_eq!(parse("d=pause@1").unwrap()["d"].action, Action::Pause);
    }

    #[test]
    fn nonsense_is_refused_by_name() {
        for bad in ["x", "x=explode", "x=abort@0", "x=error@two"] {
            let err = parse(bad).unwrap_err();
            assert!(err.contains("x"), "{bad}: {err}");
        }
        assert!(parse("").unwrap().is_empty());
    }

    #[test]
    fn unconfigured_points_pass() {
        assert!(hit("no.such.point").is_ok());
    }
}
