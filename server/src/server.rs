//! A server's lifecycle ([`Server`]): configuration in, then the listener, the accept loop, the
//! snapshot, push and tev tasks, and a graceful shutdown that ends with a final push and a final
//! snapshot of every changed frame. `splatd serve` and the demo both run it.
//!
//! The accept loop is ours (hyper's HTTP/1 connections) rather than `axum::serve`, so that every
//! connection is admitted under the cap, its request heads are read and checked within the head
//! deadline before hyper sees them, and a response that a client does not take in time is
//! dropped (see [`crate::transport`]). Request bodies are bounded by the request timeout layer.

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use tokio::net::TcpListener;

use anyhow::Context;

use super::push::PushConfig;
use super::transport::{service, Deadlines, Ended, HeadGate};
use super::{AppState, Config};

/// A bound server, ready to run.
pub struct Server {
    config: Config,
    app: AppState,
    listener: TcpListener,
    local: SocketAddr,
    push: Option<PushConfig>,
}

impl Server {
    /// Reads the tokens, opens and recovers the data directory, installs the metrics recorder
    /// (unless one is installed already in this process: the server then has no `/metrics`),
    /// and binds the listener. Nothing is served until [`Server::run`].
    pub async fn bind(mut config: Config) -> anyhow::Result<Server> {
        return_large_buffers_to_the_system();
        let nofile = super::transport::raise_descriptor_limit();
        let cap = super::transport::cap_for(config.max_connections, nofile);
        if cap < config.max_connections {
            tracing::warn!(
                max_connections = cap,
                asked = config.max_connections,
                "connection cap lowered to leave descriptors for other files"
            );
            config.max_connections = cap;
        }
        let metrics = metrics_exporter_prometheus::PrometheusBuilder::new()
            .set_buckets(&[
                0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
            ])
            .context("metric buckets")?
            .install_recorder()
            .inspect_err(|e| tracing::warn!(error = %e, "no /metrics"))
            .ok();
        let push = config.upstream.clone().map(|upstream| {
            let mut cfg = PushConfig::new(upstream);
            if let Some(node) = config.node_id.clone() {
                cfg.node = node;
            }
            cfg.interval = config.push_interval();
            cfg.token = config.upstream_token.clone();
            cfg
        });
        if let Some(cfg) = &push {
            cfg.client().context("--upstream")?;
        }
        let app = AppState::from_config(&config, metrics)?;
        if app.durable.is_some() {
            #[cfg(unix)]
            super::durable::survive_file_size_limit().context("handling SIGXFSZ")?;
        }
        let (listener, local) = bind(&config.addr)
            .await
            .with_context(|| format!("binding {}", config.addr))?;
        Ok(Server {
            config,
            app,
            listener,
            local,
            push,
        })
    }

    /// The address actually bound (port 0 picks one).
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// The state every handler shares.
    pub fn state(&self) -> &AppState {
        &self.app
    }

    /// Serves until `shutdown` resolves; then stops accepting, finishes the requests in flight,
    /// lets the pusher make its final push and the tev task stop, and snapshots every changed
    /// frame, so that everything acknowledged as applied is durable before this returns.
    pub async fn run(self, shutdown: impl Future<Output = ()>) -> anyhow::Result<()> {
        let Server {
            config,
            app,
            listener,
            local,
            push,
        } = self;
        tracing::info!(%local, "listening");
        let (stop_tasks, stop) = tokio::sync::watch::channel(false);
        let snapshots = app.durable.clone().map(|d| {
            let app = app.clone();
            tokio::spawn(d.run(move || app.store.list(), stop.clone()))
        });
        let viewer = config.tev.clone().map(|addr| {
            tokio::spawn(super::viewer::run(
                app.clone(),
                addr,
                config.tev_interval(),
                stop.clone(),
            ))
        });
        let sweeper = tokio::spawn(app.clone().release_idle_until(stop.clone()));
        let pusher = push.map(|cfg| {
            tracing::info!(upstream = cfg.upstream, node = cfg.node, "push mode");
            let mut stop = stop.clone();
            super::push::spawn_until(app.clone(), cfg, async move {
                let _ = stop.wait_for(|stopped| *stopped).await;
            })
        });
        serve(listener, app.clone(), shutdown)
            .await
            .context("serving")?;
        // A snapshot in progress finishes before the final ones; the pusher's final push
        // carries everything acknowledged, as no request is in flight any more.
        let _ = stop_tasks.send(true);
        let tasks = snapshots.into_iter().chain(viewer).chain(pusher);
        for task in tasks.chain([sweeper]) {
            let _ = task.await;
        }
        if let Some(durable) = &app.durable {
            // Every frame gets its chance, whatever happened to the one before it (a full disk
            // refuses the big frame and may still take the small one).
            let mut failed = Vec::new();
            for frame in app.store.list() {
                if let Err(e) = durable.snapshot(&frame).await {
                    tracing::error!(frame = frame.id(), error = %e, "final snapshot failed");
                    failed.push(format!("{}: {e}", frame.id()));
                }
            }
            if !failed.is_empty() {
                anyhow::bail!(
                    "the final snapshot of {} frame(s) failed; what they acknowledged since \
                     their last snapshot is lost: {}",
                    failed.len(),
                    failed.join("; ")
                );
            }
        }
        tracing::info!("stopped");
        Ok(())
    }
}

