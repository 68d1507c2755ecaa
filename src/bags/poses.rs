//! A frame's pose and depth from other topics of its bag: the camera's pose from a pose topic
//! (`nav_msgs/Odometry`, `geometry_msgs/PoseStamped`, `geometry_msgs/PoseWithCovarianceStamped`)
//! interpolated to the image's stamp, and its depth image (`sensor_msgs/Image`, 16UC1 millimetres
//! or 32FC1 metres, REP 118) nearest in stamp.
use super::msgs::{raw_image, seconds, Ros1, Time, Wire};
use crate::index::query::Pose;
use crate::verify::depth::DepthImage;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde::Deserialize;

/// Poses further apart than this are not interpolated between (the frame gets none).
pub const MAX_POSE_GAP_S: f64 = 1.0;
/// A frame this close before the first pose or after the last takes that pose.
pub const POSE_EDGE_S: f64 = 0.05;
/// A depth image further than this from the frame's stamp is not its depth.
pub const MAX_DEPTH_DT_S: f64 = 0.05;

/// The pose message types read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoseKind {
    Odometry,
    PoseStamped,
    PoseWithCovarianceStamped,
}

impl PoseKind {
    /// From a message type name, ROS 1 or ROS 2 spelling.
    pub fn of(msg_type: &str) -> Option<Self> {
        match msg_type.replace("/msg/", "/").as_str() {
            "nav_msgs/Odometry" => Some(Self::Odometry),
            "geometry_msgs/PoseStamped" => Some(Self::PoseStamped),
            "geometry_msgs/PoseWithCovarianceStamped" => Some(Self::PoseWithCovarianceStamped),
            _ => None,
        }
    }
}

#[derive(Deserialize)]
struct CdrHeader {
    stamp: Time,
    #[allow(dead_code)] // read to move past it
    frame_id: String,
}

#[derive(Deserialize)]
struct CdrPose {
    x: f64,
    y: f64,
    z: f64,
    qx: f64,
    qy: f64,
    qz: f64,
    qw: f64,
}

#[derive(Deserialize)]
struct CdrStamped {
    header: CdrHeader,
    pose: CdrPose,
}

#[derive(Deserialize)]
struct CdrOdometry {
    header: CdrHeader,
    #[allow(dead_code)] // read to move past it
    child_frame_id: String,
    pose: CdrPose,
}

/// A pose message's stamp and pose (a PoseWithCovariance's covariance and an Odometry's twist,
/// after the pose, are not read).
pub fn pose_message(kind: PoseKind, wire: Wire, bytes: &[u8]) -> Result<(f64, Pose), String> {
    let (stamp, p) = match wire {
        Wire::Cdr => match kind {
            PoseKind::Odometry => {
                let m: CdrOdometry = super::msgs::cdr(bytes)?;
                (seconds(m.header.stamp.sec as i64, m.header.stamp.nanosec), m.pose)
            }
            PoseKind::PoseStamped | PoseKind::PoseWithCovarianceStamped => {
                let m: CdrStamped = super::msgs::cdr(bytes)?;
                (seconds(m.header.stamp.sec as i64, m.header.stamp.nanosec), m.pose)
            }
        },
        Wire::Ros1 => {
            let mut r = Ros1(bytes);
            let stamp = r.header()?;
            if kind == PoseKind::Odometry {
                r.string()?;
            }
            let mut v = [0f64; 7];
            for x in &mut v {
                *x = r.f64()?;
            }
            (stamp, CdrPose { x: v[0], y: v[1], z: v[2], qx: v[3], qy: v[4], qz: v[5], qw: v[6] })
        }
    };
    Ok((stamp, checked(p)?))
}

