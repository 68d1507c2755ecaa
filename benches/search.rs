//! Exact top-10 search: loopd's index against FAISS IndexFlatIP on the same random unit
//! vectors (splitmix64 stream, benches/py/faiss_flat.py), then durable inserts, disk use and
//! index rebuild of a real sled store.
//!
//! env: LOOPD_BENCH_SIZES (default "10000,100000,1000000"), LOOPD_BENCH_DIMS (default "2048,256"),
//!      LOOPD_BENCH_SINGLES (single queries per cell, default 20), LOOPD_BENCH_INSERTS (default 100000),
//!      LOOPD_BENCH_FAISS=0 to skip FAISS,
//!      LOOPD_BENCH_SEARCH_DEVICE=cuda (or cuda:N, cpu) to add the libtorch device path's columns
use indicatif::{ProgressBar, ProgressStyle};
use loopd::index::query::LoopQuery;
use loopd::index::SessionIndex;
use loopd::index::Storage;
use loopd::store::NewSession;
use std::path::PathBuf;
use std::time::{Duration, Instant};

const SEED: u64 = 42;
const BATCH: usize = 64;

fn env(name: &str, default: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| default.to_string())
}

/// Same stream as faiss_flat.py: value i of stream `seed` is splitmix64(seed + (i+1)*golden).
fn unit_row(seed: u64, row: usize, dim: usize, out: &mut [f32]) {
    for (j, o) in out.iter_mut().enumerate() {
        let i = (row * dim + j) as u64;
        let mut z = seed.wrapping_add(i.wrapping_add(1).wrapping_mul(0x9E3779B97F4A7C15));
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
        z ^= z >> 31;
        *o = (z >> 40) as f32 * (2.0 / (1u64 << 24) as f32) - 1.0;
    }
    let norm = out.iter().map(|v| v * v).sum::<f32>().sqrt();
    out.iter_mut().for_each(|v| *v /= norm);
}

fn build(n: usize, dim: usize, storage: Storage) -> SessionIndex {
    let mut index = SessionIndex::new(dim, storage);
    let mut row = vec![0f32; dim];
    let bar = ProgressBar::new(n as u64)
        .with_style(ProgressStyle::with_template("  building {pos}/{len} {wide_bar} {eta}").expect("template"));
    for i in 0..n {
        unit_row(SEED, i, dim, &mut row);
        index.push(i as u64, "r", i as f64, None, &row);
        if i % 4096 == 0 {
            bar.set_position(i as u64);
        }
    }
    bar.finish_and_clear();
    index
}

struct Faiss {
    single_qps: f64,
    batch_qps: f64,
    top1: Vec<u64>,
}

