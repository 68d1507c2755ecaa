//! A sequence job's request as the HTTP API takes it: image files in natural name order, a tar
//! archive or a ROS bag, the robot, and query options over the job defaults; parsed and checked
//! here once, before a job starts.
use super::super::error::ApiError;
use super::super::service::QueryOverrides;
use super::super::wire::{MAX_BAG_CHUNK_BYTES, MAX_JOB_FRAMES};
use crate::bags::{self, Selection};
use crate::files::{is_image, natural_key};
use crate::index::query::{LoopQuery, Scope};
use bytes::Bytes;
use std::collections::HashMap;

/// One frame of a sequence: an encoded image and, from a bag, its robot and stamp.
pub struct SeqFrame {
    pub name: String,
    pub image: Bytes,
    /// None: the request's robot id.
    pub robot_id: Option<String>,
    /// None: the frame's place in the sequence.
    pub timestamp: Option<f64>,
    /// From a bag's pose topic.
    pub pose: Option<crate::index::query::Pose>,
    /// From a bag's depth topic.
    pub depth: Option<crate::verify::depth::DepthImage>,
    /// From a bag's right (stereo) topic: the right image's bytes.
    pub right: Option<Bytes>,
}

impl SeqFrame {
    fn file(name: String, image: Bytes) -> Self {
        Self { name, image, robot_id: None, timestamp: None, pose: None, depth: None, right: None }
    }
}

pub struct SequenceRequest {
    pub frames: Vec<SeqFrame>,
    pub robot_id: String,
    /// The job's query options over the job defaults ([`job_defaults`]) and the session's.
    pub options: QueryOverrides,
}

/// What a job asks of each frame unless the request says otherwise: its best candidate among
/// the robot's own frames more than 3 frames back, checked geometrically and by sequence (one
/// robot's trajectory), a loop when its confidence reaches the calibrator's `loop_confidence`.
pub fn job_defaults() -> QueryOverrides {
    QueryOverrides {
        k: Some(1),
        exclude_last_frames: Some(3),
        scope: Some(Scope::SameRobot),
        verify: Some(true),
        sequence: Some(true),
        ..Default::default()
    }
}

fn untar(bytes: &[u8], out: &mut Vec<SeqFrame>) -> Result<(), ApiError> {
    let bad = |e: std::io::Error| ApiError::InvalidArgument(format!("not a readable tar archive: {e}"));
    let mut archive = tar::Archive::new(std::io::Cursor::new(bytes));
    let mut found = Vec::new();
    for entry in archive.entries().map_err(bad)? {
        let mut entry = entry.map_err(bad)?;
        let name = entry.path().map_err(bad)?.to_string_lossy().to_string();
        if !entry.header().entry_type().is_file() || !is_image(&name) {
            continue;
        }
        // Never sized from the header (it may claim terabytes): the entry can hold no more
        // than the archive, which the body limit bounds.
        let mut data = Vec::new();
        std::io::Read::read_to_end(&mut entry, &mut data).map_err(bad)?;
        found.push((name, Bytes::from(data)));
    }
    // An archive's own order is arbitrary: frames go in natural name order.
    found.sort_by_cached_key(|(n, _)| natural_key(n));
    out.extend(found.into_iter().map(|(name, data)| SeqFrame::file(name, data)));
    Ok(())
}

/// What a bag job reads, from the request's fields.
fn bag_selection(fields: &mut HashMap<String, String>) -> Result<Selection, ApiError> {
    let mut sel = Selection::default();
    if let Some(v) = fields.remove("topic") {
        sel.topics = v.split(',').map(str::trim).filter(|t| !t.is_empty()).map(String::from).collect();
    }
    if let Some(v) = fields.remove("every") {
        sel.every = v.parse().ok().filter(|n| *n >= 1).ok_or_else(|| bad_field("every", &v))?;
    }
    if let Some(v) = fields.remove("min_dt") {
        sel.min_dt =
            v.parse().ok().filter(|s: &f64| s.is_finite() && *s >= 0.0).ok_or_else(|| bad_field("min_dt", &v))?;
    }
    sel.pose_topic = fields.remove("pose_topic").filter(|t| !t.trim().is_empty());
    sel.depth_topic = fields.remove("depth_topic").filter(|t| !t.trim().is_empty());
    sel.right_topic = fields.remove("right_topic").filter(|t| !t.trim().is_empty());
    sel.odom_frame = fields.remove("odom_frame").filter(|t| !t.trim().is_empty());
    sel.camera_frame = fields.remove("camera_frame").filter(|t| !t.trim().is_empty());
    Ok(sel)
}

fn bad_field(k: &str, v: &str) -> ApiError {
    ApiError::InvalidArgument(format!("field {k}: bad value '{v}'"))
}

