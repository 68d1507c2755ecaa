//! A session's loop graph as files a SLAM back end reads: `frames.csv`, one TUM
//! trajectory per robot, `loops.csv` and `graph.g2o`, in one tar. Used by the HTTP export route
//! (and so by `loopd export`).
pub mod g2o;
pub mod tables;

use crate::store::loops::LoopRecord;
use crate::store::record::FrameHeader;

/// How much the graph trusts odometry and loops without a client covariance (standard
/// deviations: metres, radians).
#[derive(Clone, Copy, Debug)]
pub struct Noise {
    pub odometry_m: f64,
    pub odometry_rad: f64,
    pub loop_m: f64,
    pub loop_rad: f64,
    /// Only loops a client accepted become edges (not verified metric loops without a verdict).
    pub accepted_only: bool,
}

impl Default for Noise {
    fn default() -> Self {
        Self { odometry_m: 0.1, odometry_rad: 0.01, loop_m: 0.2, loop_rad: 0.02, accepted_only: false }
    }
}

/// Everything exported, in frame id order.
pub struct Snapshot {
    pub frames: Vec<(u64, FrameHeader)>,
    pub loops: Vec<LoopRecord>,
}

/// A robot id as a file name: letters, digits, '.', '-' and '_' kept, every other byte %XX.
pub fn file_name(robot: &str) -> String {
    let mut out = String::new();
    for b in robot.bytes() {
        if b.is_ascii_alphanumeric() || b"-_".contains(&b) || (b == b'.' && !out.is_empty()) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// The tar (frames.csv, loops.csv, graph.g2o, trajectories/<robot>.tum, README.txt, which
/// says how many loops became edges and why the others did not) and those counts.
pub fn tar(snapshot: &Snapshot, noise: Noise) -> std::io::Result<(Vec<u8>, g2o::EdgeCounts)> {
    let (graph, counts) = g2o::graph_counted(snapshot, noise);
    let readme = format!("{README}\nthis export: {}\n", counts.summary());
    let mut files: Vec<(String, Vec<u8>)> = vec![
        ("README.txt".into(), readme.into_bytes()),
        ("frames.csv".into(), tables::frames_csv(&snapshot.frames).into_bytes()),
        ("loops.csv".into(), tables::loops_csv(&snapshot.loops).into_bytes()),
        ("graph.g2o".into(), graph.into_bytes()),
    ];
    for (robot, tum) in tables::tum_by_robot(&snapshot.frames) {
        files.push((format!("trajectories/{}.tum", file_name(&robot)), tum.into_bytes()));
    }
    let mut builder = tar::Builder::new(Vec::new());
    let mtime =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or_default();
    for (name, bytes) in files {
        let mut header = tar::Header::new_gnu();
        header.set_size(bytes.len() as u64);
        header.set_mode(0o644);
        header.set_mtime(mtime);
        builder.append_data(&mut header, name, bytes.as_slice())?;
    }
    Ok((builder.into_inner()?, counts))
}

const README: &str = "\
loopd session export
frames.csv        every frame: id, robot, time, pose (empty when the frame has none), metadata JSON
trajectories/     one TUM file per robot (frames with a pose): timestamp x y z qx qy qz qw
loops.csv         every loop candidate answered, with verification and the client's verdict
graph.g2o         VERTEX_SE3:QUAT per posed frame (id = frame id), EDGE_SE3:QUAT odometry between a
                  robot's consecutive posed frames (measured from their poses), and a loop edge per
                  loop a client accepted with a relative pose, or verified with a metric pose
                  (depth at one of its frames) and not rejected (information: the inverse of its
                  covariance, else the export's loop noise; accepted_only=true: accepted loops
                  only); other candidates and monocular poses (scale unknown) give no edge
";
