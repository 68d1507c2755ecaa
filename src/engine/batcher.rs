//! The model thread: take up to `max_batch` queued inputs, or what arrived within
//! `max_delay` of the first, and run them as one forward pass (Triton-style dynamic batching).
//! Queued inputs wait in one queue per lane (a tenant: `super::Lane`), and each batch is filled
//! from the lanes by deficit round robin, each lane's share of a batch in proportion to its
//! weight: a tenant that keeps the queue full delays another's frame by about one batch, not by
//! its whole backlog. A lane alone gets whole batches, as one queue would.
//!
//! One batch is also the wait itself: on a CPU a batch of 32 takes seconds. While more than one
//! lane has sent work within `share_window`, batches are cut to what runs in `shared_batch_time`
//! (from the measured time per image), so that a tenant's frame waits for short batches of the
//! others, not for a long one; a lane alone again gets whole batches once the others are gone
//! that long. On a GPU a whole batch runs within the time, so nothing changes there.
use super::metrics::EngineMetrics;
use super::{EngineConfig, EngineError, Lane};
use crate::model::network::Variant;
use crate::model::rows;
use crate::model::served::Served;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::mpsc::{Receiver, RecvTimeoutError, TryRecvError};
use std::sync::Arc;
use std::time::Instant;
use tch::Tensor;
use tokio::sync::oneshot;

pub(super) struct Job {
    pub input: Tensor,
    pub variant: Variant,
    pub admitted: Instant,
    pub lane: Lane,
    pub reply: oneshot::Sender<Result<Vec<f32>, EngineError>>,
}

/// One lane's waiting jobs and what it may still take this round.
struct LaneQueue {
    jobs: VecDeque<Job>,
    deficit: u64,
    weight: u64,
}

/// The queued jobs by lane, and the lanes with work in round-robin order.
#[derive(Default)]
pub(super) struct Fair {
    lanes: HashMap<Arc<str>, LaneQueue>,
    order: VecDeque<Arc<str>>,
    queued: usize,
    /// The lane whose turn a full batch cut short: the next batch goes on with it, without a
    /// new quantum, so that weights hold with batches smaller than a lane's weight.
    turn: Option<Arc<str>>,
}

impl Fair {
    pub(super) fn push(&mut self, job: Job) {
        let weight = u64::from(job.lane.weight.max(1));
        let name = job.lane.name.clone();
        let lane = match self.lanes.entry(name) {
            std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::hash_map::Entry::Vacant(e) => {
                self.order.push_back(e.key().clone());
                e.insert(LaneQueue { jobs: VecDeque::new(), deficit: 0, weight })
            }
        };
        lane.weight = weight; // a tenant's weight may change while it has work queued
        lane.jobs.push_back(job);
        self.queued += 1;
    }

    pub(super) fn len(&self) -> usize {
        self.queued
    }

    /// Up to `max` jobs by deficit round robin: each turn adds the lane's weight to its deficit
    /// and takes that many of its jobs; a batch that fills mid-turn leaves the turn to the next
    /// batch. A lane that empties leaves the round with no credit.
    pub(super) fn take(&mut self, max: usize) -> Vec<Job> {
        let mut batch = Vec::new();
        while batch.len() < max {
            let Some(name) = self.order.pop_front() else { break };
            let Some(lane) = self.lanes.get_mut(&name) else { continue };
            if self.turn.take().as_ref() != Some(&name) {
                lane.deficit += lane.weight;
            }
            while lane.deficit > 0 && batch.len() < max {
                let Some(job) = lane.jobs.pop_front() else { break };
                batch.push(job);
                lane.deficit -= 1;
                self.queued -= 1;
            }
            if lane.jobs.is_empty() {
                self.lanes.remove(&name);
            } else if lane.deficit > 0 {
                // The batch is full mid-turn: the next one goes on with this lane.
                self.order.push_front(name.clone());
                self.turn = Some(name);
            } else {
                self.order.push_back(name);
            }
        }
        batch
    }
}

/// The lanes that sent work lately, and the measured forward time per image: how large a batch
/// may be while lanes share the model (see the module's documentation).
struct Sharing {
    seen: HashMap<Arc<str>, Instant>,
    /// Seconds per image, a moving average over recent batches (0 until the first).
    per_image: f64,
}

impl Sharing {
    fn saw(&mut self, lane: &Arc<str>) {
        self.seen.insert(lane.clone(), Instant::now());
    }

    fn measured(&mut self, seconds: f64, images: usize) {
        let x = seconds / images.max(1) as f64;
        self.per_image = if self.per_image == 0.0 { x } else { 0.8 * self.per_image + 0.2 * x };
    }

