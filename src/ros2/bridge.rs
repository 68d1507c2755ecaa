//! The bridge: a ROS 2 node (ros2-client, DDS) on one thread of its own, and one sender per
//! robot talking to the server over its gRPC API (`AddAndQuery`, by idempotency key).
//!
//! - The ROS thread owns every ROS entity: it finds the topics the patterns name as they are
//!   discovered, subscribes them, turns each message into a keyframe (or a logged, counted
//!   rejection) and publishes what the senders answer. A message never waits for the server.
//! - A robot's sender takes its queue's head, sends it and drops it from the queue only once the
//!   server has answered; a server that is down or restarting is retried with the same key, so a
//!   keyframe is stored once however often it is sent.
use super::keyframes::{Rule, Selector};
use super::metrics::Metrics;
use super::msgs::{CameraInfo, CompressedImage, Image, LoopClosure, Marker, MarkerArray, Odometry};
use super::queue::{Keyframe, Queue};
use crate::client::{self, Grpc, TlsArgs};
use crate::index::query::Pose;
use crate::pb;
use anyhow::{bail, Result};
use parking_lot::Mutex;
use ros2_client::{
    Context, ContextOptions, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher, QosProfile, Subscription,
};
use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, watch, Notify};

/// Which answered candidates become LoopClosure messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Publish {
    /// Verified loops only.
    Verified,
    /// Every candidate the server answers (unverified ones as REJECTED_LOOPCLOSE).
    All,
}

#[derive(Clone, Debug)]
pub struct Config {
    pub server: String,
    pub key: Option<String>,
    pub tls: TlsArgs,
    pub session: String,
    /// The served model a new session is made with (None: the server's default).
    pub model: Option<String>,
    /// Topic patterns of camera images (`*`: any one name).
    pub images: Vec<String>,
    /// The robot of every topic (else the first name of its namespace).
    pub robot: Option<String>,
    pub camera_info: Option<String>,
    /// How long a new session waits for a usable CameraInfo.
    pub camera_wait: Duration,
    pub odom: Option<String>,
    /// Largest gap between a keyframe's stamp and the odometry pose it takes.
    pub pose_tolerance: f64,
    pub rule: Rule,
    /// Keyframes waiting per robot.
    pub queue: usize,
    /// History depth of the camera subscriptions (best effort, keep last).
    pub depth: usize,
    pub publish: Publish,
    pub loops_topic: String,
    pub markers_topic: String,
    /// The frame of the poses (odometry), for the markers.
    pub map_frame: String,
    pub options: pb::QueryOptions,
    pub domain_id: u16,
    pub node_name: String,
    /// A send that takes longer is retried.
    pub call_timeout: Duration,
    pub metrics_addr: Option<std::net::SocketAddr>,
}

/// `*` matches one name of a topic.
pub fn matches(pattern: &str, topic: &str) -> bool {
    let p: Vec<&str> = pattern.split('/').filter(|n| !n.is_empty()).collect();
    let t: Vec<&str> = topic.split('/').filter(|n| !n.is_empty()).collect();
    p.len() == t.len() && p.iter().zip(&t).all(|(p, t)| *p == "*" || p == t)
}

/// The robot of a topic: the first name of a camera topic three or more names deep
/// (`/r1/camera/image_raw`, as the bag reader says; `/camera/image_raw` is no robot's), of a
/// CameraInfo or odometry topic two or more deep (`/r1/odom`).
fn robot_of(topic: &str, camera: bool) -> Option<String> {
    if camera {
        return crate::bags::robot_of(topic);
    }
    let names: Vec<&str> = topic.split('/').filter(|n| !n.is_empty()).collect();
    (names.len() >= 2).then(|| names[0].to_string())
}

/// What a topic carries, from its DDS type name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Raw,
    Compressed,
    CameraInfo,
    Odometry,
}

impl Kind {
    fn of(dds_type: &str) -> Option<Self> {
        match dds_type {
            "sensor_msgs::msg::dds_::Image_" => Some(Self::Raw),
            "sensor_msgs::msg::dds_::CompressedImage_" => Some(Self::Compressed),
            "sensor_msgs::msg::dds_::CameraInfo_" => Some(Self::CameraInfo),
            "nav_msgs::msg::dds_::Odometry_" => Some(Self::Odometry),
            _ => None,
        }
    }
}

