//! Fair sharing of the model between tenants (issue #35): tenant A sends one real image at a time
//! over HTTP (`/v1/embed`) while tenant B sends images open-loop at a fixed rate (a camera at its
//! tenant's limit), against two servers side by side in one run: one with keyed tenants (each in
//! its own lane of the engine, batches shared by weight) and one without keys, where both share
//! the default lane (one queue, as before lanes). Also A alone with 8 callers at once on both:
//! a tenant alone keeps whole batches.
//! env: LOOPD_BENCH_SECONDS (per phase, default 15), LOOPD_BENCH_B_RATE (B's images/s, default 5)
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::auth::AuthConfig;
use loopd::engine::EngineConfig;
use loopd::model::config::ModelConfig;
use loopd::model::device::DType;
use loopd::model::Model;
use std::sync::Arc;
use std::time::{Duration, Instant};

const ADMIN: &str = "admin-key-for-the-fair-bench-0123456789";

fn env(name: &str, default: f64) -> f64 {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

struct Server {
    name: &'static str,
    running: RunningServer,
    base: String,
    /// A's and B's keys (None: no keys, both in the default lane).
    keys: [Option<String>; 2],
}

async fn start(dir: &std::path::Path, keyed: bool) -> anyhow::Result<Server> {
    let model = Model::new(ModelConfig::default(), tch::Device::Cpu, DType::F32)?;
    model.randomize(0, false);
    let cfg = ServerConfig {
        engine: EngineConfig { warm_up: true, ..Default::default() },
        auth: AuthConfig { admin_key: keyed.then(|| ADMIN.to_string()), ..Default::default() },
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    let running = RunningServer::start(cfg, model).await?;
    let base = format!("http://{}", running.http_addr);
    let mut keys = [None, None];
    if keyed {
        let c = reqwest::Client::new();
        for (i, name) in ["a", "b"].iter().enumerate() {
            let t: serde_json::Value = c
                .post(format!("{base}/v1/tenants"))
                .bearer_auth(ADMIN)
                .json(&serde_json::json!({ "name": name }))
                .send()
                .await?
                .json()
                .await?;
            keys[i] = t["key"].as_str().map(str::to_string);
        }
    }
    Ok(Server { name: if keyed { "tenants (a lane each)" } else { "no keys (one lane)" }, running, base, keys })
}

async fn embed(c: &reqwest::Client, base: &str, key: Option<&str>, image: &[u8]) -> anyhow::Result<Duration> {
    let t = Instant::now();
    let mut req = c.post(format!("{base}/v1/embed")).body(image.to_vec());
    if let Some(k) = key {
        req = req.bearer_auth(k);
    }
    let r = req.send().await?;
    anyhow::ensure!(r.status().is_success(), "embed: {}", r.status());
    r.bytes().await?;
    Ok(t.elapsed())
}

fn pct(v: &mut [Duration], p: f64) -> f64 {
    v.sort();
    v.get(((v.len() as f64 - 1.0) * p).round() as usize).map_or(f64::NAN, |d| d.as_secs_f64() * 1e3)
}

/// A: `callers` closed-loop callers for `secs`; B: open-loop at `b_rate` (0: none).
/// Returns (A's latencies, A's images/s, B's images answered/s).
async fn phase(
    s: &Server,
    images: &Arc<Vec<Vec<u8>>>,
    callers: usize,
    b_rate: f64,
    secs: f64,
) -> anyhow::Result<(Vec<Duration>, f64, f64)> {
    let c = reqwest::Client::new();
    let until = Instant::now() + Duration::from_secs_f64(secs);
    let b_done = Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let b = {
        let (c, images, b_done) = (c.clone(), images.clone(), b_done.clone());
        let (base, key) = (s.base.clone(), s.keys[1].clone());
        tokio::spawn(async move {
            if b_rate <= 0.0 {
                return;
            }
            let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / b_rate));
            let mut sent = Vec::new();
            let mut i = 0;
            while Instant::now() < until {
                tick.tick().await;
                let (c, image, b_done) = (c.clone(), images[i % images.len()].clone(), b_done.clone());
                let (url, key) = (format!("{base}/v1/embed"), key.clone());
                sent.push(tokio::spawn(async move {
                    let mut req = c.post(url).body(image);
                    if let Some(k) = key {
                        req = req.bearer_auth(k);
                    }
                    if matches!(req.send().await, Ok(r) if r.status().is_success()) {
                        b_done.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    }
                }));
                i += 1;
            }
            for t in sent {
                let _ = t.await;
            }
        })
    };
    // B's queue builds up first, as it would on a server already busy with it.
    if b_rate > 0.0 {
        tokio::time::sleep(Duration::from_secs(2)).await;
    }
    let start = Instant::now();
    let tasks: Vec<_> = (0..callers)
        .map(|k| {
            let (c, images) = (c.clone(), images.clone());
            let (base, key) = (s.base.clone(), s.keys[0].clone());
            tokio::spawn(async move {
                let mut lat = Vec::new();
                let mut i = k;
                while Instant::now() < until {
                    lat.push(embed(&c, &base, key.as_deref(), &images[i % images.len()]).await?);
                    i += callers;
                }
                anyhow::Ok(lat)
            })
        })
        .collect();
    let mut lat = Vec::new();
    for t in tasks {
        lat.extend(t.await??);
    }
    let a_rate = lat.len() as f64 / start.elapsed().as_secs_f64();
    b.await?;
    let b_rate = b_done.load(std::sync::atomic::Ordering::Relaxed) as f64 / secs;
    Ok((lat, a_rate, b_rate))
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    if std::env::args().any(|a| a == "--list") {
        return Ok(());
    }
    let secs = env("LOOPD_BENCH_SECONDS", 15.0);
    let b_rate = env("LOOPD_BENCH_B_RATE", 5.0);
    let data = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/corridor/query");
    let images: Arc<Vec<Vec<u8>>> =
        Arc::new((0..32).map(|i| std::fs::read(data.join(format!("{i:07}.jpg")))).collect::<Result<_, _>>()?);
    let (d1, d2) = (tempfile::tempdir()?, tempfile::tempdir()?);
    let servers = [start(d1.path(), true).await?, start(d2.path(), false).await?];
    println!("CPU f32, 224x224, random weights, max_batch 32; A: one image at a time; B: {b_rate} images/s open-loop; {secs} s per phase\n");
    println!("| server | phase | A p50 ms | A p99 ms | A img/s | B answered/s | A p50 / A alone |");
    println!("|--|--|--:|--:|--:|--:|--:|");
    let mut alone_tput = Vec::new();
    for s in &servers {
        let (mut alone, a1, _) = phase(s, &images, 1, 0.0, secs).await?;
        let p50_alone = pct(&mut alone, 0.5);
        println!("| {} | A alone | {p50_alone:.0} | {:.0} | {a1:.2} | - | 1.00 |", s.name, pct(&mut alone, 0.99));
        let (mut busy, a2, b2) = phase(s, &images, 1, b_rate, secs).await?;
        let p50 = pct(&mut busy, 0.5);
        println!(
            "| {} | A with B | {p50:.0} | {:.0} | {a2:.2} | {b2:.2} | {:.2} |",
            s.name,
            pct(&mut busy, 0.99),
            p50 / p50_alone
        );
        let (_, tput, _) = phase(s, &images, 8, 0.0, secs).await?;
        alone_tput.push((s.name, tput));
    }
    println!("\nA alone with 8 callers at once (batching when one tenant is alone):\n");
    println!("| server | A img/s |");
    println!("|--|--:|");
    for (name, t) in &alone_tput {
        println!("| {name} | {t:.2} |");
    }
    println!("\nkeyed / keyless: {:.3}", alone_tput[0].1 / alone_tput[1].1);
    for s in servers {
        s.running.shutdown().await?;
    }
    Ok(())
}
