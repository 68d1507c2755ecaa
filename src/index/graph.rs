//! The approximate index: an HNSW graph (usearch) over a session's rows, for maps too large to
//! scan per query. It is derived data: the rows stay the truth, the graph is filled from them in
//! the background (`SessionIndex::pending`, the store's indexer), and searches scan exactly the
//! rows it does not cover yet. The graph holds each row reduced to its first `dims` values,
//! renormalised: loopd's whitened descriptors are PCA-ordered, so that is a PCA reduction. Its
//! candidates are re-scored on the full rows, so answers carry exact scores in exact order.
use parking_lot::{Condvar, Mutex, RwLock};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use usearch::{Index, IndexOptions, MetricKind, ScalarKind};

/// How a session searches its descriptors.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum IndexKind {
    /// Exact below [`GraphParams::min_frames`] frames, approximate from there on (never back).
    #[default]
    Auto,
    /// Every query scans every row: exact, time linear in the map.
    Exact,
    /// An HNSW graph finds the candidates, whatever the session's size.
    Approximate,
}

impl IndexKind {
    pub fn parse(s: &str) -> Result<Self, String> {
        match s {
            "" | "auto" => Ok(Self::Auto),
            "exact" => Ok(Self::Exact),
            "approximate" => Ok(Self::Approximate),
            _ => Err(format!("index '{s}' is not one of auto, exact, approximate")),
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Exact => "exact",
            Self::Approximate => "approximate",
        }
    }
}

/// The graph's shape and when `auto` sessions switch to it (docs/storage.md says how each
/// default was chosen).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GraphParams {
    /// `auto` sessions build the graph once they hold this many frames.
    pub min_frames: usize,
    /// Values of each row the graph holds (the first ones); 0 or more than the row: all of them.
    pub dims: usize,
    /// Links per node (HNSW M).
    pub connectivity: usize,
    /// Candidates kept while linking a new row (efConstruction).
    pub expansion_add: usize,
    /// Candidates kept while searching (efSearch); a query asking for more results widens it.
    pub expansion_search: usize,
    /// Candidates the graph returns per result asked for (plus 64), re-scored on the full rows:
    /// the graph ranks by reduced f16 scores.
    pub candidates_per_result: usize,
    /// Threads that add rows to a graph.
    pub threads: usize,
    /// A filter expected to leave fewer rows than this is searched exactly over those rows.
    pub exact_below: usize,
    /// ...and so is one expected to leave less than this share of the session: a graph search
    /// through a filter that rejects most nodes loses recall and time (benches/ann.rs: at 10^6
    /// frames, one robot of 16 gave recall@10 0.60 in 28.6 ms; the exact scan of its frames takes
    /// about a sixteenth of 180 ms).
    pub exact_share: f32,
    /// The store saves a session's graph once it covers this many rows more than the saved one
    /// (and at most once a minute otherwise), so a restart loads it instead of rebuilding.
    pub save_rows: usize,
}

impl Default for GraphParams {
    fn default() -> Self {
        Self {
            min_frames: 200_000,
            dims: 512,
            connectivity: 16,
            expansion_add: 64,
            expansion_search: 256,
            candidates_per_result: 16,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            exact_below: 4096,
            exact_share: 0.125,
            save_rows: 50_000,
        }
    }
}

/// Rows a graph is built from on one thread before more join.
const SERIAL_ROWS: usize = 10_000;

/// usearch contexts reserved for searches, beyond one per adding thread. More concurrent
/// searches wait for one to be free ([`Contexts`]).
const SEARCH_CONTEXTS: usize = 16;

/// usearch runs each call on one of the per-thread contexts reserved with the index, and a call
/// that finds none free fails ("Reserve capacity ahead of searches!"). This counts them, so that
/// no more calls enter the index at once than it has contexts: the others wait.
struct Contexts {
    free: Mutex<usize>,
    freed: Condvar,
}

struct Context<'a>(&'a Contexts);