/// A robot the bridge has topics of.
struct Robot {
    name: String,
    index: u64,
    queue: Mutex<Queue>,
    wake: Notify,
    /// One per camera topic.
    selectors: Mutex<HashMap<String, Selector>>,
    /// Recent odometry (stamp, pose), oldest first.
    poses: Mutex<VecDeque<(f64, Pose)>>,
    /// Reasons already logged (each is logged once, then counted).
    logged: Mutex<HashSet<String>>,
}

const POSES_KEPT: usize = 512;
const LOGGED_REASONS: usize = 64;

impl Robot {
    fn pose_at(&self, stamp: f64, tolerance: f64) -> Option<Pose> {
        let poses = self.poses.lock();
        poses
            .iter()
            .map(|(t, p)| ((t - stamp).abs(), p))
            .filter(|(d, _)| *d <= tolerance)
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, p)| *p)
    }

    /// Logs a rejection the first time its reason comes up for this robot, for the first
    /// `LOGGED_REASONS` reasons (a server's refusals name the frame: months of them must not
    /// grow the set); the rest are counted only.
    fn first_time(&self, what: &str) -> bool {
        let mut logged = self.logged.lock();
        logged.len() < LOGGED_REASONS && logged.insert(what.to_string())
    }
}

/// What the senders hand the ROS thread to publish.
struct Out {
    loops: Vec<LoopClosure>,
    markers: MarkerArray,
}

struct Fleet {
    cfg: Config,
    metrics: Arc<Metrics>,
    robots: Mutex<HashMap<String, Arc<Robot>>>,
    /// Every robot named so far (ours and those answers name), in order: its index.
    names: Mutex<Vec<String>>,
    /// The session, once it is open.
    session: watch::Receiver<Option<String>>,
    link: Link,
    out: mpsc::UnboundedSender<Out>,
    runtime: tokio::runtime::Handle,
    markers: std::sync::atomic::AtomicI32,
}

impl Fleet {
    fn index_of(&self, name: &str) -> u64 {
        let mut names = self.names.lock();
        match names.iter().position(|n| n == name) {
            Some(i) => i as u64,
            None => {
                names.push(name.to_string());
                (names.len() - 1) as u64
            }
        }
    }

    /// The robot, made (with its sender) the first time it is named.
    fn robot(self: &Arc<Self>, name: &str) -> Arc<Robot> {
        let mut robots = self.robots.lock();
        if let Some(r) = robots.get(name) {
            return r.clone();
        }
        let index = self.index_of(name);
        let robot = Arc::new(Robot {
            name: name.to_string(),
            index,
            queue: Mutex::new(Queue::new(self.cfg.queue)),
            wake: Notify::new(),
            selectors: Mutex::new(HashMap::new()),
            poses: Mutex::new(VecDeque::new()),
            logged: Mutex::new(HashSet::new()),
        });
        tracing::info!(robot = name, index, "robot added (its index in LoopClosure.robot_from / robot_to)");
        robots.insert(name.to_string(), robot.clone());
        self.runtime.spawn(sender(self.clone(), robot.clone()));
        robot
    }

    fn reject(&self, robot: &Robot, what: &str, why: &str) {
        self.metrics.reject(&robot.name, what);
        if robot.first_time(&format!("{what}: {why}")) {
            tracing::warn!(robot = %robot.name, what, why, "message refused (counted in loopd_ros2_rejected; logged once per reason)");
        }
    }

