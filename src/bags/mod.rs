//! ROS bags to frames: rosbag2 MCAP (one file, or the files of a split bag in order) and ROS 1
//! bags; `sensor_msgs/Image` and `CompressedImage` topics, thinned, in recording order, each
//! frame as encoded image bytes for the engine's one decoder.
mod mcap_bag;
pub mod msgs;
pub mod pixels;
pub mod poses;
mod ros1;

use msgs::{ImageKind, Wire};
use std::collections::{BTreeMap, HashMap};

/// Called for every message: topic, type name, wire format (None: not decodable here), bag
/// time (ns), bytes.
pub type Visit<'f> = dyn FnMut(&str, &str, Option<Wire>, u64, &[u8]) -> Result<(), BagError> + 'f;

#[derive(Debug, Clone, thiserror::Error, PartialEq)]
pub enum BagError {
    #[error("not a bag: an MCAP file (rosbag2) or a ROS 1 bag (format 2.0) expected")]
    NotABag,
    #[error("{0}")]
    Corrupt(String),
    #[error("cannot keep a temporary copy of the bag: {0}")]
    Io(String),
    #[error("topic {topic}, message {index}: {why}")]
    Message { topic: String, index: usize, why: String },
    /// The topics asked for are not image topics of this bag, or several could be meant.
    #[error("{0}")]
    Topics(String),
    #[error("more than {max} frames selected: keep every Nth frame (every) or set a minimum time step (min_dt)")]
    TooManyFrames { max: usize },
}

#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// Most frames one bag may give (after thinning).
    pub max_frames: usize,
    /// Largest decompressed ROS 1 chunk (rosbag's default chunk is 768 KiB).
    pub max_chunk_bytes: usize,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TopicInfo {
    pub topic: String,
    pub msg_type: String,
    pub messages: usize,
    /// Whether loopd reads it (an image topic).
    pub image: bool,
}

/// Which frames to take.
#[derive(Clone, Debug)]
pub struct Selection {
    /// Image topics; empty: the bag's only image topic.
    pub topics: Vec<String>,
    /// Every Nth message of each topic (1: all).
    pub every: usize,
    /// Smallest step between kept frames of a topic, in seconds of header stamp.
    pub min_dt: f64,
    /// The camera's pose (Odometry, PoseStamped or PoseWithCovarianceStamped), interpolated to
    /// each frame's stamp ([`poses::Track::at`]).
    pub pose_topic: Option<String>,
    /// The camera's registered depth images (16UC1 mm or 32FC1 m), nearest in stamp.
    pub depth_topic: Option<String>,
    /// The right images of a stereo pair (raw or compressed), nearest in stamp.
    pub right_topic: Option<String>,
    /// Instead of a pose topic: the camera frame's pose in this frame from `/tf` and
    /// `/tf_static` (with `camera_frame`).
    pub odom_frame: Option<String>,
    pub camera_frame: Option<String>,
}

impl Default for Selection {
    fn default() -> Self {
        Self {
            topics: Vec::new(),
            every: 1,
            min_dt: 0.0,
            pose_topic: None,
            depth_topic: None,
            right_topic: None,
            odom_frame: None,
            camera_frame: None,
        }
    }
}

/// The tf topics read for `odom_frame` / `camera_frame`.
const TF: &str = "/tf";
const TF_STATIC: &str = "/tf_static";

#[derive(Debug)]
pub struct BagFrame {
    pub topic: String,
    /// The message's place among its topic's messages (before thinning).
    pub index: usize,
    /// Header stamp in seconds (the bag time where the header holds none).
    pub stamp: f64,
    /// From the topic's namespace: `/robot1/cam/image_raw` is robot1's.
    pub robot_id: Option<String>,
    /// JPEG or PNG as sent for a compressed image; a lossless PNG for a raw one.
    pub image: Vec<u8>,
    /// From the pose topic, when asked for and it covers the stamp.
    pub pose: Option<crate::index::query::Pose>,
    /// From the depth topic, when asked for and one is within [`poses::MAX_DEPTH_DT_S`].
    pub depth: Option<crate::verify::depth::DepthImage>,
    /// From the right topic (JPEG or PNG as [`BagFrame::image`]), when asked for and one is within
    /// [`poses::MAX_DEPTH_DT_S`].
    pub right: Option<Vec<u8>>,
}

