//! Restart of a node holding one large map (issue #33): the time from opening the data
//! directory to a store that answers, with the session's rows and frame records taken from the
//! files kept by the last run (`store/kept.rs`) against every frame read again from sled (the
//! checkpoint removed). Both runs load the saved approximate index (`graphs/`) the same way.
//!
//! Rows: the real rows of ../shared/data extended with synthetic ones (`common/embedded_rows.rs`,
//! as in `benches/ann.rs`), 1,712-d f16, 16 robots in turn, written through `Store::add_frames`
//! in batches of 500 (the server's write path: sled, group commit, kept files, the indexer).
//! Before each open the page cache is dropped (`/proc/sys/vm/drop_caches`, as root), so both
//! read from disk as after a reboot; "warm" columns open again without dropping it.
//!
//! env: LOOPD_BENCH_SIZES (default "100000"), LOOPD_BENCH_DIR (default target/bench-restart;
//! removed at the end unless LOOPD_BENCH_KEEP=1), LOOPD_BENCH_SEAL (comma-separated: each size is
//! written once per value, the graph sealed into mapped parts of that many frames,
//! `--approx-seal-frames`; 0: one graph in memory; default: the server's default).
use indicatif::{ProgressBar, ProgressStyle};
use loopd::index::graph::GraphParams;
use loopd::index::Storage;
use loopd::store::{NewFrame, NewSession, SearchConfig, Store};
use std::path::Path;
use std::time::{Duration, Instant};

#[path = "common/embedded_rows.rs"]
mod embedded_rows;
use embedded_rows::{real_rows, root, Extension, DIM};

const ID: &str = "map";
const BATCH: usize = 500;

fn rss_gib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kb = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches(" kB").parse::<f64>().ok());
    kb.unwrap_or(0.0) / (1 << 20) as f64
}

/// Drops the page cache (root only); false where it cannot.
fn drop_caches() -> bool {
    let _ = std::process::Command::new("sync").status();
    std::fs::write("/proc/sys/vm/drop_caches", "3").is_ok()
}

