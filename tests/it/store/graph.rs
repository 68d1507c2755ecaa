//! The approximate index under concurrency: the store's indexer grows a session's graph while
//! queries search it. usearch must not reserve (reallocate) beside a search, and enters each call
//! on one of a fixed set of contexts; CI's test binary died with SIGSEGV while both ran.
use crate::common::*;
use loopd::index::graph::{Graph, GraphParams, GraphScalar};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// Every Nordland image (summer, then winter) as a unit row of its raw pixels.
pub(super) fn nordland_rows() -> (Vec<Vec<f32>>, usize) {
    let mut rows = Vec::new();
    for season in ["summer", "winter"] {
        let dir = data(&format!("nordland-64x32/{season}"));
        let mut files: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
        files.sort();
        for f in files {
            let img = image::open(&f).unwrap().to_rgb8();
            let mut v: Vec<f32> = img.as_raw().iter().map(|&b| b as f32 / 255.0 - 0.5).collect();
            let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
            v.iter_mut().for_each(|x| *x /= norm);
            rows.push(v);
        }
    }
    let dim = rows[0].len();
    (rows, dim)
}

/// Each row as the graph holds it.
fn reduced_rows(graph: &Graph, rows: &[Vec<f32>]) -> Vec<Vec<f32>> {
    rows.iter()
        .map(|r| {
            let mut out = Vec::new();
            graph.reduce(r, &mut out);
            out
        })
        .collect()
}

#[test]
fn queries_search_a_graph_while_it_grows_past_several_reservations() {
    let (rows, dim) = nordland_rows();
    assert_eq!(rows.len(), 4800);
    // Two adding threads, as on CI's two cores; eight searchers, more than that. Whole rows: the
    // first 512 pixels are the sky of the image's top rows, alike across frames.
    let params = GraphParams { dims: 0, threads: 2, ..Default::default() };
    let graph = Graph::new(dim, params).unwrap();
    let reduced = reduced_rows(&graph, &rows);
    let done = AtomicBool::new(false);
    let (searches, failures) = (AtomicUsize::new(0), AtomicUsize::new(0));
    std::thread::scope(|s| {
        for t in 0..8 {
            let (graph, reduced, done, searches, failures) = (&graph, &reduced, &done, &searches, &failures);
            s.spawn(move || {
                let mut i = t * 611;
                while !done.load(Ordering::Acquire) {
                    i = (i + 97) % reduced.len();
                    let covered = graph.covered();
                    match graph.search(&reduced[i], 10, |_| true) {
                        Ok(found) => assert!(found.iter().all(|&r| r < graph.covered().max(covered))),
                        Err(e) => {
                            failures.fetch_add(1, Ordering::Relaxed);
                            eprintln!("search failed while the graph covered {covered}: {e}");
                        }
                    }
                    searches.fetch_add(1, Ordering::Relaxed);
                }
            });
        }
        // Sessions' figures (`GET /v1/sessions/{id}`, /metrics) read the graph's memory meanwhile.
        let (graph_, done_, reads) = (&graph, &done, &searches);
        s.spawn(move || {
            while !done_.load(Ordering::Acquire) {
                assert!(graph_.memory_bytes() > 0);
                reads.fetch_add(1, Ordering::Relaxed);
            }
        });
        // The indexer's part: rows in order, 200 at a time, so capacity grows 1024 -> 1536 -> ...
        for start in (0..rows.len()).step_by(200) {
            let end = (start + 200).min(rows.len());
            let chunk: Vec<f32> = reduced[start..end].concat();
            graph.add_rows(start, &chunk).unwrap();
        }
        done.store(true, Ordering::Release);
    });
    assert_eq!(graph.covered(), 4800);
    assert!(searches.load(Ordering::Relaxed) > 100, "only {} searches ran", searches.load(Ordering::Relaxed));
    assert_eq!(failures.load(Ordering::Relaxed), 0, "searches failed while the graph grew");
    // The graph it built answers: every 10th row finds itself first, or a frame as close to it (a
    // stopped train repeats its view); f16 rows are within 1e-3 of their own score 1.
    let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
    let probes: Vec<usize> = (0..rows.len()).step_by(10).collect();
    let misses: Vec<(usize, usize, f32)> = probes
        .iter()
        .map(|&i| {
            let best = graph.search(&reduced[i], 1, |_| true).unwrap()[0];
            (i, best, dot(&reduced[i], &reduced[best]))
        })
        .filter(|&(i, best, d)| best != i && d < 0.999)
        .collect();
    assert!(misses.len() * 100 <= probes.len() * 2, "{} of {} rows not found: {misses:?}", misses.len(), probes.len());
}

