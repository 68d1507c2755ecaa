//! GPU figures in one binary, run by `scripts/gpu-check` (README "GPU"): forward passes at each
//! precision and batch, the engine under concurrent JPEG clients, training steps with and without
//! autocast. Prints one JSON object per row on stdout (`scripts/gpu/report.py` makes the table;
//! GPU memory and utilisation come from nvidia-smi samples over each row's `t0..t1`); progress on
//! stderr. Random weights: speed does not depend on their values, and the 100 MB ImageNet file
//! need not travel to the GPU machine. The forward section also writes the weights, a batch of
//! inputs and loopd's descriptors of it into GPU_WORK, for the PyTorch peer
//! (`scripts/gpu/peer.py`) to time the same network and compare its descriptors.
//!
//! usage: gpu forward|engine|train
//! env: GPU_DEVICE (cuda, cuda:N or cpu; default cuda), GPU_DTYPES (default "f32,f16,bf16"),
//!      GPU_BATCHES (default "1,8,32,128"), GPU_SECONDS (per cell, default 1.5), GPU_SIDE (input
//!      side, default 224), GPU_WORK (default "gpu-work"), GPU_IMAGES (JPEG folder for the
//!      engine), GPU_CLIENTS (default "1,16,64"), GPU_ENGINE_DTYPE (default f16),
//!      GPU_ENGINE_BATCH (max_batch, default 64), GPU_ENGINE_BUCKETS (batch buckets, default
//!      "on,off"), GPU_TRAIN_BATCH (places x 4 views, default 32),
//!      GPU_AUTOCAST (default "f32,bf16")
use loopd::engine::{Engine, EngineConfig};
use loopd::model::config::{ModelConfig, Variant};
use loopd::model::device::{parse_device, DType};
use loopd::model::preprocess::ImageLimits;
use loopd::model::weights::{named_tensors, WeightFile};
use loopd::model::Model;
use loopd::train::loss::MsParams;
use loopd::train::run::{optimizer, step, Recipe};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tch::{Device, Kind, Tensor};

fn env(name: &str, default: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| default.to_string())
}

fn list<T: std::str::FromStr>(name: &str, default: &str) -> anyhow::Result<Vec<T>>
where
    T::Err: std::fmt::Display,
{
    env(name, default)
        .split(',')
        .map(|s| s.trim().parse::<T>().map_err(|e| anyhow::anyhow!("{name}: '{s}': {e}")))
        .collect()
}

fn dtype(s: &str) -> anyhow::Result<DType> {
    Ok(serde_json::from_value(s.trim().into())?)
}

fn now() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

fn pct(lat: &mut [f64], p: f64) -> f64 {
    lat.sort_by(f64::total_cmp);
    lat[((lat.len() as f64 - 1.0) * p).round() as usize]
}

/// Waits for the device's queued work (timings end when the GPU has finished, not when the
/// kernels were queued).
fn sync(device: Device) {
    if let Device::Cuda(n) = device {
        tch::Cuda::synchronize(n as i64);
    }
}

struct Ctx {
    device: Device,
    config: ModelConfig,
    budget: Duration,
    work: PathBuf,
}

impl Ctx {
    fn weights(&self) -> PathBuf {
        self.work.join("weights.safetensors")
    }

    /// The random network, written once in f32 so every precision and the PyTorch peer load
    /// the same numbers.
    fn write_weights(&self) -> anyhow::Result<()> {
        let cpu = Model::new(self.config.clone(), Device::Cpu, DType::F32)?;
        cpu.randomize(0, false);
        let meta = [("stride_layout".to_string(), "v1".to_string())].into_iter().collect();
        WeightFile::write(&self.weights(), &named_tensors(cpu.var_store()), meta)
    }

    fn model(&self, dtype: DType) -> anyhow::Result<Model> {
        if !self.weights().is_file() {
            self.write_weights()?;
        }
        Ok(Model::load(&self.weights(), self.config.clone(), self.device, dtype)?.0)
    }
}

