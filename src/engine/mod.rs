//! The inference engine: every API's frames go through it to the one model thread.
//!
//! `Engine` (this file) admits requests against a bound and decodes them on blocking workers;
//! `batcher` runs on the model thread and turns the queue into forward passes, fairly between
//! lanes (tenants, see [`Lane`]); `metrics` counts.
mod batcher;
pub mod metrics;

use crate::model::network::Variant;
use crate::model::preprocess::{ImageError, ImageLimits};
use crate::model::served::{About, InputSpec, Served};
use batcher::Job;
use metrics::EngineMetrics;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::mpsc::{self, SyncSender, TrySendError};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tch::Tensor;
use tokio::sync::{oneshot, Semaphore};

/// Whose work a request is, for fair batching: the batcher fills each batch from the lanes with
/// work queued in proportion to their weights. Requests take the lane of the task they run in
/// ([`in_lane`]); outside one they share the default lane (a server without tenants has only it).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Lane {
    pub name: Arc<str>,
    /// Share of forward passes against other lanes with work queued (at least 1).
    pub weight: u32,
}

impl Default for Lane {
    fn default() -> Self {
        Self { name: Arc::from(""), weight: 1 }
    }
}

tokio::task_local! {
    static LANE: Lane;
}

/// Runs `f` with every engine request it makes in `lane` (set once where a caller is known, so
/// the layers between need not pass it along).
pub async fn in_lane<F: std::future::Future>(lane: Lane, f: F) -> F::Output {
    LANE.scope(lane, f).await
}

/// The lane of the task this runs in (the default lane outside [`in_lane`]); a task spawned
/// from it takes its lane along with `in_lane(current_lane(), ..)`.
pub fn current_lane() -> Lane {
    LANE.try_with(Lane::clone).unwrap_or_default()
}

#[derive(Clone, Debug)]
pub struct EngineConfig {
    /// Most images in one forward pass.
    pub max_batch: usize,
    /// Longest a request waits for others to join its batch.
    pub max_delay: Duration,
    /// Requests admitted at once (decoding, queued or running); beyond it requests fail at once.
    pub queue_capacity: usize,
    /// Threads decoding and resizing images at once.
    pub decode_workers: usize,
    /// Run forward passes at start (`warm_up`: every batch shape on a CUDA device, batch 1 on the
    /// CPU) so that the first requests do not pay for allocation and autotuning.
    pub warm_up: bool,
    /// Pad each batch with zero inputs up to the next power of two (or `max_batch`), so only
    /// those few batch shapes ever run (`--batch-buckets`; None: on a CUDA device, off on the
    /// CPU). On a GPU every new input shape costs cuDNN a plan per convolution, about 0.4 s for
    /// this network on an H200, and a dynamic batcher meets every size from 1 to `max_batch`;
    /// padding costs the GPU little at these sizes and nothing on the CPU, where it stays off.
    pub batch_buckets: Option<bool>,
    /// While two or more lanes (tenants) sent work within `share_window`, each batch is cut to
    /// what runs in this time (measured per image; at least one image), so that one tenant's
    /// frame never waits for a long batch of another's (`--shared-batch-ms`; zero: off). A lane
    /// alone keeps whole batches.
    pub shared_batch_time: Duration,
    /// How long a lane counts as sharing the model after its last request.
    pub share_window: Duration,
}

impl Default for EngineConfig {
    fn default() -> Self {
        Self {
            max_batch: 32,
            max_delay: Duration::from_millis(5),
            queue_capacity: 256,
            decode_workers: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2),
            warm_up: true,
            batch_buckets: None,
            shared_batch_time: Duration::from_millis(100),
            share_window: Duration::from_secs(1),
        }
    }
}