/// A graph sealed into parts (each a mapped file) answers as one graph: every 10th Nordland row
/// finds itself across the parts; saved and loaded again it maps the parts (its own memory holds
/// only the live rows) and answers the same; the parts mapped at load are hashed one per call,
/// and a part whose bytes changed is caught there (its header and length still check out at load),
/// a truncated one at load. Parts that fit their resident bound are mapped in ahead of the
/// searches, one per call; over it they are not.
#[test]
fn sealed_parts_answer_as_one_graph_and_load_mapped() {
    let (rows, dim) = nordland_rows();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.usearch");
    let parts = loopd::index::graph::parts_dir(&path);
    let params = GraphParams { dims: 0, threads: 2, seal_rows: 1500, ..Default::default() };
    let graph = Graph::new(dim, params).unwrap();
    let reduced = reduced_rows(&graph, &rows);
    for start in (0..rows.len()).step_by(500) {
        let end = (start + 500).min(rows.len());
        graph.add_rows(start, &reduced[start..end].concat()).unwrap();
        graph.seal_if_due(&parts).unwrap();
    }
    let sealed: Vec<_> = graph.sealed_parts().into_iter().map(|(r, _)| r).collect();
    assert_eq!(sealed, [0..1500, 1500..3000, 3000..4500]);
    assert_eq!((graph.covered(), graph.live_rows()), (4800, 300));
    let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
    let answers = |g: &Graph| -> Vec<Vec<usize>> {
        (0..rows.len()).step_by(10).map(|i| g.search(&reduced[i], 5, |_| true).unwrap()).collect()
    };
    let before = answers(&graph);
    let misses: Vec<usize> = (0..rows.len())
        .step_by(10)
        .zip(&before)
        .filter(|&(i, found)| found[0] != i && dot(&reduced[i], &reduced[found[0]]) < 0.999)
        .map(|(i, _)| i)
        .collect();
    assert!(misses.len() * 100 <= before.len() * 2, "{} of {} rows not found: {misses:?}", misses.len(), before.len());
    // A filter reaches into every part: only odd rows.
    for i in [7usize, 1501, 3333, 4700] {
        let found = graph.search(&reduced[i], 5, |r| r % 2 == 1).unwrap();
        assert!(!found.is_empty() && found.iter().all(|r| r % 2 == 1), "row {i}: {found:?}");
    }
    graph.save(&path, dim).unwrap();
    // A server restarted with other expansions links its new frames at those.
    let other = GraphParams { expansion_add: 40, expansion_search: 90, ..params };
    assert_eq!(Graph::load(&path, dim, other, rows.len()).unwrap().expansions(), (40, 90));
    let loaded = Graph::load(&path, dim, params, rows.len()).unwrap();
    assert_eq!(loaded.expansions(), (params.expansion_add, params.expansion_search));
    assert_eq!(loaded.sealed_parts(), graph.sealed_parts());
    assert_eq!(answers(&loaded), before);
    // Its own memory: the 300 live rows (1,024 slots reserved, and usearch's per-thread search
    // contexts), less than the 4,500 sealed ones' files (i8: 16.8 MB against 28.5 MB).
    assert!(loaded.memory_bytes() < loaded.sealed_bytes(), "{} in memory", loaded.memory_bytes());
    assert_eq!((0..4).map(|_| loaded.verify_next().unwrap()).collect::<Vec<_>>(), [true, true, true, false]);
    drop((loaded, graph));
    // Mapped in ahead of the searches when all the parts fit their bound; left to them when not
    // (a view maps in only the pages it reads at load: under 2% here).
    let file = |r: &std::ops::Range<usize>| parts.join(format!("{}-{}.usearch", r.start, r.end));
    let files: usize = sealed.iter().map(|r| std::fs::metadata(file(r)).unwrap().len() as usize).sum();
    let mapped = || loopd::index::rows::mapped_bytes(&parts);
    let over = Graph::load(&path, dim, GraphParams { sealed_resident: files - 1, ..params }, rows.len()).unwrap();
    assert!(!over.populate_next(), "parts over their bound are not mapped in ahead");
    let at_load = mapped();
    assert!(at_load * 10 < files, "{at_load} of {files} bytes mapped in at load");
    drop(over);
    let fits = Graph::load(&path, dim, GraphParams { sealed_resident: files, ..params }, rows.len()).unwrap();
    assert_eq!((0..4).map(|_| fits.populate_next()).collect::<Vec<_>>(), [true, true, true, false]);
    assert!(mapped() >= files * 99 / 100, "{} of {files} bytes mapped in", mapped());
    drop(fits);
    // The second part's bytes change after its header: mapped, then caught by its hash.
    let file = parts.join("1500-3000.usearch");
    let mut bytes = std::fs::read(&file).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid..mid + 64].iter_mut().for_each(|b| *b ^= 0x5a);
    std::fs::write(&file, &bytes).unwrap();
    let loaded = Graph::load(&path, dim, params, rows.len()).unwrap();
    assert!(loaded.verify_next().unwrap());
    let err = loaded.verify_next().unwrap_err();
    assert!(err.contains("1500-3000") && err.contains("checksum mismatch"), "{err}");
    drop(loaded);
    // Cut short: refused at load.
    std::fs::write(&file, &bytes[..mid]).unwrap();
    let err = Graph::load(&path, dim, params, rows.len()).err().unwrap();
    assert!(err.contains("1500-3000"), "{err}");
}

