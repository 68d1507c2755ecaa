//! `graph.g2o`: the session as a pose graph (g2o's SE3:QUAT text format, as GTSAM's readG2o
//! and g2o read it). Vertices are posed frames; odometry edges join a robot's consecutive posed
//! frames; loop edges are loops a client accepted with a relative pose, and verified loops with a
//! metric pose (depth at one of the frames) no client rejected.
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

/// How many loops became edges, and why the others did not (each loop counted once, under the
/// first reason that applies).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EdgeCounts {
    /// Loop edges written.
    pub edges: usize,
    /// ...of which from a client's accepted verdict with a relative pose.
    pub accepted: usize,
    /// ...of which verified metric poses without a verdict.
    pub metric: usize,
    /// Left out: a frame at either end has no pose (no vertex).
    pub no_pose: usize,
    /// Left out: a client rejected it.
    pub rejected: usize,
    /// Left out: verified, but monocular (its translation's scale unknown) and not accepted
    /// with a pose.
    pub monocular: usize,
    /// Left out: metric, but the export asked for accepted loops only.
    pub not_accepted: usize,
    /// Left out: not verified (or not checked) and not accepted with a pose.
    pub unverified: usize,
}

impl EdgeCounts {
    pub fn left_out(&self) -> usize {
        self.no_pose + self.rejected + self.monocular + self.not_accepted + self.unverified
    }

    /// One line: the edges and each reason's count.
    pub fn summary(&self) -> String {
        format!(
            "{} loop edges ({} accepted by a client, {} verified metric); {} loops left out: {} without a pose at \
             an end, {} rejected, {} monocular (scale unknown), {} not accepted (accepted_only), {} not verified",
            self.edges,
            self.accepted,
            self.metric,
            self.left_out(),
            self.no_pose,
            self.rejected,
            self.monocular,
            self.not_accepted,
            self.unverified
        )
    }
}

/// The graph and how many loops became edges.
pub fn graph_counted(s: &Snapshot, noise: Noise) -> (String, EdgeCounts) {
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
    let mut n = EdgeCounts::default();
    for l in &s.loops {
        let verdict = l.verdict.as_ref();
        // A client's accepted pose first, else a verified metric pose nobody rejected.
        let chosen = match verdict {
            Some(v) if !v.accepted => Err(&mut n.rejected),
            Some(v) if v.relative_pose.is_some() => Ok((v.relative_pose.as_ref(), v.covariance.as_ref(), true)),
            _ if l.verified && l.metric && l.relative_pose.is_some() => match noise.accepted_only {
                true => Err(&mut n.not_accepted),
                false => Ok((l.relative_pose.as_ref(), l.covariance.as_ref(), false)),
            },
            _ if l.verified && l.relative_pose.is_some() => Err(&mut n.monocular),
            _ => Err(&mut n.unverified),
        };
        let ends_posed = posed.contains_key(&l.query_frame) && posed.contains_key(&l.match_frame);
        let (measured, covariance, accepted) = match chosen {
            _ if !ends_posed => {
                n.no_pose += 1;
                continue;
            }
            Err(count) => {
                *count += 1;
                continue;
            }
            Ok((Some(m), c, a)) => (m, c, a),
            Ok((None, ..)) => continue,
        };
        let information = covariance
            .filter(|c| c.len() == 36)
            .and_then(|c| Matrix6::from_row_slice(c).try_inverse())
            .filter(|i| i.iter().all(|v| v.is_finite()))
            .map(|i| (i + i.transpose()) * 0.5)
            .unwrap_or(fallback);
        edge(&mut out, l.query_frame, l.match_frame, &transform(measured), &information);
        n.edges += 1;
        if accepted {
            n.accepted += 1;
        } else {
            n.metric += 1;
        }
    }
    (out, n)
}
