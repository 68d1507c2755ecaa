//! Forward-pass throughput: plain backbone against the full network (attention + fusion),
//! measured interleaved in one run on random weights (speed does not depend on values).
//!
//! env: LOOPD_BENCH_DEVICE (cpu|cuda|auto, default cpu), LOOPD_BENCH_DTYPE (f32|f16|bf16),
//!      LOOPD_BENCH_BATCHES (default "1,8,32"), LOOPD_BENCH_SECONDS (per cell, default 6)
use loopd::model::config::ModelConfig;
use loopd::model::device::{device_name, parse_device, DType};
use loopd::model::network::Variant;
use loopd::model::Model;
use std::time::{Duration, Instant};
use tch::{Kind, Tensor};

fn env(name: &str, default: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| default.to_string())
}

fn main() -> anyhow::Result<()> {
    if std::env::args().any(|a| a == "--list") {
        return Ok(()); // cargo bench probing for names
    }
    let device = parse_device(&env("LOOPD_BENCH_DEVICE", "cpu"))?;
    let dtype: DType = serde_json::from_value(env("LOOPD_BENCH_DTYPE", "f32").into())?;
    let batches: Vec<i64> =
        env("LOOPD_BENCH_BATCHES", "1,8,32").split(',').map(|s| s.trim().parse()).collect::<Result<_, _>>()?;
    let budget = Duration::from_secs_f64(env("LOOPD_BENCH_SECONDS", "6").parse()?);
    let model = Model::new(ModelConfig::default(), device, dtype)?;
    model.randomize(0, false);
    let threads = tch::get_num_threads();
    println!("device {} dtype {:?} threads {threads} input 224x224", device_name(device), dtype);
    println!("| batch | backbone img/s | full img/s | full / backbone time | attention cost | fusion cost | attention+fusion cost |");
    println!("|------:|---------------:|-----------:|---------------------:|---------------:|------------:|----------------------:|");
    for &b in &batches {
        let inputs: Vec<Tensor> =
            (0..b).map(|_| Tensor::randn([3, 224, 224], (Kind::Float, tch::Device::Cpu)) * 50.0).collect();
        let run = |v: Variant| -> anyhow::Result<f64> {
            let t = Instant::now();
            let d = model.descriptors(&inputs, v)?; // copies to the CPU, so the device has finished
            assert_eq!(d.size()[0], b);
            Ok(t.elapsed().as_secs_f64())
        };
        for v in Variant::ALL {
            run(v)?; // warm-up: allocator, oneDNN/cuDNN algorithm choice
        }
        // Variant::ALL order: full, attention, fusion, backbone. Interleaved so drift hits all alike.
        let mut total = [0.0f64; 4];
        let mut n = 0;
        let start = Instant::now();
        while n < 2 || (start.elapsed() < budget && n < 200) {
            for (i, v) in Variant::ALL.iter().enumerate() {
                total[i] += run(*v)?;
            }
            n += 1;
        }
        let [full, att, fus, plain] = total;
        let rate = |t: f64| b as f64 * n as f64 / t;
        let cost = |t: f64| (t / plain - 1.0) * 100.0;
        println!(
            "| {b:>5} | {:>14.1} | {:>10.1} | {:>20.3} | {:>13.1}% | {:>10.1}% | {:>20.1}% |",
            rate(plain),
            rate(full),
            full / plain,
            cost(att),
            cost(fus),
            cost(full)
        );
    }
    Ok(())
}
