//! The model thread: take up to `max_batch` queued inputs, or what arrived within
//! `max_delay` of the first, and run them as one forward pass (Triton-style dynamic batching).
use super::metrics::EngineMetrics;
use super::{EngineConfig, EngineError};
use crate::model::network::Variant;
use crate::model::{rows, Model};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::Instant;
use tch::Tensor;
use tokio::sync::oneshot;

pub(super) struct Job {
    pub input: Tensor,
    pub variant: Variant,
    pub admitted: Instant,
    pub reply: oneshot::Sender<Result<Vec<f32>, EngineError>>,
}

pub(super) fn run(model: Model, rx: Receiver<Job>, cfg: EngineConfig, metrics: std::sync::Arc<EngineMetrics>) {
    while let Ok(first) = rx.recv() {
        let window_end = Instant::now() + cfg.max_delay;
        let mut jobs = vec![first];
        while jobs.len() < cfg.max_batch {
            match rx.recv_timeout(window_end.saturating_duration_since(Instant::now())) {
                Ok(j) => jobs.push(j),
                Err(RecvTimeoutError::Timeout) | Err(RecvTimeoutError::Disconnected) => break,
            }
        }
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
            let bucket_max = if cfg.batch_buckets == Some(true) { Some(cfg.max_batch) } else { None };
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
