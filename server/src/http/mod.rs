//! The HTTP surface: the router, its layers, the handlers and the JSON errors they answer.
//!
//! Handlers are small and grouped by concept; each takes typed extractors ([`extract`]) and
//! answers [`error::ApiError`]s. The domain below them (`store`, `frame`, `durable`) knows
//! nothing of HTTP: its errors become statuses and codes in [`error`] alone.
//!
//! * [`frames`]: create (or get), list, inspect, delete; [`ingest`]: samples and passes;
//!   [`images`]: EXR and PNG; [`need`]: where a frame needs samples; [`states`]: export and
//!   import; [`operations`]: the page, health, metrics, sync;
//! * [`extract`]: request extractors with JSON refusals; [`error`]: the one error type;
//!   [`manners`]: `Connection: close` when a body is left unread;
//!   [`blocking`]: heavy work off the reactor;
//! * [`auth`]: bearer tokens, roles, and the guard each route is declared with.

pub mod auth;
pub mod blocking;
pub mod error;
pub mod extract;
pub mod frames;
pub mod images;
pub mod ingest;
pub mod manners;
pub mod need;
pub mod operations;
pub mod states;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_budget;
#[cfg(test)]
mod tests_need;
#[cfg(test)]
mod tests_overlap;
#[cfg(test)]
mod tests_watch;

use axum::extract::Request;
use axum::handler::Handler;
use axum::http::{header, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{on, MethodFilter};
use axum::Router;
use tower_http::compression::CompressionLayer;
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::{DefaultOnFailure, TraceLayer};
use tracing::Level;

use crate::access::Role;
use crate::AppState;
use auth::Gate;
use error::ApiError;

/// The whole HTTP surface.
pub fn router(app: AppState) -> Router {
    let timeout = app.store.limits().request_timeout;
    routes(&app)
        .router
        .fallback(unknown_route)
        .layer(TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            timeout,
        ))
        .layer(axum::middleware::from_fn(json_errors))
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(request_span)
                // A 5xx here is either `busy` (503, back-pressure a flood of clients can cause
                // thousands of times a second) or an internal error that `ApiError::internal`
                // has already logged at ERROR with its cause: neither needs a second line above
                // DEBUG.
                .on_failure(DefaultOnFailure::new().level(Level::DEBUG)),
        )
        .layer(axum::middleware::from_fn(manners::close_unless_read))
        .with_state(app)
}

/// The span of one request: its method and path, never its query string, which may hold a
/// secret a client put there by mistake (a `?token=`), nor its headers (`Authorization`).
fn request_span(request: &Request) -> tracing::Span {
    tracing::debug_span!(
        "request",
        method = %request.method(),
        path = %request.uri().path(),
    )
}

/// Every endpoint, each declared with the role it needs right where its path and handler are.
fn routes(app: &AppState) -> Routes {
    use Method as M;
    use Role::{Admin, Read, Write};
    // States are mostly small integers and zeros: compress them for clients that ask.
    let export = states::export.layer(CompressionLayer::new().gzip(true).zstd(true));
    Routes::new(app)
        .open(M::GET, "/", operations::index)
        .open(M::GET, "/healthz", operations::healthz)
        .route(M::GET, "/metrics", Read, operations::metrics)
        .route(M::POST, "/v1/frames", Admin, frames::create)
        .route(M::GET, "/v1/frames", Read, frames::list)
        .route(M::GET, "/v1/frames/{id}", Read, frames::info)
        .route(M::PUT, "/v1/frames/{id}", Write, frames::put)
        .route(M::DELETE, "/v1/frames/{id}", Admin, frames::delete)
        .route(
            M::POST,
            "/v1/frames/{id}/samples",
            Write,
            ingest::post_samples,
        )
        .route(M::POST, "/v1/frames/{id}/passes", Write, ingest::post_pass)
        .route(M::POST, "/v1/frames/{id}/sync", Write, operations::sync)
        .route(M::GET, "/v1/frames/{id}/image.exr", Read, images::get_image)
        .route(
            M::GET,
            "/v1/frames/{id}/preview.png",
            Read,
            images::get_preview,
        )
        .route(M::GET, "/v1/frames/{id}/need", Read, need::get_need)
        .route(M::GET, "/v1/frames/{id}/state", Read, export)
        .route(M::POST, "/v1/frames/{id}/state", Admin, states::import)
}

/// One endpoint as declared: a method on a path, and the role it needs (`None`: open to all).
#[derive(Debug, Clone, PartialEq, Eq)]
struct Endpoint {
    method: Method,
    path: &'static str,
    role: Option<Role>,
}

/// Builds the router one endpoint at a time. Every endpoint is added with its role (or
/// explicitly as open), and its guard is attached to that endpoint alone, so there is no second
/// table to keep in step with the routes, and a method nobody declared (a read token's `POST`,
/// say) reaches no handler: it is answered 405.
struct Routes {
    app: AppState,
    router: Router<AppState>,
    /// What was declared, so tests can hold the declarations to the documented table.
    #[cfg_attr(not(test), allow(dead_code))]
    endpoints: Vec<Endpoint>,
}

impl Routes {
    fn new(app: &AppState) -> Routes {
        Routes {
            app: app.clone(),
            router: Router::new(),
            endpoints: Vec::new(),
        }
    }

    /// `method path`, open to everyone, token or not.
    fn open<H, T>(self, method: Method, path: &'static str, handler: H) -> Routes
    where
        H: Handler<T, AppState>,
        T: 'static,
    {
        self.add(method, path, None, handler)
    }

    /// `method path`, for tokens with `role` (and for everyone on an open server).
    fn route<H, T>(self, method: Method, path: &'static str, role: Role, handler: H) -> Routes
    where
        H: Handler<T, AppState>,
        T: 'static,
    {
        self.add(method, path, Some(role), handler)
    }

    fn add<H, T>(
        mut self,
        method: Method,
        path: &'static str,
        role: Option<Role>,
        handler: H,
    ) -> Routes
    where
        H: Handler<T, AppState>,
        T: 'static,
    {
        let filter = MethodFilter::try_from(method.clone())
            .unwrap_or_else(|e| panic!("{method} {path}: {e}"));
        // The guard runs before the handler: a request without the right token is refused
        // before anything reads or inflates its body (a gzip bomb from a stranger costs
        // nothing). The body extractors inflate compressed bodies themselves, after reserving
        // working memory, on the blocking pool and within the endpoint's limit.
        let mut endpoint = on(filter, handler);
        if let Some(role) = role {
            endpoint = endpoint.route_layer(axum::middleware::from_fn_with_state(
                Gate::new(self.app.clone(), role),
                auth::require_role,
            ));
        }
        self.router = self.router.route(path, endpoint);
        self.endpoints.push(Endpoint { method, path, role });
        self
    }
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
