//! `splatd serve --tev HOST:PORT`: pushes resolved frames to a running tev viewer as samples
//! arrive.
//!
//! Every `interval`, each frame whose version changed since it was last shown is resolved and
//! sent (all layers: reweighted, mean, removed) with [`crate::viewer::tev::TevSink`], one frame at a time
//! on the blocking pool. tev not running is not an error of the server: the sink connects
//! lazily, logs once per outage, and catches up with the current images when tev comes back.

pub mod tev;

use std::collections::HashMap;
use std::time::Duration;

use crate::viewer::tev::TevSink;

use super::AppState;

/// Runs until `stop` changes.
pub async fn run(
    app: AppState,
    addr: String,
    interval: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    let mut sink: Option<TevSink> = None;
    let mut shown: HashMap<String, u64> = HashMap::new();
    let mut down = false;
    loop {
        tokio::select! {
            () = tokio::time::sleep(interval) => {}
            _ = stop.changed() => return,
        }
        for frame in app.store.list() {
            let version = frame.version();
            if shown.get(frame.id()) == Some(&version) {
                continue;
            }
            let threads = app.resolve_threads;
            let params = frame.spec().resolve;
            let target = addr.clone();
            let mut current = sink.take();
            let f = frame.clone();
            let result = tokio::task::spawn_blocking(move || {
                let resolved = f.cut().resolve(&params, threads);
                let mut s = match current.take() {
                    Some(s) => s,
                    None => TevSink::connect(&target)?,
                };
                let shown = s.show(f.id(), &resolved);
                Ok::<_, crate::viewer::tev::TevError>((s, shown))
            })
            .await;
            match result {
                Ok(Ok((s, Ok(())))) => {
                    sink = Some(s);
                    shown.insert(frame.id().to_owned(), version);
                    metrics::counter!(crate::meters::TEV_UPDATES).increment(1);
                    if down {
                        tracing::info!(%addr, "tev reachable again");
                        down = false;
                    }
                }
                Ok(Ok((s, Err(e)))) => {
                    // The sink reconnects by itself on its next use.
                    sink = Some(s);
                    if !down {
                        tracing::warn!(%addr, error = %e, "sending to tev failed");
                        down = true;
                    }
                }
                Ok(Err(e)) => {
                    if !down {
                        tracing::warn!(%addr, error = %e, "tev is not reachable; will retry");
                        down = true;
                    }
                    shown.clear();
                    break;
                }
                Err(e) => tracing::error!(error = %e, "tev task failed"),
            }
        }
        // Forget deleted frames.
        let ids: std::collections::HashSet<String> =
            app.store.list().iter().map(|f| f.id().to_owned()).collect();
        shown.retain(|id, _| ids.contains(id));
    }
}