/// A query option given as a form field (the names of the JSON `options` of a query); false when
/// `k` names no option.
fn set_option(o: &mut QueryOverrides, k: &str, v: &str) -> Result<bool, ApiError> {
    fn num<T: std::str::FromStr>(k: &str, v: &str) -> Result<T, ApiError> {
        v.trim().parse().map_err(|_| bad_field(k, v))
    }
    fn real(k: &str, v: &str) -> Result<f32, ApiError> {
        num::<f32>(k, v).and_then(|x| if x.is_finite() { Ok(x) } else { Err(bad_field(k, v)) })
    }
    fn flag(k: &str, v: &str) -> Result<bool, ApiError> {
        match v.trim() {
            "true" | "1" | "on" => Ok(true),
            "false" | "0" | "off" => Ok(false),
            _ => Err(bad_field(k, v)),
        }
    }
    match k {
        "k" => o.k = Some(num(k, v)?),
        "min_score" => o.min_score = Some(real(k, v)?),
        "min_confidence" => o.min_confidence = Some(real(k, v)?),
        "exclude_last_frames" => o.exclude_last_frames = Some(num(k, v)?),
        "verify" => o.verify = Some(flag(k, v)?),
        "verify_candidates" => o.verify_candidates = Some(num(k, v)?),
        "min_inliers" => o.min_inliers = Some(num(k, v)?),
        "sequence" => o.sequence = Some(flag(k, v)?),
        "sequence_length" => o.sequence_length = Some(num(k, v)?),
        "min_sequence_margin" => o.min_sequence_margin = Some(real(k, v)?),
        _ => return Ok(false),
    }
    Ok(true)
}

/// A bag's frames (its parts in order: the files of a split rosbag2 bag).
fn from_bag(parts: &[Bytes], sel: &Selection) -> Result<Vec<SeqFrame>, ApiError> {
    let limits = bags::Limits { max_frames: MAX_JOB_FRAMES, max_chunk_bytes: MAX_BAG_CHUNK_BYTES };
    let parts: Vec<&[u8]> = parts.iter().map(|p| p.as_ref()).collect();
    let frames = bags::frames(&parts, sel, &limits).map_err(|e| match e {
        bags::BagError::Io(_) => ApiError::Internal(e.to_string()),
        e => ApiError::InvalidArgument(e.to_string()),
    })?;
    Ok(frames
        .into_iter()
        .map(|f| SeqFrame {
            name: format!("{}#{}", f.topic, f.index),
            image: Bytes::from(f.image),
            robot_id: f.robot_id,
            timestamp: Some(f.stamp),
            pose: f.pose,
            depth: f.depth,
            right: f.right.map(Bytes::from),
        })
        .collect())
}

impl SequenceRequest {
    /// From a form's text fields, its files (part name, client file name, bytes) and, for a
    /// request that was not a form, its raw body (a tar archive or a bag, told by its first bytes).
    pub fn from_form(
        mut fields: HashMap<String, String>,
        files: Vec<(String, Option<String>, Bytes)>,
        body: Option<Bytes>,
    ) -> Result<Self, ApiError> {
        let mut frames = Vec::new();
        let mut bag = Vec::new();
        for (part, file_name, data) in files {
            match part.as_str() {
                "archive" => untar(&data, &mut frames)?,
                "bag" => bag.push(data),
                _ => frames.push(SeqFrame::file(file_name.unwrap_or_else(|| frames.len().to_string()), data)),
            }
        }
        match body {
            Some(body) if bags::is_bag(&body) => bag.push(body),
            Some(body) => untar(&body, &mut frames)?,
            None => {}
        }
        let selection = bag_selection(&mut fields)?;
        if !bag.is_empty() {
            if !frames.is_empty() {
                return Err(ApiError::InvalidArgument("send images or a bag, not both".into()));
            }
            frames = from_bag(&bag, &selection)?;
        } else if !selection.topics.is_empty()
            || selection.every != 1
            || selection.min_dt != 0.0
            || selection.pose_topic.is_some()
            || selection.depth_topic.is_some()
            || selection.right_topic.is_some()
            || selection.odom_frame.is_some()
            || selection.camera_frame.is_some()
        {
            return Err(ApiError::InvalidArgument(
                "topic, every, min_dt, pose_topic, depth_topic, right_topic, odom_frame and camera_frame apply to bags only"
                    .into(),
            ));
        }
        if frames.is_empty() {
            return Err(ApiError::InvalidArgument(
                "a sequence needs images: multipart 'image' files, a tar archive or a bag".into(),
            ));
        }
        if frames.len() > MAX_JOB_FRAMES {
            return Err(ApiError::InvalidArgument(format!(
                "{} frames; at most {MAX_JOB_FRAMES} per job",
                frames.len()
            )));
        }
        let mut req = SequenceRequest { frames, robot_id: "sequence".into(), options: QueryOverrides::default() };
        // Order is applied last, whatever the field order.
        let order = fields.remove("order");
        for (k, v) in fields {
            match k.as_str() {
                "robot_id" if !v.is_empty() => {
                    // A robot named in the request is every frame's, whatever the topics say.
                    req.frames.iter_mut().for_each(|f| f.robot_id = None);
                    req.robot_id = v;
                }
                _ if set_option(&mut req.options, &k, &v)? => {}
                _ => return Err(bad_field(&k, &v)),
            }
        }
        // Checked here, before the upload becomes a job: a bad option is a 400 with nothing made.
        req.options.over(&job_defaults()).apply(&LoopQuery::default()).validate().map_err(ApiError::from)?;
        match order.as_deref() {
            Some("name") => req.frames.sort_by_cached_key(|f| natural_key(&f.name)),
            None | Some("sent") => {}
            Some(other) => return Err(ApiError::InvalidArgument(format!("field order: bad value '{other}'"))),
        }
        Ok(req)
    }
}