    /// A camera message: a keyframe for the robot's queue, or a rejection.
    fn on_image(self: &Arc<Self>, robot: &Arc<Robot>, topic: &str, msg: Camera) {
        let label = Metrics::robot(&robot.name);
        self.metrics.received.get_or_create(&label).inc();
        let (stamp, camera_frame) = match &msg {
            Camera::Raw(m) => (m.header.stamp, m.header.frame_id.clone()),
            Camera::Compressed(m) => (m.header.stamp, m.header.frame_id.clone()),
        };
        let pose = robot.pose_at(stamp.seconds(), self.cfg.pose_tolerance);
        let kept = robot.selectors.lock().entry(topic.to_string()).or_default().take(
            &self.cfg.rule,
            stamp.seconds(),
            pose.as_ref(),
        );
        if !kept {
            return;
        }
        let image = match msg.encoded() {
            Ok(i) => i,
            Err(why) => return self.reject(robot, "image", &why),
        };
        self.metrics.keyframes.get_or_create(&label).inc();
        let k = Keyframe { topic: topic.to_string(), stamp, camera_frame, image: image.into(), pose };
        let (dropped, len) = {
            let mut q = robot.queue.lock();
            let d = q.push(k);
            (d, q.len())
        };
        if let Some(d) = dropped {
            let n = self.metrics.dropped.get_or_create(&label).inc() + 1;
            // The first, then every 100th: a slow server must not flood the log.
            if n == 1 || n.is_multiple_of(100) {
                tracing::warn!(robot = %robot.name, stamp = d.stamp.seconds(), dropped = n, queue = self.cfg.queue,
                    "keyframe dropped unsent: the robot's queue is full (server slow or down)");
            }
        }
        self.metrics.queued.get_or_create(&label).set(len as i64);
        robot.wake.notify_one();
    }

    fn on_odometry(&self, robot: &Robot, m: &Odometry) {
        let mut poses = robot.poses.lock();
        poses.push_back((m.header.stamp.seconds(), m.pose.pose.loopd()));
        if poses.len() > POSES_KEPT {
            poses.pop_front();
        }
    }

    fn request(&self, session: &str, robot: &Robot, k: &Keyframe) -> pb::AddFrameRequest {
        // The keyframe's identity: robot, topic and stamp (a resend stores nothing new).
        let topic_hash =
            k.topic.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3));
        let mut key = format!("ros2:{}:{:016x}:{}", k.stamp.nanos(), topic_hash, robot.name);
        key.truncate(128);
        let metadata = serde_json::json!({ "topic": k.topic, "camera_frame": k.camera_frame });
        pb::AddFrameRequest {
            session_id: session.to_string(),
            robot_id: robot.name.clone(),
            timestamp: Some(k.stamp.seconds()),
            pose: k.pose.map(pb::Pose::from),
            metadata_json: metadata.to_string(),
            content: Some(pb::add_frame_request::Content::Image(k.image.clone())),
            options: Some(self.cfg.options),
            idempotency_key: key,
            ..Default::default()
        }
    }

    /// The answer's candidates as LoopClosure messages (and marker lines where both frames have a pose).
    fn publish(&self, session: &str, robot: &Robot, k: &Keyframe, answer: &pb::AddAndQueryResponse) {
        let mut out = Out { loops: Vec::new(), markers: MarkerArray::default() };
        for (rank, m) in answer.matches.iter().enumerate() {
            let verified = m.verification.as_ref().is_some_and(|v| v.verified);
            if self.cfg.publish == Publish::Verified && !verified {
                continue;
            }
            let from = (answer.frame_id, robot.name.as_str(), robot.index, k.stamp, k.camera_frame.as_str());
            let l = LoopClosure::of(session, from, self.index_of(&m.robot_id), rank, m);
            // Verified loops at info; the unverified candidates of --publish all at debug.
            if verified {
                tracing::info!(robot = %robot.name, frame = answer.frame_id, to_robot = %m.robot_id,
                    to_frame = m.frame_id, score = m.score, inliers = l.inliers, "verified loop closure published");
            } else {
                tracing::debug!(robot = %robot.name, frame = answer.frame_id, to_robot = %m.robot_id,
                    to_frame = m.frame_id, score = m.score, inliers = l.inliers, "loop candidate published");
            }
            if let (Some(a), Some(b)) = (&k.pose, &m.pose) {
                let b = Pose::from(*b);
                let id = self.markers.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                out.markers.markers.push(Marker::line(&self.cfg.map_frame, id, k.stamp, a, &b, verified));
            }
            out.loops.push(l);
        }
        if out.loops.is_empty() {
            return;
        }
        self.metrics.loops.get_or_create(&Metrics::robot(&robot.name)).inc_by(out.loops.len() as u64);
        let _ = self.out.send(out);
    }
}

/// A camera message as received.
enum Camera {
    Raw(Image),
    Compressed(CompressedImage),
}