/// The robot a topic belongs to: the first name of a topic three or more names deep.
pub fn robot_of(topic: &str) -> Option<String> {
    let names: Vec<&str> = topic.split('/').filter(|n| !n.is_empty()).collect();
    (names.len() >= 3).then(|| names[0].to_string())
}

/// Whether `bytes` start like a bag (not a tar archive or an image).
pub fn is_bag(bytes: &[u8]) -> bool {
    bytes.starts_with(mcap_bag::MAGIC) || bytes.starts_with(ros1::MAGIC)
}

/// Every message of every part, parts in order.
fn each(parts: &[&[u8]], limits: &Limits, visit: &mut Visit) -> Result<(), BagError> {
    for part in parts {
        if part.starts_with(mcap_bag::MAGIC) {
            mcap_bag::visit(part, visit)?;
        } else if part.starts_with(ros1::MAGIC) {
            ros1::visit(part, limits.max_chunk_bytes, visit)?;
        } else {
            return Err(BagError::NotABag);
        }
    }
    Ok(())
}

/// Every topic with its type and message count, by name.
pub fn topics(parts: &[&[u8]], limits: &Limits) -> Result<Vec<TopicInfo>, BagError> {
    let mut found: BTreeMap<String, TopicInfo> = BTreeMap::new();
    each(parts, limits, &mut |topic, tp, _, _, _| {
        let t = found.entry(topic.to_string()).or_insert_with(|| TopicInfo {
            topic: topic.into(),
            msg_type: tp.into(),
            messages: 0,
            image: ImageKind::of(tp).is_some(),
        });
        t.messages += 1;
        Ok(())
    })?;
    Ok(found.into_values().collect())
}

fn listing(topics: &[TopicInfo]) -> String {
    let all: Vec<String> = topics.iter().map(|t| format!("{} ({}, {})", t.topic, t.msg_type, t.messages)).collect();
    if all.is_empty() {
        "none".into()
    } else {
        all.join(", ")
    }
}

/// The topics to read: those asked for, which must be image topics of the bag, or its only one.
fn chosen(sel: &Selection, topics: &[TopicInfo]) -> Result<Vec<String>, BagError> {
    check_pose_and_depth(sel, topics)?;
    // The right images of a stereo pair are not frames of their own.
    let images: Vec<&TopicInfo> =
        topics.iter().filter(|t| t.image && Some(&t.topic) != sel.right_topic.as_ref()).collect();
    if sel.topics.is_empty() {
        return match images.as_slice() {
            [one] => Ok(vec![one.topic.clone()]),
            [] => Err(BagError::Topics(format!(
                "the bag has no sensor_msgs/Image or CompressedImage topic; its topics: {}",
                listing(topics)
            ))),
            _ => Err(BagError::Topics(format!(
                "the bag has several image topics; name one or more (topic): {}",
                listing(&images.into_iter().cloned().collect::<Vec<_>>())
            ))),
        };
    }
    for want in &sel.topics {
        match topics.iter().find(|t| &t.topic == want) {
            Some(t) if t.image => {}
            Some(t) => {
                return Err(BagError::Topics(format!("topic {want} is {}, not an image topic", t.msg_type)));
            }
            None => {
                return Err(BagError::Topics(format!("the bag has no topic {want}; its topics: {}", listing(topics))));
            }
        }
    }
    Ok(sel.topics.clone())
}

