//! The one form reader of the HTTP API: a frame or query as JSON, a multipart form or a raw
//! image with its fields in the query string, parsed once into the service's `FrameInput`; and
//! the fields and files of any form (sequence uploads too), size limits answering 413.
use super::state::{body_error, json_error};
use crate::api::error::ApiError;
use crate::api::service::{Content, FrameInput, QueryOverrides};
use crate::index::query::Pose;
use axum::body::Bytes;
use axum::extract::{FromRequest, Multipart, Query, Request};
use axum::http::header;
use axum::Json;
use serde::Deserialize;
use std::collections::HashMap;

/// A frame or query as sent: JSON body, multipart form (an `image` file plus fields), or a raw
/// image body with the fields in the query string. Field names are the same in all three.
///
/// As JSON: give `descriptor` (an image needs multipart or a raw body); a query may instead name
/// a stored `frame_id` to query with.
#[derive(Default, Deserialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
#[schema(as = FrameRequest)]
pub struct FrameFields {
    /// The robot that saw the frame (1-128 bytes, no control characters).
    pub robot_id: Option<String>,
    pub timestamp: Option<f64>,
    /// A frame: its id (unset: assigned). A query: the stored frame to query with.
    pub frame_id: Option<u64>,
    pub pose: Option<Pose>,
    /// A JSON object stored with the frame.
    #[schema(value_type = Option<Object>)]
    pub metadata: Option<serde_json::Value>,
    pub descriptor: Option<Vec<f32>>,
    /// Optional, with `descriptor`: the descriptor space its values come from (a served model's
    /// `descriptor_id`, `GET /v1/models`); a session of another space refuses them (409).
    pub descriptor_id: Option<String>,
    pub options: Option<QueryOverrides>,
    /// A write's idempotency key (1-128 visible ASCII characters): sent again with it, the
    /// write stores nothing and answers the first write's frame id.
    pub idempotency_key: Option<String>,
    #[serde(skip)]
    pub image: Option<Bytes>,
    /// The `depth` part of a multipart form: the image's registered depth image.
    #[serde(skip)]
    pub depth: Option<Bytes>,
    /// The `right` part of a multipart form: the right image of a stereo pair.
    #[serde(skip)]
    pub right: Option<Bytes>,
}

/// Text form fields (multipart or query string) into the same JSON shape as a JSON body.
fn fields_from_text(
    map: HashMap<String, String>,
    image: Option<Bytes>,
    depth: Option<Bytes>,
    right: Option<Bytes>,
) -> Result<FrameFields, ApiError> {
    let mut obj = serde_json::Map::new();
    for (k, v) in map {
        let value = match k.as_str() {
            "robot_id" | "idempotency_key" | "descriptor_id" => serde_json::Value::String(v),
            "timestamp" | "frame_id" | "pose" | "metadata" | "descriptor" | "options" => serde_json::from_str(&v)
                .map_err(|e| ApiError::InvalidArgument(format!("field {k}: not valid JSON/number ({e})")))?,
            other => return Err(ApiError::InvalidArgument(format!("unknown field '{other}'"))),
        };
        obj.insert(k, value);
    }
    let mut f: FrameFields =
        serde_json::from_value(serde_json::Value::Object(obj)).map_err(|e| ApiError::InvalidArgument(e.to_string()))?;
    f.image = image;
    f.depth = depth;
    f.right = right;
    Ok(f)
}

/// A frame request as `POST /v1/sessions/{id}/frames` reads it (JSON, multipart or raw body),
/// converted and validated: the fuzz target's entry.
pub async fn parse_frame_request(req: Request) -> Result<(FrameInput, QueryOverrides), ApiError> {
    let (f, opts) = frame_input(read_fields(req).await?)?;
    f.validate(&opts)?;
    Ok((f, opts))
}

