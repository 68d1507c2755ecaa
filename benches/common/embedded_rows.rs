//! The rows the index benches search (`ann`, `restart`): every image of ../shared/data embedded
//! once with the shipped model (cached in target/bench-cache), extended to any size with
//! synthetic rows, each a real row mixed with another (weight 0.5-1) plus isotropic Gaussian
//! noise of norm `LOOPD_BENCH_NOISE` (default 0.5), renormalised (`benches/ann.rs` says why
//! that is not easier than real data).
use std::path::PathBuf;

/// Values per descriptor (the shipped model with its heads).
pub const DIM: usize = 1712;

fn env(name: &str, default: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| default.to_string())
}

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Every image under ../shared/data, embedded with the shipped model (cached).
pub fn real_rows() -> anyhow::Result<Vec<Vec<f32>>> {
    let data = root().join("../shared/data");
    let mut files = Vec::new();
    let mut dirs = vec![data];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d)? {
            let p = e?.path();
            if p.is_dir() {
                dirs.push(p);
            } else if loopd::files::is_image(&p.file_name().unwrap_or_default().to_string_lossy()) {
                files.push(p);
            }
        }
    }
    files.sort();
    let weights = root().join("weights/resnet50-imagenet.safetensors");
    let (mut model, _) = loopd::model::Model::load(
        &weights,
        loopd::model::config::ModelConfig::default(),
        tch::Device::Cpu,
        loopd::model::device::DType::F32,
    )?;
    model.load_heads(&root().join(loopd::cli::DEFAULT_HEADS))?;
    let cfg = loopd::engine::EngineConfig { max_batch: 16, warm_up: false, ..Default::default() };
    let engine = loopd::engine::Engine::start(model, cfg, Default::default())?;
    let cache = root().join("target/bench-cache");
    let setup = loopd::eval::run::EmbedSetup {
        weights: &weights,
        variant: loopd::model::network::Variant::FULL,
        cache_dir: Some(&cache),
        max_batch: 16,
    };
    loopd::eval::run::embed_files(&engine, &files, &setup, "every image of ../shared/data")
}

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E3779B97F4A7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
        z ^ (z >> 31)
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
    fn gauss(&mut self) -> f32 {
        let (u, v) = (self.unit().max(1e-7), self.unit());
        (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
    }
}

/// The rows in order: the real rows first, then the synthetic extension, one at a time (a
/// 10^7-row set need not be held).
pub struct Extension<'a> {
    real: &'a [Vec<f32>],
    rng: Rng,
    sigma: f32,
    next: usize,
}

impl<'a> Extension<'a> {
    pub fn new(real: &'a [Vec<f32>]) -> Self {
        let dim = real.first().map_or(DIM, Vec::len);
        let sigma = env("LOOPD_BENCH_NOISE", "0.5").parse::<f32>().unwrap_or(0.5) / (dim as f32).sqrt();
        Self { real, rng: Rng(7), sigma, next: 0 }
    }
}

impl Iterator for Extension<'_> {
    type Item = Vec<f32>;
    fn next(&mut self) -> Option<Vec<f32>> {
        let (i, real, rng) = (self.next, self.real, &mut self.rng);
        self.next += 1;
        if i < real.len() {
            return Some(real[i].clone());
        }
        let (a, b) = (&real[rng.next() as usize % real.len()], &real[rng.next() as usize % real.len()]);
        let w = 0.5 + 0.5 * rng.unit();
        let mut v: Vec<f32> = a.iter().zip(b).map(|(x, y)| w * x + (1.0 - w) * y + self.sigma * rng.gauss()).collect();
        loopd::index::normalize(&mut v).expect("non-zero");
        Some(v)
    }
}