fn wait(what: &str, mut done: impl FnMut() -> bool) {
    let t = Instant::now();
    while !done() {
        assert!(t.elapsed() < Duration::from_secs(1800), "{what}: not after 30 minutes");
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn checkpointed(dir: &Path) -> usize {
    let Ok(json) = std::fs::read(dir.join(format!("rows/{ID}.json"))) else { return 0 };
    let v: serde_json::Value = serde_json::from_slice(&json).unwrap_or_default();
    v["frames"].as_u64().unwrap_or(0) as usize
}

/// Opens the store (no checkpoint written meanwhile); seconds to ready, frames taken from the
/// kept files, frames, RSS after.
fn open(dir: &Path, config: SearchConfig) -> anyhow::Result<(f64, usize, usize, f64)> {
    let t = Instant::now();
    let store = Store::open_with(dir, SearchConfig { checkpoint_frames: usize::MAX, ..config })?;
    let secs = t.elapsed().as_secs_f64();
    let s = store.session(ID)?;
    let out = (secs, s.restored_frames(), s.info().frames, rss_gib());
    drop((s, store));
    // The indexer lets go of the session within a turn.
    std::thread::sleep(Duration::from_secs(2));
    Ok(out)
}

fn main() -> anyhow::Result<()> {
    let sizes: Vec<usize> = std::env::var("LOOPD_BENCH_SIZES")
        .unwrap_or_else(|_| "100000".into())
        .split(',')
        .map(|s| s.trim().parse())
        .collect::<Result<_, _>>()?;
    let base = std::env::var("LOOPD_BENCH_DIR").map_or_else(|_| root().join("target/bench-restart"), Into::into);
    let real = real_rows()?;
    let rt = tokio::runtime::Runtime::new()?;
    println!(
        "restart of one {DIM}-d f16 session ({} real rows, the rest synthetic); page cache dropped before each cold open: {}",
        real.len(),
        drop_caches()
    );
    println!(
        "| frames | graph sealed in parts of | written rows/s | sled + rows + graph on disk GiB | cold open, kept rows: s | restored from files | warm open, kept rows: s | cold open, every frame from sled: s | warm, from sled: s | RSS after open GiB |"
    );
    println!("|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|");
    let seals: Vec<usize> = match std::env::var("LOOPD_BENCH_SEAL") {
        Ok(v) => v.split(',').map(|s| s.trim().parse()).collect::<Result<_, _>>()?,
        Err(_) => vec![GraphParams::default().seal_rows],
    };
    for (n, seal_rows) in sizes.iter().flat_map(|&n| seals.iter().map(move |&s| (n, s))) {
        let config = SearchConfig { graph: GraphParams { seal_rows, ..Default::default() }, ..Default::default() };
        let dir = base.join(n.to_string());
        let _ = std::fs::remove_dir_all(&dir);
        let written = rt.block_on(async {
            let store = Store::open_with(&dir, config)?;
            let new = NewSession {
                name: ID.into(),
                dim: DIM,
                descriptor_id: "bench".into(),
                storage: Storage::F16,
                default_query: Default::default(),
                camera: None,
                thumbnails: false,
                // What a session this large uses (`auto` switches at 200,000 frames).
                index: loopd::index::graph::IndexKind::Approximate,
                model: None,
            };
            store.create_session(Some(ID.into()), new).await?;
            let s = store.session(ID)?;
            let bar = ProgressBar::new(n as u64)
                .with_style(ProgressStyle::with_template("{msg} {bar:40} {pos}/{len} frames, {per_sec}, eta {eta}")?);
            bar.set_message("writing");
            let t = Instant::now();
            let mut rows = Extension::new(&real).enumerate();
            let mut left = n;
            while left > 0 {
                let batch: Vec<NewFrame> = rows
                    .by_ref()
                    .take(BATCH.min(left))
                    .map(|(i, descriptor)| NewFrame {
                        frame_id: None,
                        robot_id: format!("robot{}", i % 16),
                        timestamp: i as f64,
                        pose: None,
                        metadata: None,
                        descriptor,
                        features: None,
                        thumbnail: None,
                        idempotency_key: None,
                    })
                    .collect();
                left -= batch.len();
                bar.inc(batch.len() as u64);
                store.add_frames(&s, batch).await?;
            }
            let rate = n as f64 / t.elapsed().as_secs_f64();
            bar.set_message("graph and checkpoint");
            // The graph covers every frame and is saved, the kept rows are checkpointed.
            let graph = dir.join(format!("graphs/{ID}.json"));
            let saved_rows = || {
                std::fs::read(&graph)
                    .ok()
                    .and_then(|j| serde_json::from_slice::<serde_json::Value>(&j).ok())
                    .and_then(|v| v["rows"].as_u64())
            };
            wait("graph", || s.info().approximate_frames == Some(n) && saved_rows() == Some(n as u64));
            wait("checkpoint", || checkpointed(&dir) == n);
            bar.finish_and_clear();
            anyhow::Ok(rate)
        })?;
        let disk = {
            let mut bytes = 0u64;
            let mut dirs = vec![dir.clone()];
            while let Some(d) = dirs.pop() {
                for e in std::fs::read_dir(&d)?.flatten() {
                    let m = e.metadata()?;
                    if m.is_dir() {
                        dirs.push(e.path());
                    } else {
                        bytes += m.len();
                    }
                }
            }
            bytes as f64 / (1u64 << 30) as f64
        };
        drop_caches();
        let (cold, restored, frames, _) = open(&dir, config)?;
        assert_eq!(frames, n);
        let (warm, _, _, rss) = open(&dir, config)?;
        std::fs::remove_file(dir.join(format!("rows/{ID}.json")))?;
        drop_caches();
        let (cold_sled, from_files, frames, _) = open(&dir, config)?;
        assert_eq!((frames, from_files), (n, 0));
        std::fs::remove_file(dir.join(format!("rows/{ID}.json"))).ok();
        let (warm_sled, _, _, _) = open(&dir, config)?;
        println!(
            "| {n} | {seal_rows} | {written:.0} | {disk:.2} | {cold:.2} | {restored} | {warm:.2} | {cold_sled:.2} | {warm_sled:.2} | {rss:.2} |"
        );
        if std::env::var("LOOPD_BENCH_KEEP").as_deref() != Ok("1") {
            std::fs::remove_dir_all(&dir)?;
        }
    }
    Ok(())
}
