//! One error type for every API, with the HTTP status each case means.
use crate::engine::EngineError;
use crate::model::preprocess::ImageError;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    #[error("{0}")]
    Engine(#[from] EngineError),
    #[error("{0}")]
    BadRequest(String),
}

impl ApiError {
    pub fn status(&self) -> StatusCode {
        match self {
            ApiError::Engine(EngineError::Image(ImageError::TooManyBytes { .. })) => StatusCode::PAYLOAD_TOO_LARGE,
            ApiError::Engine(EngineError::Image(_)) | ApiError::BadRequest(_) => StatusCode::BAD_REQUEST,
            ApiError::Engine(EngineError::Overloaded(_)) => StatusCode::TOO_MANY_REQUESTS,
            ApiError::Engine(EngineError::Stopped) => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::Engine(EngineError::DeadlineExceeded) => StatusCode::GATEWAY_TIMEOUT,
            ApiError::Engine(EngineError::Inference(_)) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        (status, Json(serde_json::json!({ "error": self.to_string(), "code": status.as_u16() }))).into_response()
    }
}