/// An i8 graph (`--approx-scalar i8`: each row scaled to ±127, compared by cosine) finds the
/// rows an f16 graph finds, in about half the bytes: built over every Nordland row and sealed into
/// parts, its top 10 of every 20th row holds the exact top 10 as well as the f16 graph's does;
/// saved and loaded it answers the same (also by a server since set to f16: a graph keeps its
/// scalar), the sampled check of a loaded graph against the session's rows tells its own row
/// from another, and a record naming another scalar than its files is refused.
#[test]
fn an_i8_graph_finds_what_an_f16_graph_finds_in_half_the_bytes() {
    let (rows, dim) = nordland_rows();
    let dir = tempfile::tempdir().unwrap();
    let build = |scalar: GraphScalar| {
        let params = GraphParams { dims: 0, threads: 2, seal_rows: 1500, scalar, ..Default::default() };
        let graph = Graph::new(dim, params).unwrap();
        let reduced = reduced_rows(&graph, &rows);
        let parts = dir.path().join(format!("{}.parts", scalar.as_str()));
        for start in (0..rows.len()).step_by(500) {
            let end = (start + 500).min(rows.len());
            graph.add_rows(start, &reduced[start..end].concat()).unwrap();
            graph.seal_if_due(&parts).unwrap();
        }
        (graph, reduced, params)
    };
    let (f16, reduced, _) = build(GraphScalar::F16);
    let (i8g, _, i8_params) = build(GraphScalar::I8);
    let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
    let probes: Vec<usize> = (0..rows.len()).step_by(20).collect();
    let recall = |g: &Graph| -> f32 {
        let mut hits = 0;
        for &i in &probes {
            let mut exact: Vec<(f32, usize)> = (0..rows.len()).map(|r| (dot(&reduced[i], &reduced[r]), r)).collect();
            exact.sort_by(|a, b| b.0.total_cmp(&a.0));
            // Ties at the 10th score count as found either way.
            let tenth = exact[9].0;
            let found = g.search(&reduced[i], 10, |_| true).unwrap();
            hits += found.iter().filter(|&&r| dot(&reduced[i], &reduced[r]) >= tenth - 1e-6).count().min(10);
        }
        hits as f32 / (probes.len() * 10) as f32
    };
    let (r16, r8) = (recall(&f16), recall(&i8g));
    eprintln!("recall@10 of the graphs' own top 10: f16 {r16:.4}, i8 {r8:.4}");
    assert!(r8 >= 0.9 && r8 >= r16 - 0.02, "i8 recall@10 {r8} against f16's {r16}");
    // The sealed parts' files (4,500 rows each; the live part's memory counts reserved slots).
    let (b8, b16) = (i8g.sealed_bytes(), f16.sealed_bytes());
    assert!(b8 * 100 < b16 * 55, "i8 parts {b8} bytes, f16 {b16}");
    // Saved and loaded (the parts mapped): the same answers.
    let path = dir.path().join("i8.usearch");
    i8g.save(&path, dim).unwrap();
    let before: Vec<_> = probes.iter().map(|&i| i8g.search(&reduced[i], 5, |_| true).unwrap()).collect();
    let loaded = Graph::load(&path, dim, i8_params, rows.len()).unwrap();
    let after: Vec<_> = probes.iter().map(|&i| loaded.search(&reduced[i], 5, |_| true).unwrap()).collect();
    assert_eq!(after, before);
    assert_eq!((loaded.holds(4700, &reduced[4700]), loaded.holds(1600, &reduced[1600])), (Some(true), Some(true)));
    assert_eq!(loaded.holds(1600, &reduced[4700]), Some(false));
    // A server since set to f16 keeps the saved graph's i8 (no rebuild), and adds to it as i8.
    drop(loaded);
    let f16_params = GraphParams { scalar: GraphScalar::F16, ..i8_params };
    let kept = Graph::load(&path, dim, f16_params, rows.len()).unwrap();
    assert_eq!(kept.params().scalar, GraphScalar::I8);
    let after: Vec<_> = probes.iter().map(|&i| kept.search(&reduced[i], 5, |_| true).unwrap()).collect();
    assert_eq!(after, before);
    drop(kept);
    // A record naming another scalar than its files' headers is refused (the server then rebuilds
    // the graph from the rows), whether a sealed part or the live part shows it.
    let misnamed = |path: &std::path::Path| {
        let record = path.with_extension("json");
        let json = std::fs::read_to_string(&record).unwrap();
        assert!(json.contains(r#""scalar":"i8""#), "{json}");
        std::fs::write(&record, json.replace(r#""scalar":"i8""#, r#""scalar":"f16""#)).unwrap();
        Graph::load(path, dim, i8_params, rows.len()).err().unwrap()
    };
    let err = misnamed(&path);
    assert!(err.contains("i8.parts") && err.contains("not a f16 graph"), "{err}");
    let live = Graph::new(dim, GraphParams { seal_rows: rows.len() + 1, ..i8_params }).unwrap();
    live.add_rows(0, &reduced[..500].concat()).unwrap();
    let live_path = dir.path().join("live.usearch");
    live.save(&live_path, dim).unwrap();
    let err = misnamed(&live_path);
    assert!(err.contains("live.usearch: not a f16 graph"), "{err}");
}

/// Writes and the store's indexer never wait on each other. The indexer once took a session's
/// index lock for reading twice in one turn; parking_lot's locks are fair, so a writer queued
/// between the two reads blocked the second and waited on the first: the frame's publish on the
/// flusher thread, and with it every later write, waited forever (CI timed out in
/// `kept::kept_rows_that_do_not_check_out_are_read_again_from_sled`). Four writers add Nordland
/// frames one at a time for 3 s while the indexer builds the session's graph from them.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn writers_never_wait_on_the_indexer() {
    use loopd::index::graph::IndexKind;
    use loopd::store::{NewSession, SearchConfig, Store};
    use std::sync::Arc;
    use std::time::{Duration, Instant};
    let (rows, dim) = nordland_rows();
    let rows = Arc::new(rows);
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::open_with(dir.path(), SearchConfig::default()).unwrap());
    let new = NewSession { index: IndexKind::Approximate, ..super::kept::nordland_session(dim) };
    store.create_session(Some("nordland".into()), new).await.unwrap();
    let s = store.session("nordland").unwrap();
    let until = Instant::now() + Duration::from_secs(3);
    let writers: Vec<_> = (0..4)
        .map(|w| {
            let (store, s, rows) = (store.clone(), s.clone(), rows.clone());
            tokio::spawn(async move {
                let mut added = 0;
                for i in (w..rows.len()).step_by(4) {
                    if Instant::now() > until {
                        break;
                    }
                    let write = store.add_frames(&s, vec![super::kept::frame(&rows, i)]);
                    match tokio::time::timeout(Duration::from_secs(20), write).await {
                        Ok(written) => added += written.unwrap().len(),
                        Err(_) => return Err(format!("writer {w}: frame {i} not written after 20 s")),
                    }
                }
                Ok(added)
            })
        })
        .collect();
    let (mut added, mut stuck) = (0, Vec::new());
    for w in writers {
        match w.await.unwrap() {
            Ok(n) => added += n,
            Err(e) => stuck.push(e),
        }
    }
    if !stuck.is_empty() {
        // A store whose flusher waits forever cannot be dropped: its drop waits for the flusher.
        std::mem::forget((s, store));
        panic!("writes waited on the indexer: {stuck:?}");
    }
    assert!(added >= 40, "only {added} frames written in 3 s");
    // The indexer kept going too: its graph takes every written frame.
    let t = Instant::now();
    while s.info().approximate_frames != Some(added) {
        assert!(t.elapsed() < Duration::from_secs(30), "graph: {:?} of {added} frames", s.info().approximate_frames);
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