/// The pose and depth topics asked for exist and have their types (tf: the bag has /tf).
fn check_pose_and_depth(sel: &Selection, topics: &[TopicInfo]) -> Result<(), BagError> {
    let need = |want: &Option<String>, what: &str, ok: &dyn Fn(&str) -> bool| -> Result<(), BagError> {
        let Some(want) = want else { return Ok(()) };
        match topics.iter().find(|t| &t.topic == want) {
            Some(t) if ok(&t.msg_type) => Ok(()),
            Some(t) => Err(BagError::Topics(format!("topic {want} is {}, not {what}", t.msg_type))),
            None => Err(BagError::Topics(format!("the bag has no topic {want}; its topics: {}", listing(topics)))),
        }
    };
    need(
        &sel.pose_topic,
        "a pose (nav_msgs/Odometry, geometry_msgs/PoseStamped or PoseWithCovarianceStamped)",
        &|t| poses::PoseKind::of(t).is_some(),
    )?;
    need(&sel.depth_topic, "a depth image (sensor_msgs/Image)", &|t| ImageKind::of(t) == Some(ImageKind::Raw))?;
    need(&sel.right_topic, "a right image (sensor_msgs/Image or CompressedImage)", &|t| ImageKind::of(t).is_some())?;
    if sel.right_topic.is_some() && sel.depth_topic.is_some() {
        return Err(BagError::Topics("a depth topic or a right (stereo) topic, not both".into()));
    }
    match (&sel.odom_frame, &sel.camera_frame, &sel.pose_topic) {
        (None, None, _) => {}
        (Some(_), Some(_), None) => {
            need(&Some(TF.to_string()), "tf2_msgs/TFMessage", &|t| t.replace("/msg/", "/") == "tf2_msgs/TFMessage")?
        }
        (Some(_), Some(_), Some(_)) => {
            return Err(BagError::Topics("a pose topic or odom_frame + camera_frame (tf), not both".into()))
        }
        _ => return Err(BagError::Topics("odom_frame and camera_frame go together".into())),
    }
    Ok(())
}

/// Per topic: messages seen, stamp of the last kept frame.
#[derive(Default)]
struct Thinning {
    seen: usize,
    last: Option<f64>,
}

