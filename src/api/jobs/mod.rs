//! Offline sequences: many images in order, embedded in batches, added to a session and
//! searched for loops, as a background job whose progress can be polled. `request.rs` parses
//! what a client sends; this file admits, runs and records the jobs.
mod request;
pub use request::{job_defaults, SeqFrame, SequenceRequest};

use super::error::ApiError;
use super::service::{check_robot_id, make_thumbnail, Content, FrameInput, LoopService, QueryOverrides};
use super::wire::{JobState, JobStatus, LoopClosure};
use crate::auth::quota::Quota;
use crate::engine::{current_lane, in_lane, Lane};
use crate::store::{Session, Store};
use futures::StreamExt;
use parking_lot::Mutex;
use std::collections::HashMap;
use std::sync::Arc;
use tokio_util::task::AbortOnDropHandle;

/// Finished jobs whose status stays available.
const KEPT_JOBS: usize = 100;

/// How often a running job's record is rewritten (its progress and loops so far).
const SAVE_EVERY: std::time::Duration = std::time::Duration::from_secs(2);

pub struct Jobs {
    jobs: Mutex<HashMap<String, Arc<Mutex<JobStatus>>>>,
    next: std::sync::atomic::AtomicU64,
    pub max_running: usize,
    /// A keyed tenant's jobs running at once at most (`--max-jobs-per-tenant`); see [`Jobs::admit`].
    pub max_per_tenant: usize,
    /// Where job records are kept (they outlive the process).
    store: Arc<Store>,
}

/// A job's number: `job-N-SECRET` (or `job-N`, ids given before the secret part) -> N.
fn job_number(id: &str) -> u64 {
    let n = id.trim_start_matches("job-");
    n.split('-').next().unwrap_or(n).parse().unwrap_or(0)
}

/// A new job's id: its number (the order jobs were given in, for pruning) and 64 random bits, so
/// that an id names nothing another caller can guess (a tenant does not learn how many jobs others
/// ran, nor reach one by counting).
fn job_id(n: u64) -> String {
    format!("job-{n}-{:016x}", rand::random::<u64>())
}

impl Jobs {
    /// The jobs recorded in the store; those that were running when the server stopped are
    /// marked interrupted.
    pub fn new(max_running: usize, max_per_tenant: Option<usize>, store: Arc<Store>) -> Self {
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
        let max_running = max_running.max(1);
        let max_per_tenant = max_per_tenant.unwrap_or(max_running).clamp(1, max_running);
        Self { jobs: Mutex::new(jobs), next: next.into(), max_running, max_per_tenant, store }
    }

    /// Starts an offline sequence job on a session; its id is returned once its record is
    /// durable (it answers after a restart), before the job has done anything.
    /// `tenant`: the keyed tenant that sends it and its quota (its frames wait for its rate and
    /// count as its; its jobs are held to their share of the slots), None for the default tenant.
    pub async fn start_sequence(
        &self,
        service: &LoopService,
        s: &Session,
        seq: SequenceRequest,
        tenant: Option<(String, Arc<Quota>)>,
        lane: Lane,
    ) -> Result<String, ApiError> {
        service.check_space(s)?;
        check_robot_id(&seq.robot_id)?;
        let asked = seq.options.over(&job_defaults()).apply(&s.meta.default_query);
        service.check_confidence(s, &asked)?;
        let id = self.launch(service.clone(), s.meta.id.clone(), seq, tenant, lane).await?;
        service.store.durable_records().await?;
        Ok(id)
    }

    pub async fn job(&self, job_id: &str) -> Result<JobStatus, ApiError> {
        self.status(job_id).await?.ok_or_else(|| ApiError::NotFound(format!("job '{job_id}' not found")))
    }

    /// A job's status: this node's if it runs or ran the job here since it started, else (in a
    /// cluster) the log's, where a job still running on a node that is gone is interrupted.
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

