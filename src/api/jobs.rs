//! Offline sequences: many images in order, embedded in batches, added to a session and
//! searched for loops, as a background job whose progress can be polled.
use super::error::ApiError;
use super::service::{check_robot_id, make_thumbnail, Content, FrameInput, LoopService, QueryOverrides};
use crate::bags::{self, Selection};
use crate::files::{is_image, natural_key};
use crate::store::query::{LoopQuery, Scope};
use crate::store::Store;
use bytes::Bytes;
use futures::StreamExt;
use parking_lot::Mutex;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::Arc;

/// Finished jobs whose status stays available.
const KEPT_JOBS: usize = 100;

/// How often a running job's record is rewritten (its progress and loops so far).
const SAVE_EVERY: std::time::Duration = std::time::Duration::from_secs(2);

/// Most frames one job may hold (bounded memory); the body size limit applies as well.
pub const MAX_JOB_FRAMES: usize = 100_000;

/// Most bytes of a decompressed ROS 1 bag chunk (rosbag records 768 KiB chunks).
pub const MAX_BAG_CHUNK_BYTES: usize = 256 << 20;

/// One frame of a sequence: an encoded image and, from a bag, its robot and stamp.
pub struct SeqFrame {
    pub name: String,
    pub image: Bytes,
    /// None: the request's robot id.
    pub robot_id: Option<String>,
    /// None: the frame's place in the sequence.
    pub timestamp: Option<f64>,
}

impl SeqFrame {
    fn file(name: String, image: Bytes) -> Self {
        Self { name, image, robot_id: None, timestamp: None }
    }
}

pub struct SequenceRequest {
    pub frames: Vec<SeqFrame>,
    pub robot_id: String,
    /// The job's query options over the job defaults ([`job_defaults`]) and the session's.
    pub options: QueryOverrides,
}

