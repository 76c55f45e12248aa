//! Errors of the HTTP API: a status, a stable machine-readable code and a sentence naming the
//! problem, sent as the JSON `ErrorBody` every client understands.
//!
//! This is the one place where the domain's errors (the store's, the frame's, the data
//! directory's, the wire formats') become statuses and codes: the domain modules say what went
//! wrong, and only the HTTP layer decides how that is answered.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use splatd_estimator::{MergeError, ParamError, SampleError};
use splatd_proto::{ErrorBody, StateError, WireError};

use crate::durable::DurabilityError;
use crate::frame::{ImportRefused, IngestError};
use crate::store::StoreError;
use crate::transport::HeadError;
use splatd_formats::passes::PassError;
use splatd_formats::state::ImportError;

/// An error answered to a client.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ApiError {
    /// HTTP status.
    pub status: StatusCode,
    /// Stable code, e.g. `pixel_out_of_range`.
    pub code: &'static str,
    /// What went wrong, for people.
    pub message: String,
    /// Seconds after which a retry may succeed (`Retry-After`), for 503s.
    pub retry_after: Option<u64>,
}

impl ApiError {
    /// An error with any status.
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> ApiError {
        ApiError {
            status,
            code,
            message: message.into(),
            retry_after: None,
        }
    }

    /// 503 with `Retry-After`: the server is short of working memory for now.
    pub fn busy(busy: &crate::work::Busy) -> ApiError {
        ApiError {
            retry_after: Some(busy.retry_after.as_secs().max(1)),
            ..ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "busy", busy.to_string())
        }
    }

    /// 400 with `code`.
    pub fn bad_request(code: &'static str, message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::BAD_REQUEST, code, message)
    }

    /// 404 for a frame the server does not have.
    pub fn unknown_frame(id: &str) -> ApiError {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown_frame",
            format!("no frame {id:?} on this server"),
        )
    }

    /// 500 for a failure that is the server's fault; details go to the log, not the client.
    pub fn internal(what: &str, error: impl std::fmt::Display) -> ApiError {
        tracing::error!(%error, "{what}");
        ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal_error",
            format!("{what} failed on the server; see its log"),
        )
    }

    /// 422 for a pass that cannot be read or does not fit `frame`.
    pub fn invalid_pass(frame: &str, e: &PassError) -> ApiError {
        ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_pass",
            format!("pass for frame {frame:?}: {e}"),
        )
    }
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} {}: {}",
            self.status.as_u16(),
            self.code,
            self.message
        )
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut response =
            (self.status, Json(ErrorBody::new(self.code, self.message))).into_response();
        if let Some(secs) = self.retry_after {
            response
                .headers_mut()
                .insert(axum::http::header::RETRY_AFTER, secs.into());
        }
        response
    }
}

impl From<&WireError> for ApiError {
    fn from(e: &WireError) -> ApiError {
        let status = match e {
            WireError::TooManyRecords { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            _ => StatusCode::BAD_REQUEST,
        };
        ApiError::new(status, e.code(), e.to_string())
    }
}

impl From<&StateError> for ApiError {
    fn from(e: &StateError) -> ApiError {
        let status = match e {
            StateError::TooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            _ => StatusCode::BAD_REQUEST,
        };
        ApiError::new(status, e.code(), e.to_string())
    }
}

impl From<IngestError> for ApiError {
    fn from(e: IngestError) -> ApiError {
        let code = match &e {
            IngestError::WrongFrame { .. } => {
                return ApiError::bad_request("frame_mismatch", e.to_string())
            }
            IngestError::IdReused { .. } => {
                return ApiError::new(StatusCode::CONFLICT, "batch_id_reused", e.to_string())
            }
            IngestError::IdUnverified { .. } => {
                return ApiError::new(StatusCode::CONFLICT, "batch_id_unverified", e.to_string())
            }
            IngestError::Deleted { .. } => {
                return ApiError::new(StatusCode::NOT_FOUND, "unknown_frame", e.to_string())
            }
            IngestError::AovFull { .. } => "pixel_full",
            IngestError::Sample { error, .. } => match error {
                SampleError::OutOfFrame { .. } => "pixel_out_of_range",
                SampleError::NonFinite => "non_finite_sample",
                SampleError::Negative => "negative_sample",
                SampleError::TooBright { .. } => "sample_too_bright",
                SampleError::PixelFull { .. } => "pixel_full",
            },
        };
        ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, code, e.to_string())
    }
}