enum Pixels<'a> {
    Raw(msgs::RawImage<'a>),
    /// JPEG or PNG bytes as recorded.
    Encoded(&'a [u8]),
}

/// The selected frames in recording order (bag time; parts in order).
pub fn frames(parts: &[&[u8]], sel: &Selection, limits: &Limits) -> Result<Vec<BagFrame>, BagError> {
    let all = topics(parts, limits)?;
    let wanted = chosen(sel, &all)?;
    let every = sel.every.max(1);
    let mut state: HashMap<String, Thinning> = wanted.iter().map(|t| (t.clone(), Thinning::default())).collect();
    let mut out: Vec<(u64, BagFrame)> = Vec::new();
    let mut track = poses::Track::default();
    let mut tf = poses::TfTree::default();
    let use_tf = sel.odom_frame.is_some();
    // Each depth message's stamp, by its place in the topic: decoded in a second pass, only those
    // nearest a frame.
    let mut depth_stamps: Vec<f64> = Vec::new();
    let mut right_stamps: Vec<f64> = Vec::new();
    each(parts, limits, &mut |topic, tp, wire, time, bytes| {
        if sel.pose_topic.as_deref() == Some(topic) {
            let index = track.len();
            let bad = |why: String| BagError::Message { topic: topic.into(), index, why };
            let kind = poses::PoseKind::of(tp).ok_or_else(|| bad(format!("{tp} is not a pose type")))?;
            let (stamp, pose) =
                poses::pose_message(kind, wire.ok_or_else(|| bad("not CDR".into()))?, bytes).map_err(bad)?;
            track.push(if stamp > 0.0 { stamp } else { time as f64 * 1e-9 }, &pose);
        }
        if use_tf && (topic == TF || topic == TF_STATIC) && tp.replace("/msg/", "/") == "tf2_msgs/TFMessage" {
            let bad = |why: String| BagError::Message { topic: topic.into(), index: 0, why };
            for (stamp, parent, child, pose) in
                poses::tf_message(wire.ok_or_else(|| bad("not CDR".into()))?, bytes).map_err(bad)?
            {
                let stamp = if stamp > 0.0 { stamp } else { time as f64 * 1e-9 };
                tf.push(stamp, parent, child, &pose, topic == TF_STATIC);
            }
        }
        if sel.depth_topic.as_deref() == Some(topic) {
            let index = depth_stamps.len();
            let bad = |why: String| BagError::Message { topic: topic.into(), index, why };
            let m = msgs::raw_image(wire.ok_or_else(|| bad("not CDR".into()))?, bytes).map_err(bad)?;
            depth_stamps.push(if m.stamp > 0.0 { m.stamp } else { time as f64 * 1e-9 });
        }
        if sel.right_topic.as_deref() == Some(topic) {
            let index = right_stamps.len();
            let bad = |why: String| BagError::Message { topic: topic.into(), index, why };
            let (stamp, _) = image_message(tp, wire, bytes).map_err(bad)?;
            right_stamps.push(if stamp > 0.0 { stamp } else { time as f64 * 1e-9 });
        }
        let Some(st) = state.get_mut(topic) else { return Ok(()) };
        let index = st.seen;
        st.seen += 1;
        if index % every != 0 {
            return Ok(());
        }
        let bad = |why: String| BagError::Message { topic: topic.into(), index, why };
        let (stamp, pixels) = image_message(tp, wire, bytes).map_err(bad)?;
        let stamp = if stamp > 0.0 { stamp } else { time as f64 * 1e-9 };
        if st.last.is_some_and(|last| stamp - last < sel.min_dt) {
            return Ok(());
        }
        st.last = Some(stamp);
        if out.len() >= limits.max_frames {
            return Err(BagError::TooManyFrames { max: limits.max_frames });
        }
        let image = pixels.bytes().map_err(bad)?;
        let robot_id = robot_of(topic);
        let frame =
            BagFrame { topic: topic.into(), index, stamp, robot_id, image, pose: None, depth: None, right: None };
        out.push((time, frame));
        Ok(())
    })?;
    // Topics interleave by recording time; a stable sort keeps each topic's own order.
    out.sort_by_key(|(time, _)| *time);
    let mut out: Vec<BagFrame> = out.into_iter().map(|(_, f)| f).collect();
    track.finish();
    tf.finish();
    for f in &mut out {
        f.pose = match (&sel.odom_frame, &sel.camera_frame) {
            (Some(odom), Some(camera)) => tf.at(f.stamp, odom, camera),
            _ => track.at(f.stamp),
        };
    }
    if let Some(depth_topic) = &sel.depth_topic {
        attach_nearest(parts, limits, depth_topic, &depth_stamps, &mut out, &mut |f, _, wire, bytes| {
            f.depth = poses::depth_message(wire.ok_or("not CDR")?, bytes)?;
            Ok(())
        })?;
    }
    if let Some(right_topic) = &sel.right_topic {
        attach_nearest(parts, limits, right_topic, &right_stamps, &mut out, &mut |f, tp, wire, bytes| {
            f.right = Some(image_message(tp, wire, bytes)?.1.bytes()?);
            Ok(())
        })?;
    }
    Ok(out)
}

/// A raw or compressed image message: its header stamp and pixels.
fn image_message<'a>(tp: &str, wire: Option<Wire>, bytes: &'a [u8]) -> Result<(f64, Pixels<'a>), String> {
    let wire = wire.ok_or("not CDR: rosbag2 records CDR")?;
    match ImageKind::of(tp).ok_or_else(|| format!("{tp} is not an image type"))? {
        ImageKind::Raw => {
            let m = msgs::raw_image(wire, bytes)?;
            Ok((m.stamp, Pixels::Raw(m)))
        }
        ImageKind::Compressed => {
            let m = msgs::compressed_image(wire, bytes)?;
            Ok((m.stamp, Pixels::Encoded(m.data)))
        }
    }
}

impl Pixels<'_> {
    /// A lossless PNG of raw pixels; JPEG or PNG bytes as recorded.
    fn bytes(self) -> Result<Vec<u8>, String> {
        match self {
            Pixels::Raw(raw) => pixels::to_png(&raw),
            Pixels::Encoded(data) => Ok(data.to_vec()),
        }
    }
}

