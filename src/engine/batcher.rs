//! Dynamic batching: take up to `max_batch` queued inputs, or what arrived within
//! `max_delay` of the first, and run them as one forward pass on the model thread.
use crate::model::network::Variant;
use crate::model::{rows, Model};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::time::{Duration, Instant};
use tch::Tensor;
use tokio::sync::oneshot;

#[derive(Clone, Debug)]
pub struct EngineConfig {
    pub max_batch: usize,
    pub max_delay: Duration,
    /// Requests waiting for the model; beyond this a request fails at once (overload).
    pub queue_capacity: usize,
}

impl Default for EngineConfig {
    fn default() -> Self {
        Self { max_batch: 32, max_delay: Duration::from_millis(5), queue_capacity: 256 }
    }
}

#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
pub enum EngineError {
    #[error("inference queue is full ({0} requests waiting); retry later")]
    Overloaded(usize),
    #[error("inference engine has stopped")]
    Stopped,
    #[error("inference failed: {0}")]
    Inference(String),
}

struct Job {
    input: Tensor,
    variant: Variant,
    reply: oneshot::Sender<Result<Vec<f32>, EngineError>>,
}

/// Cheap to clone; every clone feeds the same model thread.
#[derive(Clone)]
pub struct Engine {
    tx: SyncSender<Job>,
    capacity: usize,
    pub descriptor_id: String,
    pub preprocess: crate::model::config::Preprocess,
}

impl Engine {
    /// Moves the model onto its own thread. The thread ends when every `Engine` clone is dropped.
    pub fn start(model: Model, cfg: EngineConfig) -> Self {
        let (tx, rx) = mpsc::sync_channel(cfg.queue_capacity);
        let descriptor_id = model.config.descriptor_id();
        let preprocess = model.config.preprocess.clone();
        let capacity = cfg.queue_capacity;
        std::thread::Builder::new()
            .name("loopd-model".into())
            .spawn(move || run(model, rx, cfg))
            .expect("spawning the model thread");
        Self { tx, capacity, descriptor_id, preprocess }
    }

    /// Queues one preprocessed input ([3, H, W]) and waits for its unit descriptor.
    pub async fn embed(&self, input: Tensor, variant: Variant) -> Result<Vec<f32>, EngineError> {
        let (reply, rx) = oneshot::channel();
        self.tx.try_send(Job { input, variant, reply }).map_err(|e| match e {
            TrySendError::Full(_) => EngineError::Overloaded(self.capacity),
            TrySendError::Disconnected(_) => EngineError::Stopped,
        })?;
        rx.await.map_err(|_| EngineError::Stopped)?
    }
}

fn run(model: Model, rx: Receiver<Job>, cfg: EngineConfig) {
    while let Ok(first) = rx.recv() {
        let deadline = Instant::now() + cfg.max_delay;
        let mut jobs = vec![first];
        while jobs.len() < cfg.max_batch {
            match rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
                Ok(j) => jobs.push(j),
                Err(RecvTimeoutError::Timeout) | Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        // A caller that gave up costs no forward pass.
        jobs.retain(|j| !j.reply.is_closed());
        while !jobs.is_empty() {
            // One forward pass per (size, variant) group.
            let (size, variant) = (jobs[0].input.size(), jobs[0].variant);
            let (group, rest): (Vec<Job>, Vec<Job>) =
                jobs.into_iter().partition(|j| j.input.size() == size && j.variant == variant);
            jobs = rest;
            let inputs: Vec<Tensor> = group.iter().map(|j| j.input.shallow_clone()).collect();
            match model.descriptors(&inputs, variant).and_then(|d| rows(&d)) {
                Ok(descs) => {
                    for (job, d) in group.into_iter().zip(descs) {
                        let _ = job.reply.send(Ok(d));
                    }
                }
                Err(e) => {
                    for job in group {
                        let _ = job.reply.send(Err(EngineError::Inference(format!("{e:#}"))));
                    }
                }
            }
        }
    }
}