#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
pub enum EngineError {
    #[error("inference queue is full ({0} requests admitted); retry later")]
    Overloaded(usize),
    #[error("inference engine has stopped")]
    Stopped,
    #[error("{0}")]
    Image(#[from] ImageError),
    #[error("inference failed: {0}")]
    Inference(String),
}

/// Cheap to clone; every clone feeds the same model thread, which ends when the last clone drops.
#[derive(Clone)]
pub struct Engine {
    tx: SyncSender<Job>,
    cfg: EngineConfig,
    decode: Arc<Semaphore>,
    metrics: Arc<EngineMetrics>,
    info: Arc<EngineInfo>,
}

/// What the engine computes, for clients and stored sessions.
#[derive(Debug, Clone)]
pub struct EngineInfo {
    /// The model's name in the server (sessions name it: `model`).
    pub name: String,
    pub about: About,
    /// The descriptor space of the full network (what sessions store).
    pub descriptor_id: String,
    /// Each ablation variant's descriptor space.
    pub variant_ids: Vec<(Variant, String)>,
    /// The full network's ids as earlier releases named them (`Model::earlier_descriptor_ids`):
    /// sessions created then by this same configuration stay usable.
    pub earlier_ids: Vec<String>,
    /// Length of the descriptors (2048, or a whitening's output size).
    pub dim: usize,
    pub input: InputSpec,
    pub limits: ImageLimits,
    pub device: String,
    pub dtype: String,
}

/// Counts a request as admitted until it is answered or dropped.
/// A place in the engine's queue ([`Engine::admit`]), held until the request's forward pass is
/// answered or the request is dropped.
pub struct Admission(Arc<EngineMetrics>);

impl Drop for Admission {
    fn drop(&mut self) {
        self.0.queued.fetch_sub(1, Relaxed);
    }
}

/// The batch sizes padded batches run at: powers of two below `max_batch`, and `max_batch`.
pub fn buckets(max_batch: usize) -> Vec<usize> {
    let mut b: Vec<usize> =
        std::iter::successors(Some(1usize), |n| n.checked_mul(2)).take_while(|&n| n < max_batch).collect();
    b.push(max_batch.max(1));
    b
}

/// Forward passes on zeros: on a CUDA device one at each batch size that will run (every bucket,
/// or batch 1 and `max_batch`): first-call allocations, kernels and cuDNN's plans for those
/// shapes. On the CPU batch 1 only (the thread's OpenMP team, the weights' first touch): there a
/// first batch of 32 ran as fast without its own warm-up (2.5 s either way), while warming it
/// up held readiness back 2.7 s and cost about 5 CPU-s per start (docs/performance.md, "Engine").
fn warm_up(model: &Served, max_batch: usize, buckets: bool) -> anyhow::Result<()> {
    let (width, height) = model.input().size();
    let input = Tensor::zeros([3, height as i64, width as i64], tch::kind::FLOAT_CPU);
    let sizes = match (model.device().is_cuda(), buckets) {
        (false, _) => vec![1],
        (true, true) => self::buckets(max_batch),
        (true, false) => vec![1, max_batch],
    };
    for n in sizes {
        let batch: Vec<Tensor> = (0..n).map(|_| input.shallow_clone()).collect();
        let _ = model.descriptors(&batch, Variant::FULL)?;
    }
    Ok(())
}

impl EngineInfo {
    /// The descriptor space of `variant`.
    pub fn variant_id(&self, variant: Variant) -> &str {
        self.variant_ids.iter().find(|(v, _)| *v == variant).map_or(&self.descriptor_id, |(_, id)| id)
    }

    /// Whether it computes `variant` (a TorchScript model computes its whole output only).
    pub fn has_variant(&self, variant: Variant) -> bool {
        self.variant_ids.iter().any(|(v, _)| *v == variant)
    }

