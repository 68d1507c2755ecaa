//! The ROS 2 messages the bridge reads and writes, as serde types in their `.msg` field order
//! (ros2-client serialises them as CDR). Read: `sensor_msgs/Image`, `CompressedImage`,
//! `CameraInfo`, `nav_msgs/Odometry`. Written: `loopd_msgs/LoopClosure`
//! (`ros/loopd_msgs/msg/LoopClosure.msg`) and `visualization_msgs/MarkerArray`.
use crate::bags::msgs::RawImage;
use crate::index::query::Pose;
use crate::pb;
use serde::de::{self, SeqAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    pub fn seconds(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }

    pub fn from_seconds(t: f64) -> Self {
        let sec = t.floor();
        let nanosec = ((t - sec) * 1e9).round().min(999_999_999.0) as u32;
        Self { sec: sec as i32, nanosec }
    }

    /// Nanoseconds since the epoch: the keyframe's identity (its idempotency key).
    pub fn nanos(&self) -> i64 {
        self.sec as i64 * 1_000_000_000 + self.nanosec as i64
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

impl Image {
    /// The view `bags::pixels::to_png` reads: the bags and the bridge decode pixels alike.
    pub fn raw(&self) -> RawImage<'_> {
        RawImage {
            stamp: self.header.stamp.seconds(),
            height: self.height,
            width: self.width,
            encoding: self.encoding.clone(),
            big_endian: self.is_bigendian != 0,
            step: self.step,
            data: &self.data,
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

impl CameraInfo {
    /// The session camera it describes, or why it cannot be one (a CameraInfo of zeros, as an
    /// uncalibrated driver publishes, a distortion model loopd does not apply).
    pub fn camera(&self) -> Result<pb::Camera, String> {
        let (fx, fy, cx, cy) = (self.k[0], self.k[4], self.k[2], self.k[5]);
        if !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite() && cx.is_finite() && cy.is_finite()) {
            return Err(format!("intrinsics fx {fx}, fy {fy} (k[0], k[4]) are not a calibrated camera"));
        }
        let distortion = match self.distortion_model.as_str() {
            _ if self.d.iter().all(|v| *v == 0.0) => Vec::new(),
            "plumb_bob" | "rational_polynomial" if self.d.len() >= 5 => self.d[..5].to_vec(),
            m => {
                return Err(format!(
                    "distortion model '{m}' with {} coefficients is not read (plumb_bob k1 k2 p1 p2 k3)",
                    self.d.len()
                ))
            }
        };
        if distortion.iter().any(|v| !v.is_finite()) {
            return Err("a distortion coefficient is not finite".into());
        }
        Ok(pb::Camera { fx, fy, cx, cy, distortion, ..Default::default() })
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RosPose {
    pub position: Point,
    pub orientation: Quaternion,
}

impl RosPose {
    pub fn loopd(&self) -> Pose {
        let (p, q) = (self.position, self.orientation);
        Pose { x: p.x, y: p.y, z: p.z, qx: q.x, qy: q.y, qz: q.z, qw: q.w }
    }
}

/// A fixed-size `float64[36]` (a 6x6 covariance): serde derives arrays up to 32 only.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl Default for Covariance {
    fn default() -> Self {
        Self([0.0; 36])
    }
}

impl Serialize for Covariance {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeTuple;
        let mut t = s.serialize_tuple(36)?;
        for v in &self.0 {
            t.serialize_element(v)?;
        }
        t.end()
    }
}

impl<'de> Deserialize<'de> for Covariance {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Covariance;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("36 float64 values")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Covariance, A::Error> {
                let mut c = [0.0; 36];
                for (i, v) in c.iter_mut().enumerate() {
                    *v = seq.next_element()?.ok_or_else(|| de::Error::invalid_length(i, &self))?;
                }
                Ok(Covariance(c))
            }
        }
        d.deserialize_tuple(36, V)
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    pub pose: RosPose,
    pub covariance: Covariance,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    pub twist: Twist,
    pub covariance: Covariance,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    pub pose: PoseWithCovariance,
    pub twist: TwistWithCovariance,
}

/// `loopd_msgs/LoopClosure`, field for field as `ros/loopd_msgs/msg/LoopClosure.msg`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LoopClosure {
    pub header: Header,
    pub key_from: u64,
    pub key_to: u64,
    pub robot_from: u64,
    pub robot_to: u64,
    pub r#type: i32,
    pub pose: RosPose,
    pub covariance: Covariance,
    pub session_id: String,
    pub robot_from_id: String,
    pub robot_to_id: String,
    pub stamp_to: Time,
    pub rank: u32,
    pub score: f32,
    pub confidence: f32,
    pub checked: bool,
    pub verified: bool,
    pub matches: u32,
    pub inliers: u32,
    pub inlier_ratio: f32,
    pub reason: String,
    pub has_pose: bool,
    pub metric: bool,
    pub pose_inliers: u32,
}

/// pose_graph_tools/PoseGraphEdge's edge types, as LoopClosure.msg repeats them.
pub const LOOPCLOSE: i32 = 1;
pub const REJECTED_LOOPCLOSE: i32 = 3;

impl LoopClosure {
    /// One answered candidate of a keyframe (its frame id, robot and stamp): loopd's relative
    /// pose becomes the edge's pose, its covariance (metric poses only) the edge's.
    pub fn of(session: &str, from: (u64, &str, u64, Time, &str), robot_to: u64, rank: usize, m: &pb::Match) -> Self {
        let (key_from, robot_from_id, robot_from, stamp, camera_frame) = from;
        let v = m.verification.clone().unwrap_or_default();
        let (pose, has_pose) = match &v.relative_pose {
            Some(p) => (
                RosPose {
                    position: Point { x: p.tx, y: p.ty, z: p.tz },
                    orientation: Quaternion { x: p.qx, y: p.qy, z: p.qz, w: p.qw },
                },
                true,
            ),
            None => (RosPose::default(), false),
        };
        let mut covariance = Covariance::default();
        if v.metric && v.covariance.len() == 36 {
            covariance.0.copy_from_slice(&v.covariance);
        }
        Self {
            header: Header { stamp, frame_id: camera_frame.to_string() },
            key_from,
            key_to: m.frame_id,
            robot_from,
            robot_to,
            r#type: if v.verified { LOOPCLOSE } else { REJECTED_LOOPCLOSE },
            pose,
            covariance,
            session_id: session.to_string(),
            robot_from_id: robot_from_id.to_string(),
            robot_to_id: m.robot_id.clone(),
            stamp_to: Time::from_seconds(m.timestamp),
            rank: rank as u32,
            score: m.score,
            confidence: m.confidence.unwrap_or(f32::NAN),
            checked: m.verification.is_some(),
            verified: v.verified,
            matches: v.matches,
            inliers: v.inliers,
            inlier_ratio: v.inlier_ratio,
            reason: v.reason,
            has_pose,
            metric: v.metric,
            pose_inliers: v.pose_inliers,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRgba {
    pub r: f32,
    pub g: f32,
    pub b: f32,
    pub a: f32,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UvCoordinate {
    pub u: f32,
    pub v: f32,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    pub filename: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `visualization_msgs/Marker` (Kilted's fields, texture and mesh included).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    pub header: Header,
    pub ns: String,
    pub id: i32,
    pub r#type: i32,
    pub action: i32,
    pub pose: RosPose,
    pub scale: Vector3,
    pub color: ColorRgba,
    pub lifetime: Duration,
    pub frame_locked: bool,
    pub points: Vec<Point>,
    pub colors: Vec<ColorRgba>,
    pub texture_resource: String,
    pub texture: CompressedImage,
    pub uv_coordinates: Vec<UvCoordinate>,
    pub text: String,
    pub mesh_resource: String,
    pub mesh_file: MeshFile,
    pub mesh_use_embedded_materials: bool,
}

pub const LINE_LIST: i32 = 5;

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    pub markers: Vec<Marker>,
}

impl Marker {
    /// A line between the two frames' positions in `frame` (the poses' frame): green for a
    /// verified loop, grey for an unverified candidate.
    pub fn line(frame: &str, id: i32, stamp: Time, from: &Pose, to: &Pose, verified: bool) -> Self {
        let color = if verified {
            ColorRgba { r: 0.1, g: 0.8, b: 0.2, a: 1.0 }
        } else {
            ColorRgba { r: 0.6, g: 0.6, b: 0.6, a: 0.6 }
        };
        Self {
            header: Header { stamp, frame_id: frame.to_string() },
            ns: "loopd_loops".into(),
            id,
            r#type: LINE_LIST,
            pose: RosPose::default(),
            scale: Vector3 { x: 0.05, y: 0.0, z: 0.0 },
            color,
            points: vec![Point { x: from.x, y: from.y, z: from.z }, Point { x: to.x, y: to.y, z: to.z }],
            ..Default::default()
        }
    }
}

impl ros2_client::Message for Image {}
impl ros2_client::Message for CompressedImage {}
impl ros2_client::Message for CameraInfo {}
impl ros2_client::Message for Odometry {}
impl ros2_client::Message for LoopClosure {}
impl ros2_client::Message for MarkerArray {}

#[cfg(test)]
mod tests {
    use super::*;

    fn cdr<T: Serialize>(v: &T) -> Vec<u8> {
        let mut out = vec![0, 1, 0, 0];
        out.extend(cdr_encoding::to_vec::<T, byteorder::LittleEndian>(v).unwrap());
        out
    }

    #[test]
    fn an_image_reads_as_the_bags_read_it() {
        let m = Image {
            header: Header { stamp: Time { sec: 12, nanosec: 500_000_000 }, frame_id: "cam".into() },
            height: 1,
            width: 2,
            encoding: "rgb8".into(),
            is_bigendian: 0,
            step: 6,
            data: vec![1, 2, 3, 4, 5, 6],
        };
        // The bytes ros2-client sends for it are what the bag reader decodes.
        let bytes = cdr(&m);
        let bag = crate::bags::msgs::raw_image(crate::bags::msgs::Wire::Cdr, &bytes).unwrap();
        let ours = m.raw();
        assert_eq!((bag.stamp, bag.width, bag.step, bag.data), (ours.stamp, ours.width, ours.step, ours.data));
        let (back, _) = cdr_encoding::from_bytes::<Image, byteorder::LittleEndian>(&bytes[4..]).unwrap();
        assert_eq!(back, m);
    }

    #[test]
    fn covariance_is_36_values_without_a_length() {
        let mut o = Odometry::default();
        o.pose.covariance.0[35] = 7.0;
        let bytes = cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&o.pose).unwrap();
        assert_eq!(bytes.len(), 7 * 8 + 36 * 8);
        let (back, _) = cdr_encoding::from_bytes::<PoseWithCovariance, byteorder::LittleEndian>(&bytes).unwrap();
        assert_eq!(back.covariance.0[35], 7.0);
    }

    #[test]
    fn camera_info_of_zeros_is_refused() {
        let mut c = CameraInfo::default();
        assert!(c.camera().unwrap_err().contains("not a calibrated camera"));
        c.k = [520.9, 0.0, 325.1, 0.0, 521.0, 249.7, 0.0, 0.0, 1.0];
        c.distortion_model = "plumb_bob".into();
        c.d = vec![0.0; 5];
        let cam = c.camera().unwrap();
        assert_eq!((cam.fx, cam.cy, cam.distortion.len()), (520.9, 249.7, 0));
        c.distortion_model = "equidistant".into();
        c.d = vec![0.1, 0.0, 0.0, 0.0];
        assert!(c.camera().unwrap_err().contains("equidistant"));
    }

    #[test]
    fn stamps_round_trip() {
        let t = Time::from_seconds(1_700_000_000.25);
        assert_eq!((t.sec, t.nanosec), (1_700_000_000, 250_000_000));
        assert_eq!(Time { sec: 2, nanosec: 5 }.nanos(), 2_000_000_005);
    }
}
