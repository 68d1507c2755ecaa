//! `loopd ingest BAG`: a ROS bag (MCAP file, rosbag2 folder, ROS 1 .bag) as an offline sequence
//! job on a running server, which reads the bag (the same code as an HTTP bag upload); without
//! --session, the bag's topics.
use crate::api::wire::{JobState, JobStatus, MAX_BAG_CHUNK_BYTES, MAX_JOB_FRAMES};
use crate::bags;
use crate::client::{failed, Http, ServerArgs};
use anyhow::{bail, Context, Result};
use clap::Args;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Args)]
pub struct IngestArgs {
    /// An MCAP file, a rosbag2 folder (its metadata.yaml lists the files of a split bag) or a
    /// ROS 1 .bag.
    bag: PathBuf,
    /// The session that gets the frames (created when missing); without it, the bag's topics
    /// are listed.
    #[arg(long)]
    session: Option<String>,
    /// Image topics to read (repeat for several); default: the bag's only image topic.
    #[arg(long)]
    topic: Vec<String>,
    /// Keep every Nth message of each topic.
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Smallest step between kept frames of a topic (seconds of header stamp).
    #[arg(long, default_value_t = 0.0)]
    min_dt: f64,
    /// The camera's pose for each frame (nav_msgs/Odometry, geometry_msgs/PoseStamped or
    /// PoseWithCovarianceStamped), interpolated to the image's stamp: the exported graph.g2o
    /// gets a vertex per frame and odometry edges.
    #[arg(long, conflicts_with_all = ["odom_frame", "camera_frame"])]
    pose_topic: Option<String>,
    /// Instead of --pose-topic: the camera frame's pose in this frame (e.g. odom or map) from
    /// /tf and /tf_static, interpolated to the image's stamp (with --camera-frame).
    #[arg(long, requires = "camera_frame")]
    odom_frame: Option<String>,
    /// The camera's tf frame (with --odom-frame).
    #[arg(long, requires = "odom_frame")]
    camera_frame: Option<String>,
    /// The camera's registered depth images (sensor_msgs/Image 16UC1 mm or 32FC1 m), nearest in
    /// stamp within 50 ms: verified loops get metric poses (needs --camera).
    #[arg(long, conflicts_with = "right_topic")]
    depth_topic: Option<String>,
    /// The right images of a stereo pair (sensor_msgs/Image or CompressedImage), nearest in stamp
    /// within 50 ms: verified loops get metric poses (needs a session whose camera has stereo,
    /// e.g. created with the Python client's create_session(stereo=...)).
    #[arg(long)]
    right_topic: Option<String>,
    /// Create the session with this camera: fx,fy,cx,cy[,k1,k2,p1,p2,k3] in pixels.
    #[arg(long, value_delimiter = ',')]
    camera: Option<Vec<f64>>,
    /// Every frame's robot (default: from the topic's namespace, /robot1/cam/image_raw ->
    /// robot1, else "sequence").
    #[arg(long)]
    robot_id: Option<String>,
    /// Loops scoring below this cosine are not reported.
    #[arg(long)]
    min_score: Option<f32>,
    /// Loops below this calibrated confidence are not reported (default: the server's loop
    /// confidence, /v1/info).
    #[arg(long)]
    min_confidence: Option<f32>,
    /// Check loops geometrically (ORB + RANSAC): true (the job default) or false.
    #[arg(long)]
    verify: Option<bool>,
    /// Check loops by sequence (the frames before query and candidate): true (the job default) or false.
    #[arg(long)]
    sequence: Option<bool>,
    /// Frames just before a query that are never its loop.
    #[arg(long)]
    exclude_last_frames: Option<usize>,
    /// Create the session keeping a small JPEG of each frame (the loop inspector shows them at
    /// /v1/sessions/SESSION/inspect); an existing session keeps its own setting.
    #[arg(long)]
    thumbnails: bool,
    /// Print the finished job (frames, loops, errors) as JSON.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    remote: ServerArgs,
}

#[derive(Deserialize)]
struct Metadata {
    rosbag2_bagfile_information: BagInfo,
}

#[derive(Deserialize)]
struct BagInfo {
    storage_identifier: String,
    relative_file_paths: Vec<String>,
}

/// The bag's files in order: one file, or those a rosbag2 folder's metadata.yaml lists.
fn bag_files(path: &Path) -> Result<Vec<PathBuf>> {
    if !path.is_dir() {
        return Ok(vec![path.to_path_buf()]);
    }
    let meta = path.join("metadata.yaml");
    let text = std::fs::read_to_string(&meta).with_context(|| format!("reading {}", meta.display()))?;
    let info = serde_yaml::from_str::<Metadata>(&text)
        .with_context(|| format!("{} is not rosbag2 metadata", meta.display()))?
        .rosbag2_bagfile_information;
    if info.storage_identifier != "mcap" {
        bail!("the bag is stored as {}; loopd reads MCAP (`ros2 bag convert` writes it)", info.storage_identifier);
    }
    Ok(info.relative_file_paths.iter().map(|f| path.join(f)).collect())
}

fn list_topics(files: &[PathBuf]) -> Result<()> {
    let data: Vec<Vec<u8>> = files
        .iter()
        .map(|f| std::fs::read(f).with_context(|| format!("reading {}", f.display())))
        .collect::<Result<_>>()?;
    let parts: Vec<&[u8]> = data.iter().map(Vec::as_slice).collect();
    let limits = bags::Limits { max_frames: MAX_JOB_FRAMES, max_chunk_bytes: MAX_BAG_CHUNK_BYTES };
    let topics = bags::topics(&parts, &limits)?;
    println!("{:<40} {:<36} {:>9}  read", "topic", "type", "messages");
    for t in &topics {
        println!("{:<40} {:<36} {:>9}  {}", t.topic, t.msg_type, t.messages, if t.image { "image" } else { "-" });
    }
    if !topics.iter().any(|t| t.image) {
        bail!("no image topic (sensor_msgs/Image or CompressedImage) in the bag");
    }
    Ok(())
}

