//! What sled holds: session metadata (JSON) and frame records (small header + raw descriptor).
use crate::index::query::Pose;
use serde::{Deserialize, Serialize};

/// A session as created: its id, name, descriptor space and defaults.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SessionMeta {
    pub id: String,
    pub name: String,
    /// Unix time, seconds.
    pub created: f64,
    pub dim: usize,
    /// The descriptor space (model, variant, input size): only matching descriptors may be added.
    pub descriptor_id: String,
    pub storage: Storage,
    /// Defaults applied to this session's loop queries.
    pub default_query: crate::index::query::LoopQuery,
    /// The camera that takes the session's frames: verified loops then carry a relative pose.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<Camera>,
    /// Each frame keeps a small JPEG for people to look at (the loop inspector).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub thumbnails: bool,
    /// How its frames are searched: exact, approximate, or auto (approximate once it is large).
    #[serde(default)]
    pub index: crate::index::graph::IndexKind,
    /// The served model it was created with (`serve --models`; absent: the server's default
    /// at the time). Its `descriptor_id` pins which model's descriptors it holds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
}

/// Pinhole intrinsics in pixels, with optional radial-tangential distortion (k1 k2 p1 p2 k3).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 5, max_items = 5)]
    pub distortion: Option<[f64; 5]>,
    /// Units per metre of the 16-bit depth images its frames may carry (unset: 1000, i.e.
    /// millimetres; TUM RGB-D: 5000). Float depth images are in metres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_scale: Option<f64>,
    /// A stereo pair's right camera: frames may then carry the right image, and loops verified
    /// against them get metric poses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stereo: Option<StereoCamera>,
}

/// The right camera of a stereo pair: either `baseline` (a rectified pair: the right camera is
/// this camera moved `baseline` metres along its x axis), or the calibrated right camera
/// (`right_intrinsics` fx fy cx cy, `right_distortion` k1 k2 p1 p2 k3) and its pose in the left
/// camera (`rotation` row-major 3x3 and `translation` in metres: X_right = R X_left + t).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct StereoCamera {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub baseline: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 9, max_items = 9)]
    pub rotation: Option<[f64; 9]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 3, max_items = 3)]
    pub translation: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 4, max_items = 4)]
    pub right_intrinsics: Option<[f64; 4]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 5, max_items = 5)]
    pub right_distortion: Option<[f64; 5]>,
}

impl Camera {
    pub fn intrinsics(&self) -> crate::verify::geometric::Intrinsics {
        crate::verify::geometric::Intrinsics {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            dist: self.distortion,
        }
    }

    /// The stereo rig for images of this size, if the camera is one side of a pair; why not,
    /// for a pair described wrongly.
    pub fn stereo_rig(
        &self,
        width: u32,
        height: u32,
    ) -> Option<Result<crate::verify::stereo::StereoRig, crate::verify::VerifyError>> {
        use crate::verify::stereo::StereoRig;
        let s = self.stereo.as_ref()?;
        let left = self.intrinsics();
        Some(match (s.baseline, s.rotation, s.translation) {
            (Some(b), None, None) => StereoRig::rectified(left, b, width, height),
            (None, r, Some(t)) => {
                let right = match s.right_intrinsics {
                    Some([fx, fy, cx, cy]) => {
                        crate::verify::geometric::Intrinsics { fx, fy, cx, cy, dist: s.right_distortion }
                    }
                    None => left,
                };
                StereoRig::new(
                    left,
                    right,
                    r.unwrap_or([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
                    t,
                    width,
                    height,
                )
            }
            _ => Err(crate::verify::VerifyError::Invalid(
                "stereo: give baseline (a rectified pair) or translation (and rotation, right_intrinsics) of the \
                 right camera, not both"
                    .into(),
            )),
        })
    }

    /// Depth units per metre.
    pub fn depth_scale(&self) -> f64 {
        self.depth_scale.unwrap_or(crate::verify::depth::DEFAULT_DEPTH_SCALE)
    }
}

/// A frame as stored (without its descriptor, which follows the JSON header raw).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameHeader {
    pub robot_id: String,
    pub timestamp: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose: Option<Pose>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metadata: Option<serde_json::Value>,
    /// The client's idempotency key of the write that stored it (`keys.rs`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub idempotency_key: Option<String>,
}

use crate::index::Storage;

const VERSION: u8 = 1;

/// `[version][storage][u32 header length][header JSON][descriptor, little endian]`.
pub fn encode_frame(h: &FrameHeader, descriptor: &[f32], storage: Storage) -> Vec<u8> {
    let json = serde_json::to_vec(h).expect("frame header serialises");
    let mut out = Vec::with_capacity(6 + json.len() + descriptor.len() * storage.bytes_per_value());
    out.push(VERSION);
    out.push(match storage {
        Storage::F16 => 0,
        Storage::F32 => 1,
    });
    out.extend((json.len() as u32).to_le_bytes());
    out.extend(json);
    match storage {
        Storage::F16 => descriptor.iter().for_each(|&v| out.extend(half::f16::from_f32(v).to_bits().to_le_bytes())),
        Storage::F32 => descriptor.iter().for_each(|&v| out.extend(v.to_le_bytes())),
    }
    out
}

pub fn decode_frame(bytes: &[u8]) -> Result<(FrameHeader, Vec<f32>), String> {
    let bad = || "corrupt frame record".to_string();
    if bytes.len() < 6 || bytes[0] != VERSION {
        return Err(bad());
    }
    let len = u32::from_le_bytes([bytes[2], bytes[3], bytes[4], bytes[5]]) as usize;
    let json = bytes.get(6..6 + len).ok_or_else(bad)?;
    let header: FrameHeader = serde_json::from_slice(json).map_err(|e| e.to_string())?;
    let raw = &bytes[6 + len..];
    let descriptor = match bytes[1] {
        0 => raw.chunks_exact(2).map(|c| half::f16::from_bits(u16::from_le_bytes([c[0], c[1]])).to_f32()).collect(),
        1 => raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect(),
        _ => return Err(bad()),
    };
    Ok((header, descriptor))
}

pub fn frame_key(frame_id: u64) -> [u8; 8] {
    frame_id.to_be_bytes()
}

pub fn key_frame(key: &[u8]) -> Option<u64> {
    Some(u64::from_be_bytes(key.try_into().ok()?))
}
