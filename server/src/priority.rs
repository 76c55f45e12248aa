//! Background work at a lower scheduling priority: renders and snapshots take only the cores
//! that the request loop and ingest leave idle.
//!
//! A resolve may use every core, and at equal priority it starved the request loop (`/healthz`
//! took 374 ms behind 64 image requests on two cores); a snapshot's encoding on a saturated
//! machine slowed ingest instead of letting durability lag.

/// The nice value renders and snapshots run at (the request loop and ingest run at the process's own, 0).
pub const RENDER_NICE: i32 = 10;

/// Runs `work` on a new thread named `name` at the renders' lower priority ([`RENDER_NICE`]):
/// background work (renders, snapshots) that must take only the cores ingest leaves idle.
pub async fn on_low_priority_thread<T: Send + 'static>(
    name: &str,
    work: impl FnOnce() -> T + Send + 'static,
) -> Result<T, tokio::task::JoinError> {
    let name = name.to_owned();
    tokio::task::spawn_blocking(move || {
        let thread = std::thread::Builder::new()
            .name(name)
            .spawn(move || {
                lower_priority();
                work()
            })
            .expect("spawning a low-priority thread");
        match thread.join() {
            Ok(result) => result,
            Err(panic) => std::panic::resume_unwind(panic),
        }
    })
    .await
}

/// Lowers the calling thread's priority to [`RENDER_NICE`] (Linux keeps a nice value per
/// thread; threads it starts inherit it). Failing to is harmless: the render runs at normal
/// priority.
pub fn lower_priority() {
    // SAFETY: gettid and setpriority only read their arguments.
    let result = unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, RENDER_NICE)
    };
    if result != 0 {
        tracing::debug!(error = %std::io::Error::last_os_error(), "renders keep normal priority");
    }
}
