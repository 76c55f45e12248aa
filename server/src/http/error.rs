//! Errors of the HTTP API: a status, a stable machine-readable code and a sentence naming the
//! problem, sent as the JSON `ErrorBody` every client understands.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use splatd_proto::{ErrorBody, StateError, WireError};

use crate::frame::{ImportRefused, IngestError};
use splatd_estimator::{MergeError, SampleError};

/// An error answered to a client.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ApiError {
    /// HTTP status.
    pub status: StatusCode,
    /// Stable code, e.g. `pixel_out_of_range`.
    pub code: &'static str,
    /// What went wrong, for people.
    pub message: String,
}

impl ApiError {
    /// An error with any status.
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> ApiError {
        ApiError {
            status,
            code,
            message: message.into(),
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
        (self.status, Json(ErrorBody::new(self.code, self.message))).into_response()
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
            IngestError::Deleted { .. } => {
                return ApiError::new(StatusCode::NOT_FOUND, "unknown_frame", e.to_string())
            }
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
        }
    }
}