/// Times `f` (one call handles `items` images) for the budget after two warm-up calls:
/// (images/s, per-call latencies in ms, t0, t1).
fn timed(
    ctx: &Ctx,
    items: usize,
    mut f: impl FnMut() -> anyhow::Result<()>,
) -> anyhow::Result<(f64, Vec<f64>, f64, f64)> {
    f()?;
    f()?;
    sync(ctx.device);
    let t0 = now();
    let start = Instant::now();
    let mut lat = Vec::new();
    while lat.len() < 5 || (start.elapsed() < ctx.budget && lat.len() < 2000) {
        let t = Instant::now();
        f()?;
        sync(ctx.device);
        lat.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let rate = (items * lat.len()) as f64 / start.elapsed().as_secs_f64();
    Ok((rate, lat, t0, now()))
}

fn forward(ctx: &Ctx) -> anyhow::Result<()> {
    let dtypes: Vec<DType> = env("GPU_DTYPES", "f32,f16,bf16").split(',').map(dtype).collect::<Result<_, _>>()?;
    let batches: Vec<usize> = list("GPU_BATCHES", "1,8,32,128")?;
    ctx.write_weights()?;
    let side = ctx.config.preprocess.width as i64;
    tch::manual_seed(0);
    let check: Vec<Tensor> = (0..4).map(|_| Tensor::randn([3, side, side], tch::kind::FLOAT_CPU)).collect();
    WeightFile::write(
        &ctx.work.join("inputs.safetensors"),
        &[("inputs".to_string(), Tensor::stack(&check, 0))],
        Default::default(),
    )?;
    for &dt in &dtypes {
        let model = ctx.model(dt)?;
        let mut kept = Vec::new();
        for v in [Variant::FULL, Variant::BACKBONE] {
            kept.push((v.name().to_string(), model.descriptors(&check, v)?));
        }
        let name = format!("{dt:?}").to_lowercase();
        WeightFile::write(&ctx.work.join(format!("loopd-{name}.safetensors")), &kept, Default::default())?;
        for &b in &batches {
            let inputs: Vec<Tensor> = (0..b).map(|_| Tensor::randn([3, side, side], tch::kind::FLOAT_CPU)).collect();
            for v in [Variant::BACKBONE, Variant::FULL] {
                eprintln!("forward {name} batch {b} {}", v.name());
                let (rate, mut lat, t0, t1) = timed(ctx, b, || {
                    let d = model.descriptors(&inputs, v)?; // on the CPU: the device has finished
                    anyhow::ensure!(d.size()[0] == b as i64, "batch of {b} gave {:?}", d.size());
                    Ok(())
                })?;
                println!(
                    "{}",
                    json!({"section": "forward", "impl": "loopd", "dtype": name, "batch": b, "variant": v.name(),
                           "img_s": rate, "p50_ms": pct(&mut lat, 0.5), "calls": lat.len(), "t0": t0, "t1": t1})
                );
            }
        }
    }
    Ok(())
}

/// JPEGs of a folder, read once (the clients send them round robin).
fn jpegs(dir: &Path) -> anyhow::Result<Vec<bytes::Bytes>> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| anyhow::anyhow!("GPU_IMAGES {}: {e}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "jpg" || x == "jpeg"))
        .collect();
    paths.sort();
    paths.truncate(64);
    anyhow::ensure!(!paths.is_empty(), "no JPEG in {}", dir.display());
    paths.iter().map(|p| Ok(std::fs::read(p)?.into())).collect()
}

async fn engine(ctx: &Ctx) -> anyhow::Result<()> {
    let images = jpegs(Path::new(&env("GPU_IMAGES", "../shared/data/corridor/query")))?;
    let dt = dtype(&env("GPU_ENGINE_DTYPE", "f16"))?;
    let max_batch: usize = env("GPU_ENGINE_BATCH", "64").parse()?;
    let cells: Vec<(String, usize)> = env("GPU_ENGINE_BUCKETS", "on,off")
        .split(',')
        .flat_map(|b| {
            list::<usize>("GPU_CLIENTS", "1,16,64").unwrap_or_default().into_iter().map(move |c| (b.to_string(), c))
        })
        .collect();
    for (buckets, clients) in cells {
        eprintln!("engine {clients} clients, batch buckets {buckets}");
        let cfg = EngineConfig {
            max_batch,
            max_delay: Duration::from_millis(2),
            queue_capacity: 4096,
            batch_buckets: Some(buckets == "on"),
            ..Default::default()
        };
        let workers = cfg.decode_workers;
        let engine = Engine::start(ctx.model(dt)?, cfg, ImageLimits::default())?;
        // One untimed round so every client count starts warm.
        for b in images.iter().take(clients.min(images.len())) {
            engine.embed_image(b.clone(), Variant::FULL).await?;
        }
        let m = engine.metrics().clone();
        let (count0, sum0) = (m.batch_size.count(), m.batch_size.sum());
        let t0 = now();
        let start = Instant::now();
        let budget = ctx.budget * 2;
        let tasks: Vec<_> = (0..clients)
            .map(|c| {
                let (e, images) = (engine.clone(), images.clone());
                tokio::spawn(async move {
                    let mut lat = Vec::new();
                    let mut i = c;
                    while start.elapsed() < budget || lat.len() < 2 {
                        let t = Instant::now();
                        e.embed_image(images[i % images.len()].clone(), Variant::FULL).await?;
                        lat.push(t.elapsed().as_secs_f64() * 1e3);
                        i += clients;
                    }
                    anyhow::Ok(lat)
                })
            })
            .collect();
        let mut lat = Vec::new();
        for t in tasks {
            lat.extend(t.await??);
        }
        let rate = lat.len() as f64 / start.elapsed().as_secs_f64();
        let t1 = now();
        let batches = (m.batch_size.count() - count0).max(1) as f64;
        println!(
            "{}",
            json!({"section": "engine", "impl": "loopd", "dtype": format!("{dt:?}").to_lowercase(),
                   "clients": clients, "max_batch": max_batch, "decode_workers": workers, "batch_buckets": buckets,
                   "img_s": rate, "p50_ms": pct(&mut lat, 0.5), "p99_ms": pct(&mut lat, 0.99),
                   "mean_batch": (m.batch_size.sum() - sum0) / batches, "largest_batch_bucket": m.batch_size.max_bucket(),
                   "images": m.images.load(Relaxed), "t0": t0, "t1": t1})
        );
    }
    Ok(())
}

fn train(ctx: &Ctx) -> anyhow::Result<()> {
    let batch: usize = env("GPU_TRAIN_BATCH", "32").parse()?;
    let views = 4;
    let places = (batch / views).max(2);
    let b = (places * views) as i64;
    let side = ctx.config.preprocess.width as i64;
    // Place i / views: views of one place are positives of each other, other places negatives.
    let place = Tensor::arange(b, (Kind::Int64, Device::Cpu)).divide_scalar_mode(views as i64, "floor");
    let same = place.unsqueeze(1).eq_tensor(&place.unsqueeze(0)).to_kind(Kind::Float);
    let pos = (&same - Tensor::eye(b, (Kind::Float, Device::Cpu))).to_device(ctx.device);
    let neg = (1.0f64 - &same).to_device(ctx.device);
    for name in env("GPU_AUTOCAST", "f32,bf16").split(',') {
        let autocast = dtype(name)?;
        eprintln!("train batch {b} autocast {name}");
        let model = ctx.model(DType::F32)?;
        let r = Recipe {
            epochs: 1,
            places_per_batch: places,
            views,
            lr: 1e-4,
            weight_decay: 1e-4,
            warmup_steps: 0,
            clip_norm: 1.0,
            seed: 0,
            steps_per_epoch: None,
            patience: 0,
            train_layer4: false,
            augment_labelled: false,
            loss: MsParams::default(),
            autocast,
        };
        let (mut opt, params) = optimizer(&model, &r)?;
        let x = Tensor::randn([b, 3, side, side], (Kind::Float, ctx.device));
        let mut losses = Vec::new();
        let (rate, mut lat, t0, t1) = timed(ctx, b as usize, || {
            losses.push(step(&model, &mut opt, &params, &x, &pos, &neg, &r, r.lr)?);
            Ok(())
        })?;
        anyhow::ensure!(losses.iter().all(|l| l.is_finite()), "a training loss is not finite: {losses:?}");
        println!(
            "{}",
            json!({"section": "train", "impl": "loopd", "autocast": name.trim(), "batch": b, "img_s": rate,
                   "step_ms": pct(&mut lat, 0.5), "steps": lat.len(), "t0": t0, "t1": t1})
        );
    }
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    if std::env::args().any(|a| a == "--list") || args.is_empty() {
        return Ok(()); // cargo bench probing for names, or a plain `cargo bench`
    }
    let side: u32 = env("GPU_SIDE", "224").parse()?;
    let mut config = ModelConfig::default();
    (config.preprocess.width, config.preprocess.height) = (side, side);
    let ctx = Ctx {
        device: parse_device(&env("GPU_DEVICE", "cuda"))?,
        config,
        budget: Duration::from_secs_f64(env("GPU_SECONDS", "1.5").parse()?),
        work: PathBuf::from(env("GPU_WORK", "gpu-work")),
    };
    std::fs::create_dir_all(&ctx.work)?;
    for section in &args {
        match section.as_str() {
            "forward" => forward(&ctx)?,
            "engine" => tokio::runtime::Runtime::new()?.block_on(engine(&ctx))?,
            "train" => train(&ctx)?,
            other => anyhow::bail!("unknown section '{other}': forward, engine or train"),
        }
    }
    Ok(())
}