    /// `max_batch` for a lane alone; while two or more have work queued or sent some within the
    /// window, what runs in `shared_batch_time` (at least one image).
    fn cap(&mut self, cfg: &EngineConfig, fair: &Fair) -> usize {
        let now = Instant::now();
        self.seen.retain(|lane, t| now.duration_since(*t) < cfg.share_window || fair.lanes.contains_key(lane));
        if self.seen.len() < 2 || self.per_image <= 0.0 || cfg.shared_batch_time.is_zero() {
            return cfg.max_batch;
        }
        ((cfg.shared_batch_time.as_secs_f64() / self.per_image) as usize).clamp(1, cfg.max_batch)
    }
}

pub(super) fn run(model: Served, rx: Receiver<Job>, cfg: EngineConfig, metrics: std::sync::Arc<EngineMetrics>) {
    let mut fair = Fair::default();
    let mut sharing = Sharing { seen: HashMap::new(), per_image: 0.0 };
    let bucket_max = if cfg.batch_buckets == Some(true) { Some(cfg.max_batch) } else { None };
    let push = |fair: &mut Fair, job: Job, sharing: &mut Sharing| {
        sharing.saw(&job.lane.name);
        fair.push(job);
    };
    loop {
        if fair.len() == 0 {
            match rx.recv() {
                Ok(job) => push(&mut fair, job, &mut sharing),
                Err(_) => return, // every sender gone: the engine was dropped
            }
        }
        // Everything sent so far joins its lane; then wait out the window for a full batch.
        let window_end = Instant::now() + cfg.max_delay;
        loop {
            match rx.try_recv() {
                Ok(job) => {
                    push(&mut fair, job, &mut sharing);
                    continue;
                }
                Err(TryRecvError::Empty) | Err(TryRecvError::Disconnected) => {}
            }
            if fair.len() >= sharing.cap(&cfg, &fair) {
                break;
            }
            match rx.recv_timeout(window_end.saturating_duration_since(Instant::now())) {
                Ok(job) => push(&mut fair, job, &mut sharing),
                Err(RecvTimeoutError::Timeout) | Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        let cap = sharing.cap(&cfg, &fair);
        if cap < cfg.max_batch {
            metrics.shared_batches.fetch_add(1, Relaxed);
        }
        let mut jobs = fair.take(cap);
        // A caller that gave up (client gone, gRPC deadline passed) costs no forward pass.
        let before = jobs.len();
        jobs.retain(|j| !j.reply.is_closed());
        metrics.cancelled.fetch_add((before - jobs.len()) as u64, Relaxed);
        while !jobs.is_empty() {
            // One forward pass per (input size, variant): inputs must stack.
            let (size, variant) = (jobs[0].input.size(), jobs[0].variant);
            let (group, rest): (Vec<Job>, Vec<Job>) =
                jobs.into_iter().partition(|j| j.input.size() == size && j.variant == variant);
            jobs = rest;
            let (started, n) = (Instant::now(), group.len());
            forward(&model, group, variant, &metrics, bucket_max);
            sharing.measured(started.elapsed().as_secs_f64(), n);
        }
    }
}

/// `bucket_max`: pad the batch with zero inputs up to its bucket (`super::buckets`); the padded
/// rows' descriptors are dropped (each row of a forward pass depends on its own input alone).
fn forward(model: &Served, group: Vec<Job>, variant: Variant, metrics: &EngineMetrics, bucket_max: Option<usize>) {
    let start = Instant::now();
    for j in &group {
        metrics.queue_wait.observe(start.duration_since(j.admitted).as_secs_f64());
    }
    let mut inputs: Vec<Tensor> = group.iter().map(|j| j.input.shallow_clone()).collect();
    let n = inputs.len();
    if let Some(max) = bucket_max {
        let size = super::buckets(max).into_iter().find(|&b| b >= n).unwrap_or(n);
        let zeros = inputs[0].zeros_like();
        inputs.resize_with(size, || zeros.shallow_clone());
        metrics.padded.fetch_add((size - n) as u64, Relaxed);
    }
    let result = model.descriptors(&inputs, variant).and_then(|d| rows(&d.narrow(0, 0, n as i64)));
    metrics.forward_seconds.observe(start.elapsed().as_secs_f64());
    metrics.batch_size.observe(group.len() as f64);
    match result {
        Ok(descs) => {
            metrics.images.fetch_add(group.len() as u64, Relaxed);
            for (job, d) in group.into_iter().zip(descs) {
                let _ = job.reply.send(Ok(d));
            }
        }
        Err(e) => {
            metrics.failed.fetch_add(group.len() as u64, Relaxed);
            tracing::error!(error = %e, batch = group.len(), "forward pass failed");
            for job in group {
                let _ = job.reply.send(Err(EngineError::Inference(format!("{e:#}"))));
            }
        }
    }
}
