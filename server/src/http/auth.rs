//! The HTTP side of the access rules ([`crate::access`]): every route is declared with its
//! role in `http::router` and guarded there by [`require_role`], which answers a refusal before
//! the handler (and so before any extractor reads or decompresses the body).

use axum::extract::{Request, State};
use axum::http::{header, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use crate::access::Role;
use crate::http::error::ApiError;
use crate::AppState;

/// What guards one route: the server's access rules and the role the route was declared with
/// (see `http::router`, where every route names its role next to its path).
#[derive(Debug, Clone)]
pub struct Gate {
    app: AppState,
    role: Role,
}

impl Gate {
    /// The guard of a route that needs `role`.
    pub fn new(app: AppState, role: Role) -> Gate {
        Gate { app, role }
    }
}

/// Middleware in front of one route's handler: refuses a request without the route's role
/// (401 with `WWW-Authenticate: Bearer`, or 403) before the handler, and so before any of its
/// extractors, reads or decompresses the body.
pub async fn require_role(State(gate): State<Gate>, request: Request, next: Next) -> Response {
    let authorization = request.headers().get(header::AUTHORIZATION);
    match gate
        .app
        .auth
        .check(gate.role, authorization.map(|v| v.as_bytes()))
    {
        Ok(()) => next.run(request).await,
        Err(e) => {
            let e = ApiError::from(e);
            metrics::counter!(crate::meters::AUTH_REFUSED, "status" => e.status.as_str().to_owned())
                .increment(1);
            let mut response = e.into_response();
            if response.status() == StatusCode::UNAUTHORIZED {
                response.headers_mut().insert(
                    header::WWW_AUTHENTICATE,
                    header::HeaderValue::from_static("Bearer"),
                );
            }
            response
        }
    }
}
