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
//! The rows are streamed into the session's mapped rows file, not held by the bench (10^7 rows
//! fit), and the exact answers come from loopd's exact scan of those same rows (the kernel a
//! filter that leaves few rows gets), so the bench's RSS is the session's.
//!
//! env: LOOPD_BENCH_SIZES (default "100000,1000000"), LOOPD_BENCH_QUERIES (default 200),
//!      LOOPD_BENCH_GRAPH_DIMS, LOOPD_BENCH_M, LOOPD_BENCH_EF_ADD, LOOPD_BENCH_SCALAR (f16 or i8)
//!      (the graph's settings),
//!      LOOPD_BENCH_FAISS_MAX (largest size FAISS also builds, default 100000; 0: none),
//!      LOOPD_BENCH_SWEEP_MAX (largest size the search-time settings are swept at, default 100000),
//!      LOOPD_BENCH_NOISE (the synthetic rows' noise norm, default 0.5),
//!      LOOPD_BENCH_ROW_DIMS (the rows' values: the first ones of each real row, renormalised,
//!      which is the PCA reduction of the model's whitened output; default all 1,712),
//!      LOOPD_BENCH_ROWS_RESIDENT_MB (the approximate index's rows are in a mapped file, as the
//!      server keeps them, with this resident bound; default the server's, 1024),
//!      LOOPD_BENCH_SEALED_RESIDENT_MB (the sealed graph parts' resident bound; default the
//!      rows' bound, as the server's `--approx-sealed-resident-mb`),
//!      LOOPD_BENCH_SEAL (comma-separated: the graph is built once per value, sealed into mapped
//!      parts of that many rows as the store's indexer does; 0: one graph in memory; default "0")
//!
//! Memory columns: "approx GiB in process" is what the approximate session holds in the
//! process (graph, frame records, and the rows mapped in at the end, from /proc/self/smaps,
//! also given alone);
//! "graph reopen" what a restart does with the saved graph (sealed parts mapped, live part read).
//! "rows file GiB" the rows in their mapped file; "RSS GiB" the whole bench (also the real rows,
//! and at FAISS's sizes the f32 rows FAISS is given).
use indicatif::{ProgressBar, ProgressStyle};
use loopd::index::graph::{Graph, GraphParams, IndexKind};
use loopd::index::query::{LoopQuery, Match, Scope};
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

/// The graph's settings: the defaults, or LOOPD_BENCH_GRAPH_DIMS / LOOPD_BENCH_M / LOOPD_BENCH_EF_ADD.
fn params() -> GraphParams {
    let d = GraphParams::default();
    let num = |name: &str, default: usize| env(name, &default.to_string()).parse().unwrap_or(default);
    GraphParams {
        dims: num("LOOPD_BENCH_GRAPH_DIMS", d.dims),
        connectivity: num("LOOPD_BENCH_M", d.connectivity),
        expansion_add: num("LOOPD_BENCH_EF_ADD", d.expansion_add),
        scalar: loopd::index::graph::GraphScalar::parse(&env("LOOPD_BENCH_SCALAR", d.scalar.as_str()))
            .unwrap_or(d.scalar),
        ..d
    }
}

/// The real rows as the bench's sessions hold them: their first `dims` values (the model's
/// whitened output is in PCA order, so that is the PCA reduction), renormalised.
fn reduced_real(real: &[Vec<f32>], dims: usize) -> Vec<Vec<f32>> {
    real.iter()
        .map(|r| {
            let mut v = r[..dims.min(r.len())].to_vec();
            loopd::index::normalize(&mut v).expect("non-zero");
            v
        })
        .collect()
}

