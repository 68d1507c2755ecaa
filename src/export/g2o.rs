//! `graph.g2o`: the session as a pose graph (g2o's SE3:QUAT text format, as GTSAM's readG2o
//! and g2o read it). Vertices are posed frames; odometry edges join a robot's consecutive posed
//! frames; loop edges are loops a client accepted with a relative pose.
use super::{Noise, Snapshot};
use crate::index::query::Pose;
use crate::store::loops::Transform;
use nalgebra::{Isometry3, Matrix6, Quaternion, Translation3, UnitQuaternion};
use std::collections::{BTreeMap, HashMap};
use std::fmt::Write;

fn iso(p: &Pose) -> Isometry3<f64> {
    let q = UnitQuaternion::from_quaternion(Quaternion::new(p.qw, p.qx, p.qy, p.qz));
    Isometry3::from_parts(Translation3::new(p.x, p.y, p.z), q)
}

fn transform(t: &Transform) -> Isometry3<f64> {
    let q = UnitQuaternion::from_quaternion(Quaternion::new(t.qw, t.qx, t.qy, t.qz));
    Isometry3::from_parts(Translation3::new(t.tx, t.ty, t.tz), q)
}

fn diagonal(sigma_m: f64, sigma_rad: f64) -> Matrix6<f64> {
    let (t, r) = (1.0 / (sigma_m * sigma_m), 1.0 / (sigma_rad * sigma_rad));
    Matrix6::from_diagonal(&nalgebra::Vector6::new(t, t, t, r, r, r))
}

fn edge(out: &mut String, i: u64, j: u64, m: &Isometry3<f64>, information: &Matrix6<f64>) {
    let (t, q) = (m.translation.vector, m.rotation.quaternion());
    let _ = write!(out, "EDGE_SE3:QUAT {i} {j} {} {} {} {} {} {} {}", t.x, t.y, t.z, q.i, q.j, q.k, q.w);
    for r in 0..6 {
        for c in r..6 {
            let _ = write!(out, " {}", information[(r, c)]);
        }
    }
    out.push('\n');
}

pub fn graph(s: &Snapshot, noise: Noise) -> String {
    let mut out = String::new();
    let mut posed: HashMap<u64, Isometry3<f64>> = HashMap::new();
    let mut trajectories: BTreeMap<&str, Vec<(f64, u64)>> = BTreeMap::new();
    for (id, h) in &s.frames {
        let Some(p) = &h.pose else { continue };
        let pose = iso(p);
        let (t, q) = (pose.translation.vector, pose.rotation.quaternion());
        let _ = writeln!(out, "VERTEX_SE3:QUAT {id} {} {} {} {} {} {} {}", t.x, t.y, t.z, q.i, q.j, q.k, q.w);
        posed.insert(*id, pose);
        trajectories.entry(&h.robot_id).or_default().push((h.timestamp, *id));
    }
    let odometry = diagonal(noise.odometry_m, noise.odometry_rad);
    for frames in trajectories.values_mut() {
        frames.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for w in frames.windows(2) {
            let (i, j) = (w[0].1, w[1].1);
            edge(&mut out, i, j, &(posed[&i].inverse() * posed[&j]), &odometry);
        }
    }
    let fallback = diagonal(noise.loop_m, noise.loop_rad);
    for l in &s.loops {
        let Some(v) = l.verdict.as_ref().filter(|v| v.accepted) else { continue };
        let Some(measured) = v.relative_pose.as_ref() else { continue };
        if !(posed.contains_key(&l.query_frame) && posed.contains_key(&l.match_frame)) {
            continue;
        }
        let information = v
            .covariance
            .as_ref()
            .and_then(|c| Matrix6::from_row_slice(c).try_inverse())
            .map(|i| (i + i.transpose()) * 0.5)
            .unwrap_or(fallback);
        edge(&mut out, l.query_frame, l.match_frame, &transform(measured), &information);
    }
    out
}