impl Contexts {
    fn new(n: usize) -> Self {
        Self { free: Mutex::new(n), freed: Condvar::new() }
    }

    fn take(&self) -> Context<'_> {
        let mut free = self.free.lock();
        while *free == 0 {
            self.freed.wait(&mut free);
        }
        *free -= 1;
        Context(self)
    }
}

impl Drop for Context<'_> {
    fn drop(&mut self) {
        *self.0.free.lock() += 1;
        self.0.freed.notify_one();
    }
}

/// One session's graph. Rows `0..covered()` are in it; only the store's indexer adds (in row
/// order), searches only read.
pub struct Graph {
    /// usearch's `reserve` reallocates the nodes, contexts and vector table that additions and
    /// searches read, and must not run beside them (its documentation: "no update or search
    /// operations should be running during this operation"); growing the graph while a query
    /// searched it crashed the server (SIGSEGV in CI). Growing takes this lock for writing,
    /// every other call for reading.
    index: RwLock<Index>,
    /// Calls inside the index at once, at most the contexts it reserved.
    contexts: Contexts,
    /// How many contexts the index reserves.
    context_count: usize,
    dims: usize,
    covered: AtomicUsize,
    /// usearch's `memory_usage` as of the last addition. It walks the nodes, and a node being
    /// added meanwhile is not there yet: reading it beside `add` crashed (SIGSEGV,
    /// `store::graph::queries_search_a_graph_while_it_grows_past_several_reservations`), so only
    /// the adding thread reads it, after its additions.
    memory: AtomicUsize,
    params: GraphParams,
}

impl Graph {
    pub fn new(row_dim: usize, params: GraphParams) -> Result<Self, String> {
        let dims = if params.dims == 0 || params.dims > row_dim { row_dim } else { params.dims };
        let options = IndexOptions {
            dimensions: dims,
            metric: MetricKind::IP,
            quantization: ScalarKind::F16,
            connectivity: params.connectivity,
            expansion_add: params.expansion_add,
            expansion_search: params.expansion_search,
            multi: false,
        };
        let index = Index::new(&options).map_err(|e| format!("creating the approximate index: {e}"))?;
        let context_count = params.threads.max(1) + SEARCH_CONTEXTS;
        // Contexts from the start: a search of the empty graph needs one too.
        index
            .reserve_capacity_and_threads(1024, context_count)
            .map_err(|e| format!("reserving the approximate index: {e}"))?;
        let memory = AtomicUsize::new(index.memory_usage());
        Ok(Self {
            index: RwLock::new(index),
            contexts: Contexts::new(context_count),
            context_count,
            dims,
            covered: AtomicUsize::new(0),
            memory,
            params,
        })
    }

    pub fn dims(&self) -> usize {
        self.dims
    }

    /// Changes the search-time settings (expansion, candidates per result).
    pub fn tune(&mut self, expansion_search: usize, candidates_per_result: usize) {
        self.index.get_mut().change_expansion_search(expansion_search);
        self.params.expansion_search = expansion_search;
        self.params.candidates_per_result = candidates_per_result;
    }

    pub fn params(&self) -> GraphParams {
        self.params
    }

    /// Rows `0..covered()` are in the graph.
    pub fn covered(&self) -> usize {
        self.covered.load(Ordering::Acquire)
    }

    /// Bytes the graph holds, as of its last addition (safe beside additions and searches).
    pub fn memory_bytes(&self) -> usize {
        self.memory.load(Ordering::Relaxed)
    }

    /// The graph's view of a unit row: its first `dims` values, renormalised.
    pub fn reduce(&self, row: &[f32], out: &mut Vec<f32>) {
        out.clear();
        out.extend_from_slice(&row[..self.dims]);
        let norm = out.iter().map(|v| v * v).sum::<f32>().sqrt();
        if norm > 1e-12 {
            out.iter_mut().for_each(|v| *v /= norm);
        }
    }

