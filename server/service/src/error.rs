//! One error type for the API, mapped to gRPC status and HTTP status in one place.
//! gRPC errors carry `google.rpc` details (BadRequest field violations with the JSON
//! path, ResourceInfo, RetryInfo) beside their message, so that any gRPC client can act
//! on them without parsing text. Client errors (bad input, bad token) are not logged as
//! server faults.

use std::time::Duration;

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use tonic::Code;
use tonic_types::{ErrorDetails, StatusExt};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ApiError {
    #[error("no session {0:?}; list the sessions to see their ids")]
    UnknownSession(String),
    #[error("{0}")]
    Unauthenticated(String),
    #[error("{0}")]
    PermissionDenied(String),
    #[error("{0}")]
    InvalidArgument(String),
    /// A value in a request's JSON (a scene, a script) that cannot be used: `field` is
    /// its JSON path inside the request field `request_field`.
    #[error("{message}")]
    BadField { request_field: &'static str, field: String, message: String },
    /// A limit: `resource` names what is full ("sessions", "cores", "memory", …).
    #[error("{message}")]
    ResourceExhausted { resource: &'static str, message: String },
    /// A client over its request rate: retry after `retry_after`.
    #[error("{message}")]
    RateLimited { message: String, retry_after: Duration },
    #[error("{0}")]
    FailedPrecondition(String),
    /// A session whose physics failed, or a part of the server that stopped: the request
    /// may work elsewhere or later.
    #[error("{0}")]
    Unavailable(String),
    #[error("internal error: {0}")]
    Internal(String),
}

impl ApiError {
    /// A limit refused, naming what is full.
    pub fn exhausted(resource: &'static str, message: impl Into<String>) -> Self {
        ApiError::ResourceExhausted { resource, message: message.into() }
    }

    pub fn code(&self) -> Code {
        match self {
            ApiError::UnknownSession(_) => Code::NotFound,
            ApiError::Unauthenticated(_) => Code::Unauthenticated,
            ApiError::PermissionDenied(_) => Code::PermissionDenied,
            ApiError::InvalidArgument(_) | ApiError::BadField { .. } => Code::InvalidArgument,
            ApiError::ResourceExhausted { .. } | ApiError::RateLimited { .. } => Code::ResourceExhausted,
            ApiError::FailedPrecondition(_) => Code::FailedPrecondition,
            ApiError::Unavailable(_) => Code::Unavailable,
            ApiError::Internal(_) => Code::Internal,
        }
    }

    pub fn http_status(&self) -> StatusCode {
        match self.code() {
            Code::NotFound => StatusCode::NOT_FOUND,
            Code::Unauthenticated => StatusCode::UNAUTHORIZED,
            Code::PermissionDenied => StatusCode::FORBIDDEN,
            Code::InvalidArgument => StatusCode::BAD_REQUEST,
            Code::ResourceExhausted => StatusCode::TOO_MANY_REQUESTS,
            Code::FailedPrecondition => StatusCode::CONFLICT,
            Code::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
            _ => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    /// The `google.rpc` details this error carries.
    fn details(&self) -> Option<ErrorDetails> {
        match self {
            ApiError::BadField { request_field, field, message } => {
                let path = if field.is_empty() { (*request_field).to_owned() } else { format!("{request_field}.{field}") };
                Some(ErrorDetails::with_bad_request_violation(path, message.clone()))
            }
            ApiError::UnknownSession(id) => Some(ErrorDetails::with_resource_info("cutsim.v1.Session", id.clone(), "", "no such session on this server")),
            ApiError::ResourceExhausted { resource, message } => Some(ErrorDetails::with_resource_info(*resource, "", "", message.clone())),
            ApiError::RateLimited { retry_after, .. } => Some(ErrorDetails::with_retry_info(Some(*retry_after))),
            _ => None,
        }
    }
}

impl From<ApiError> for tonic::Status {
    fn from(e: ApiError) -> Self {
        let message = e.to_string();
        if let ApiError::Internal(_) = &e {
            tracing::error!(%message, "internal error");
        }
        match e.details() {
            Some(details) => tonic::Status::with_error_details(e.code(), message, details),
            None => tonic::Status::new(e.code(), message),
        }
    }
}

impl From<cutsim_sim::scene::SceneError> for ApiError {
    fn from(e: cutsim_sim::scene::SceneError) -> Self {
        let message = e.to_string();
        ApiError::BadField { request_field: "scene_json", field: e.path, message }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        if let ApiError::Internal(m) = &self {
            tracing::error!(message = %m, "internal error");
        }
        let mut response = (self.http_status(), self.to_string()).into_response();
        if let ApiError::RateLimited { retry_after, .. } = &self {
            let seconds = retry_after.as_secs_f64().ceil().max(1.0) as u64;
            response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(seconds));
        }
        response
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grpc_errors_carry_google_rpc_details() {
        let status: tonic::Status = ApiError::BadField { request_field: "scene_json", field: "model.msm.material.young_pa".into(), message: "too soft".into() }.into();
        assert_eq!(status.code(), Code::InvalidArgument);
        let details = status.get_error_details();
        let violation = &details.bad_request().expect("a BadRequest").field_violations[0];
        assert_eq!(violation.field, "scene_json.model.msm.material.young_pa");

        let status: tonic::Status = ApiError::RateLimited { message: "slow down".into(), retry_after: Duration::from_millis(250) }.into();
        assert_eq!(status.get_error_details().retry_info().expect("a RetryInfo").retry_delay, Some(Duration::from_millis(250)));

        let status: tonic::Status = ApiError::exhausted("cores", "full").into();
        assert_eq!(status.get_error_details().resource_info().expect("a ResourceInfo").resource_type, "cores");
        assert_eq!(tonic::Status::from(ApiError::Unavailable("gone".into())).code(), Code::Unavailable);
    }
}
