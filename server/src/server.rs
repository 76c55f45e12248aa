//! The router, its layers, and the listener.
//!
//! The accept loop is hyper-util's rather than `axum::serve`, for one reason: a header read
//! timeout. Without it a client that opens a connection and trickles (or never sends) its headers
//! holds a task and a socket forever; with it, such connections are closed after the idle
//! timeout. Request bodies are bounded by the request timeout layer instead.

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use axum::extract::Request;
use axum::http::{header, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tower_http::compression::CompressionLayer;
use tower_http::decompression::RequestDecompressionLayer;
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;

use super::error::ApiError;
use super::routes;
use super::AppState;

/// The whole HTTP surface.
pub fn router(app: AppState) -> Router {
    let timeout = app.store.limits().request_timeout;
    let v1 = Router::new()
        .route(
            "/frames",
            post(routes::create_frame).get(routes::list_frames),
        )
        .route(
            "/frames/{id}",
            get(routes::frame_info).delete(routes::delete_frame),
        )
        .route("/frames/{id}/samples", post(routes::post_samples))
        .route("/frames/{id}/image.exr", get(routes::get_image))
        .route("/frames/{id}/sync", post(routes::sync_frame))
        .route("/frames/{id}/passes", post(routes::post_pass))
        .route("/frames/{id}/preview.png", get(routes::get_preview))
        .route(
            "/frames/{id}/state",
            // States are mostly small integers and zeros: compress them for clients that ask.
            get(routes::export_state)
                .layer(CompressionLayer::new().gzip(true).zstd(true))
                .post(routes::import_state),
        );
    Router::new()
        .route("/", get(routes::index))
        .route("/healthz", get(routes::healthz))
        .route("/metrics", get(routes::metrics_text))
        .nest("/v1", v1)
        .fallback(unknown_route)
        .layer(RequestDecompressionLayer::new().gzip(true).zstd(true))
        // Outside decompression: a request without the right token is refused before its
        // body is read.
        .layer(axum::middleware::from_fn_with_state(
            app.clone(),
            super::auth::require_token,
        ))
        .layer(TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            timeout,
        ))
        .layer(axum::middleware::from_fn(json_errors))
        .layer(TraceLayer::new_for_http())
        .with_state(app)
}

async fn unknown_route(request: Request) -> ApiError {
    ApiError::new(
        StatusCode::NOT_FOUND,
        "unknown_route",
        format!("no endpoint {} {}", request.method(), request.uri().path()),
    )
}

/// Gives every error a JSON body, including the ones produced by layers and by axum itself (an
/// unsupported `Content-Encoding`, a wrong method), so clients can always parse an `ErrorBody`.
async fn json_errors(request: Request, next: Next) -> Response {
    let response = next.run(request).await;
    let status = response.status();
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let code = match status {
        StatusCode::METHOD_NOT_ALLOWED => "method_not_allowed",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_content_encoding",
        StatusCode::REQUEST_TIMEOUT => "request_timeout",
        StatusCode::PAYLOAD_TOO_LARGE => "body_too_large",
        _ => "http_error",
    };
    let reason = status.canonical_reason().unwrap_or("error");
    let message = match status {
        StatusCode::UNSUPPORTED_MEDIA_TYPE => {
            "unsupported Content-Encoding; use gzip, zstd or none".to_owned()
        }
        StatusCode::REQUEST_TIMEOUT => {
            "the request took longer than this server's request timeout".to_owned()
        }
        _ => reason.to_owned(),
    };
    let mut error = ApiError::new(status, code, message).into_response();
    for name in [header::ALLOW, header::RETRY_AFTER] {
        if let Some(v) = response.headers().get(&name) {
            error.headers_mut().insert(name, v.clone());
        }
    }
    error
}

/// Serves `app` on `listener` until `shutdown` resolves, then stops accepting, lets requests in
/// flight finish (batches being applied are applied and acknowledged), and returns.
pub async fn serve(
    listener: TcpListener,
    app: AppState,
    shutdown: impl Future<Output = ()>,
) -> std::io::Result<()> {
    let idle = app.store.limits().idle_timeout;
    let service = TowerToHyperService::new(router(app));
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(idle)
        .keep_alive(true);
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
                let _ = stream.set_nodelay(true);
                let connection = builder
                    .serve_connection_with_upgrades(TokioIo::new(stream), service.clone())
                    .into_owned();
                let connection = graceful.watch(connection);
                tokio::spawn(async move {
                    if let Err(e) = connection.await {
                        tracing::debug!(%peer, error = %e, "connection ended with an error");
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

/// Resolves on SIGTERM or Ctrl-C.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {}
        () = terminate => {}
    }
}

/// Binds `addr`; the address actually bound (port 0 picks a free one) is returned with it.
pub async fn bind(addr: &str) -> std::io::Result<(TcpListener, SocketAddr)> {
    let listener = TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    Ok((listener, local))
}