/// What a job asks of each frame unless the request says otherwise: its best candidate among
/// the robot's own frames more than 3 frames back, checked geometrically and by sequence (one
/// robot's trajectory), a loop when its confidence reaches the calibrator's `loop_confidence`.
pub fn job_defaults() -> QueryOverrides {
    QueryOverrides {
        k: Some(1),
        exclude_last_frames: Some(3),
        scope: Some(Scope::SameRobot),
        verify: Some(true),
        sequence: Some(true),
        ..Default::default()
    }
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct LoopClosure {
    pub query_index: usize,
    pub query_name: String,
    pub query_frame_id: u64,
    pub match_index: usize,
    pub match_name: String,
    pub match_frame_id: u64,
    /// Cosine similarity of the descriptors.
    pub score: f32,
    /// The calibrated confidence (absent without a calibrator for the session's descriptors).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confidence: Option<f32>,
    /// Geometric verification passed, with these inliers.
    #[serde(default)]
    pub verified: bool,
    #[serde(default)]
    pub inliers: u32,
    /// The sequence check's margin, when it ran.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sequence_margin: Option<f32>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Running,
    Done,
    Failed,
    /// The server stopped while the job ran: its first `done` frames are in the session and its
    /// loops so far are kept; the images are not, so a client restarts it by sending them again.
    Interrupted,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobStatus {
    pub job_id: String,
    pub session_id: String,
    pub state: JobState,
    pub total: usize,
    pub done: usize,
    pub loops: Vec<LoopClosure>,
    /// Frames that could not be used (bad image), by name.
    pub errors: Vec<String>,
}

fn untar(bytes: &[u8], out: &mut Vec<SeqFrame>) -> Result<(), ApiError> {
    let bad = |e: std::io::Error| ApiError::InvalidArgument(format!("not a readable tar archive: {e}"));
    let mut archive = tar::Archive::new(std::io::Cursor::new(bytes));
    let mut found = Vec::new();
    for entry in archive.entries().map_err(bad)? {
        let mut entry = entry.map_err(bad)?;
        let name = entry.path().map_err(bad)?.to_string_lossy().to_string();
        if !entry.header().entry_type().is_file() || !is_image(&name) {
            continue;
        }
        // Never sized from the header (it may claim terabytes): the entry can hold no more
        // than the archive, which the body limit bounds.
        let mut data = Vec::new();
        std::io::Read::read_to_end(&mut entry, &mut data).map_err(bad)?;
        found.push((name, Bytes::from(data)));
    }
    // An archive's own order is arbitrary: frames go in natural name order.
    found.sort_by_cached_key(|(n, _)| natural_key(n));
    out.extend(found.into_iter().map(|(name, data)| SeqFrame::file(name, data)));
    Ok(())
}

/// What a bag job reads, from the request's fields.
fn bag_selection(fields: &mut HashMap<String, String>) -> Result<Selection, ApiError> {
    let mut sel = Selection::default();
    if let Some(v) = fields.remove("topic") {
        sel.topics = v.split(',').map(str::trim).filter(|t| !t.is_empty()).map(String::from).collect();
    }
    if let Some(v) = fields.remove("every") {
        sel.every = v.parse().ok().filter(|n| *n >= 1).ok_or_else(|| bad_field("every", &v))?;
    }
    if let Some(v) = fields.remove("min_dt") {
        sel.min_dt =
            v.parse().ok().filter(|s: &f64| s.is_finite() && *s >= 0.0).ok_or_else(|| bad_field("min_dt", &v))?;
    }
    Ok(sel)
}

fn bad_field(k: &str, v: &str) -> ApiError {
    ApiError::InvalidArgument(format!("field {k}: bad value '{v}'"))
}

/// A query option given as a form field (the names of the JSON `options` of a query); false when
/// `k` names no option.
fn set_option(o: &mut QueryOverrides, k: &str, v: &str) -> Result<bool, ApiError> {
    fn num<T: std::str::FromStr>(k: &str, v: &str) -> Result<T, ApiError> {
        v.trim().parse().map_err(|_| bad_field(k, v))
    }
    fn real(k: &str, v: &str) -> Result<f32, ApiError> {
        num::<f32>(k, v).and_then(|x| if x.is_finite() { Ok(x) } else { Err(bad_field(k, v)) })
    }
    fn flag(k: &str, v: &str) -> Result<bool, ApiError> {
        match v.trim() {
            "true" | "1" | "on" => Ok(true),
            "false" | "0" | "off" => Ok(false),
            _ => Err(bad_field(k, v)),
        }
    }
    match k {
        "k" => o.k = Some(num(k, v)?),
        "min_score" => o.min_score = Some(real(k, v)?),
        "min_confidence" => o.min_confidence = Some(real(k, v)?),
        "exclude_last_frames" => o.exclude_last_frames = Some(num(k, v)?),
        "verify" => o.verify = Some(flag(k, v)?),
        "verify_candidates" => o.verify_candidates = Some(num(k, v)?),
        "min_inliers" => o.min_inliers = Some(num(k, v)?),
        "sequence" => o.sequence = Some(flag(k, v)?),
        "sequence_length" => o.sequence_length = Some(num(k, v)?),
        "min_sequence_margin" => o.min_sequence_margin = Some(real(k, v)?),
        _ => return Ok(false),
    }
    Ok(true)
}

/// A bag's frames (its parts in order: the files of a split rosbag2 bag).
fn from_bag(parts: &[Bytes], sel: &Selection) -> Result<Vec<SeqFrame>, ApiError> {
    let limits = bags::Limits { max_frames: MAX_JOB_FRAMES, max_chunk_bytes: MAX_BAG_CHUNK_BYTES };
    let parts: Vec<&[u8]> = parts.iter().map(|p| p.as_ref()).collect();
    let frames = bags::frames(&parts, sel, &limits).map_err(|e| match e {
        bags::BagError::Io(_) => ApiError::Internal(e.to_string()),
        e => ApiError::InvalidArgument(e.to_string()),
    })?;
    Ok(frames
        .into_iter()
        .map(|f| SeqFrame {
            name: format!("{}#{}", f.topic, f.index),
            image: Bytes::from(f.image),
            robot_id: f.robot_id,
            timestamp: Some(f.stamp),
        })
        .collect())
}

impl SequenceRequest {
    /// From a form's text fields, its files (part name, client file name, bytes) and, for a
    /// request that was not a form, its raw body (a tar archive or a bag, told by its first bytes).
    pub fn from_form(
        mut fields: HashMap<String, String>,
        files: Vec<(String, Option<String>, Bytes)>,
        body: Option<Bytes>,
    ) -> Result<Self, ApiError> {
        let mut frames = Vec::new();
        let mut bag = Vec::new();
        for (part, file_name, data) in files {
            match part.as_str() {
                "archive" => untar(&data, &mut frames)?,
                "bag" => bag.push(data),
                _ => frames.push(SeqFrame::file(file_name.unwrap_or_else(|| frames.len().to_string()), data)),
            }
        }
        match body {
            Some(body) if bags::is_bag(&body) => bag.push(body),
            Some(body) => untar(&body, &mut frames)?,
            None => {}
        }
        let selection = bag_selection(&mut fields)?;
        if !bag.is_empty() {
            if !frames.is_empty() {
                return Err(ApiError::InvalidArgument("send images or a bag, not both".into()));
            }
            frames = from_bag(&bag, &selection)?;
        } else if !selection.topics.is_empty() || selection.every != 1 || selection.min_dt != 0.0 {
            return Err(ApiError::InvalidArgument("topic, every and min_dt apply to bags only".into()));
        }
        if frames.is_empty() {
            return Err(ApiError::InvalidArgument(
                "a sequence needs images: multipart 'image' files, a tar archive or a bag".into(),
            ));
        }
        if frames.len() > MAX_JOB_FRAMES {
            return Err(ApiError::InvalidArgument(format!(
                "{} frames; at most {MAX_JOB_FRAMES} per job",
                frames.len()
            )));
        }
        let mut req = SequenceRequest { frames, robot_id: "sequence".into(), options: QueryOverrides::default() };
        // Order is applied last, whatever the field order.
        let order = fields.remove("order");
        for (k, v) in fields {
            match k.as_str() {
                "robot_id" if !v.is_empty() => {
                    // A robot named in the request is every frame's, whatever the topics say.
                    req.frames.iter_mut().for_each(|f| f.robot_id = None);
                    req.robot_id = v;
                }
                _ if set_option(&mut req.options, &k, &v)? => {}
                _ => return Err(bad_field(&k, &v)),
            }
        }
        // Checked here, before the upload becomes a job: a bad option is a 400 with nothing made.
        req.options.over(&job_defaults()).apply(&LoopQuery::default()).validate().map_err(ApiError::InvalidArgument)?;
        match order.as_deref() {
            Some("name") => req.frames.sort_by_cached_key(|f| natural_key(&f.name)),
            None | Some("sent") => {}
            Some(other) => return Err(ApiError::InvalidArgument(format!("field order: bad value '{other}'"))),
        }
        Ok(req)
    }
}

pub struct Jobs {
    jobs: Mutex<HashMap<String, Arc<Mutex<JobStatus>>>>,
    next: std::sync::atomic::AtomicU64,
    pub max_running: usize,
    /// Where job records are kept (they outlive the process).
    store: Arc<Store>,
}

fn job_number(id: &str) -> u64 {
    id.trim_start_matches("job-").parse().unwrap_or(0)
}

impl Jobs {
    /// The jobs recorded in the store; those that were running when the server stopped are
    /// marked interrupted.
    pub fn new(max_running: usize, store: Arc<Store>) -> Self {
        let mut jobs = HashMap::new();
        let records = store.jobs().unwrap_or_else(|e| {
            tracing::error!(error = %e, "job records not readable");
            Vec::new()
        });
        for (id, bytes) in records {
            let mut status: JobStatus = match serde_json::from_slice(&bytes) {
                Ok(s) => s,
                Err(e) => {
                    tracing::warn!(job = %id, error = %e, "job record not readable: skipped");
                    continue;
                }
            };
            if status.state == JobState::Running {
                status.state = JobState::Interrupted;
                if let Err(e) = store.put_job(&id, &record(&status)) {
                    tracing::warn!(job = %id, error = %e, "job record not saved");
                }
                tracing::warn!(job = %id, done = status.done, total = status.total, "job interrupted by a restart");
            }
            jobs.insert(id, Arc::new(Mutex::new(status)));
        }
        let next = jobs.keys().map(|k| job_number(k)).max().unwrap_or(0);
        Self { jobs: Mutex::new(jobs), next: next.into(), max_running: max_running.max(1), store }
    }

    /// A job's status: this node's if it runs or ran the job here since it started, else (in a
    /// cluster) the log's, where a job still running on a node that is gone is interrupted.
    /// Starts an offline sequence job on a session; its id is returned once its record is
    /// durable (it answers after a restart), before the job has done anything.
    pub async fn start_sequence(
        &self,
        service: &LoopService,
        session: &str,
        seq: SequenceRequest,
    ) -> Result<String, ApiError> {
        let s = service.store.session(session)?;
        service.check_space(&s)?;
        check_robot_id(&seq.robot_id)?;
        let asked = seq.options.over(&job_defaults()).apply(&s.meta.default_query);
        service.check_confidence(&s, &asked)?;
        let id = self.start(service.clone(), s.meta.id.clone(), seq).await?;
        service.store.durable_records().await?;
        Ok(id)
    }

    pub async fn job(&self, job_id: &str) -> Result<JobStatus, ApiError> {
        self.status(job_id).await?.ok_or_else(|| ApiError::NotFound(format!("job '{job_id}' not found")))
    }

    pub async fn status(&self, id: &str) -> Result<Option<JobStatus>, ApiError> {
        let here = self.jobs.lock().get(id).map(|j| j.lock().clone());
        if here.is_some() {
            return Ok(here);
        }
        let Some(logged) = self.store.logged_job(id).await? else { return Ok(None) };
        let mut status: JobStatus = serde_json::from_slice(&logged.record)
            .map_err(|e| ApiError::Internal(format!("job record not readable: {e}")))?;
        if status.state == JobState::Running && !logged.runner_alive {
            status.state = JobState::Interrupted;
        }
        Ok(Some(status))
    }

    /// Starts a job; its id is returned once its record is kept (in a cluster, in the log).
    pub async fn start(&self, service: LoopService, session: String, seq: SequenceRequest) -> Result<String, ApiError> {
        // In a cluster the log numbers jobs, so no two nodes give the same id.
        let n = match self.store.cluster_job_number().await? {
            Some(n) => n,
            None => self.next.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1,
        };
        let id = format!("job-{n}");
        let status = self.admit(&id, &session, seq.frames.len())?;
        let first = status.lock().clone();
        if let Err(e) = self.store.keep_job(&id, n, &record(&first), KEPT_JOBS).await {
            self.jobs.lock().remove(&id);
            return Err(e.into());
        }
        tokio::spawn(run(service, session, seq, status));
        Ok(id)
    }

    /// Takes a new job into this node's list, unless too many run already.
    fn admit(&self, id: &str, session: &str, total: usize) -> Result<Arc<Mutex<JobStatus>>, ApiError> {
        let mut jobs = self.jobs.lock();
        let running = jobs.values().filter(|j| matches!(j.lock().state, JobState::Running)).count();
        if running >= self.max_running {
            return Err(ApiError::Overloaded(format!("{running} sequence jobs running; at most {}", self.max_running)));
        }
        // Finished jobs are kept for polling, the oldest dropped beyond KEPT_JOBS (bounded memory).
        if jobs.len() >= KEPT_JOBS {
            let mut finished: Vec<(u64, String)> = jobs
                .iter()
                .filter(|(_, j)| !matches!(j.lock().state, JobState::Running))
                .map(|(k, _)| (job_number(k), k.clone()))
                .collect();
            finished.sort();
            for (_, k) in finished.iter().take(jobs.len() + 1 - KEPT_JOBS) {
                jobs.remove(k);
                if let Err(e) = self.store.remove_job(k) {
                    tracing::warn!(job = %k, error = %e, "job record not removed");
                }
            }
        }
        let status = Arc::new(Mutex::new(JobStatus {
            job_id: id.into(),
            session_id: session.into(),
            state: JobState::Running,
            total,
            done: 0,
            loops: Vec::new(),
            errors: Vec::new(),
        }));
        jobs.insert(id.into(), status.clone());
        Ok(status)
    }
}

fn record(status: &JobStatus) -> Vec<u8> {
    serde_json::to_vec(status).expect("a job status serialises")
}

/// Keeps the job's record (with sled durable with the next group commit, in a cluster in the
/// log); a failure is logged, the job goes on.
async fn save(store: &Store, status: &JobStatus) {
    if let Err(e) = store.keep_job(&status.job_id, job_number(&status.job_id), &record(status), KEPT_JOBS).await {
        tracing::warn!(job = %status.job_id, error = %e, "job record not saved");
    }
}

async fn run(service: LoopService, session: String, seq: SequenceRequest, status: Arc<Mutex<JobStatus>>) {
    let engine = service.engine.clone();
    let width = engine.config().max_batch.max(1);
    // Held while the job runs: a cluster node drops a session it does not own once no one holds
    // it (owners.rs), and the job's frames go into it one by one.
    let held = service.store.session(&session).ok();
    let thumbnails = held.as_ref().is_some_and(|s| s.meta.thumbnails);
    let limits = engine.info().limits;
    // The options every frame is queried with: the request's over the job's defaults over the
    // session's; the job's loops are the first candidates whose confidence reaches
    // `min_confidence` (default: the calibrator's loop confidence), every candidate kept.
    let defaults = held.as_ref().map(|s| s.meta.default_query.clone()).unwrap_or_default();
    let asked = seq.options.over(&job_defaults());
    let effective = asked.apply(&defaults);
    let calibrated = service
        .calibrator
        .as_ref()
        .filter(|_| held.as_ref().is_some_and(|s| engine.info().compatible(&s.meta.descriptor_id)));
    let min_confidence = asked.min_confidence.unwrap_or_else(|| calibrated.map_or(0.0, |c| c.loop_confidence));
    let opts = QueryOverrides { min_confidence: Some(0.0), ..asked };
    let features = effective.verify.geometric || service.keeps_features();
    // Embedding, feature extraction and thumbnails run ahead in batches, order kept; adding,
    // searching and checking go one frame at a time, exactly as `add_and_query` answers a robot.
    // Each frame ahead is a task of its own: it runs while this loop waits for a check. Polled
    // only from here, a frame ahead granted a verification worker (the pool's semaphore is
    // first come, first served) would hold it, unpolled, while this loop's check waited for
    // that worker: the job stopped for good.
    let mut embedded = futures::stream::iter(seq.frames.into_iter().enumerate())
        .map(|(i, f)| {
            let (engine, verifier) = (engine.clone(), service.verifier.clone());
            tokio::spawn(async move {
                let embed = engine.embed_image(f.image.clone(), crate::model::network::Variant::FULL);
                let extract = async {
                    match features {
                        true => {
                            verifier.extract(f.image.clone(), limits).await.map_err(|e| format!("no features: {e}"))
                        }
                        false => Err("feature extraction is off".to_string()),
                    }
                };
                let (result, extracted, thumbnail) =
                    tokio::join!(embed, extract, make_thumbnail(&f.image, limits, thumbnails));
                (i, f.name, f.robot_id, f.timestamp, result.map(|d| (d, extracted)), thumbnail)
            })
        })
        .buffered(width);
    let mut names: HashMap<u64, (usize, String)> = HashMap::new();
    let mut failed = None;
    let mut saved = std::time::Instant::now();
    while let Some(prepared) = embedded.next().await {
        let (i, name, robot_id, timestamp, result, thumbnail) = match prepared {
            Ok(p) => p,
            Err(e) => {
                failed = Some(format!("preparing a frame: {e}"));
                break;
            }
        };
        if saved.elapsed() >= SAVE_EVERY {
            // With sled, durable with the next frame's commit.
            let now = status.lock().clone();
            save(&service.store, &now).await;
            saved = std::time::Instant::now();
        }
        let (descriptor, features) = match result {
            Ok(d) => d,
            Err(e) => {
                let mut s = status.lock();
                s.errors.push(format!("{name}: {e}"));
                s.done += 1;
                continue;
            }
        };
        let frame = FrameInput {
            robot_id: robot_id.unwrap_or_else(|| seq.robot_id.clone()),
            timestamp: timestamp.or(Some(i as f64)),
            frame_id: None,
            pose: None,
            metadata: Some(serde_json::json!({ "name": name, "index": i })),
            content: Content::Embedded { descriptor, features },
            thumbnail,
        };
        match service.add_and_query(&session, frame, &opts).await {
            Ok((frame_id, matches)) => {
                let mut s = status.lock();
                let first = matches.first().filter(|c| c.confidence.unwrap_or(1.0) >= min_confidence);
                if let Some(c) = first {
                    if let Some((mi, mname)) = names.get(&c.m.frame_id) {
                        let v = c.verification.as_ref();
                        s.loops.push(LoopClosure {
                            query_index: i,
                            query_name: name.clone(),
                            query_frame_id: frame_id,
                            match_index: *mi,
                            match_name: mname.clone(),
                            match_frame_id: c.m.frame_id,
                            score: c.m.score,
                            confidence: c.confidence,
                            verified: v.is_some_and(|v| v.verified),
                            inliers: v.map_or(0, |v| v.inliers as u32),
                            sequence_margin: c.sequence.as_ref().map(|q| q.margin),
                        });
                    }
                }
                names.insert(frame_id, (i, name));
                s.done += 1;
            }
            Err(e) => {
                failed = Some(format!("{name}: {e}"));
                break;
            }
        }
    }
    let finished = {
        let mut s = status.lock();
        match failed {
            Some(e) => {
                s.errors.push(e);
                s.state = JobState::Failed;
            }
            None => s.state = JobState::Done,
        }
        tracing::info!(job = %s.job_id, frames = s.done, loops = s.loops.len(), "sequence job finished");
        s.clone()
    };
    save(&service.store, &finished).await;
    if let Err(e) = service.store.durable_records().await {
        tracing::warn!(job = %finished.job_id, error = %e, "job record not made durable");
    }
}
