//! The CSV tables and TUM trajectories of an export.
use crate::store::loops::LoopRecord;
use crate::store::record::FrameHeader;
use std::collections::BTreeMap;
use std::fmt::Write;

/// A CSV field: quoted when it holds a comma, quote or line break.
fn field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

pub fn frames_csv(frames: &[(u64, FrameHeader)]) -> String {
    let mut out = String::from("frame_id,robot_id,timestamp,x,y,z,qx,qy,qz,qw,metadata\n");
    for (id, h) in frames {
        let pose = h.pose.map_or_else(
            || ",,,,,,".to_string(),
            |p| format!("{},{},{},{},{},{},{}", p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw),
        );
        let metadata = h.metadata.as_ref().map(|m| m.to_string()).unwrap_or_default();
        let _ = writeln!(out, "{id},{},{:.9},{pose},{}", field(&h.robot_id), h.timestamp, field(&metadata));
    }
    out
}

pub fn loops_csv(loops: &[LoopRecord]) -> String {
    let mut out = String::from(
        "query_frame,match_frame,query_robot,match_robot,query_time,match_time,score,rank,checked,verified,inliers,\
         verdict,verdict_tx,verdict_ty,verdict_tz,verdict_qx,verdict_qy,verdict_qz,verdict_qw,confidence\n",
    );
    for l in loops {
        let verdict = match &l.verdict {
            None => "none",
            Some(v) if v.accepted => "accepted",
            Some(_) => "rejected",
        };
        let pose = l.verdict.as_ref().and_then(|v| v.relative_pose).map_or_else(
            || ",,,,,,".to_string(),
            |p| format!("{},{},{},{},{},{},{}", p.tx, p.ty, p.tz, p.qx, p.qy, p.qz, p.qw),
        );
        // Empty without a calibrator for the session's descriptors.
        let confidence = l.confidence.map_or_else(String::new, |c| c.to_string());
        let _ = writeln!(
            out,
            "{},{},{},{},{:.9},{:.9},{},{},{},{},{},{verdict},{pose},{confidence}",
            l.query_frame,
            l.match_frame,
            field(&l.query_robot),
            field(&l.match_robot),
            l.query_time,
            l.match_time,
            l.score,
            l.rank,
            l.checked,
            l.verified,
            l.inliers
        );
    }
    out
}

/// Per robot, its posed frames as a TUM trajectory, in time order (equal times keep one pose:
/// TUM readers need increasing stamps).
pub fn tum_by_robot(frames: &[(u64, FrameHeader)]) -> BTreeMap<String, String> {
    let mut by_robot: BTreeMap<String, Vec<&FrameHeader>> = BTreeMap::new();
    for (_, h) in frames.iter().filter(|(_, h)| h.pose.is_some()) {
        by_robot.entry(h.robot_id.clone()).or_default().push(h);
    }
    by_robot
        .into_iter()
        .map(|(robot, mut hs)| {
            hs.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
            hs.dedup_by(|b, a| a.timestamp == b.timestamp);
            let mut out = String::new();
            for h in hs {
                let p = h.pose.expect("filtered to posed frames");
                let _ = writeln!(out, "{:.9} {} {} {} {} {} {} {}", h.timestamp, p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw);
            }
            (robot, out)
        })
        .collect()
}