/// A pose with finite values and a (normalised) unit quaternion.
fn checked(p: CdrPose) -> Result<Pose, String> {
    let norm = (p.qx * p.qx + p.qy * p.qy + p.qz * p.qz + p.qw * p.qw).sqrt();
    let values = [p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw];
    if values.iter().any(|v| !v.is_finite()) || !(0.5..2.0).contains(&norm) {
        return Err(format!("not a pose (non-finite values or no unit quaternion: {values:?})"));
    }
    Ok(Pose { x: p.x, y: p.y, z: p.z, qx: p.qx / norm, qy: p.qy / norm, qz: p.qz / norm, qw: p.qw / norm })
}

fn iso(p: &Pose) -> Isometry3<f64> {
    let q = UnitQuaternion::from_quaternion(Quaternion::new(p.qw, p.qx, p.qy, p.qz));
    Isometry3::from_parts(Translation3::new(p.x, p.y, p.z), q)
}

fn pose_of(t: &Isometry3<f64>) -> Pose {
    let (v, q) = (t.translation.vector, t.rotation);
    Pose { x: v.x, y: v.y, z: v.z, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
}

/// A pose topic's poses in stamp order.
#[derive(Default)]
pub struct Track {
    poses: Vec<(f64, Isometry3<f64>)>,
}

impl Track {
    pub fn push(&mut self, stamp: f64, pose: &Pose) {
        self.poses.push((stamp, iso(pose)));
    }

    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// Sorts by stamp (bags interleave by receive time).
    pub fn finish(&mut self) {
        self.poses.sort_by(|a, b| a.0.total_cmp(&b.0));
    }

    /// The pose at `stamp`: interpolated between the poses around it (linear in position,
    /// spherical in rotation) when they are at most [`MAX_POSE_GAP_S`] apart; the first or last
    /// pose within [`POSE_EDGE_S`] beyond the track's ends; else None.
    pub fn at(&self, stamp: f64) -> Option<Pose> {
        let (first, last) = (self.poses.first()?, self.poses.last()?);
        if stamp <= first.0 {
            return (first.0 - stamp <= POSE_EDGE_S).then(|| pose_of(&first.1));
        }
        if stamp >= last.0 {
            return (stamp - last.0 <= POSE_EDGE_S).then(|| pose_of(&last.1));
        }
        let after = self.poses.partition_point(|(t, _)| *t < stamp);
        let ((t0, a), (t1, b)) = (&self.poses[after - 1], &self.poses[after]);
        if t1 - t0 > MAX_POSE_GAP_S {
            return None;
        }
        let s = if t1 > t0 { (stamp - t0) / (t1 - t0) } else { 0.0 };
        Some(pose_of(&a.lerp_slerp(b, s)))
    }
}

/// `tf2_msgs/TFMessage`: each transform's stamp, parent frame, child frame and transform.
pub fn tf_message(wire: Wire, bytes: &[u8]) -> Result<Vec<(f64, String, String, Pose)>, String> {
    #[derive(Deserialize)]
    struct CdrTransform {
        header: CdrHeaderFrame,
        child_frame_id: String,
        transform: CdrPose,
    }
    #[derive(Deserialize)]
    struct CdrHeaderFrame {
        stamp: Time,
        frame_id: String,
    }
    #[derive(Deserialize)]
    struct CdrTf {
        transforms: Vec<CdrTransform>,
    }
    let raw: Vec<(f64, String, String, CdrPose)> = match wire {
        Wire::Cdr => {
            let m: CdrTf = super::msgs::cdr(bytes)?;
            m.transforms
                .into_iter()
                .map(|t| {
                    let stamp = seconds(t.header.stamp.sec as i64, t.header.stamp.nanosec);
                    (stamp, t.header.frame_id, t.child_frame_id, t.transform)
                })
                .collect()
        }
        Wire::Ros1 => {
            let mut r = Ros1(bytes);
            let n = r.u32()? as usize;
            let mut out = Vec::with_capacity(n.min(1024));
            for _ in 0..n {
                let (stamp, parent) = r.header_frame()?;
                let child = r.string()?;
                let mut v = [0f64; 7];
                for x in &mut v {
                    *x = r.f64()?;
                }
                out.push((
                    stamp,
                    parent,
                    child,
                    CdrPose { x: v[0], y: v[1], z: v[2], qx: v[3], qy: v[4], qz: v[5], qw: v[6] },
                ));
            }
            out
        }
    };
    raw.into_iter()
        .map(|(stamp, parent, child, p)| {
            let pose = checked(p)?;
            Ok((stamp, parent.trim_start_matches('/').to_string(), child.trim_start_matches('/').to_string(), pose))
        })
        .collect()
}

/// A tf tree from /tf (each link's transforms over time) and /tf_static (fixed links).
#[derive(Default)]
pub struct TfTree {
    /// child frame -> (parent frame, its transforms over time).
    dynamic: std::collections::HashMap<String, (String, Track)>,
    /// child frame -> (parent frame, its fixed transform).
    fixed: std::collections::HashMap<String, (String, Pose)>,
}

/// Links followed from the camera frame up to the odometry frame, at most.
const MAX_TF_DEPTH: usize = 64;

impl TfTree {
    pub fn push(&mut self, stamp: f64, parent: String, child: String, pose: &Pose, fixed: bool) {
        if fixed {
            self.fixed.insert(child, (parent, *pose));
        } else {
            self.dynamic.entry(child).or_insert_with(|| (parent, Track::default())).1.push(stamp, pose);
        }
    }

    pub fn finish(&mut self) {
        self.dynamic.values_mut().for_each(|(_, t)| t.finish());
    }

    /// The camera frame's pose in the odometry frame at `stamp`: the chain of its parents up to
    /// `odom`, each link interpolated ([`Track::at`]) or fixed; None where a link has no
    /// transform at that time or the chain does not reach `odom`.
    pub fn at(&self, stamp: f64, odom: &str, camera: &str) -> Option<Pose> {
        let mut frame = camera.trim_start_matches('/');
        let odom = odom.trim_start_matches('/');
        let mut t = Isometry3::identity();
        for _ in 0..MAX_TF_DEPTH {
            if frame == odom {
                return Some(pose_of(&t));
            }
            let (parent, link) = match (self.fixed.get(frame), self.dynamic.get(frame)) {
                (Some((parent, p)), _) => (parent, *p),
                (None, Some((parent, track))) => (parent, track.at(stamp)?),
                (None, None) => return None,
            };
            t = iso(&link) * t;
            frame = parent;
        }
        None
    }
}

/// A depth image message as a [`DepthImage`]: 16UC1 (millimetres) or 32FC1 (metres), either
/// byte order, rows of `step` bytes; None when no pixel has a depth (the frame goes without).
pub fn depth_message(wire: Wire, bytes: &[u8]) -> Result<Option<DepthImage>, String> {
    let m = raw_image(wire, bytes)?;
    let (w, h) = (m.width as usize, m.height as usize);
    let (size, scale) = match m.encoding.as_str() {
        "16UC1" | "mono16" => (2, 1e-3f32),
        "32FC1" => (4, 1.0),
        other => return Err(format!("depth encoding '{other}': 16UC1 (mm) or 32FC1 (m) expected")),
    };
    let step = m.step as usize;
    if w == 0 || h == 0 || step < w * size || m.data.len() < step * (h - 1) + w * size {
        return Err(format!("a {w}x{h} depth image with step {step} in {} bytes", m.data.len()));
    }
    let mut metres = Vec::with_capacity(w * h);
    for row in 0..h {
        for px in m.data[row * step..row * step + w * size].chunks_exact(size) {
            let v = match (size, m.big_endian) {
                (2, false) => u16::from_le_bytes([px[0], px[1]]) as f32,
                (2, true) => u16::from_be_bytes([px[0], px[1]]) as f32,
                (_, false) => f32::from_le_bytes([px[0], px[1], px[2], px[3]]),
                (_, true) => f32::from_be_bytes([px[0], px[1], px[2], px[3]]),
            };
            metres.push(v * scale);
        }
    }
    Ok(DepthImage::from_metres(m.width, m.height, metres).ok())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(x: f64, yaw: f64) -> Pose {
        let q = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
        Pose { x, y: 0.0, z: 0.0, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
    }

    #[test]
    fn tracks_interpolate_and_stop_at_gaps_and_ends() {
        let mut t = Track::default();
        for (s, x) in [(2.0, 2.0), (0.0, 0.0), (1.0, 1.0), (5.0, 5.0)] {
            t.push(s, &pose(x, x * 0.1));
        }
        t.finish();
        let p = t.at(0.5).unwrap();
        assert!((p.x - 0.5).abs() < 1e-9);
        let yaw = UnitQuaternion::from_quaternion(Quaternion::new(p.qw, p.qx, p.qy, p.qz)).euler_angles().2;
        assert!((yaw - 0.05).abs() < 1e-9);
        assert!(t.at(3.0).is_none(), "2 s between poses: no interpolation");
        assert!((t.at(-0.04).unwrap().x).abs() < 1e-9);
        assert!(t.at(-0.06).is_none());
        assert!((t.at(5.05).unwrap().x - 5.0).abs() < 1e-9);
        assert!(t.at(5.2).is_none());
        assert!(Track::default().at(1.0).is_none());
    }

    #[test]
    fn tf_chains_compose_fixed_and_moving_links() {
        let mut tf = TfTree::default();
        // odom -> base moves along x; base -> cam is fixed 0.5 m up.
        tf.push(0.0, "odom".into(), "base".into(), &pose(0.0, 0.0), false);
        tf.push(1.0, "odom".into(), "base".into(), &pose(2.0, 0.0), false);
        let up = Pose { x: 0.0, y: 0.0, z: 0.5, qx: 0.0, qy: 0.0, qz: 0.0, qw: 1.0 };
        tf.push(0.0, "base".into(), "cam".into(), &up, true);
        tf.finish();
        let p = tf.at(0.25, "/odom", "cam").unwrap();
        assert!((p.x - 0.5).abs() < 1e-9 && (p.z - 0.5).abs() < 1e-9, "{p:?}");
        assert!(tf.at(3.0, "odom", "cam").is_none(), "no transform of odom -> base then");
        assert!(tf.at(0.5, "map", "cam").is_none(), "the chain does not reach map");
        assert!(tf.at(0.5, "odom", "lidar").is_none());
    }

    #[test]
    fn ros1_pose_messages() {
        let mut m = Vec::new();
        for v in [1u32, 3, 250_000_000] {
            m.extend(v.to_le_bytes());
        }
        m.extend(3u32.to_le_bytes());
        m.extend(b"map");
        let with_pose = |mut m: Vec<u8>, q: [f64; 4]| {
            for v in [1.0f64, 2.0, 3.0].into_iter().chain(q) {
                m.extend(v.to_le_bytes());
            }
            m
        };
        let stamped = with_pose(m.clone(), [0.0, 0.0, 0.0, 1.0]);
        let (s, p) = pose_message(PoseKind::PoseStamped, Wire::Ros1, &stamped).unwrap();
        assert_eq!((s, p.x, p.z, p.qw), (3.25, 1.0, 3.0, 1.0));
        let mut odom = m.clone();
        odom.extend(4u32.to_le_bytes());
        odom.extend(b"base");
        let odom = with_pose(odom, [0.0, 0.0, 0.0, 1.0]);
        assert_eq!(pose_message(PoseKind::Odometry, Wire::Ros1, &odom).unwrap().1.y, 2.0);
        let zero_q = with_pose(m, [0.0; 4]);
        assert!(pose_message(PoseKind::PoseStamped, Wire::Ros1, &zero_q).is_err());
        assert!(pose_message(PoseKind::PoseStamped, Wire::Ros1, &stamped[..20]).is_err());
    }
}
