//! The approximate index as a map grows: build rate, recall against exact search, single-query
//! latency with and without filters, batch throughput and memory, side by side in one run with
//! FAISS `IndexHNSWFlat` (benches/py/faiss_hnsw.py) on the same vectors.
//!
//! Rows: every image of ../shared/data (7,9xx real frames) embedded once with the shipped model
//! (cached in target/bench-cache), extended to each size with synthetic rows, each a real row
//! mixed with another (weight 0.5-1) plus isotropic Gaussian noise of norm ~0.5, renormalised:
//! near real places, but with a noise part spread evenly over all 1,712 whitened dimensions, which
//! the graph's PCA reduction keeps least of and no two rows share (the table shows each set's
//! median best-match similarity beside the real set's). Frames belong to 16 robots in turn.
//! Queries: real rows, as stored-frame queries (the frame itself excluded).
//!
//! env: LOOPD_BENCH_SIZES (default "100000,1000000"), LOOPD_BENCH_QUERIES (default 200),
//!      LOOPD_BENCH_GRAPH_DIMS, LOOPD_BENCH_M, LOOPD_BENCH_EF_ADD (the graph's settings),
//!      LOOPD_BENCH_FAISS_MAX (largest size FAISS also builds, default 100000; 0: none),
//!      LOOPD_BENCH_SWEEP_MAX (largest size the search-time settings are swept at, default 100000),
//!      LOOPD_BENCH_NOISE (the synthetic rows' noise norm, default 0.5),
//!      LOOPD_BENCH_ROWS_RESIDENT_MB (the approximate index's rows are in a mapped file, as the
//!      server keeps them, with this resident bound, also the sealed parts'; default the
//!      server's, 1024),
//!      LOOPD_BENCH_SEAL (comma-separated: the graph is built once per value, sealed into mapped
//!      parts of that many rows as the store's indexer does; 0: one graph in memory; default "0")
//!
//! Memory columns: "approx GiB in process" is what the approximate session holds in the
//! process (graph, frame records, and the rows mapped in at the end, from /proc/self/smaps,
//! also given alone);
//! "rows file GiB" the rows in their mapped file; "RSS GiB" the whole bench (it also holds the
//! f32 source rows and the exact index).
use indicatif::{ProgressBar, ProgressStyle};
use loopd::index::graph::{GraphParams, IndexKind};
use loopd::index::query::{LoopQuery, Scope};
use loopd::index::rows::Mapping;
use loopd::index::{SessionIndex, Storage};
use std::path::Path;
use std::time::Instant;

#[path = "common/embedded_rows.rs"]
mod embedded_rows;
use embedded_rows::{real_rows, root, Extension, DIM};
const ROBOTS: usize = 16;

fn env(name: &str, default: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| default.to_string())
}

/// `n` unit rows (row-major): the real rows first, then the synthetic extension.
fn rows(real: &[Vec<f32>], n: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(n * DIM);
    Extension::new(real).take(n).for_each(|r| out.extend_from_slice(&r));
    out
}

/// The graph's settings: the defaults, or LOOPD_BENCH_GRAPH_DIMS / LOOPD_BENCH_M / LOOPD_BENCH_EF_ADD.
fn params() -> GraphParams {
    let d = GraphParams::default();
    let num = |name: &str, default: usize| env(name, &default.to_string()).parse().unwrap_or(default);
    GraphParams {
        dims: num("LOOPD_BENCH_GRAPH_DIMS", d.dims),
        connectivity: num("LOOPD_BENCH_M", d.connectivity),
        expansion_add: num("LOOPD_BENCH_EF_ADD", d.expansion_add),
        ..d
    }
}