impl Camera {
    /// The bytes the server decodes: a lossless PNG of raw pixels (as the bag reader makes), or
    /// the compressed image when it is a JPEG or PNG.
    fn encoded(self) -> Result<Vec<u8>, String> {
        match self {
            Camera::Raw(m) => crate::bags::pixels::to_png(&m.raw()),
            Camera::Compressed(m) => match image::guess_format(&m.data) {
                Ok(image::ImageFormat::Jpeg | image::ImageFormat::Png) => Ok(m.data),
                _ => Err(format!(
                    "a CompressedImage of format '{}' that is neither JPEG nor PNG ({} bytes)",
                    m.format,
                    m.data.len()
                )),
            },
        }
    }
}

/// The gRPC client, made again after a failure that may have broken the connection.
struct Link {
    cfg: (String, Option<String>, TlsArgs),
    client: tokio::sync::Mutex<Option<Grpc>>,
}

impl Link {
    async fn get(&self) -> Result<Grpc, tonic::Status> {
        let mut c = self.client.lock().await;
        if let Some(c) = &*c {
            return Ok(c.clone());
        }
        let (addr, key, tls) = &self.cfg;
        let made = tokio::time::timeout(Duration::from_secs(5), client::grpc(addr, key.clone(), tls)).await;
        match made {
            Ok(Ok(g)) => {
                *c = Some(g.clone());
                Ok(g)
            }
            Ok(Err(e)) => Err(tonic::Status::unavailable(format!("{e:#}"))),
            Err(_) => Err(tonic::Status::unavailable(format!("connecting to {addr} took over 5 s"))),
        }
    }

    async fn reset(&self) {
        *self.client.lock().await = None;
    }
}

/// Whether a failed send is tried again: the server is away, busy or restarting (always), or a
/// failure that may be the connection's (a few times).
fn retried(code: tonic::Code, failures: u32) -> bool {
    use tonic::Code::*;
    match code {
        Unavailable | DeadlineExceeded | ResourceExhausted | Aborted | Cancelled => true,
        Unknown | Internal => failures < 5,
        _ => false,
    }
}

/// A robot's sender: its keyframes in order, each until the server has it.
async fn sender(fleet: Arc<Fleet>, robot: Arc<Robot>) {
    let mut session = fleet.session.clone();
    let Ok(id) = session.wait_for(|s| s.is_some()).await.map(|s| s.as_ref().cloned().unwrap_or_default()) else {
        return;
    };
    let label = Metrics::robot(&robot.name);
    let mut failures = 0u32;
    loop {
        let next = robot.queue.lock().head();
        let Some(k) = next else {
            robot.wake.notified().await;
            continue;
        };
        let mut request = tonic::Request::new(fleet.request(&id, &robot, &k));
        request.set_timeout(fleet.cfg.call_timeout);
        let answer = match fleet.link.get().await {
            Ok(mut c) => c.add_and_query(request).await.map(|r| r.into_inner()),
            Err(s) => Err(s),
        };
        match answer {
            Ok(a) => {
                if failures > 0 {
                    tracing::info!(robot = %robot.name, after = failures, "server reached again: sending");
                }
                failures = 0;
                robot.queue.lock().done(&k);
                fleet.metrics.sent.get_or_create(&label).inc();
                tracing::debug!(robot = %robot.name, frame = a.frame_id, stamp = k.stamp.seconds(), "keyframe stored");
                fleet.publish(&id, &robot, &k, &a);
            }
            Err(s) if retried(s.code(), failures) => {
                if failures == 0 {
                    tracing::warn!(robot = %robot.name, code = ?s.code(), error = s.message(),
                        "cannot send to the server: retrying the same keyframe until it answers");
                }
                failures += 1;
                fleet.metrics.retries.get_or_create(&label).inc();
                fleet.link.reset().await;
                let wait = Duration::from_millis(100u64 << failures.min(5)).min(Duration::from_secs(2));
                tokio::time::sleep(wait).await;
            }
            Err(s) => {
                failures = 0;
                robot.queue.lock().done(&k);
                fleet.reject(&robot, "server", &format!("{:?}: {}", s.code(), s.message()));
            }
        }
        fleet.metrics.queued.get_or_create(&label).set(robot.queue.lock().len() as i64);
    }
}