    /// Adds rows `start..start + n` (`reduced`: n rows of `dims()` values, from [`Graph::reduce`]),
    /// on the configured threads. `start` must be `covered()`: the indexer adds in order.
    pub fn add_rows(&self, start: usize, reduced: &[f32]) -> Result<(), String> {
        let n = reduced.len() / self.dims;
        if start < SERIAL_ROWS && start + n > SERIAL_ROWS {
            // The serial part first, then the rest on every thread.
            let split = (SERIAL_ROWS - start) * self.dims;
            self.add_rows(start, &reduced[..split])?;
            return self.add_rows(SERIAL_ROWS, &reduced[split..]);
        }
        if start != self.covered() {
            return Err(format!("rows from {start} added to a graph covering {}", self.covered()));
        }
        // Concurrent inserts into a small graph link it worse (measured: 111 Corridor rows on two
        // threads lost 1.3% of recall@5 in a one-off probe); one thread until it has grown.
        let threads = if start < SERIAL_ROWS { 1 } else { self.params.threads.clamp(1, n.max(1)) };
        let want = start + n;
        let capacity = self.index.read().capacity();
        if capacity < want {
            // Grow geometrically: usearch copies its slots on each reserve. Alone in the index.
            let capacity = want.max(capacity * 3 / 2).max(1024);
            self.index
                .write()
                .reserve_capacity_and_threads(capacity, self.context_count)
                .map_err(|e| format!("reserving the approximate index: {e}"))?;
        }
        let index = self.index.read();
        let failed = std::sync::Mutex::new(None);
        std::thread::scope(|s| {
            for t in 0..threads {
                let (failed, index) = (&failed, &*index);
                s.spawn(move || {
                    let _context = self.contexts.take();
                    for i in (t..n).step_by(threads) {
                        let row = &reduced[i * self.dims..(i + 1) * self.dims];
                        if let Err(e) = index.add((start + i) as u64, row) {
                            *failed.lock().unwrap_or_else(|p| p.into_inner()) = Some(e.to_string());
                            return;
                        }
                    }
                });
            }
        });
        // Every addition has returned, and only this thread adds: the nodes hold still.
        self.memory.store(index.memory_usage(), Ordering::Relaxed);
        if let Some(e) = failed.into_inner().unwrap_or_else(|p| p.into_inner()) {
            return Err(format!("adding to the approximate index: {e}"));
        }
        self.covered.store(want, Ordering::Release);
        Ok(())
    }

    /// Up to `count` rows near `query` (already reduced) among those `allow` passes, best first
    /// by the graph's (reduced, f16) scores.
    pub fn search(&self, query: &[f32], count: usize, allow: impl Fn(usize) -> bool) -> Result<Vec<usize>, String> {
        let covered = self.covered();
        let index = self.index.read();
        let _context = self.contexts.take();
        let found = index
            .filtered_search(query, count, |key| (key as usize) < covered && allow(key as usize))
            .map_err(|e| format!("searching the approximate index: {e}"))?;
        Ok(found.keys.into_iter().map(|k| k as usize).collect())
    }
}

/// What a saved graph must match to be used, written beside it (`<file>.json`) after the graph
/// file itself, so a graph file without its record, or with another's, is never trusted.
#[derive(Debug, PartialEq, Serialize, Deserialize)]
struct SavedGraph {
    rows: usize,
    dims: usize,
    row_dim: usize,
    connectivity: usize,
    /// SHA-256 of the graph file.
    sha256: String,
}

fn sha256_file(path: &Path) -> Result<String, String> {
    let mut f = std::fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(|e| format!("{}: {e}", path.display()))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(format!("{:x}", h.finalize()))
}

fn record_path(path: &Path) -> PathBuf {
    path.with_extension("json")
}

fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), String> {
    let mut f = std::fs::File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
    f.write_all(bytes).and_then(|_| f.sync_all()).map_err(|e| format!("{}: {e}", path.display()))
}