/// What a message of a second pass gives the frames that take it: (frame, type, wire, bytes).
type Attach<'a> = dyn FnMut(&mut BagFrame, &str, Option<Wire>, &[u8]) -> Result<(), String> + 'a;

/// Gives each frame the message of `topic` nearest its stamp (within [`poses::MAX_DEPTH_DT_S`]),
/// decoding only those in a second pass over the bag.
fn attach_nearest(
    parts: &[&[u8]],
    limits: &Limits,
    topic: &str,
    stamps: &[f64],
    frames: &mut [BagFrame],
    attach: &mut Attach,
) -> Result<(), BagError> {
    let mut order: Vec<usize> = (0..stamps.len()).collect();
    order.sort_by(|&a, &b| stamps[a].total_cmp(&stamps[b]));
    let sorted: Vec<f64> = order.iter().map(|&i| stamps[i]).collect();
    // Which depth message each frame takes, and the frames waiting for each message.
    let mut wanted: HashMap<usize, Vec<usize>> = HashMap::new();
    for (fi, f) in frames.iter().enumerate() {
        let at = sorted.partition_point(|&s| s < f.stamp);
        let nearest = [at.checked_sub(1), Some(at).filter(|&i| i < sorted.len())]
            .into_iter()
            .flatten()
            .min_by(|&a, &b| (sorted[a] - f.stamp).abs().total_cmp(&(sorted[b] - f.stamp).abs()));
        if let Some(k) = nearest.filter(|&k| (sorted[k] - f.stamp).abs() <= poses::MAX_DEPTH_DT_S) {
            wanted.entry(order[k]).or_default().push(fi);
        }
    }
    if wanted.is_empty() {
        return Ok(());
    }
    let mut index = 0;
    each(parts, limits, &mut |t, tp, wire, _, bytes| {
        if t != topic {
            return Ok(());
        }
        let i = index;
        index += 1;
        let Some(takers) = wanted.get(&i) else { return Ok(()) };
        let bad = |why: String| BagError::Message { topic: topic.into(), index: i, why };
        for &fi in takers {
            attach(&mut frames[fi], tp, wire, bytes).map_err(bad)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn robots_from_namespaces() {
        assert_eq!(robot_of("/robot1/cam/image_raw").as_deref(), Some("robot1"));
        assert_eq!(robot_of("/cam/image_raw"), None);
        assert_eq!(robot_of("image"), None);
    }

    #[test]
    fn not_bags() {
        let limits = Limits { max_frames: 10, max_chunk_bytes: 1 << 20 };
        assert_eq!(topics(&[b"ustar"], &limits), Err(BagError::NotABag));
        let cut = [ros1::MAGIC, &[5, 0, 0, 0][..]].concat();
        assert!(matches!(topics(&[&cut], &limits), Err(BagError::Corrupt(m)) if m.contains("truncated")));
        let cut = [mcap_bag::MAGIC, &[1, 2][..]].concat();
        assert!(matches!(topics(&[&cut], &limits), Err(BagError::Corrupt(m)) if m.starts_with("MCAP")));
    }

    /// The `sequence_upload` fuzz target's find: a record claiming 2^64 - 1 bytes made the `mcap`
    /// crate's MessageStream overflow an index and panic.
    #[test]
    fn an_mcap_record_longer_than_the_file_is_an_error() {
        let limits = Limits { max_frames: 10, max_chunk_bytes: 1 << 20 };
        let bag = [mcap_bag::MAGIC, &[0xff; 11][..], b"H8888888888"].concat();
        assert!(matches!(topics(&[&bag], &limits), Err(BagError::Corrupt(m)) if m.starts_with("MCAP")));
        // The second find: an attachment record too short for its own header.
        let bag = include_bytes!("../../fuzz/corpus/bag/mcap-short-attachment");
        assert!(topics(&[bag], &limits).is_err());
    }
}