/// The session: opened if it exists, else made (with the first usable CameraInfo's camera when
/// `--camera-info` is given); retried while the server is away.
async fn open_session(fleet: &Fleet, camera: &mut watch::Receiver<Option<pb::Camera>>) -> Result<String> {
    let cfg = &fleet.cfg;
    let mut warned = false;
    loop {
        let mut c = match fleet.link.get().await {
            Ok(c) => c,
            Err(s) => {
                if !warned {
                    tracing::warn!(server = %cfg.server, error = s.message(), "server not reachable yet: retrying");
                    warned = true;
                }
                tokio::time::sleep(Duration::from_millis(500)).await;
                continue;
            }
        };
        match c.get_session(pb::GetSessionRequest { id: cfg.session.clone() }).await {
            Ok(s) => {
                let s = s.into_inner();
                tracing::info!(session = %s.id, frames = s.frames, model = %s.model, "session opened");
                return Ok(s.id);
            }
            Err(s) if s.code() == tonic::Code::NotFound => {}
            Err(s) if retried(s.code(), 0) => {
                fleet.link.reset().await;
                tokio::time::sleep(Duration::from_millis(500)).await;
                continue;
            }
            Err(s) => bail!("opening session {}: {:?}: {}", cfg.session, s.code(), s.message()),
        }
        let cam = match &cfg.camera_info {
            None => None,
            Some(pattern) => {
                let got = tokio::time::timeout(cfg.camera_wait, camera.wait_for(|c| c.is_some())).await;
                match got {
                    Ok(Ok(c)) => (*c).clone(),
                    _ => {
                        tracing::warn!(pattern, wait_s = cfg.camera_wait.as_secs_f64(),
                            "no usable CameraInfo yet: the session is made without a camera (loops carry no relative pose)");
                        None
                    }
                }
            }
        };
        let with_camera = cam.is_some();
        let request = pb::CreateSessionRequest {
            id: cfg.session.clone(),
            name: cfg.session.clone(),
            camera: cam,
            model: cfg.model.clone().unwrap_or_default(),
            ..Default::default()
        };
        match c.create_session(request).await {
            Ok(s) => {
                tracing::info!(session = %s.get_ref().id, camera = with_camera, "session created");
                return Ok(s.into_inner().id);
            }
            // Made meanwhile by another client.
            Err(s) if s.code() == tonic::Code::AlreadyExists => continue,
            Err(s) if retried(s.code(), 0) => {
                fleet.link.reset().await;
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
            Err(s) => bail!("creating session {}: {:?}: {}", cfg.session, s.code(), s.message()),
        }
    }
}

/// Runs the bridge until `stop` turns true.
pub async fn run(cfg: Config, mut stop: watch::Receiver<bool>) -> Result<()> {
    if cfg.images.is_empty() {
        bail!("no image topics: give --images (a topic, or a pattern such as /*/camera/image_raw/compressed)");
    }
    for p in cfg.images.iter().chain(&cfg.camera_info).chain(&cfg.odom) {
        Name::parse(&p.replace('*', "x")).map_err(|e| anyhow::anyhow!("'{p}' is not a ROS 2 topic name: {e:?}"))?;
    }
    Name::parse(&cfg.loops_topic).map_err(|e| anyhow::anyhow!("--loops-topic: {e:?}"))?;
    Name::parse(&cfg.markers_topic).map_err(|e| anyhow::anyhow!("--markers-topic: {e:?}"))?;
    let metrics = Arc::new(Metrics::default());
    if let Some(addr) = cfg.metrics_addr {
        let m = metrics.clone();
        tokio::spawn(async move {
            if let Err(e) = super::metrics::serve(addr, m).await {
                tracing::error!(error = %e, "metrics server stopped");
            }
        });
    }
    let (session_tx, session_rx) = watch::channel(None);
    let (camera_tx, mut camera_rx) = watch::channel(None);
    let (out_tx, out_rx) = mpsc::unbounded_channel();
    let fleet = Arc::new(Fleet {
        link: Link {
            cfg: (cfg.server.clone(), cfg.key.clone(), cfg.tls.clone()),
            client: tokio::sync::Mutex::new(None),
        },
        cfg,
        metrics,
        robots: Mutex::new(HashMap::new()),
        names: Mutex::new(Vec::new()),
        session: session_rx,
        out: out_tx,
        runtime: tokio::runtime::Handle::current(),
        markers: std::sync::atomic::AtomicI32::new(0),
    });
    let (ros_stop_tx, ros_stop_rx) = watch::channel(false);
    let (ros_done_tx, ros_done_rx) = tokio::sync::oneshot::channel();
    let ros_fleet = fleet.clone();
    std::thread::Builder::new().name("ros2".into()).spawn(move || {
        let _ = ros_done_tx.send(ros_thread(ros_fleet, out_rx, camera_tx, ros_stop_rx));
    })?;
    let mut ros_done = ros_done_rx;
    tokio::select! {
        r = open_session(&fleet, &mut camera_rx) => { session_tx.send_replace(Some(r?)); }
        r = &mut ros_done => return r.unwrap_or_else(|_| Err(anyhow::anyhow!("the ROS 2 thread ended"))),
        _ = stop.wait_for(|s| *s) => return Ok(()),
    }
    tokio::select! {
        r = &mut ros_done => r.unwrap_or_else(|_| Err(anyhow::anyhow!("the ROS 2 thread ended")))?,
        _ = stop.wait_for(|s| *s) => {}
    }
    let _ = ros_stop_tx.send(true);
    // The ROS thread's entities go before the process does (their peers hear them leave).
    let _ = tokio::time::timeout(Duration::from_secs(3), ros_done).await;
    for r in fleet.robots.lock().values() {
        let q = r.queue.lock().len();
        if q > 0 {
            tracing::warn!(robot = %r.name, unsent = q, "stopping with keyframes not yet stored");
        }
    }
    Ok(())
}

/// The ROS side, on a thread of its own (ros2-client's entities stay on it).
fn ros_thread(
    fleet: Arc<Fleet>,
    mut out: mpsc::UnboundedReceiver<Out>,
    camera: watch::Sender<Option<pb::Camera>>,
    mut stop: watch::Receiver<bool>,
) -> Result<()> {
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let local = tokio::task::LocalSet::new();
    local.block_on(&rt, async move {
        let cfg = &fleet.cfg;
        let context = Context::with_options(ContextOptions::new().domain_id(cfg.domain_id))
            .map_err(|e| anyhow::anyhow!("starting DDS (domain {}): {e:?}", cfg.domain_id))?;
        let mut node = context
            .new_node(
                NodeName::new("/", &cfg.node_name).map_err(|e| anyhow::anyhow!("--node-name: {e:?}"))?,
                NodeOptions::new().enable_rosout(false),
            )
            .map_err(|e| anyhow::anyhow!("making the ROS 2 node: {e:?}"))?;
        let spinner = node.spinner().map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let spin = tokio::task::spawn_local(async move {
            if let Err(e) = spinner.spin().await {
                tracing::error!(error = ?e, "the ROS 2 node's spinner stopped");
            }
        });
        // Loop closures: reliable, kept for a subscriber that joins late (a back end restarted).
        let reliable = QosProfile::publisher_default()
            .reliability_reliable(ros2_client::qos::WhenFull::DEFAULT)
            .durability(ros2_client::qos::Durability::TransientLocal)
            .history(ros2_client::qos::History::KeepLast { depth: 1000 });
        let loops: Publisher<LoopClosure> = publisher(&mut node, &cfg.loops_topic, ("loopd_msgs", "LoopClosure"), &reliable)?;
        let markers: Publisher<MarkerArray> =
            publisher(&mut node, &cfg.markers_topic, ("visualization_msgs", "MarkerArray"), &reliable)?;
        tracing::info!(node = %cfg.node_name, domain = cfg.domain_id, loops = %cfg.loops_topic, markers = %cfg.markers_topic,
            "ROS 2 node up");
        let camera = Arc::new(camera);
        let mut readers: Vec<tokio::task::JoinHandle<()>> = Vec::new();
        let mut subscribed: HashSet<String> = HashSet::new();
        let mut refused: HashSet<String> = HashSet::new();
        let mut tick = tokio::time::interval(Duration::from_millis(200));
        loop {
            tokio::select! {
                _ = tick.tick() => {
                    for t in context.discovered_topics() {
                        // Topics only ("rt/"), not services' request and reply topics.
                        let Some(name) = t.name.strip_prefix("rt").filter(|n| n.starts_with('/')) else { continue };
                        let name = name.to_string();
                        if subscribed.contains(&name) || refused.contains(&name) {
                            continue;
                        }
                        match subscribe(&fleet, &mut node, &name, &t.type_name, &camera) {
                            Ok(Some(reader)) => {
                                readers.push(reader);
                                subscribed.insert(name);
                            }
                            Ok(None) => {}
                            Err(e) => {
                                tracing::warn!(topic = %name, error = %e, "topic not subscribed");
                                refused.insert(name);
                            }
                        }
                    }
                }
                o = out.recv() => {
                    let Some(o) = o else { break };
                    for l in o.loops {
                        if let Err(e) = loops.async_publish(l).await {
                            tracing::warn!(error = ?e, "publishing a loop closure failed");
                        }
                    }
                    if !o.markers.markers.is_empty() {
                        if let Err(e) = markers.async_publish(o.markers).await {
                            tracing::warn!(error = ?e, "publishing markers failed");
                        }
                    }
                }
                _ = stop.wait_for(|s| *s) => break,
            }
        }
        // The readers first (each holds a DDS reader of the participant), then the node.
        for r in &readers {
            r.abort();
        }
        for r in readers {
            let _ = r.await;
        }
        // Dropping the node stops its spinner, which holds the node's own services: they go
        // before the participant does.
        drop((loops, markers, node));
        let _ = tokio::time::timeout(Duration::from_secs(2), spin).await;
        drop(context);
        Ok::<(), anyhow::Error>(())
    })
}

/// After a message that did not decode: a reader whose stream keeps failing must not spin.
async fn pause() {
    tokio::time::sleep(Duration::from_millis(5)).await;
}

fn publisher<M: serde::Serialize>(
    node: &mut Node,
    topic: &str,
    (package, ty): (&str, &str),
    qos: &QosProfile,
) -> Result<Publisher<M>> {
    let name = Name::parse(topic).map_err(|e| anyhow::anyhow!("'{topic}': {e:?}"))?;
    let t = node.create_topic(&name, MessageTypeName::new(package, ty), qos).map_err(|e| anyhow::anyhow!("{e:?}"))?;
    node.create_publisher(&t, None).map_err(|e| anyhow::anyhow!("publishing {topic}: {e:?}"))
}

fn subscription<M: 'static>(
    node: &mut Node,
    topic: &str,
    (package, ty): (&str, &str),
    qos: QosProfile,
) -> Result<Subscription<M>> {
    let name = Name::parse(topic).map_err(|e| anyhow::anyhow!("'{topic}': {e:?}"))?;
    let t = node.create_topic(&name, MessageTypeName::new(package, ty), &qos).map_err(|e| anyhow::anyhow!("{e:?}"))?;
    node.create_subscription(&t, Some(qos)).map_err(|e| anyhow::anyhow!("subscribing {topic}: {e:?}"))
}