pub async fn read_fields(req: Request) -> Result<FrameFields, ApiError> {
    if content_type(&req).starts_with("application/json") {
        let Json(f) = Json::<FrameFields>::from_request(req, &()).await.map_err(json_error)?;
        return Ok(f);
    }
    let mut form = read_form(req, &["image", "depth", "right"]).await?;
    let mut part = |name: &str| {
        let mut files: Vec<Bytes> = Vec::new();
        form.files.retain(|f| {
            let mine = f.part == name;
            if mine {
                files.push(f.data.clone());
            }
            !mine
        });
        match files.len() {
            0 | 1 => Ok(files.pop()),
            _ => Err(ApiError::InvalidArgument(format!("one '{name}' part per frame"))),
        }
    };
    let (image, depth, right) = (part("image")?, part("depth")?, part("right")?);
    let image = image.or(form.body.filter(|b| !b.is_empty()));
    fields_from_text(form.fields, image, depth, right)
}

fn content_type(req: &Request) -> String {
    req.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_string()
}

/// One uploaded file of a form.
pub struct FormFile {
    /// The form part's name (`image`, `archive`).
    pub part: String,
    /// The client's file name, if it sent one.
    pub file_name: Option<String>,
    pub data: Bytes,
}

/// A request as fields and files: a multipart form (parts named in `file_parts` are files, the
/// rest text fields), or a raw body with the fields in the query string. The one form reader
/// of the HTTP API: size limits answer 413 wherever they are hit.
pub struct Form {
    pub fields: HashMap<String, String>,
    pub files: Vec<FormFile>,
    /// The raw body of a non-multipart request.
    pub body: Option<Bytes>,
}

pub async fn read_form(req: Request, file_parts: &[&str]) -> Result<Form, ApiError> {
    let Query(mut fields) = Query::<HashMap<String, String>>::try_from_uri(req.uri())
        .map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    if !content_type(&req).starts_with("multipart/form-data") {
        let body = Bytes::from_request(req, &()).await.map_err(|e| body_error(e.status(), e.body_text()))?;
        return Ok(Form { fields, files: Vec::new(), body: Some(body) });
    }
    let mut mp = Multipart::from_request(req, &()).await.map_err(|e| body_error(e.status(), e.body_text()))?;
    let mut files = Vec::new();
    while let Some(field) = mp.next_field().await.map_err(multipart_error)? {
        let part = field.name().unwrap_or("").to_string();
        if file_parts.contains(&part.as_str()) {
            let file_name = field.file_name().filter(|n| !n.is_empty()).map(str::to_string);
            files.push(FormFile { part, file_name, data: field.bytes().await.map_err(multipart_error)? });
        } else {
            let data = field.bytes().await.map_err(multipart_error)?;
            let text = String::from_utf8(data.to_vec())
                .map_err(|_| ApiError::InvalidArgument(format!("field {part} is not text")))?;
            fields.insert(part, text);
        }
    }
    Ok(Form { fields, files, body: None })
}

fn multipart_error(e: axum::extract::multipart::MultipartError) -> ApiError {
    body_error(e.status(), e.body_text())
}

pub fn content(f: &mut FrameFields) -> Result<Content, ApiError> {
    let (depth, right) = (f.depth.take(), f.right.take());
    match (f.image.take(), f.descriptor.take()) {
        (Some(_), Some(_)) => Err(ApiError::InvalidArgument("send an image or a descriptor, not both".into())),
        (Some(image), None) => Ok(Content::Image { image, depth, right }),
        (None, _) if depth.is_some() || right.is_some() => {
            Err(ApiError::InvalidArgument("a 'depth' or 'right' part goes with an 'image' part".into()))
        }
        (None, Some(d)) => Ok(Content::Descriptor(d, f.descriptor_id.take())),
        (None, None) => Err(ApiError::InvalidArgument("an image or a descriptor is required".into())),
    }
}

pub fn frame_input(mut f: FrameFields) -> Result<(FrameInput, QueryOverrides), ApiError> {
    let content = content(&mut f)?;
    let input = FrameInput {
        robot_id: f.robot_id.unwrap_or_default(),
        timestamp: f.timestamp,
        frame_id: f.frame_id,
        pose: f.pose,
        metadata: f.metadata,
        content,
        thumbnail: None,
        idempotency_key: f.idempotency_key,
    };
    Ok((input, f.options.unwrap_or_default()))
}