impl Graph {
    /// Saves the graph (rows `0..covered()` at the call) to `path` and its record beside it, each
    /// through a temporary file renamed into place: a crash leaves the old pair or the new one.
    /// Only the indexer calls it, between its additions.
    pub fn save(&self, path: &Path, row_dim: usize) -> Result<usize, String> {
        let rows = self.covered();
        let tmp = path.with_extension("usearch.tmp");
        let tmp_str = tmp.to_str().ok_or_else(|| format!("{}: not a UTF-8 path", tmp.display()))?;
        self.index.read().save(tmp_str).map_err(|e| format!("saving the approximate index: {e}"))?;
        std::fs::File::open(&tmp).and_then(|f| f.sync_all()).map_err(|e| format!("{}: {e}", tmp.display()))?;
        let record = SavedGraph {
            rows,
            dims: self.dims,
            row_dim,
            connectivity: self.params.connectivity,
            sha256: sha256_file(&tmp)?,
        };
        let json = serde_json::to_vec(&record).map_err(|e| e.to_string())?;
        // The record goes first: until the rename of the graph file, the old graph no longer
        // matches it and is rebuilt rather than trusted.
        let rec_tmp = path.with_extension("json.tmp");
        write_synced(&rec_tmp, &json)?;
        std::fs::rename(&rec_tmp, record_path(path)).map_err(|e| format!("{}: {e}", path.display()))?;
        std::fs::rename(&tmp, path).map_err(|e| format!("{}: {e}", path.display()))?;
        if let Some(dir) = path.parent() {
            let _ = std::fs::File::open(dir).and_then(|d| d.sync_all());
        }
        Ok(rows)
    }

    /// The graph saved at `path`, if its record matches it, these parameters and a session of
    /// `row_dim`-d rows holding at least the rows it covers; why not, otherwise.
    pub fn load(path: &Path, row_dim: usize, params: GraphParams, rows_held: usize) -> Result<Self, String> {
        let json = std::fs::read(record_path(path)).map_err(|e| format!("no record beside the graph file: {e}"))?;
        let saved: SavedGraph = serde_json::from_slice(&json).map_err(|e| format!("unreadable record: {e}"))?;
        let mut graph = Self::new(row_dim, params)?;
        if (saved.dims, saved.row_dim, saved.connectivity) != (graph.dims, row_dim, params.connectivity) {
            return Err(format!(
                "saved for {}-d of {}-d rows, connectivity {}; this server wants {}-d of {row_dim}-d, connectivity {}",
                saved.dims, saved.row_dim, saved.connectivity, graph.dims, params.connectivity
            ));
        }
        if saved.rows > rows_held {
            return Err(format!("covers {} rows; the session holds {rows_held}", saved.rows));
        }
        let sha = sha256_file(path)?;
        if sha != saved.sha256 {
            return Err(format!("checksum mismatch (file {sha}, record {})", saved.sha256));
        }
        let path_str = path.to_str().ok_or_else(|| format!("{}: not a UTF-8 path", path.display()))?;
        let context_count = graph.context_count;
        let index = graph.index.get_mut();
        index.load(path_str).map_err(|e| format!("loading: {e}"))?;
        if index.size() != saved.rows || index.dimensions() != graph.dims {
            return Err(format!(
                "holds {} rows of {}-d; its record says {}",
                index.size(),
                index.dimensions(),
                saved.rows
            ));
        }
        // Loading sizes the contexts by the machine's threads; this graph counts its own.
        index
            .reserve_capacity_and_threads(index.capacity().max(saved.rows).max(1024), context_count)
            .map_err(|e| format!("reserving the approximate index: {e}"))?;
        index.change_expansion_search(params.expansion_search);
        graph.memory.store(index.memory_usage(), Ordering::Relaxed);
        graph.covered.store(saved.rows, Ordering::Release);
        Ok(graph)
    }

    /// The graph's stored (reduced, f16) values of a row, if it holds it.
    pub fn stored(&self, row: usize) -> Option<Vec<f32>> {
        let mut out = vec![0f32; self.dims];
        match self.index.read().get(row as u64, &mut out) {
            Ok(1) => Some(out),
            _ => None,
        }
    }
}
