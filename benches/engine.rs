//! Engine against direct forward passes, side by side in one run, and client latency.
//!
//! Throughput: N closed-loop clients through the engine (max_batch = N) against
//! `Model::descriptors` on a batch of N, alternating so machine drift hits both.
//! Latency: p50/p99 per request for 1, 8, 32 clients at two max_delay values.
//! Two models (`serve --models`): the built-in network and a TorchScript model (exported here by
//! tests/reference/script_models.py with the venv's torch), each its own engine, alone and both
//! under load at once, in one run: what each keeps of its throughput when they share the machine.
//! env: LOOPD_BENCH_DEVICE (default cpu), LOOPD_BENCH_DTYPE, LOOPD_BENCH_SECONDS (per cell, default 8),
//!      LOOPD_BENCH_INPUT (input side, default 224), LOOPD_BENCH_CLIENTS (default "1,8,32"),
//!      LOOPD_BENCH_SECTIONS (default "throughput,latency,models")
use loopd::engine::{Engine, EngineConfig};
use loopd::model::config::ModelConfig;
use loopd::model::device::{device_name, parse_device, DType};
use loopd::model::network::Variant;
use loopd::model::preprocess::ImageLimits;
use loopd::model::Model;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use tch::{Device, Tensor};

fn env(name: &str, default: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| default.to_string())
}

struct Setup {
    device: Device,
    dtype: DType,
    config: ModelConfig,
    budget: Duration,
}

impl Setup {
    fn model(&self) -> anyhow::Result<Model> {
        let m = Model::new(self.config.clone(), self.device, self.dtype)?;
        m.randomize(0, false);
        Ok(m)
    }

    fn engine(&self, max_batch: usize, max_delay: Duration) -> anyhow::Result<Engine> {
        let cfg = EngineConfig { max_batch, max_delay, queue_capacity: 1024, ..Default::default() };
        Engine::start(self.model()?, cfg, ImageLimits::default())
    }
}

enum Payload {
    Input(Tensor),
    Jpeg(bytes::Bytes),
}

/// Runs `clients` closed-loop clients for the budget; returns (images/s, per-request latencies).
async fn drive(engine: &Engine, clients: usize, payloads: &[Payload], budget: Duration) -> (f64, Vec<Duration>) {
    let start = Instant::now();
    let mut tasks = Vec::new();
    for c in 0..clients {
        let e = engine.clone();
        let p = match &payloads[c % payloads.len()] {
            Payload::Input(t) => Payload::Input(t.shallow_clone()),
            Payload::Jpeg(b) => Payload::Jpeg(b.clone()),
        };
        tasks.push(tokio::spawn(async move {
            let mut lat = Vec::new();
            while start.elapsed() < budget || lat.len() < 2 {
                let t = Instant::now();
                let r = match &p {
                    Payload::Input(x) => e.embed_input(x.shallow_clone(), Variant::FULL).await,
                    Payload::Jpeg(b) => e.embed_image(b.clone(), Variant::FULL).await,
                };
                r.expect("embedding");
                lat.push(t.elapsed());
            }
            lat
        }));
    }
    let mut all = Vec::new();
    for t in tasks {
        all.extend(t.await.expect("client task"));
    }
    (all.len() as f64 / start.elapsed().as_secs_f64(), all)
}

fn direct(model: &Model, inputs: &[Tensor], budget: Duration) -> anyhow::Result<f64> {
    let start = Instant::now();
    let mut n = 0;
    while start.elapsed() < budget || n < 2 {
        let _ = model.descriptors(inputs, Variant::FULL)?;
        n += inputs.len();
    }
    Ok(n as f64 / start.elapsed().as_secs_f64())
}

