//! One error type for both APIs, with what it means in gRPC and in HTTP.
use crate::auth::tenants::AuthError;
use crate::engine::EngineError;
use crate::model::preprocess::ImageError;
use crate::store::StoreError;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;

/// What 429 and 503 answers give as `Retry-After` (seconds).
const RETRY_AFTER_SECS: &str = "1";

/// Longest error message sent back (client input echoed in it is cut).
const MAX_MESSAGE_BYTES: usize = 1024;

/// Every HTTP error's body.
#[derive(serde::Serialize, utoipa::ToSchema)]
#[schema(as = Error)]
pub struct ErrorBody {
    /// What went wrong (cut at 1 KiB).
    pub error: String,
    /// The HTTP status.
    pub code: u16,
}

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    #[error("{0}")]
    InvalidArgument(String),
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    AlreadyExists(String),
    #[error("{0}")]
    TooLarge(String),
    #[error("{0}")]
    Overloaded(String),
    #[error("{0}")]
    Unavailable(String),
    /// The request is well formed but the target cannot take it (another descriptor space).
    #[error("{0}")]
    FailedPrecondition(String),
    #[error("{0}")]
    Internal(String),
    /// No key, or one that is malformed, unknown or revoked.
    #[error("{0}")]
    Unauthenticated(String),
    /// A valid key that may not use the route (a tenant's key on an admin route).
    #[error("{0}")]
    PermissionDenied(String),
}

impl From<AuthError> for ApiError {
    fn from(e: AuthError) -> Self {
        let msg = e.to_string();
        match e {
            AuthError::Unauthenticated(_) => ApiError::Unauthenticated(msg),
            AuthError::PermissionDenied(_) => ApiError::PermissionDenied(msg),
            AuthError::InvalidArgument(_) => ApiError::InvalidArgument(msg),
            AuthError::NotFound(_) => ApiError::NotFound(msg),
            AuthError::Store(e) => e.into(),
        }
    }
}

impl From<EngineError> for ApiError {
    fn from(e: EngineError) -> Self {
        let msg = e.to_string();
        match e {
            EngineError::Image(ImageError::TooManyBytes { .. } | ImageError::TooMuchMemory { .. }) => {
                ApiError::TooLarge(msg)
            }
            EngineError::Image(_) => ApiError::InvalidArgument(msg),
            EngineError::Overloaded(_) => ApiError::Overloaded(msg),
            EngineError::Stopped => ApiError::Unavailable(msg),
            EngineError::Inference(_) => ApiError::Internal(msg),
        }
    }
}

impl From<crate::verify::VerifyError> for ApiError {
    fn from(e: crate::verify::VerifyError) -> Self {
        use crate::verify::VerifyError;
        let msg = e.to_string();
        match e {
            VerifyError::Invalid(_) => ApiError::InvalidArgument(msg),
            VerifyError::Corrupt(_) | VerifyError::Failed(_) => ApiError::Internal(msg),
        }
    }
}

impl From<crate::index::query::InvalidQuery> for ApiError {
    fn from(e: crate::index::query::InvalidQuery) -> Self {
        ApiError::InvalidArgument(e.0)
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        let msg = e.to_string();
        match e {
            StoreError::SessionNotFound(_) | StoreError::FrameNotFound(..) | StoreError::LoopNotFound(_) => {
                ApiError::NotFound(msg)
            }
            StoreError::SessionExists(_) | StoreError::FrameExists(..) | StoreError::KeyReused(_) => {
                ApiError::AlreadyExists(msg)
            }
            StoreError::InvalidArgument(_) => ApiError::InvalidArgument(msg),
            StoreError::Storage(_) => ApiError::Internal(msg),
            StoreError::Stopped | StoreError::Unavailable(_) => ApiError::Unavailable(msg),
        }
    }
}

impl ApiError {
    pub fn http_status(&self) -> StatusCode {
        match self {
            ApiError::InvalidArgument(_) => StatusCode::BAD_REQUEST,
            ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::AlreadyExists(_) => StatusCode::CONFLICT,
            ApiError::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            ApiError::Overloaded(_) => StatusCode::TOO_MANY_REQUESTS,
            ApiError::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::FailedPrecondition(_) => StatusCode::CONFLICT,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
            ApiError::Unauthenticated(_) => StatusCode::UNAUTHORIZED,
            ApiError::PermissionDenied(_) => StatusCode::FORBIDDEN,
        }
    }

    /// The message as sent to clients: bounded, so an echoed oversized input cannot push a gRPC
    /// status past the metadata limit.
    pub fn message(&self) -> String {
        let msg = self.to_string();
        if msg.len() <= MAX_MESSAGE_BYTES {
            return msg;
        }
        let mut end = MAX_MESSAGE_BYTES;
        while !msg.is_char_boundary(end) {
            end -= 1;
        }
        format!("{}... ({} bytes in all)", &msg[..end], msg.len())
    }

    pub fn grpc_status(&self) -> tonic::Status {
        let msg = self.message();
        match self {
            ApiError::InvalidArgument(_) => tonic::Status::invalid_argument(msg),
            // What tonic itself answers for a message over its size limit: one code for "too large".
            ApiError::TooLarge(_) => tonic::Status::out_of_range(msg),
            ApiError::NotFound(_) => tonic::Status::not_found(msg),
            ApiError::AlreadyExists(_) => tonic::Status::already_exists(msg),
            ApiError::Overloaded(_) => tonic::Status::resource_exhausted(msg),
            ApiError::Unavailable(_) => tonic::Status::unavailable(msg),
            ApiError::FailedPrecondition(_) => tonic::Status::failed_precondition(msg),
            ApiError::Internal(_) => tonic::Status::internal(msg),
            ApiError::Unauthenticated(_) => tonic::Status::unauthenticated(msg),
            ApiError::PermissionDenied(_) => tonic::Status::permission_denied(msg),
        }
    }
}

impl From<ApiError> for tonic::Status {
    fn from(e: ApiError) -> Self {
        e.grpc_status()
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.http_status();
        if status.is_server_error() {
            tracing::error!(error = %self, "request failed");
        }
        let body = Json(ErrorBody { error: self.message(), code: status.as_u16() });
        match self {
            // Overload and outages pass: a client knows when to come back.
            ApiError::Overloaded(_) | ApiError::Unavailable(_) => {
                (status, [(axum::http::header::RETRY_AFTER, RETRY_AFTER_SECS)], body).into_response()
            }
            ApiError::Unauthenticated(_) => {
                (status, [(axum::http::header::WWW_AUTHENTICATE, "Bearer")], body).into_response()
            }
            _ => (status, body).into_response(),
        }
    }
}