impl From<ImportRefused> for ApiError {
    fn from(e: ImportRefused) -> ApiError {
        match e {
            ImportRefused::Invalid(e) => e.into(),
            ImportRefused::WrongFrame { .. } => {
                ApiError::bad_request("frame_mismatch", e.to_string())
            }
            ImportRefused::Mismatch {
                error: MergeError::TooManySamples { .. },
                ..
            } => ApiError::new(StatusCode::CONFLICT, "too_many_samples", e.to_string()),
            ImportRefused::Mismatch { .. } => {
                ApiError::new(StatusCode::CONFLICT, "state_mismatch", e.to_string())
            }
            ImportRefused::Deleted { .. } => {
                ApiError::new(StatusCode::NOT_FOUND, "unknown_frame", e.to_string())
            }
            ImportRefused::Overlap { .. } => {
                ApiError::new(StatusCode::CONFLICT, "batches_overlap", e.to_string())
            }
            ImportRefused::Aovs { .. } => {
                ApiError::new(StatusCode::CONFLICT, "aov_mismatch", e.to_string())
            }
        }
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> ApiError {
        let message = e.to_string();
        match e {
            StoreError::InvalidParameters(e) => e.into(),
            StoreError::TooManyPixels { .. } | StoreError::TooManyCascades { .. } => {
                ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, "frame_too_large", message)
            }
            StoreError::Exists { .. } => {
                ApiError::new(StatusCode::CONFLICT, "frame_exists", message)
            }
            StoreError::TooManyFrames { .. } => {
                ApiError::new(StatusCode::CONFLICT, "too_many_frames", message)
            }
            StoreError::MemoryLimit { .. } => {
                ApiError::new(StatusCode::CONFLICT, "memory_limit", message)
            }
            StoreError::UnknownFrame { id } => ApiError::unknown_frame(&id),
        }
    }
}

/// Parameters that break their own rules (a create request's, an image query's overrides).
impl From<ParamError> for ApiError {
    fn from(e: ParamError) -> ApiError {
        ApiError::bad_request("invalid_parameters", e.to_string())
    }
}

/// A change that could not be made durable is the server's fault: 500, details in the log.
impl From<DurabilityError> for ApiError {
    fn from(e: DurabilityError) -> ApiError {
        if e.source.is_out_of_space() {
            // Not the client's fault and not a bug: the operator has to free space. Say so.
            tracing::error!(error = %e.source, "{}", e.action);
            return ApiError::new(
                StatusCode::INSUFFICIENT_STORAGE,
                "insufficient_storage",
                format!(
                    "{} failed: the data directory is full or over a size limit; \
                     acknowledged samples are not becoming durable",
                    e.action
                ),
            );
        }
        ApiError::internal(e.action, e.source)
    }
}

/// A request the access rules refused: 401 `unauthorized` without a valid token, 403
/// `forbidden` for a token without the role.
impl From<crate::access::Refused> for ApiError {
    fn from(e: crate::access::Refused) -> ApiError {
        use crate::access::Refused;
        let (status, code) = match e {
            Refused::NoToken | Refused::UnknownToken => (StatusCode::UNAUTHORIZED, "unauthorized"),
            Refused::LacksRole(_) => (StatusCode::FORBIDDEN, "forbidden"),
        };
        ApiError::new(status, code, e.to_string())
    }
}

/// A need map or figures that could not be computed: a bad tile is the query's fault (400), a
/// spent working budget 503 with `Retry-After`.
impl From<crate::render::figures::FiguresError> for ApiError {
    fn from(e: crate::render::figures::FiguresError) -> ApiError {
        use crate::render::figures::FiguresError;
        match e {
            FiguresError::Param(e) => e.into(),
            FiguresError::Busy(busy) => ApiError::busy(&busy),
            FiguresError::Internal { what, detail } => ApiError::internal(what, detail),
        }
    }
}

