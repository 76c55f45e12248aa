//! Running heavy work off the reactor.
//!
//! Anything heavier than a lookup (decoding a batch, splatting it, resolving, encoding an EXR or
//! a PNG) runs on tokio's blocking pool, so a 4-million-record batch never stalls the requests
//! sharing its worker thread.

use crate::http::error::ApiError;

/// Runs `f` on the blocking pool; a panic in it becomes a 500 naming `what`.
pub async fn blocking<T, F>(what: &'static str, f: F) -> Result<T, ApiError>
where
    T: Send + 'static,
    F: FnOnce() -> Result<T, ApiError> + Send + 'static,
{
    match tokio::task::spawn_blocking(f).await {
        Ok(result) => result,
        Err(e) => Err(ApiError::internal(what, e)),
    }
}