    /// Launches a checked job; its id is returned once its record is kept (in a cluster, in the
    /// log). [`Jobs::start_sequence`] is the one way in.
    async fn launch(
        &self,
        service: LoopService,
        session: String,
        seq: SequenceRequest,
        tenant: Option<(String, Arc<Quota>)>,
        lane: Lane,
    ) -> Result<String, ApiError> {
        // In a cluster the log numbers jobs, so no two nodes give the same id.
        let n = match self.store.cluster_job_number().await? {
            Some(n) => n,
            None => self.next.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1,
        };
        let id = job_id(n);
        let status = self.admit(&id, &session, seq.frames.len(), tenant.as_ref().map(|(name, _)| name.as_str()))?;
        let first = status.lock().clone();
        if let Err(e) = self.store.keep_job(&id, n, &record(&first), KEPT_JOBS).await {
            self.jobs.lock().remove(&id);
            return Err(e.into());
        }
        // The job's frames share the model in its tenant's lane, as its requests do.
        tokio::spawn(in_lane(lane, run(service, session, seq, status, tenant.map(|(_, q)| q))));
        Ok(id)
    }

    /// Takes a new job into this node's list, unless too many run already: at most
    /// `max_running` in all and, for a keyed tenant, at most `max_per_tenant` of its own, and a
    /// tenant that runs a job already never takes the last free slot (it stays for a tenant
    /// that runs none, so one tenant's bulk work cannot shut the others out).
    fn admit(
        &self,
        id: &str,
        session: &str,
        total: usize,
        tenant: Option<&str>,
    ) -> Result<Arc<Mutex<JobStatus>>, ApiError> {
        let mut jobs = self.jobs.lock();
        let running: Vec<String> = jobs
            .values()
            .filter_map(|j| {
                let j = j.lock();
                matches!(j.state, JobState::Running).then(|| j.session_id.clone())
            })
            .collect();
        if running.len() >= self.max_running {
            return Err(ApiError::Overloaded(format!(
                "{} sequence jobs running; at most {}",
                running.len(),
                self.max_running
            )));
        }
        if let Some(tenant) = tenant {
            let mine = running.iter().filter(|s| tenant_of(s) == tenant).count();
            if mine >= self.max_per_tenant {
                return Err(ApiError::Overloaded(format!(
                    "tenant '{tenant}' runs {mine} sequence jobs; at most {} per tenant (retry when one ends)",
                    self.max_per_tenant
                )));
            }
            if mine > 0 && running.len() + 1 == self.max_running {
                return Err(ApiError::Overloaded(format!(
                    "tenant '{tenant}' runs {mine} sequence jobs and one job slot of {} is free: it is kept for \
                     a tenant that runs none (retry when one ends)",
                    self.max_running
                )));
            }
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

/// The tenant of a store session id (`Caller::store_id`): its prefix, else the default tenant.
fn tenant_of(store_id: &str) -> &str {
    store_id.split_once('/').map_or(crate::auth::caller::DEFAULT_TENANT, |(tenant, _)| tenant)
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

async fn run(
    service: LoopService,
    session: String,
    seq: SequenceRequest,
    status: Arc<Mutex<JobStatus>>,
    quota: Option<Arc<Quota>>,
) {
    // Held while the job runs: a cluster node drops a session it does not own once no one holds
    // it (owners.rs), and the job's frames go into it one by one.
    let held = service.store.session(&session).ok();
    // The session's model embeds its frames (a session of no served model: the default's, and
    // adding them refuses them).
    let engine = held.as_ref().and_then(|s| service.engine_of(s).ok()).unwrap_or(service.engine()).clone();
    let width = engine.config().max_batch.max(1);
    let thumbnails = held.as_ref().is_some_and(|s| s.meta.thumbnails);
    let camera = held.as_ref().and_then(|s| s.meta.camera);
    let limits = engine.info().limits;
    // The options every frame is queried with: the request's over the job's defaults over the
    // session's; the job's loops are the first candidates whose confidence reaches
    // `min_confidence` (default: the calibrator's loop confidence), every candidate kept.
    let defaults = held.as_ref().map(|s| s.meta.default_query.clone()).unwrap_or_default();
    let asked = seq.options.over(&job_defaults());
    let effective = asked.apply(&defaults);
    let calibrated = held.as_ref().and_then(|s| service.calibrator_of(&s.meta.descriptor_id));
    let min_confidence = asked.min_confidence.unwrap_or_else(|| calibrated.map_or(0.0, |c| c.loop_confidence));
    let opts = QueryOverrides { min_confidence: Some(0.0), ..asked };
    let features = effective.verify.geometric || service.keeps_features();
    // Embedding, feature extraction and thumbnails run ahead in batches, order kept; adding,
    // searching and checking go one frame at a time, exactly as `add_and_query` answers a robot.
    // Each frame ahead is a task of its own: it runs while this loop waits for a check. Polled
    // only from here, a frame ahead granted a verification worker (the pool's semaphore is
    // first come, first served) would hold it, unpolled, while this loop's check waited for
    // that worker: the job stopped for good. A job that ends early aborts the frames ahead it
    // drops (no embedding or extraction left running for nothing).
    let lane = current_lane();
    let mut embedded = futures::stream::iter(seq.frames.into_iter().enumerate())
        .map(|(i, f)| {
            let (engine, verifier) = (engine.clone(), service.verifier.clone());
            AbortOnDropHandle::new(tokio::spawn(in_lane(lane.clone(), async move {
                let embed = engine.embed_image(f.image.clone(), crate::model::network::Variant::FULL);
                let extract = async {
                    match features {
                        true => {
                            let mut x = verifier
                                .extract(f.image.clone(), limits, f.depth.is_some() || f.right.is_some())
                                .await
                                .map_err(crate::api::service::no_features)?;
                            // Depth of another size than the image: the frame goes without it.
                            if let Some(Err(e)) = f.depth.as_ref().map(|d| d.attach(&mut x)) {
                                tracing::warn!(frame = %f.name, error = %e, "bag depth image not used");
                            }
                            // A stereo pair's right image: depth at the left keypoints, as over
                            // the APIs; without a stereo camera or on a bad pair, none.
                            if let Some(right) = &f.right {
                                let rig = camera.as_ref().and_then(|c| c.stereo_rig(x.width, x.height));
                                let attached = match rig {
                                    None => Err("the session camera has no stereo".to_string()),
                                    Some(rig) => match (rig, verifier.extract(right.clone(), limits, false).await) {
                                        (Ok(rig), Ok(rf)) => rig.attach(&mut x, &rf).map_err(|e| e.to_string()),
                                        (Err(e), _) => Err(e.to_string()),
                                        (_, Err(e)) => Err(e.to_string()),
                                    },
                                };
                                if let Err(e) = attached {
                                    tracing::warn!(frame = %f.name, error = %e, "bag right image not used");
                                }
                            }
                            Ok(x)
                        }
                        false => Err("feature extraction is off".to_string()),
                    }
                };
                let (result, extracted, thumbnail) =
                    tokio::join!(embed, extract, make_thumbnail(&f.image, limits, thumbnails));
                let place = (f.robot_id, f.timestamp, f.pose);
                (i, f.name, place, result.map(|d| (d, extracted)), thumbnail)
            })))
        })
        .buffered(width);
    let mut names: HashMap<u64, (usize, String)> = HashMap::new();
    let mut failed = None;
    let mut saved = std::time::Instant::now();
    while let Some(prepared) = embedded.next().await {
        let (i, name, (robot_id, timestamp, pose), result, thumbnail) = match prepared {
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
            pose,
            metadata: Some(serde_json::json!({ "name": name, "index": i })),
            content: Content::Embedded { descriptor, features },
            thumbnail,
            idempotency_key: None,
        };
        // The tenant's rate: each frame waits for a token, as a request of it would need one.
        if let Some(q) = &quota {
            q.pace().await;
        }
        // Looked up for each frame: a session deleted while its job runs ends the job.
        let answer = match service.store.session(&session) {
            Ok(s) => service.add_and_query(&s, frame, &opts).await,
            Err(e) => Err(e.into()),
        };
        match answer {
            Ok((frame_id, matches)) => {
                if let Some(q) = &quota {
                    q.added(1);
                }
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