fn pct(lat: &mut [Duration], p: f64) -> f64 {
    lat.sort();
    let i = ((lat.len() as f64 - 1.0) * p).round() as usize;
    lat[i].as_secs_f64() * 1e3
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    if std::env::args().any(|a| a == "--list") {
        return Ok(());
    }
    let side: u32 = env("LOOPD_BENCH_INPUT", "224").parse()?;
    let mut config = ModelConfig::default();
    config.preprocess.width = side;
    config.preprocess.height = side;
    let s = Setup {
        device: parse_device(&env("LOOPD_BENCH_DEVICE", "cpu"))?,
        dtype: serde_json::from_value(env("LOOPD_BENCH_DTYPE", "f32").into())?,
        config,
        budget: Duration::from_secs_f64(env("LOOPD_BENCH_SECONDS", "8").parse()?),
    };
    let sections = env("LOOPD_BENCH_SECTIONS", "throughput,latency,models");
    let clients: Vec<usize> =
        env("LOOPD_BENCH_CLIENTS", "1,8,32").split(',').map(|c| c.trim().parse()).collect::<Result<_, _>>()?;
    let data = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/corridor/query");
    let jpegs: Vec<bytes::Bytes> =
        (0..32).map(|i| std::fs::read(data.join(format!("{i:07}.jpg"))).map(Into::into)).collect::<Result<_, _>>()?;
    let inputs: Vec<Tensor> = jpegs
        .iter()
        .map(|b| loopd::model::preprocess::prepare(b, &ImageLimits::default(), &s.config.preprocess))
        .collect::<Result<_, _>>()?;
    println!(
        "device {} dtype {:?} threads {} input {side}x{side}, {}s per cell",
        device_name(s.device),
        s.dtype,
        tch::get_num_threads(),
        s.budget.as_secs_f64()
    );

    if sections.contains("models") {
        two_models(&s, &jpegs).await?;
    }
    if !sections.contains("throughput") {
        return latency(&s, &clients, &jpegs, &sections).await;
    }
    println!("\nThroughput: N clients through the engine (max_batch N, max_delay 5 ms) vs direct forward of batch N");
    println!("| N | direct img/s | engine img/s (preprocessed) | engine / direct | engine img/s (JPEG decode on workers) | JPEG / direct |");
    println!("|--:|-------------:|----------------------------:|----------------:|--------------------------------------:|--------------:|");
    let model = s.model()?;
    for &n in &clients {
        let batch: Vec<Tensor> = inputs.iter().cycle().take(n).map(|t| t.shallow_clone()).collect();
        let engine = s.engine(n, Duration::from_millis(5))?;
        let pre: Vec<Payload> = inputs.iter().map(|t| Payload::Input(t.shallow_clone())).collect();
        let jpg: Vec<Payload> = jpegs.iter().map(|b| Payload::Jpeg(b.clone())).collect();
        // Two alternating rounds each, summed.
        let (mut d, mut e, mut j) = (0.0, 0.0, 0.0);
        for _ in 0..2 {
            d += direct(&model, &batch, s.budget / 2)?;
            e += drive(&engine, n, &pre, s.budget / 2).await.0;
            j += drive(&engine, n, &jpg, s.budget / 2).await.0;
        }
        let (d, e, j) = (d / 2.0, e / 2.0, j / 2.0);
        println!("| {n} | {d:.1} | {e:.1} | {:.3} | {j:.1} | {:.3} |", e / d, j / d);
    }
    drop(model);
    latency(&s, &clients, &jpegs, &sections).await
}

async fn latency(s: &Setup, clients: &[usize], jpegs: &[bytes::Bytes], sections: &str) -> anyhow::Result<()> {
    if !sections.contains("latency") {
        return Ok(());
    }
    println!("\nLatency per request, JPEG in, max_batch 32");
    println!("| clients | max_delay ms | img/s | p50 ms | p99 ms |");
    println!("|--:|--:|--:|--:|--:|");
    let jpg: Vec<Payload> = jpegs.iter().map(|b| Payload::Jpeg(b.clone())).collect();
    for delay in [2u64, 20] {
        let engine = s.engine(32, Duration::from_millis(delay))?;
        for &n in clients {
            let (rate, mut lat) = drive(&engine, n, &jpg, s.budget).await;
            println!("| {n} | {delay} | {rate:.1} | {:.1} | {:.1} |", pct(&mut lat, 0.5), pct(&mut lat, 0.99));
        }
    }
    Ok(())
}

/// The built-in network and a TorchScript model, each its own engine (as `serve --models` runs
/// them), 8 closed-loop JPEG clients each: alone, then both at once, alternating twice.
async fn two_models(s: &Setup, jpegs: &[bytes::Bytes]) -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let exported = std::process::Command::new(root.join(".venv/bin/python"))
        .arg(root.join("tests/reference/script_models.py"))
        .arg("export")
        .arg(dir.path())
        .status()?;
    anyhow::ensure!(exported.success(), "exporting the TorchScript model failed");
    let script = loopd::model::script::ScriptModel::load(&dir.path().join("small-resnet"), s.device)?;
    let label = format!(
        "{} ({}x{}, {}-d)",
        script.manifest.name,
        script.manifest.input.width,
        script.manifest.input.height,
        script.dim()
    );
    let cfg = EngineConfig { max_batch: 8, queue_capacity: 1024, ..Default::default() };
    let builtin = Engine::start(s.model()?, cfg.clone(), ImageLimits::default())?;
    let other = Engine::start(script, cfg, ImageLimits::default())?;
    let jpg: Vec<Payload> = jpegs.iter().map(|b| Payload::Jpeg(b.clone())).collect();
    let (mut alone, mut mixed) = ([0.0f64; 2], [0.0f64; 2]);
    for _ in 0..2 {
        alone[0] += drive(&builtin, 8, &jpg, s.budget / 2).await.0 / 2.0;
        alone[1] += drive(&other, 8, &jpg, s.budget / 2).await.0 / 2.0;
        let (a, b) = tokio::join!(drive(&builtin, 8, &jpg, s.budget / 2), drive(&other, 8, &jpg, s.budget / 2));
        mixed[0] += a.0 / 2.0;
        mixed[1] += b.0 / 2.0;
    }
    println!("\nTwo models, each its own engine (max_batch 8), 8 JPEG clients per model; alone, then both at once");
    println!("| model | alone img/s | with the other loaded img/s | share kept | the other's img/s meanwhile |");
    println!("|---|--:|--:|--:|--:|");
    let builtin_label =
        format!("built-in ({}x{}, {}-d)", s.config.preprocess.width, s.config.preprocess.height, builtin.info().dim);
    for (i, name) in [builtin_label, label].iter().enumerate() {
        println!("| {name} | {:.1} | {:.1} | {:.2} | {:.1} |", alone[i], mixed[i], mixed[i] / alone[i], mixed[1 - i]);
    }
    Ok(())
}