    /// Whether a session of descriptor space `id` may take this engine's (full network) descriptors.
    pub fn compatible(&self, id: &str) -> bool {
        id == self.descriptor_id || self.earlier_ids.iter().any(|e| e == id)
    }
}

impl Engine {
    /// Moves the model onto its own thread and warms it up there (if asked for).
    /// One engine per served model: its own queue, batches, metrics and model thread.
    pub fn start(model: impl Into<Served>, cfg: EngineConfig, limits: ImageLimits) -> anyhow::Result<Self> {
        let model: Served = model.into();
        let cfg = EngineConfig {
            max_batch: cfg.max_batch.max(1),
            queue_capacity: cfg.queue_capacity.max(1),
            batch_buckets: Some(cfg.batch_buckets.unwrap_or(model.device().is_cuda())),
            ..cfg
        };
        let info = Arc::new(EngineInfo {
            name: model.name.clone(),
            about: model.about(),
            descriptor_id: model.descriptor_id(Variant::FULL),
            variant_ids: model.variants().into_iter().map(|v| (v, model.descriptor_id(v))).collect(),
            earlier_ids: model.earlier_descriptor_ids(),
            dim: model.dim(),
            input: model.input(),
            limits,
            device: model.device_name(),
            dtype: model.dtype(),
        });
        // The channel never fills before admission refuses: admission bounds it.
        let (tx, rx) = mpsc::sync_channel(cfg.queue_capacity);
        let metrics = Arc::new(EngineMetrics::default());
        let (m, c) = (metrics.clone(), cfg.clone());
        let (ready_tx, ready_rx) = mpsc::sync_channel(1);
        let device = info.device.clone();
        std::thread::Builder::new().name(format!("loopd-model-{}", info.name)).spawn(move || {
            // Warm up on the thread that will run every forward pass: its thread pool (OpenMP
            // team) and allocator caches are the ones that get used.
            let t = Instant::now();
            let warmed = if c.warm_up { warm_up(&model, c.max_batch, c.batch_buckets == Some(true)) } else { Ok(()) };
            let ok = warmed.is_ok();
            if ok && c.warm_up {
                tracing::info!(elapsed_ms = t.elapsed().as_millis() as u64, %device, "engine warmed up");
            }
            let _ = ready_tx.send(warmed);
            if ok {
                batcher::run(model, rx, c, m)
            }
        })?;
        ready_rx.recv().map_err(|_| anyhow::anyhow!("model thread ended during warm-up"))??;
        let decode = Arc::new(Semaphore::new(cfg.decode_workers.max(1)));
        Ok(Self { tx, cfg, decode, metrics, info })
    }

    pub fn info(&self) -> &EngineInfo {
        &self.info
    }

    pub fn metrics(&self) -> &Arc<EngineMetrics> {
        &self.metrics
    }

    pub fn config(&self) -> &EngineConfig {
        &self.cfg
    }

    /// Takes a place in the queue, or refuses at once (overloaded): a caller that would do other
    /// work on the request beside its forward pass (decoding, features) takes its place first, so
    /// that a refused request costs nothing but this check.
    pub fn admit(&self) -> Result<Admission, EngineError> {
        let before = self.metrics.queued.fetch_add(1, Relaxed);
        let admission = Admission(self.metrics.clone());
        if before as usize >= self.cfg.queue_capacity {
            self.metrics.rejected_overload.fetch_add(1, Relaxed);
            return Err(EngineError::Overloaded(self.cfg.queue_capacity));
        }
        Ok(admission)
    }

    /// Decodes `bytes` on a worker and returns the frame's unit descriptor.
    /// Dropping the future (a client gone, a gRPC deadline passed) before the forward pass costs
    /// no forward pass.
    pub async fn embed_image(&self, bytes: bytes::Bytes, variant: Variant) -> Result<Vec<f32>, EngineError> {
        self.embed_admitted(self.admit()?, bytes, variant).await
    }

    /// [`Engine::embed_image`] in a place already taken with [`Engine::admit`].
    pub async fn embed_admitted(
        &self,
        admission: Admission,
        bytes: bytes::Bytes,
        variant: Variant,
    ) -> Result<Vec<f32>, EngineError> {
        let admitted = Instant::now();
        let input = {
            let _permit = self.decode.acquire().await.map_err(|_| EngineError::Stopped)?;
            let (limits, input) = (self.info.limits, self.info.input.clone());
            tokio::task::spawn_blocking(move || input.prepare(&bytes, &limits))
                .await
                .map_err(|e| EngineError::Inference(format!("decoder worker failed: {e}")))??
        };
        self.submit(input, variant, admitted, admission).await
    }

    /// Embeds an already preprocessed input ([3, H, W], see `model::preprocess::to_input`): the
    /// engine benchmark measures batching without decoding through it.
    pub async fn embed_input(&self, input: Tensor, variant: Variant) -> Result<Vec<f32>, EngineError> {
        let admission = self.admit()?;
        self.submit(input, variant, Instant::now(), admission).await
    }

    async fn submit(
        &self,
        input: Tensor,
        variant: Variant,
        admitted: Instant,
        admission: Admission,
    ) -> Result<Vec<f32>, EngineError> {
        let (reply, rx) = oneshot::channel();
        let job = Job { input, variant, admitted, lane: current_lane(), reply };
        self.tx.try_send(job).map_err(|e| match e {
            TrySendError::Full(_) => EngineError::Overloaded(self.cfg.queue_capacity),
            TrySendError::Disconnected(_) => EngineError::Stopped,
        })?;
        let result = rx.await.map_err(|_| EngineError::Stopped)?;
        drop(admission);
        result
    }
}
