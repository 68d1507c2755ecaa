//! `loopd ros2`: the ROS 2 bridge node (docs/ros2.md). A subcommand of the one binary, not a
//! second one: it shares the gRPC client, TLS and key handling and the pixel decoding of the bag
//! reader, and a fleet installs one program. The server never starts a ROS 2 entity.
use crate::client::{tenant_key, TlsArgs};
use crate::pb;
use crate::ros2::bridge::{self, Publish};
use crate::ros2::keyframes::Rule;
use anyhow::{bail, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Args)]
pub struct Ros2Args {
    /// The loopd server's gRPC address (host:port, http://… or https://… with --ca).
    #[arg(long, env = "LOOPD_SERVER_GRPC", default_value = "127.0.0.1:50051")]
    pub server: String,
    /// A file holding the tenant's key (else LOOPD_KEY; none on a server without keys).
    #[arg(long, env = "LOOPD_KEY_FILE")]
    pub key_file: Option<PathBuf>,
    #[command(flatten)]
    pub tls: TlsArgs,
    /// The map session every robot's keyframes go to; made when it does not exist.
    #[arg(long)]
    pub session: String,
    /// The served model a new session is made with (default: the server's).
    #[arg(long)]
    pub model: Option<String>,
    /// Camera topics (sensor_msgs/Image or CompressedImage): a topic, or a pattern where `*` is
    /// any one name, e.g. /*/camera/image_raw/compressed (the robot: the first name). Repeatable.
    #[arg(long, required = true)]
    pub images: Vec<String>,
    /// The robot of every topic, for topics outside a robot's namespace.
    #[arg(long)]
    pub robot: Option<String>,
    /// sensor_msgs/CameraInfo topic or pattern: a new session gets the first usable one's
    /// intrinsics (verified loops then carry their relative pose).
    #[arg(long)]
    pub camera_info: Option<String>,
    /// Seconds a new session waits for a usable CameraInfo before it is made without a camera.
    #[arg(long, default_value_t = 10.0)]
    pub camera_wait: f64,
    /// nav_msgs/Odometry topic or pattern: a keyframe's pose is the odometry nearest its stamp.
    #[arg(long)]
    pub odom: Option<String>,
    /// Largest gap (s) between a keyframe's stamp and the odometry it takes.
    #[arg(long, default_value_t = 0.1)]
    pub pose_tolerance: f64,
    /// Keyframes: every Nth camera message of a robot.
    #[arg(long, default_value_t = 1)]
    pub every: u64,
    /// Keyframes: at least this many seconds (header stamps) apart.
    #[arg(long, default_value_t = 0.0)]
    pub min_dt: f64,
    /// Keyframes: at least this many metres apart (needs --odom).
    #[arg(long, default_value_t = 0.0)]
    pub min_distance: f64,
    /// Keyframes waiting for the server per robot; when full, the oldest is dropped (counted).
    #[arg(long, default_value_t = 16)]
    pub queue: usize,
    /// History depth of the camera subscriptions (best effort, keep last).
    #[arg(long, default_value_t = 5)]
    pub depth: usize,
    /// Which answered candidates are published.
    #[arg(long, value_enum, default_value = "verified")]
    pub publish: Publish,
    #[arg(long, default_value = "/loopd/loop_closures")]
    pub loops_topic: String,
    #[arg(long, default_value = "/loopd/loop_markers")]
    pub markers_topic: String,
    /// The frame the odometry poses are in (the markers' header).
    #[arg(long, default_value = "map")]
    pub map_frame: String,
    #[arg(long, env = "ROS_DOMAIN_ID", default_value_t = 0)]
    pub domain_id: u16,
    #[arg(long, default_value = "loopd_bridge")]
    pub node_name: String,
    /// Seconds before a send is given up and retried.
    #[arg(long, default_value_t = 60.0)]
    pub call_timeout: f64,
    /// Serve the bridge's counters on http://ADDR/metrics.
    #[arg(long)]
    pub metrics_addr: Option<std::net::SocketAddr>,
    /// Query options (default: the session's): candidates answered.
    #[arg(long)]
    pub k: Option<u32>,
    /// Inliers for a verified loop.
    #[arg(long)]
    pub min_inliers: Option<u32>,
    /// Candidates checked geometrically.
    #[arg(long)]
    pub verify_candidates: Option<u32>,
    /// The robot's own newest frames left out of its queries.
    #[arg(long)]
    pub exclude_last_frames: Option<u32>,
    /// The robot's own frames of the last seconds left out of its queries.
    #[arg(long)]
    pub exclude_last_seconds: Option<f64>,
}

fn seconds(v: f64, what: &str) -> Result<Duration> {
    if !(v.is_finite() && v >= 0.0) {
        bail!("{what} must be a number of seconds >= 0, got {v}");
    }
    Ok(Duration::from_secs_f64(v))
}

pub fn run(a: Ros2Args) -> Result<ExitCode> {
    if a.every == 0 {
        bail!("--every must be at least 1");
    }
    if !(a.min_dt.is_finite() && a.min_dt >= 0.0 && a.min_distance.is_finite() && a.min_distance >= 0.0) {
        bail!("--min-dt and --min-distance must be >= 0");
    }
    if a.queue == 0 || a.depth == 0 {
        bail!("--queue and --depth must be at least 1");
    }
    let cfg = bridge::Config {
        key: tenant_key(a.key_file.as_deref())?,
        server: a.server,
        tls: a.tls,
        session: a.session,
        model: a.model,
        images: a.images,
        robot: a.robot,
        camera_info: a.camera_info,
        camera_wait: seconds(a.camera_wait, "--camera-wait")?,
        odom: a.odom,
        pose_tolerance: seconds(a.pose_tolerance, "--pose-tolerance")?.as_secs_f64(),
        rule: Rule { every: a.every, min_dt: a.min_dt, min_distance: a.min_distance },
        queue: a.queue,
        depth: a.depth,
        publish: a.publish,
        loops_topic: a.loops_topic,
        markers_topic: a.markers_topic,
        map_frame: a.map_frame,
        options: pb::QueryOptions {
            k: a.k,
            min_inliers: a.min_inliers,
            verify_candidates: a.verify_candidates,
            exclude_last_frames: a.exclude_last_frames,
            exclude_last_seconds: a.exclude_last_seconds,
            ..Default::default()
        },
        domain_id: a.domain_id,
        node_name: a.node_name,
        call_timeout: seconds(a.call_timeout, "--call-timeout")?,
        metrics_addr: a.metrics_addr,
    };
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        tokio::spawn(async move {
            super::serve::wait_for_signal().await;
            tracing::info!("stopping the bridge");
            let _ = stop_tx.send(true);
        });
        bridge::run(cfg, stop_rx).await
    })?;
    Ok(ExitCode::SUCCESS)
}