/// Serves `app` on `listener` until `shutdown` resolves, then stops accepting, lets requests in
/// flight finish (batches being applied are applied and acknowledged), and returns.
///
/// Each connection is admitted under the cap ([`Connections::admit`](crate::transport::Connections::admit)), its request heads pass
/// the [`HeadGate`], and it is closed when a response outlives the response deadline.
pub async fn serve(
    listener: TcpListener,
    app: AppState,
    shutdown: impl Future<Output = ()>,
) -> std::io::Result<()> {
    let limits = app.store.limits();
    let deadlines = Deadlines {
        head: limits.head_timeout,
        idle: limits.idle_timeout,
        response: limits.response_timeout,
    };
    let connections = app.connections.clone();
    let router = crate::http::router(app);
    let mut builder = http1::Builder::new();
    // The gate keeps the head deadline and the idle timeout; hyper's own would also close
    // keep-alive connections idling between requests.
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(None)
        .keep_alive(true)
        // A client may shut its side of the socket once its request is sent (`nc`, HTTP/1.0
        // habits): the request is still answered. A half-closed connection that sends nothing
        // is still bound by the head and response deadlines.
        .half_close(true);
    let graceful = GracefulShutdown::new();
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            accepted = listener.accept() => {
                let (stream, peer) = match accepted {
                    Ok(a) => a,
                    Err(e) => {
                        // Out of file descriptors and the like: wait instead of spinning.
                        tracing::warn!(error = %e, "accept failed");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                };
                let Ok(registered) = connections.admit() else {
                    tracing::debug!(%peer, "connection refused: every connection is serving a request");
                    drop(stream);
                    continue;
                };
                let _ = stream.set_nodelay(true);
                let conn = registered.conn().clone();
                let io = TokioIo::new(HeadGate::new(stream, conn.clone(), deadlines));
                let connection = builder.serve_connection(io, service(router.clone(), conn.clone()));
                let connection = graceful.watch(connection);
                tokio::spawn(async move {
                    let _place = registered;
                    match conn.drive(connection, deadlines.response).await {
                        Ended::Done(Ok(())) => {}
                        Ended::Done(Err(e)) => {
                            tracing::debug!(%peer, error = %e, "connection ended with an error");
                        }
                        Ended::Evicted => {
                            tracing::debug!(%peer, "connection closed to make room for a new one");
                        }
                        Ended::SlowReader => {
                            tracing::info!(%peer, "response not taken within the response timeout: connection closed");
                        }
                    }
                });
            }
            () = &mut shutdown => break,
        }
    }
    drop(listener);
    tracing::info!("shutting down: finishing requests in flight");
    graceful.shutdown().await;
    Ok(())
}

/// A future that resolves on SIGTERM or Ctrl-C (SIGINT). The handlers are installed by this call,
/// not when the future is first polled: call it before announcing the address, so a signal sent
/// as soon as the server says it listens is not taken by the default action (death by signal).
/// Must be called inside a tokio runtime.
pub fn shutdown_signal() -> impl Future<Output = ()> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let mut term = signal(SignalKind::terminate()).ok();
        let mut int = signal(SignalKind::interrupt()).ok();
        async move {
            let wait = |s: Option<tokio::signal::unix::Signal>| async move {
                match s {
                    Some(mut s) => {
                        s.recv().await;
                    }
                    None => std::future::pending::<()>().await,
                }
            };
            tokio::select! {
                () = wait(term.take()) => {}
                () = wait(int.take()) => {}
            }
        }
    }
    #[cfg(not(unix))]
    async {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// Makes glibc's allocator give large buffers back to the system when they are freed, and keep
/// batch-sized ones for reuse.
///
/// Request bodies, decoded records and images are tens to hundreds of megabytes, bounded in
/// number by the working budget; but glibc raises its mmap threshold after each large free, so
/// later large buffers came from the heap arenas and stayed resident after use. A fixed
/// threshold of 8 MiB keeps every large buffer mmapped (freeing it returns it, and RSS follows
/// the budget) while a worker's batch (1.3 MB on the wire, decoded and sorted by band) is still
/// reused from the arenas instead of being mapped, faulted in and unmapped every time. Fixing
/// it also pins the trim threshold, so it is set to 8 MiB too (an arena keeps that much free at
/// its top instead of giving back and faulting in again every batch), and at most 4 arenas
/// bound what stays resident beyond the buffers in use to 32 MiB.
fn return_large_buffers_to_the_system() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; called before the server allocates much.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 8 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 8 << 20);
        libc::mallopt(libc::M_ARENA_MAX, 4);
    }
}

/// Binds `addr`; the address actually bound (port 0 picks a free one) is returned with it.
pub async fn bind(addr: &str) -> std::io::Result<(TcpListener, SocketAddr)> {
    let listener = TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    Ok((listener, local))
}