impl<E: Into<ApiError>> From<crate::render::RenderError<E>> for ApiError {
    fn from(e: crate::render::RenderError<E>) -> ApiError {
        match e {
            crate::render::RenderError::Busy(busy) => ApiError::busy(&busy),
            crate::render::RenderError::Failed(e) => e.into(),
        }
    }
}

/// A denoise the server cannot run: 501 without a usable OIDN (the request is fine, the server
/// lacks the part), 500 when OIDN failed on the frame (its message is passed on: it names no
/// secret and says what went wrong).
impl From<crate::render::denoise::DenoiseError> for ApiError {
    fn from(e: crate::render::denoise::DenoiseError) -> ApiError {
        match e {
            crate::render::denoise::DenoiseError::Unavailable { .. } => ApiError::new(
                StatusCode::NOT_IMPLEMENTED,
                "denoiser_unavailable",
                e.to_string(),
            ),
            crate::render::denoise::DenoiseError::Failed { .. } => {
                tracing::error!(error = %e, "denoise failed");
                ApiError::new(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "denoise_failed",
                    e.to_string(),
                )
            }
        }
    }
}

/// A state that decodes but does not describe a frame this build can hold.
impl From<ImportError> for ApiError {
    fn from(e: ImportError) -> ApiError {
        match e {
            ImportError::State(e) => ApiError::from(&e),
            e => ApiError::new(StatusCode::CONFLICT, "state_mismatch", e.to_string()),
        }
    }
}

impl From<WireError> for ApiError {
    fn from(e: WireError) -> ApiError {
        ApiError::from(&e)
    }
}

impl From<StateError> for ApiError {
    fn from(e: StateError) -> ApiError {
        ApiError::from(&e)
    }
}

/// A request head the transport refused: 400 for one that cannot be read, 414 for a request
/// line too long, 431 for too many or too large headers (hyper's own statuses for them, with a
/// JSON body hyper would not give).
impl From<HeadError> for ApiError {
    fn from(e: HeadError) -> ApiError {
        let (status, code) = match e {
            HeadError::Malformed(_) => (StatusCode::BAD_REQUEST, "malformed_request"),
            HeadError::UriTooLong => (StatusCode::URI_TOO_LONG, "uri_too_long"),
            HeadError::HeadTooLarge | HeadError::TooManyHeaders => (
                StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
                "headers_too_large",
            ),
        };
        ApiError::new(status, code, e.to_string())
    }
}

/// How the transport's service answers a head it refused, in place of the request.
impl IntoResponse for HeadError {
    fn into_response(self) -> Response {
        ApiError::from(self).into_response()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::{MAX_HEADERS, MAX_HEAD_BYTES, MAX_REQUEST_LINE_BYTES};

    /// The statuses, codes and messages of refused heads are the ones clients have always read.
    #[test]
    fn refused_heads_keep_their_statuses_codes_and_messages() {
        let answer = |e: HeadError| {
            let e = ApiError::from(e);
            (e.status.as_u16(), e.code, e.message)
        };
        assert_eq!(
            answer(HeadError::Malformed("invalid Content-Length".into())),
            (
                400,
                "malformed_request",
                "the request head could not be read: invalid Content-Length".to_owned()
            )
        );
        assert_eq!(
            answer(HeadError::UriTooLong),
            (
                414,
                "uri_too_long",
                format!("the request line exceeds {MAX_REQUEST_LINE_BYTES} bytes")
            )
        );
        assert_eq!(
            answer(HeadError::HeadTooLarge),
            (
                431,
                "headers_too_large",
                format!("the request head exceeds {MAX_HEAD_BYTES} bytes")
            )
        );
        assert_eq!(
            answer(HeadError::TooManyHeaders),
            (
                431,
                "headers_too_large",
                format!("the request has more than {MAX_HEADERS} headers")
            )
        );
    }
}