/// A topic's reader task: each message to `on`, or (one that does not decode) a rejection of
/// `what`, counted and logged.
#[allow(clippy::too_many_arguments)]
fn reader<M: serde::de::DeserializeOwned + 'static>(
    node: &mut Node,
    topic: &str,
    (package, ty): (&str, &str),
    qos: QosProfile,
    fleet: &Arc<Fleet>,
    robot: &Arc<Robot>,
    what: &'static str,
    on: impl Fn(&Arc<Robot>, M) + 'static,
) -> Result<tokio::task::JoinHandle<()>> {
    let s: Subscription<M> = subscription(node, topic, (package, ty), qos)?;
    let (fleet, robot) = (fleet.clone(), robot.clone());
    let type_name = format!("{package}/{ty}");
    Ok(tokio::task::spawn_local(async move {
        loop {
            match s.async_take().await {
                Ok((m, _)) => on(&robot, m),
                Err(e) => {
                    fleet.reject(&robot, what, &format!("not a {type_name}: {e}"));
                    pause().await;
                }
            }
        }
    }))
}

/// Subscribes a discovered topic if a pattern names it: its reader task, None when no pattern does.
fn subscribe(
    fleet: &Arc<Fleet>,
    node: &mut Node,
    topic: &str,
    dds_type: &str,
    camera: &Arc<watch::Sender<Option<pb::Camera>>>,
) -> Result<Option<tokio::task::JoinHandle<()>>> {
    let cfg = &fleet.cfg;
    let is_image = cfg.images.iter().any(|p| matches(p, topic));
    let is_info = cfg.camera_info.as_ref().is_some_and(|p| matches(p, topic));
    let is_odom = cfg.odom.as_ref().is_some_and(|p| matches(p, topic));
    if !(is_image || is_info || is_odom) {
        return Ok(None);
    }
    let robot_name = match cfg.robot.clone().or_else(|| robot_of(topic, is_image)) {
        Some(r) => r,
        None => bail!("no robot: the topic is not in a robot's namespace (/ROBOT/.../NAME); give --robot"),
    };
    let kind = Kind::of(dds_type);
    let want = match (is_image, is_info, is_odom) {
        (true, _, _) => "sensor_msgs/Image or CompressedImage",
        (_, true, _) => "sensor_msgs/CameraInfo",
        _ => "nav_msgs/Odometry",
    };
    let fits = match kind {
        Some(Kind::Raw | Kind::Compressed) => is_image,
        Some(Kind::CameraInfo) => is_info,
        Some(Kind::Odometry) => is_odom,
        None => false,
    };
    let Some(kind) = kind.filter(|_| fits) else { bail!("its type is {dds_type}, not {want}") };
    let robot = fleet.robot(&robot_name);
    // Camera topics: best effort (what camera drivers publish; a reliable reader would not
    // match a best-effort writer), keep last --depth.
    let sensor = QosProfile::subscription_default().history(ros2_client::qos::History::KeepLast { depth: cfg.depth });
    let (f, t) = (fleet.clone(), topic.to_string());
    let reader = match kind {
        Kind::Raw => reader(node, topic, ("sensor_msgs", "Image"), sensor, fleet, &robot, "image", move |r, m| {
            f.on_image(r, &t, Camera::Raw(m))
        })?,
        Kind::Compressed => {
            reader(node, topic, ("sensor_msgs", "CompressedImage"), sensor, fleet, &robot, "image", move |r, m| {
                f.on_image(r, &t, Camera::Compressed(m))
            })?
        }
        Kind::CameraInfo => {
            let camera = camera.clone();
            reader(
                node,
                topic,
                ("sensor_msgs", "CameraInfo"),
                sensor,
                fleet,
                &robot,
                "camera_info",
                move |r, m: CameraInfo| match m.camera() {
                    Ok(c) => {
                        camera.send_if_modified(|held| {
                            let first = held.is_none();
                            if first {
                                tracing::info!(robot = %r.name, fx = c.fx, fy = c.fy, cx = c.cx, cy = c.cy,
                                    "camera intrinsics from CameraInfo");
                                *held = Some(c);
                            }
                            first
                        });
                    }
                    Err(why) => f.reject(r, "camera_info", &why),
                },
            )?
        }
        // Odometry: reliable or best effort writers both match a best-effort reader.
        Kind::Odometry => {
            reader(node, topic, ("nav_msgs", "Odometry"), sensor, fleet, &robot, "odometry", move |r, m| {
                f.on_odometry(r, &m)
            })?
        }
    };
    tracing::info!(topic, kind = ?kind, robot = %robot_name, "subscribed");
    Ok(Some(reader))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_match_one_name_per_star() {
        assert!(matches("/*/camera/image_raw/compressed", "/r1/camera/image_raw/compressed"));
        assert!(!matches("/*/camera/image_raw/compressed", "/fleet/r1/camera/image_raw/compressed"));
        assert!(matches("/desk/camera/image_raw", "/desk/camera/image_raw"));
        assert!(!matches("/desk/camera/image_raw", "/desk/camera/image_raw/compressed"));
    }

    #[test]
    fn a_topic_s_robot_is_its_namespace() {
        assert_eq!(robot_of("/r1/camera/image_raw", true).as_deref(), Some("r1"));
        assert_eq!(robot_of("/camera/image_raw", true), None, "a camera topic outside a namespace");
        assert_eq!(robot_of("/r1/odom", false).as_deref(), Some("r1"));
        assert_eq!(robot_of("/odom", false), None);
    }

    #[test]
    fn only_an_away_or_busy_server_is_retried_for_ever() {
        assert!(retried(tonic::Code::Unavailable, 1000));
        assert!(retried(tonic::Code::Unknown, 2) && !retried(tonic::Code::Unknown, 5));
        assert!(!retried(tonic::Code::InvalidArgument, 0));
        assert!(!retried(tonic::Code::FailedPrecondition, 0));
    }
}
