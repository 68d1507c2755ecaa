//! HTTP routes of offline sequence jobs: start one from an upload, read its progress.
use super::doc::{
    BadRequest, Binary, Conflict, NotFound, Overloaded, SequenceFields, SequenceForm, TooLarge, Unauthorized,
    Unavailable,
};
use super::form::read_form;
use super::state::AppState;
use crate::api::error::ApiError;
use crate::api::jobs::SequenceRequest;
use crate::api::wire::JobStatus;
use crate::auth::Caller;
use axum::extract::{Path, Request, State};
use axum::http::StatusCode;
use axum::{Extension, Json};
use serde::Serialize;
use std::sync::Arc;

/// A started job and where to read its progress.
#[derive(Serialize, utoipa::ToSchema)]
pub struct JobCreated {
    job_id: String,
    status_url: String,
}

/// Offline sequence job (many images in order, a tar archive, or a ROS bag)
///
/// Each frame is embedded and its ORB features extracted, then it is added and queried exactly
/// as `add_and_query` answers a robot (the same checks, the same confidence; its frames keep
/// their features and their answered candidates are kept loops), in the order of the sequence.
/// Defaults: the robot's own frames more than 3 frames back (`k` 1), geometric and sequence
/// verification on. The job reports each frame whose first candidate reaches `min_confidence`
/// (default: the server's `loop_confidence`, /v1/info; every first candidate when the server has
/// no calibrator) as a loop closure. Any field of the query options (QueryOptions) may be given
/// here as a form or query field.
///
/// The upload: multipart with many `image` files (in the order sent, or natural name order with
/// `order=name`), one tar archive (`archive` part or a tar body), or a bag (`bag` parts, the
/// files of a split bag in order, or an MCAP / ROS 1 bag body). A bag is a rosbag2 MCAP file
/// (chunks uncompressed, zstd or lz4) or a ROS 1 bag (format 2.0; chunks uncompressed, bz2 or
/// lz4). Its `sensor_msgs/Image` (rgb8, bgr8, rgba8, bgra8, mono8, mono16, 8UC1, 8UC3, 16UC1;
/// `step` padding and `is_bigendian` honoured) and `sensor_msgs/CompressedImage` (JPEG, PNG)
/// messages become frames in recording order, stamped from their headers, with the robot id taken
/// from the topic's namespace (`/robot1/cam/image_raw` is robot1's) unless `robot_id` is given. A
/// truncated or corrupt bag, one without the topic asked for, or without image topics is a 400
/// that says what is wrong.
#[utoipa::path(
    post, path = "/v1/sessions/{id}/sequences", tag = "jobs",
    params(("id" = String, Path), SequenceFields),
    request_body(content(
        (SequenceForm = "multipart/form-data"), (Binary = "application/x-tar"), (Binary = "application/octet-stream"),
    )),
    responses(
        (status = 202, description = "Started.", body = JobCreated),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 409, response = Conflict),
        (status = 413, response = TooLarge), (status = 429, response = Overloaded),
        (status = 503, response = Unavailable),
    )
)]
pub async fn start_sequence(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    req: Request,
) -> Result<(StatusCode, Json<JobCreated>), ApiError> {
    let scoped = s.service.scoped(caller);
    scoped.session(&id).await?;
    let form = read_form(req, &["image", "archive", "bag"]).await?;
    let files = form.files.into_iter().map(|f| (f.part, f.file_name, f.data)).collect();
    // Unpacking a bag (decompression, raw pixels to PNG) is CPU work: off the async workers.
    let seq = tokio::task::spawn_blocking(move || SequenceRequest::from_form(form.fields, files, form.body))
        .await
        .map_err(|e| ApiError::Internal(format!("reading the upload failed: {e}")))??;
    let job_id = scoped.start_sequence(&s.jobs, &id, seq).await?;
    Ok((StatusCode::ACCEPTED, Json(JobCreated { status_url: format!("/v1/jobs/{job_id}"), job_id })))
}

/// Progress and results of a sequence job
///
/// In a cluster any node answers for a job started through any other (its record is in the
/// cluster's database); a job still running on a node that is gone reads as interrupted.
#[utoipa::path(
    get, path = "/v1/jobs/{job_id}", tag = "jobs",
    params(("job_id" = String, Path)),
    responses(
        (status = 200, description = "The job.", body = JobStatus),
        (status = 401, response = Unauthorized), (status = 404, response = NotFound),
        (status = 503, response = Unavailable),
    )
)]
pub async fn job_status(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(job_id): Path<String>,
) -> Result<Json<JobStatus>, ApiError> {
    Ok(Json(s.service.scoped(caller).job(&s.jobs, &job_id).await?))
}