fn build(flat: &[f32], kind: IndexKind, mapping: Option<Mapping<'_>>, seal_rows: usize) -> SessionIndex {
    let mut index = SessionIndex::with_rows(DIM, Storage::F16, mapping);
    let sealed_resident = mapping.map_or(GraphParams::default().sealed_resident, |m| m.resident);
    index.set_index(kind, GraphParams { seal_rows, sealed_resident, ..params() });
    let n = flat.len() / DIM;
    let bar = ProgressBar::new(n as u64)
        .with_style(ProgressStyle::with_template("  adding {pos}/{len} {wide_bar} {eta}").expect("template"));
    for (i, row) in flat.chunks_exact(DIM).enumerate() {
        index.push(i as u64, &format!("r{}", i % ROBOTS), i as f64, None, row);
        if i % 4096 == 0 {
            bar.set_position(i as u64);
        }
    }
    bar.finish_and_clear();
    index
}

/// Builds the graph over every row, as the store's indexer does: with `seal_rows`, at most that
/// many rows in the live part, sealed into a mapped file in `dir` when full.
fn index_all(approx: &SessionIndex, dir: &Path) -> anyhow::Result<()> {
    let graph = approx.graph().ok_or_else(|| anyhow::anyhow!("no graph"))?;
    let seal = graph.params().seal_rows;
    let bar = ProgressBar::new(approx.len() as u64)
        .with_style(ProgressStyle::with_template("  indexing {pos}/{len} {wide_bar} {eta}").expect("template"));
    loop {
        let room = if seal == 0 { 1 << 16 } else { (1 << 16).min(seal - graph.live_rows()) };
        let Some(p) = approx.pending(room) else { break };
        p.graph.add_rows(p.start, &p.reduced).map_err(anyhow::Error::msg)?;
        graph.seal_if_due(dir).map_err(anyhow::Error::msg)?;
        bar.set_position(graph.covered() as u64);
    }
    bar.finish_and_clear();
    Ok(())
}

fn rss_mib() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kb: f64 = s
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches(" kB").parse().ok())
        .unwrap_or(0.0);
    kb / 1024.0
}