/// An approximate session of the first `n` rows (streamed: nothing else holds them), its rows in
/// a mapped file in `dir`; also the f32 rows when `keep` (FAISS reads them).
fn build(
    real: &[Vec<f32>],
    n: usize,
    dir: &Path,
    (resident, sealed_resident): (usize, usize),
    seal_rows: usize,
    keep: bool,
) -> (SessionIndex, Vec<f32>) {
    let dim = real[0].len();
    let mut index = SessionIndex::with_rows(dim, Storage::F16, Some(Mapping { dir, resident }));
    index.set_index(IndexKind::Approximate, GraphParams { seal_rows, sealed_resident, ..params() });
    let mut kept = Vec::with_capacity(if keep { n * dim } else { 0 });
    let bar = ProgressBar::new(n as u64)
        .with_style(ProgressStyle::with_template("  adding {pos}/{len} {wide_bar} {eta}").expect("template"));
    for (i, row) in Extension::new(real).take(n).enumerate() {
        index.push(i as u64, &format!("r{}", i % ROBOTS), i as f64, None, &row);
        if keep {
            kept.extend_from_slice(&row);
        }
        if i % 4096 == 0 {
            bar.set_position(i as u64);
        }
    }
    bar.finish_and_clear();
    (index, kept)
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

fn drop_caches() -> bool {
    let _ = std::process::Command::new("sync").status();
    std::fs::write("/proc/sys/vm/drop_caches", "3").is_ok()
}

/// Saves the session's graph as the store does, drops the session, and times what a restart
/// does with the graph (`Graph::load`: sealed parts mapped and checked by header, the live part
/// hashed and read), first with the page cache dropped (NaN if it could not be), then again.
fn reopen(approx: SessionIndex, dir: &Path) -> anyhow::Result<(f64, f64)> {
    let graph = approx.graph().ok_or_else(|| anyhow::anyhow!("no graph"))?;
    let (path, dim, rows, params) = (dir.join("graph.usearch"), approx.dim(), approx.len(), graph.params());
    graph.save(&path, dim).map_err(anyhow::Error::msg)?;
    drop((graph, approx));
    let cold = drop_caches();
    let mut secs = [0.0; 2];
    for s in &mut secs {
        let t = Instant::now();
        let g = Graph::load(&path, dim, params, rows).map_err(anyhow::Error::msg)?;
        *s = t.elapsed().as_secs_f64();
        anyhow::ensure!(g.covered() == rows, "the reopened graph covers {} of {rows} rows", g.covered());
    }
    Ok((if cold { secs[0] } else { f64::NAN }, secs[1]))
}

fn pct(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// Switches the session between its graph and loopd's exact scan of every allowed row (the
/// kernel a filter leaving few rows gets): the ground truth, on the same mapped rows.
fn force_exact(index: &mut SessionIndex, exact: bool) {
    let exact_share = if exact { f32::INFINITY } else { GraphParams::default().exact_share };
    index.set_index(IndexKind::Approximate, GraphParams { exact_share, ..index.graph_params() });
}

/// The exact answers (frame ids) to each query, and their p50 latency in ms.
fn truth(
    index: &mut SessionIndex,
    queries: &[Vec<f32>],
    ids: &[usize],
    opts: &dyn Fn(usize) -> LoopQuery,
) -> (Vec<Vec<Match>>, f64) {
    force_exact(index, true);
    let bar = ProgressBar::new(queries.len() as u64)
        .with_style(ProgressStyle::with_template("  exact answers {pos}/{len} {wide_bar} {eta}").expect("template"));
    let mut lat = Vec::new();
    let found = queries
        .iter()
        .zip(ids)
        .map(|(q, &id)| {
            let t = Instant::now();
            let m = index.search(q, &opts(id), 2);
            lat.push(t.elapsed().as_secs_f64() * 1e3);
            bar.inc(1);
            m
        })
        .collect();
    bar.finish_and_clear();
    force_exact(index, false);
    lat.sort_by(f64::total_cmp);
    (found, pct(&lat, 0.5))
}

/// Scores this close to the exact k-th best count as ties (the same row values: the real
/// images hold exact duplicates, 48 groups of up to 17 among 7,935).
const TIE: f32 = 1e-6;

struct Recall {
    /// The best answer scores as the exact best (a tie counts).
    r1: f64,
    /// Answers scoring at least the exact 10th best, per exact answer (ties count: what
    /// ann-benchmarks counts).
    r10: f64,
    /// The same by frame id, ties not counted.
    r10_ids: f64,
    p50: f64,
    p99: f64,
}

/// Recall and latency of the graph against the exact answers.
fn measure(
    approx: &SessionIndex,
    queries: &[Vec<f32>],
    ids: &[usize],
    exact: &[Vec<Match>],
    opts: &dyn Fn(usize) -> LoopQuery,
) -> Recall {
    let (mut r1, mut r10, mut r10_ids, mut lat) = (0.0, 0.0, 0.0, Vec::new());
    for ((q, &id), e) in queries.iter().zip(ids).zip(exact) {
        let t = Instant::now();
        let a = approx.search(q, &opts(id), 2);
        lat.push(t.elapsed().as_secs_f64() * 1e3);
        let (Some(best), Some(last)) = (e.first(), e.last()) else { continue };
        r1 += a.first().is_some_and(|m| m.score >= best.score - TIE) as u8 as f64;
        r10 += a.iter().take(e.len()).filter(|m| m.score >= last.score - TIE).count() as f64 / e.len() as f64;
        r10_ids += e.iter().filter(|x| a.iter().any(|m| m.frame_id == x.frame_id)).count() as f64 / e.len() as f64;
    }
    lat.sort_by(f64::total_cmp);
    let n = queries.len() as f64;
    Recall { r1: r1 / n, r10: r10 / n, r10_ids: r10_ids / n, p50: pct(&lat, 0.5), p99: pct(&lat, 0.99) }
}

fn median(mut v: Vec<f32>) -> f32 {
    v.sort_by(f32::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f32::NAN)
}

struct Faiss {
    build_per_s: f64,
    ef: u64,
    recall10: f64,
    p50_ms: f64,
}

/// FAISS IndexHNSWFlat on the same rows (f32, all their values), built with the graph's
/// connectivity and expansion (`graph`), at the smallest efSearch reaching `recall10` (or its best).
fn faiss(flat: &[f32], dim: usize, queries: &[usize], recall10: f64, graph: &GraphParams) -> Option<Faiss> {
    let dir = tempfile::tempdir().ok()?;
    let (rows, qs) = (dir.path().join("rows.f32"), dir.path().join("queries.txt"));
    let bytes: Vec<u8> = flat.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(&rows, bytes).ok()?;
    std::fs::write(&qs, queries.iter().map(|q| q.to_string()).collect::<Vec<_>>().join("\n")).ok()?;
    let out = std::process::Command::new(root().join(".venv/bin/python"))
        .arg(root().join("benches/py/faiss_hnsw.py"))
        .args([rows.as_path(), qs.as_path()].map(Path::as_os_str))
        .args([dim, graph.connectivity, graph.expansion_add].map(|v| v.to_string()))
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
    let dim: usize = env("LOOPD_BENCH_ROW_DIMS", &DIM.to_string()).parse()?;
    let real = reduced_real(&real_rows()?, dim);
    let dim = real[0].len();
    let p = params();
    println!(
        "approximate index (usearch HNSW, {}-d {} graph of the {dim}-d f16 rows, M {}, ef add {}, ef search {}, {} threads adding); \
         {} real rows of ../shared/data, the rest synthetic; {nq} real stored-frame queries; exact = loopd's exact scan of the same mapped rows, 2 threads\n",
        p.dims.min(dim), p.scalar.as_str(), p.connectivity, p.expansion_add, p.expansion_search, p.threads, real.len()
    );
    println!("| n | row dims | sealed parts | median best sim (real / synthetic) | build rows/s | recall@1 | recall@10 | recall@10 by id | p50 ms | p99 ms | exact p50 ms | same robot (1/16): recall@10, p50 ms | time 25%: recall@10, p50 ms | batch-64 q/s | graph bytes/frame | approx GiB in process | of it mapped in, GiB | rows file GiB | RSS GiB | graph reopen s, cold / warm | FAISS HNSWFlat build rows/s | FAISS ef | FAISS recall@10 | FAISS p50 ms |");
    println!("|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|");
    let seals: Vec<usize> =
        env("LOOPD_BENCH_SEAL", "0").split(',').map(|s| s.trim().parse()).collect::<Result<_, _>>()?;
    let resident: usize = env("LOOPD_BENCH_ROWS_RESIDENT_MB", "1024").parse::<usize>()? << 20;
    let sealed_resident: usize = match std::env::var("LOOPD_BENCH_SEALED_RESIDENT_MB") {
        Ok(v) => v.parse::<usize>()? << 20,
        Err(_) => resident,
    };
    let (mut sweep, mut restart) = (Vec::new(), Vec::new());
    for &n in &sizes {
        for (s, &seal) in seals.iter().enumerate() {
            let rows_dir = tempfile::tempdir_in(root().join("target"))?;
            let parts_dir = rows_dir.path().join("graph.parts");
            let with_faiss = n <= faiss_max && s + 1 == seals.len();
            let (mut approx, flat) = build(&real, n, rows_dir.path(), (resident, sealed_resident), seal, with_faiss);
            let t = Instant::now();
            index_all(&approx, &parts_dir)?;
            let rate = n as f64 / t.elapsed().as_secs_f64();
            let parts = approx.graph().map_or(0, |g| g.sealed_parts().len());
            let sealed_bytes = approx.graph().map_or(0, |g| g.sealed_bytes());
            let step = real.len() / nq;
            let ids: Vec<usize> = (0..nq).map(|i| i * step).collect();
            let queries: Vec<Vec<f32>> = ids.iter().map(|&i| real[i].clone()).collect();
            let plain = |q: usize| LoopQuery { k: 10, exclude_frame: Some(q as u64), ..Default::default() };
            let same = |q: usize| LoopQuery {
                robot_id: Some(format!("r{}", q % ROBOTS)),
                scope: Scope::SameRobot,
                ..plain(q)
            };
            let quarter = |q: usize| LoopQuery { time_range: Some((0.0, (n / 4) as f64)), ..plain(q) };
            let (exact_plain, exact_p50) = truth(&mut approx, &queries, &ids, &plain);
            let (exact_same, _) = truth(&mut approx, &queries, &ids, &same);
            let (exact_quarter, _) = truth(&mut approx, &queries, &ids, &quarter);
            let sim_real = median(exact_plain.iter().filter_map(|m| m.first()).map(|m| m.score).collect());
            let sim_syn = if n > real.len() {
                let syn: Vec<usize> = (0..nq).map(|i| real.len() + i * (n - real.len()) / nq).collect();
                let rows: Vec<Vec<f32>> = syn.iter().filter_map(|&i| approx.descriptor(i as u64)).collect();
                let best = |q: usize| LoopQuery { k: 1, ..plain(q) };
                let (found, _) = truth(&mut approx, &rows, &syn, &best);
                median(found.iter().filter_map(|m| m.first()).map(|m| m.score).collect())
            } else {
                f32::NAN
            };
            let all = measure(&approx, &queries, &ids, &exact_plain, &plain);
            let robot = measure(&approx, &queries, &ids, &exact_same, &same);
            let time = measure(&approx, &queries, &ids, &exact_quarter, &quarter);
            // A restart finds the sealed parts mapped in only where the load read them, and in
            // the page cache or not (a reboot, other files since): the first queries against
            // that, then against the parts mapped in ahead, as the store's indexer now does; both
            // from the page cache as it is, then both with it dropped first (when it can be).
            for drop_first in [false, true] {
                let Some(g) = approx.graph().filter(|_| parts > 0) else { break };
                g.release_sealed();
                if drop_first && !drop_caches() {
                    break;
                }
                // One exact scan maps every row in again: both measure the parts alone.
                truth(&mut approx, &queries[..1], &ids[..1], &plain);
                let demand = measure(&approx, &queries, &ids, &exact_plain, &plain);
                g.release_sealed();
                if drop_first {
                    drop_caches();
                }
                truth(&mut approx, &queries[..1], &ids[..1], &plain);
                let t = Instant::now();
                let mut ahead_parts = 0;
                while g.populate_next() {
                    ahead_parts += 1;
                }
                let ahead_s = t.elapsed().as_secs_f64();
                let ahead = measure(&approx, &queries, &ids, &exact_plain, &plain);
                restart.push(format!(
                    "| {n} | {parts} | {:.2} | {} | {} | {:.2} | {:.2} | {ahead_s:.2} | {:.2} | {:.2} |",
                    sealed_bytes as f64 / (1u64 << 30) as f64,
                    sealed_resident >> 20,
                    if drop_first { "dropped" } else { "as left" },
                    demand.p50,
                    demand.p99,
                    ahead.p50,
                    ahead.p99,
                ));
                if ahead_parts < parts {
                    restart.push(format!("|  | ({ahead_parts} of {parts} parts mapped in ahead: over the bound) |"));
                }
            }
            let batch: Vec<Vec<f32>> = queries.iter().take(64).cloned().collect();
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
                let r = measure(&approx, &queries, &ids, &exact_plain, &plain);
                sweep.push(format!(
                    "| {n} | {ef} | {} | {:.3} | {:.4} | {:.4} | {:.2} | {:.2} |",
                    per * 10 + 64,
                    r.r1,
                    r.r10,
                    r.r10_ids,
                    r.p50,
                    r.p99
                ));
            }
            let rss = rss_mib() / 1024.0;
            // Rows and sealed parts, both mapped files under the bench's folder.
            let mapped_in = loopd::index::rows::mapped_bytes(rows_dir.path()) as f64 / (1u64 << 30) as f64;
            let in_process = approx.memory_bytes() as f64 / (1u64 << 30) as f64 + mapped_in;
            let rows_file = approx.rows_file_bytes() as f64 / (1u64 << 30) as f64;
            let (reopen_cold, reopen_warm) = reopen(approx, rows_dir.path())?;
            let f = if with_faiss { faiss(&flat, dim, &ids, all.r10, &params()) } else { None };
            drop(flat);
            let fc = |g: fn(&Faiss) -> String| f.as_ref().map_or_else(|| "-".to_string(), g);
            println!(
            "| {n} | {dim} | {parts} | {sim_real:.3} / {sim_syn:.3} | {rate:.0} | {:.3} | {:.4} | {:.4} | {:.2} | {:.2} | {exact_p50:.2} | {:.4}, {:.2} | {:.4}, {:.2} | {batch_qps:.0} | {} | {in_process:.2} | {mapped_in:.2} | {rows_file:.2} | {rss:.1} | {reopen_cold:.2} / {reopen_warm:.2} | {} | {} | {} | {} |",
            all.r1,
            all.r10,
            all.r10_ids,
            all.p50,
            all.p99,
            robot.r10,
            robot.p50,
            time.r10,
            time.p50,
            (graph_bytes + sealed_bytes) / n,
            fc(|f| format!("{:.0}", f.build_per_s)),
            fc(|f| f.ef.to_string()),
            fc(|f| format!("{:.4}", f.recall10)),
            fc(|f| format!("{:.2}", f.p50_ms)),
        );
        }
    }
    println!("\nsearch-time settings on the same graphs (k = 10; candidates = per-result x 10 + 64, re-scored):\n");
    println!("| n | ef search | candidates | recall@1 | recall@10 | recall@10 by id | p50 ms | p99 ms |\n|--:|--:|--:|--:|--:|--:|--:|--:|");
    sweep.iter().for_each(|row| println!("{row}"));
    if !restart.is_empty() {
        println!("\nafter a restart (sealed parts not mapped in): the first queries with the parts mapped in by the searches, then mapped in ahead:\n");
        println!("| n | sealed parts | parts GiB | parts' bound MiB | page cache | on demand p50 ms | p99 ms | mapped in ahead, s | ahead p50 ms | p99 ms |\n|--:|--:|--:|--:|---|--:|--:|--:|--:|--:|");
        restart.iter().for_each(|row| println!("{row}"));
    }
    Ok(())
}