fn faiss(n: usize, dim: usize, singles: usize) -> Option<Faiss> {
    if env("LOOPD_BENCH_FAISS", "1") == "0" {
        return None;
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let out = std::process::Command::new(root.join(".venv/bin/python"))
        .arg(root.join("benches/py/faiss_flat.py"))
        .args([n, dim, SEED as usize, singles, BATCH].map(|v| v.to_string()))
        .output()
        .ok()?;
    if !out.status.success() {
        eprintln!("faiss failed: {}", String::from_utf8_lossy(&out.stderr));
        return None;
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).ok()?;
    Some(Faiss {
        single_qps: v["single_qps"].as_f64()?,
        batch_qps: v["batch_qps"].as_f64()?,
        top1: v["top1"].as_array()?.iter().filter_map(|x| x.as_u64()).collect(),
    })
}

/// The libtorch device to time searches on besides the host kernels, if asked for.
fn search_device() -> anyhow::Result<Option<tch::Device>> {
    Ok(match std::env::var("LOOPD_BENCH_SEARCH_DEVICE") {
        Ok(s) if !s.is_empty() => Some(loopd::model::device::parse_device(&s)?),
        _ => None,
    })
}

fn main() -> anyhow::Result<()> {
    if std::env::args().any(|a| a == "--list") {
        return Ok(());
    }
    let sizes: Vec<usize> = env("LOOPD_BENCH_SIZES", "10000,100000,1000000")
        .split(',')
        .map(|s| s.trim().parse())
        .collect::<Result<_, _>>()?;
    let dims: Vec<usize> =
        env("LOOPD_BENCH_DIMS", "2048,256").split(',').map(|s| s.trim().parse()).collect::<Result<_, _>>()?;
    let singles: usize = env("LOOPD_BENCH_SINGLES", "20").parse()?;
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    println!("exact top-10, {threads} threads; loopd stores f16 (single) and f32; FAISS IndexFlatIP f32\n");
    println!("| n | dim | FAISS single q/s | loopd f16 single q/s | ratio | loopd f16 GB/s | loopd f32 single q/s | FAISS batch-64 q/s | loopd f16 batch-64 q/s | ratio | top-1 agree |");
    println!("|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|");
    let mut device_rows = Vec::new();
    for &dim in &dims {
        for &n in &sizes {
            let f = faiss(n, dim, singles);
            let mut queries = vec![vec![0f32; dim]; singles.max(BATCH)];
            for (i, q) in queries.iter_mut().enumerate() {
                unit_row(SEED + 1, i, dim, q);
            }
            let opts = LoopQuery { k: 10, ..Default::default() };
            let time_single = |index: &SessionIndex| -> (f64, Vec<u64>) {
                index.search(&queries[0], &opts, threads); // warm-up
                let t = Instant::now();
                let top1: Vec<u64> =
                    queries[..singles].iter().map(|q| index.search(q, &opts, threads)[0].frame_id).collect();
                (singles as f64 / t.elapsed().as_secs_f64(), top1)
            };
            // (queries/s, batches run) for batches of 64 over about 2 s.
            let time_batch = |index: &SessionIndex| -> (f64, usize) {
                let t = Instant::now();
                let mut batches = 0;
                while batches < 2 || t.elapsed() < Duration::from_secs(2) {
                    index.search_batch(&queries[..BATCH], &opts, threads);
                    batches += 1;
                }
                ((batches * BATCH) as f64 / t.elapsed().as_secs_f64(), batches)
            };
            let (f32_qps, _) = {
                let index = build(n, dim, Storage::F32);
                time_single(&index)
            };
            let index = build(n, dim, Storage::F16);
            let (qps, top1) = time_single(&index);
            let gbs = qps * (n * dim * 2) as f64 / 1e9;
            let (batch_qps, _) = time_batch(&index);
            if let Some(device) = search_device()? {
                let mut index = index;
                index.search_on(device, 0);
                index.upload();
                let (dev_qps, dev_top1) = time_single(&index);
                let (dev_batch, batches) = time_batch(&index);
                // Every timed search was answered on the device, none by the host fallback.
                assert_eq!(index.device_searches() as usize, singles + 1 + batches);
                let agree = dev_top1.iter().zip(&top1).filter(|(a, b)| a == b).count();
                device_rows.push(format!(
                    "| {n} | {dim} | {device:?} | {qps:.1} | {dev_qps:.1} | {:.2} | {batch_qps:.1} | {dev_batch:.1} | {:.2} | {agree}/{} |",
                    dev_qps / qps,
                    dev_batch / batch_qps,
                    top1.len()
                ));
            }
            match f {
                Some(f) => {
                    let agree = top1.iter().zip(&f.top1).filter(|(a, b)| a == b).count();
                    println!(
                        "| {n} | {dim} | {:.1} | {qps:.1} | {:.2} | {gbs:.1} | {f32_qps:.1} | {:.1} | {batch_qps:.1} | {:.2} | {agree}/{} |",
                        f.single_qps,
                        qps / f.single_qps,
                        f.batch_qps,
                        batch_qps / f.batch_qps,
                        top1.len()
                    );
                }
                None => println!(
                    "| {n} | {dim} | - | {qps:.1} | - | {gbs:.1} | {f32_qps:.1} | - | {batch_qps:.1} | - | - |"
                ),
            }
        }
    }
    if !device_rows.is_empty() {
        println!("\nlibtorch device path (f16 rows on the device) against the host kernels, same index:\n");
        println!("| n | dim | device | host single q/s | device single q/s | ratio | host batch-64 q/s | device batch-64 q/s | ratio | top-1 = host |");
        println!("|--:|--:|--|--:|--:|--:|--:|--:|--:|--:|");
        device_rows.iter().for_each(|r| println!("{r}"));
    }
    store_bench()
}

/// Durable inserts from concurrent robots into a real sled store, disk use, rebuild time.
fn store_bench() -> anyhow::Result<()> {
    use loopd::store::{NewFrame, Store};
    let n: usize = env("LOOPD_BENCH_INSERTS", "100000").parse()?;
    if n == 0 {
        return Ok(());
    }
    let dim = 2048;
    let robots = 16;
    let dir = tempfile::tempdir()?;
    let rt = tokio::runtime::Runtime::new()?;
    let store = std::sync::Arc::new(Store::open(dir.path())?);
    let t = Instant::now();
    rt.block_on(async {
        store
            .create_session(
                Some("bench".into()),
                NewSession {
                    name: "bench".into(),
                    dim,
                    descriptor_id: "bench".into(),
                    storage: Storage::F16,
                    default_query: LoopQuery::default(),
                    camera: None,
                    thumbnails: false,
                    index: loopd::index::graph::IndexKind::Exact,
                    model: None,
                },
            )
            .await?;
        let bar = ProgressBar::new(n as u64).with_style(
            ProgressStyle::with_template("  inserting {pos}/{len} {wide_bar} {per_sec}").expect("template"),
        );
        let tasks: Vec<_> = (0..robots)
            .map(|r| {
                let (store, bar) = (store.clone(), bar.clone());
                tokio::spawn(async move {
                    let session = store.session("bench")?;
                    let mut row = vec![0f32; dim];
                    for i in (r..n).step_by(robots) {
                        unit_row(SEED, i, dim, &mut row);
                        let f = NewFrame {
                            frame_id: None,
                            robot_id: format!("robot{r}"),
                            timestamp: i as f64,
                            pose: None,
                            metadata: None,
                            descriptor: row.clone(),
                            features: None,
                            thumbnail: None,
                            idempotency_key: None,
                        };
                        store.add_frames(&session, vec![f]).await?;
                        bar.inc(1);
                    }
                    anyhow::Ok(())
                })
            })
            .collect();
        for t in tasks {
            t.await??;
        }
        bar.finish_and_clear();
        anyhow::Ok(())
    })?;
    let insert_rate = n as f64 / t.elapsed().as_secs_f64();
    store.flush()?;
    drop(store);
    let disk = dir_size(dir.path());
    let t = Instant::now();
    let reopened = Store::open(dir.path())?;
    let rebuild = t.elapsed();
    assert_eq!(reopened.list()[0].frames, n);
    println!(
        "\n| frames | writers | durable inserts/s (one frame per call) | bytes on disk per frame | index rebuild |"
    );
    println!("|--:|--:|--:|--:|--:|");
    println!("| {n} | {robots} | {insert_rate:.0} | {:.0} | {:.2} s |", disk as f64 / n as f64, rebuild.as_secs_f64());
    Ok(())
}

fn dir_size(p: &std::path::Path) -> u64 {
    std::fs::read_dir(p)
        .map(|rd| {
            rd.flatten()
                .map(
                    |e| {
                        if e.path().is_dir() {
                            dir_size(&e.path())
                        } else {
                            e.metadata().map(|m| m.len()).unwrap_or(0)
                        }
                    },
                )
                .sum()
        })
        .unwrap_or(0)
}