fn pct(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// (recall@1, recall@10, p50 ms, p99 ms) of the approximate index against the exact one.
fn measure(
    exact: &SessionIndex,
    approx: &SessionIndex,
    flat: &[f32],
    queries: &[usize],
    opts: &dyn Fn(usize) -> LoopQuery,
) -> (f64, f64, f64, f64, f64) {
    let (mut r1, mut r10, mut lat, mut lat_exact) = (0.0, 0.0, Vec::new(), Vec::new());
    for &q in queries {
        let d = &flat[q * DIM..(q + 1) * DIM];
        let o = opts(q);
        let t = Instant::now();
        let e = exact.search(d, &o, 2);
        lat_exact.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        let a = approx.search(d, &o, 2);
        lat.push(t.elapsed().as_secs_f64() * 1e3);
        let (e, a): (Vec<u64>, Vec<u64>) =
            (e.iter().map(|m| m.frame_id).collect(), a.iter().map(|m| m.frame_id).collect());
        r1 += (e.first() == a.first()) as u8 as f64;
        r10 += e.iter().filter(|id| a.contains(id)).count() as f64 / e.len().max(1) as f64;
    }
    lat.sort_by(f64::total_cmp);
    lat_exact.sort_by(f64::total_cmp);
    let n = queries.len() as f64;
    (r1 / n, r10 / n, pct(&lat, 0.5), pct(&lat, 0.99), pct(&lat_exact, 0.5))
}

/// Median best-match similarity of the rows `from..` (stored-frame queries, exact).
fn median_best(exact: &SessionIndex, flat: &[f32], rows: impl Iterator<Item = usize>) -> f32 {
    let mut s: Vec<f32> = rows
        .map(|q| {
            let o = LoopQuery { k: 1, exclude_frame: Some(q as u64), ..Default::default() };
            exact.search(&flat[q * DIM..(q + 1) * DIM], &o, 2)[0].score
        })
        .collect();
    s.sort_by(f32::total_cmp);
    s[s.len() / 2]
}

struct Faiss {
    build_per_s: f64,
    ef: u64,
    recall10: f64,
    p50_ms: f64,
}

/// FAISS IndexHNSWFlat (M 16, efConstruction 64) on the same rows (f32, all 1,712 values), at
/// the smallest efSearch reaching `recall10` (or its best).
fn faiss(flat: &[f32], queries: &[usize], recall10: f64) -> Option<Faiss> {
    let dir = tempfile::tempdir().ok()?;
    let (rows, qs) = (dir.path().join("rows.f32"), dir.path().join("queries.txt"));
    let bytes: Vec<u8> = flat.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(&rows, bytes).ok()?;
    std::fs::write(&qs, queries.iter().map(|q| q.to_string()).collect::<Vec<_>>().join("\n")).ok()?;
    let out = std::process::Command::new(root().join(".venv/bin/python"))
        .arg(root().join("benches/py/faiss_hnsw.py"))
        .args([rows.as_path(), qs.as_path()].map(Path::as_os_str))
        .arg(DIM.to_string())
        .output()
        .ok()?;
    if !out.status.success() {
        eprintln!("faiss failed: {}", String::from_utf8_lossy(&out.stderr));
        return None;
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).ok()?;
    let build_per_s = v["build_per_s"].as_f64()?;
    let sweep = v["sweep"].as_array()?;
    let pick = sweep.iter().find(|s| s["recall10"].as_f64().unwrap_or(0.0) >= recall10).or_else(|| sweep.last())?;
    Some(Faiss {
        build_per_s,
        ef: pick["ef"].as_u64()?,
        recall10: pick["recall10"].as_f64()?,
        p50_ms: pick["p50_ms"].as_f64()?,
    })
}

fn main() -> anyhow::Result<()> {
    if std::env::args().any(|a| a == "--list") {
        return Ok(());
    }
    let sizes: Vec<usize> =
        env("LOOPD_BENCH_SIZES", "100000,1000000").split(',').map(|s| s.trim().parse()).collect::<Result<_, _>>()?;
    let nq: usize = env("LOOPD_BENCH_QUERIES", "200").parse()?;
    let faiss_max: usize = env("LOOPD_BENCH_FAISS_MAX", "100000").parse()?;
    let sweep_max: usize = env("LOOPD_BENCH_SWEEP_MAX", "100000").parse()?;
    let real = real_rows()?;
    let p = params();
    println!(
        "approximate index (usearch HNSW, {}-d f16 graph of the {DIM}-d rows, M {}, ef add {}, ef search {}, {} threads adding); \
         {} real rows of ../shared/data, the rest synthetic; {nq} real stored-frame queries; exact = loopd's exact kernels, 2 threads\n",
        p.dims, p.connectivity, p.expansion_add, p.expansion_search, p.threads, real.len()
    );
    println!("| n | sealed parts | median best sim (real / synthetic) | build rows/s | recall@1 | recall@10 | p50 ms | p99 ms | exact p50 ms | same robot (1/16): recall@10, p50 ms | time 25%: recall@10, p50 ms | batch-64 q/s | graph bytes/frame | approx GiB in process | of it rows mapped in, GiB | rows file GiB | RSS GiB | FAISS HNSWFlat build rows/s | FAISS ef | FAISS recall@10 | FAISS p50 ms |");
    println!("|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|");
    let seals: Vec<usize> =
        env("LOOPD_BENCH_SEAL", "0").split(',').map(|s| s.trim().parse()).collect::<Result<_, _>>()?;
    let mut sweep = Vec::new();
    for &n in &sizes {
        let flat = rows(&real, n);
        let exact = build(&flat, IndexKind::Exact, None, 0);
        for (s, &seal) in seals.iter().enumerate() {
            let rows_dir = tempfile::tempdir_in(root().join("target"))?;
            let parts_dir = rows_dir.path().join("graph.parts");
            let resident: usize = env("LOOPD_BENCH_ROWS_RESIDENT_MB", "1024").parse::<usize>()? << 20;
            let mut approx =
                build(&flat, IndexKind::Approximate, Some(Mapping { dir: rows_dir.path(), resident }), seal);
            let t = Instant::now();
            index_all(&approx, &parts_dir)?;
            let rate = n as f64 / t.elapsed().as_secs_f64();
            let parts = approx.graph().map_or(0, |g| g.sealed_parts().len());
            let sealed_bytes = approx.graph().map_or(0, |g| g.sealed_bytes());
            let step = real.len() / nq;
            let queries: Vec<usize> = (0..nq).map(|i| i * step).collect();
            let sim_real = median_best(&exact, &flat, queries.iter().copied());
            let sim_syn = if n > real.len() {
                median_best(&exact, &flat, (0..nq).map(|i| real.len() + i * (n - real.len()) / nq))
            } else {
                f32::NAN
            };
            let plain = |q: usize| LoopQuery { k: 10, exclude_frame: Some(q as u64), ..Default::default() };
            let (r1, r10, p50, p99, exact_p50) = measure(&exact, &approx, &flat, &queries, &plain);
            let same = |q: usize| LoopQuery {
                robot_id: Some(format!("r{}", q % ROBOTS)),
                scope: Scope::SameRobot,
                ..plain(q)
            };
            let (_, same_r10, same_p50, _, _) = measure(&exact, &approx, &flat, &queries, &same);
            let quarter = |q: usize| LoopQuery { time_range: Some((0.0, (n / 4) as f64)), ..plain(q) };
            let (_, tr_r10, tr_p50, _, _) = measure(&exact, &approx, &flat, &queries, &quarter);
            let batch: Vec<Vec<f32>> =
                queries.iter().take(64).map(|&q| flat[q * DIM..(q + 1) * DIM].to_vec()).collect();
            let t = Instant::now();
            approx.search_batch(&batch, &LoopQuery { k: 10, ..Default::default() }, 2);
            let batch_qps = batch.len() as f64 / t.elapsed().as_secs_f64();
            let graph_bytes = approx.graph_bytes();
            // Search-time settings on the same graph: recall against time.
            let sweeps: &[(usize, usize)] = if n <= sweep_max && s == 0 {
                &[(64, 4), (128, 8), (256, 8), (256, 16), (512, 16), (512, 32), (1024, 32)]
            } else {
                &[]
            };
            for &(ef, per) in sweeps {
                approx.tune_graph(ef, per);
                let (r1, r10, p50, p99, _) = measure(&exact, &approx, &flat, &queries, &plain);
                sweep.push(format!("| {n} | {ef} | {} | {r1:.3} | {r10:.4} | {p50:.2} | {p99:.2} |", per * 10 + 64));
            }
            let rss = rss_mib() / 1024.0;
            // Rows and sealed parts, both mapped files under the bench's folder.
            let mapped_in = loopd::index::rows::mapped_bytes(rows_dir.path()) as f64 / (1u64 << 30) as f64;
            let in_process = approx.memory_bytes() as f64 / (1u64 << 30) as f64 + mapped_in;
            let rows_file = approx.rows_file_bytes() as f64 / (1u64 << 30) as f64;
            drop(approx);
            let f = if n <= faiss_max && s + 1 == seals.len() { faiss(&flat, &queries, r10) } else { None };
            let fc = |g: fn(&Faiss) -> String| f.as_ref().map_or_else(|| "-".to_string(), g);
            println!(
            "| {n} | {parts} | {sim_real:.3} / {sim_syn:.3} | {rate:.0} | {r1:.3} | {r10:.4} | {p50:.2} | {p99:.2} | {exact_p50:.2} | {same_r10:.4}, {same_p50:.2} | {tr_r10:.4}, {tr_p50:.2} | {batch_qps:.0} | {} | {in_process:.2} | {mapped_in:.2} | {rows_file:.2} | {rss:.1} | {} | {} | {} | {} |",
            (graph_bytes + sealed_bytes) / n,
            fc(|f| format!("{:.0}", f.build_per_s)),
            fc(|f| f.ef.to_string()),
            fc(|f| format!("{:.4}", f.recall10)),
            fc(|f| format!("{:.2}", f.p50_ms)),
        );
        }
        drop(exact);
    }
    println!("\nsearch-time settings on the same graphs (k = 10; candidates = per-result x 10 + 64, re-scored):\n");
    println!("| n | ef search | candidates | recall@1 | recall@10 | p50 ms | p99 ms |\n|--:|--:|--:|--:|--:|--:|--:|");
    sweep.iter().for_each(|row| println!("{row}"));
    Ok(())
}