/// Creates the session unless it exists; true when this call created it.
fn ensure_session(remote: &Http, id: &str, thumbnails: bool, camera: Option<&[f64]>) -> Result<bool> {
    let create = remote.client.post(format!("{}/v1/sessions", remote.base));
    let mut body = serde_json::json!({ "id": id, "name": id, "thumbnails": thumbnails });
    match camera {
        Some(&[fx, fy, cx, cy]) => body["camera"] = serde_json::json!({ "fx": fx, "fy": fy, "cx": cx, "cy": cy }),
        Some(&[fx, fy, cx, cy, k1, k2, p1, p2, k3]) => {
            let distortion = [k1, k2, p1, p2, k3];
            body["camera"] = serde_json::json!({ "fx": fx, "fy": fy, "cx": cx, "cy": cy, "distortion": distortion })
        }
        Some(other) => bail!("--camera takes fx,fy,cx,cy or fx,fy,cx,cy,k1,k2,p1,p2,k3; got {} values", other.len()),
        None => {}
    }
    let r = remote.call(create.json(&body))?;
    if r.status() == reqwest::StatusCode::CONFLICT {
        return Ok(false); // it exists: the frames go on after its own
    }
    if !r.status().is_success() {
        return Err(failed(r).context(format!("creating session {id}")));
    }
    Ok(true)
}

/// Takes back a session this run created for an upload the server refused (nothing in it).
fn remove_session(remote: &Http, id: &str) {
    let delete = remote.client.delete(format!("{}/v1/sessions/{id}", remote.base));
    match remote.call(delete) {
        Ok(r) if r.status().is_success() => {}
        Ok(r) => eprintln!("warning: the empty session {id} was not removed: {}", failed(r)),
        Err(e) => eprintln!("warning: the empty session {id} was not removed: {e:#}"),
    }
}

fn upload(remote: &Http, a: &IngestArgs, session: &str, files: &[PathBuf]) -> Result<String> {
    let mut form = reqwest::blocking::multipart::Form::new()
        .text("every", a.every.to_string())
        .text("min_dt", a.min_dt.to_string());
    if !a.topic.is_empty() {
        form = form.text("topic", a.topic.join(","));
    }
    let frames = [("odom_frame", &a.odom_frame), ("camera_frame", &a.camera_frame)];
    let topics = [("pose_topic", &a.pose_topic), ("depth_topic", &a.depth_topic), ("right_topic", &a.right_topic)];
    for (k, v) in topics.into_iter().chain(frames) {
        if let Some(v) = v {
            form = form.text(k, v.clone());
        }
    }
    let options = [
        ("robot_id", a.robot_id.clone()),
        ("min_score", a.min_score.map(|s| s.to_string())),
        ("min_confidence", a.min_confidence.map(|s| s.to_string())),
        ("verify", a.verify.map(|s| s.to_string())),
        ("sequence", a.sequence.map(|s| s.to_string())),
    ];
    for (k, v) in options {
        if let Some(v) = v {
            form = form.text(k, v);
        }
    }
    if let Some(n) = a.exclude_last_frames {
        form = form.text("exclude_last_frames", n.to_string());
    }
    for f in files {
        form = form.file("bag", f).with_context(|| format!("reading {}", f.display()))?;
    }
    let url = format!("{}/v1/sessions/{session}/sequences", remote.base);
    let created: serde_json::Value = remote.send(remote.client.post(url).multipart(form))?.json()?;
    created["job_id"].as_str().map(String::from).context("the server's answer has no job id")
}

fn wait(remote: &Http, job: &str) -> Result<JobStatus> {
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} {bar:40} {pos}/{len} frames, {elapsed}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(job.to_string());
    loop {
        let s: JobStatus = remote.send(remote.client.get(format!("{}/v1/jobs/{job}", remote.base)))?.json()?;
        bar.set_length(s.total as u64);
        bar.set_position(s.done as u64);
        if s.state != JobState::Running {
            bar.finish_and_clear();
            return Ok(s);
        }
        std::thread::sleep(std::time::Duration::from_millis(300));
    }
}

pub fn run(a: IngestArgs) -> Result<ExitCode> {
    let files = bag_files(&a.bag)?;
    let Some(session) = a.session.clone() else {
        list_topics(&files)?;
        return Ok(ExitCode::SUCCESS);
    };
    let remote = a.remote.connect()?;
    let created = ensure_session(&remote, &session, a.thumbnails, a.camera.as_deref())?;
    let job = match upload(&remote, &a, &session, &files) {
        Ok(job) => job,
        Err(e) => {
            // Refused (a broken bag, a bad option): a session made for it goes again.
            if created {
                remove_session(&remote, &session);
            }
            return Err(e);
        }
    };
    let s = wait(&remote, &job)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        for l in &s.loops {
            let confidence = l.confidence.map_or_else(|| "-".to_string(), |c| format!("{c:.3}"));
            println!("{:<32} -> {:<32} {:.3} confidence {confidence}", l.query_name, l.match_name, l.score);
        }
        eprintln!(
            "{job}: {:?}, {} of {} frames, {} loops, {} errors",
            s.state,
            s.done,
            s.total,
            s.loops.len(),
            s.errors.len()
        );
        for e in &s.errors {
            eprintln!("  {e}");
        }
    }
    Ok(if s.state == JobState::Done { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}
