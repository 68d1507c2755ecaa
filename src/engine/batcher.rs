//! The model thread: take up to `max_batch` queued inputs, or what arrived within
//! `max_delay` of the first, and run them as one forward pass (Triton-style dynamic batching).
//! Queued inputs wait in one queue per lane (a tenant: `super::Lane`), and each batch is filled
//! from the lanes by deficit round robin, each lane's share of a batch in proportion to its
//! weight: a tenant that keeps the queue full delays another's frame by about one batch, not by
//! its whole backlog. A lane alone gets whole batches, as one queue would.
use super::metrics::EngineMetrics;
use super::{EngineConfig, EngineError, Lane};
use crate::model::network::Variant;
use crate::model::{rows, Model};
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

    /// Up to `max` jobs by deficit round robin: each visit adds the lane's weight to its
    /// deficit and takes that many of its jobs (fewer if the batch fills; the rest of its
    /// deficit stays for its next visit). A lane that empties leaves the round with no credit.
    pub(super) fn take(&mut self, max: usize) -> Vec<Job> {
        let mut batch = Vec::new();
        while batch.len() < max {
            let Some(name) = self.order.pop_front() else { break };
            let Some(lane) = self.lanes.get_mut(&name) else { continue };
            lane.deficit += lane.weight;
            while lane.deficit > 0 && batch.len() < max {
                let Some(job) = lane.jobs.pop_front() else { break };
                batch.push(job);
                lane.deficit -= 1;
                self.queued -= 1;
            }
            if lane.jobs.is_empty() {
                self.lanes.remove(&name);
            } else {
                self.order.push_back(name);
            }
        }
        batch
    }
}

pub(super) fn run(model: Model, rx: Receiver<Job>, cfg: EngineConfig, metrics: std::sync::Arc<EngineMetrics>) {
    let mut fair = Fair::default();
    let bucket_max = if cfg.batch_buckets == Some(true) { Some(cfg.max_batch) } else { None };
    loop {
        if fair.len() == 0 {
            match rx.recv() {
                Ok(job) => fair.push(job),
                Err(_) => return, // every sender gone: the engine was dropped
            }
        }
        // Everything sent so far joins its lane; then wait out the window for a full batch.
        let window_end = Instant::now() + cfg.max_delay;
        loop {
            match rx.try_recv() {
                Ok(job) => {
                    fair.push(job);
                    continue;
                }
                Err(TryRecvError::Empty) | Err(TryRecvError::Disconnected) => {}
            }
            if fair.len() >= cfg.max_batch {
                break;
            }
            match rx.recv_timeout(window_end.saturating_duration_since(Instant::now())) {
                Ok(job) => fair.push(job),
                Err(RecvTimeoutError::Timeout) | Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        let mut jobs = fair.take(cfg.max_batch);
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
            forward(&model, group, variant, &metrics, bucket_max);
        }
    }
}

/// `bucket_max`: pad the batch with zero inputs up to its bucket (`super::buckets`); the padded
/// rows' descriptors are dropped (each row of a forward pass depends on its own input alone).
fn forward(model: &Model, group: Vec<Job>, variant: Variant, metrics: &EngineMetrics, bucket_max: Option<usize>) {
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
