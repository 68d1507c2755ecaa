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
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use usearch::ffi::IndexMetadata;
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

/// How the graph stores each reduced row. The graph only finds candidates (they are re-scored on
/// the full rows), so its values need only rank neighbours as the rows do.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GraphScalar {
    /// Half floats, compared by inner product (the rows are unit vectors). Graphs saved before
    /// i8 existed are f16 (their records name no scalar).
    #[default]
    F16,
    /// Bytes: each row scaled so its largest value is ±127 and rounded, compared by cosine, which
    /// that scale does not change. The server's default since 2026-12-07: at 10^6 frames (256-d,
    /// four parts) 404 graph bytes a frame against 660, build 1.26x and p50 0.68x f16's at the
    /// same recall (docs/performance.md "An i8 graph").
    I8,
}

impl GraphScalar {
    pub fn parse(s: &str) -> Result<Self, String> {
        match s {
            "f16" => Ok(Self::F16),
            "i8" => Ok(Self::I8),
            _ => Err(format!("'{s}' is not one of f16, i8")),
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Self::F16 => "f16",
            Self::I8 => "i8",
        }
    }
}

/// `row` as an i8 graph holds it: scaled so its largest value is ±127, rounded.
pub fn to_i8(row: &[f32], out: &mut Vec<i8>) {
    let max = row.iter().fold(0f32, |m, v| m.max(v.abs()));
    let scale = if max > 0.0 && max.is_finite() { 127.0 / max } else { 0.0 };
    out.clear();
    out.extend(row.iter().map(|v| (v * scale).round().clamp(-127.0, 127.0) as i8));
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
    /// the graph ranks by its reduced (i8 or f16) scores.
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
    /// The live part of a graph (in the process's memory) is sealed into a mapped file of its
    /// own once it holds this many rows (0: never), so memory and restart are bounded by it,
    /// not by the map; each sealed part costs a query one more graph search.
    pub seal_rows: usize,
    /// Bytes of a sealed part's pages a session keeps mapped in before it releases them.
    pub sealed_resident: usize,
    /// How the graph stores its rows.
    pub scalar: GraphScalar,
}

impl Default for GraphParams {
    fn default() -> Self {
        Self {
            min_frames: 200_000,
            dims: 512,
            connectivity: 16,
            expansion_add: 128,
            expansion_search: 256,
            candidates_per_result: 16,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            exact_below: 4096,
            exact_share: 0.125,
            save_rows: 50_000,
            seal_rows: 2_000_000,
            sealed_resident: 1 << 30,
            scalar: GraphScalar::I8,
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

/// A sealed part of a graph: rows `start..end`, written to a file of its own once and searched
/// through a read-only mapping of it (usearch's view), so it costs the process the pages searches
/// touch, not its size, and a restart maps it instead of reading it.
struct Sealed {
    // Dropped in this order: the view points into the mapping.
    index: Index,
    map: memmap2::Mmap,
    start: usize,
    end: usize,
    file: PathBuf,
    sha256: String,
    /// Its file hashed against `sha256` since it was mapped (a sealed part written by this
    /// process is; one mapped at start is checked by sample at once, hashed in full later).
    verified: AtomicBool,
    /// Its pages mapped in ahead of the searches (`Graph::populate_next`).
    populated: AtomicBool,
    contexts: Contexts,
}

/// Bytes a search is estimated to map in per candidate it keeps, per link of a node: each visited
/// node's vector and links sit on a page of their own in a large file.
const PAGE: usize = 4096;

impl Sealed {
    /// Maps `file` (rows `start..end` of `dims`-d) and views it as a graph.
    fn open(
        file: &Path,
        (start, end): (usize, usize),
        (dims, scalar): (usize, GraphScalar),
        sha256: String,
        bytes: Option<u64>,
    ) -> Result<Self, String> {
        let f = std::fs::File::open(file).map_err(|e| format!("{}: {e}", file.display()))?;
        let len = f.metadata().map_err(|e| format!("{}: {e}", file.display()))?.len();
        if bytes.is_some_and(|b| b != len) {
            return Err(format!("{}: {len} bytes; its record says {}", file.display(), bytes.unwrap_or(0)));
        }
        // SAFETY: the file is this store's own (the data directory is locked by sled), written
        // once through a temporary file and a rename and never written again: nothing changes
        // the mapped bytes while the mapping lives. It is read-only.
        let map = unsafe { memmap2::Mmap::map(&f) }.map_err(|e| format!("mapping {}: {e}", file.display()))?;
        let meta =
            Index::metadata_from_buffer(&map).map_err(|e| format!("{}: not a graph file: {e}", file.display()))?;
        if meta.dimensions != dims as u64 || meta.count_present != (end - start) as u64 {
            return Err(format!(
                "{}: {} rows of {}-d; its record says {} of {dims}-d",
                file.display(),
                meta.count_present,
                meta.dimensions,
                end - start
            ));
        }
        Graph::check_kinds(file, &meta, scalar)?;
        let index =
            Index::new(&IndexOptions::from(meta)).map_err(|e| format!("creating the approximate index: {e}"))?;
        // SAFETY: the view points into `map`, which `Self` owns and drops after `index` (field
        // order), and whose bytes nothing changes (above).
        unsafe { index.view_from_buffer(&map) }.map_err(|e| format!("viewing {}: {e}", file.display()))?;
        if index.size() != end - start || index.dimensions() != dims {
            return Err(format!("{}: holds {} rows of {}-d", file.display(), index.size(), index.dimensions()));
        }
        // The view walked the nodes in order; searches visit them all over the file: no
        // read-ahead around each miss from now on.
        let _ = map.advise(memmap2::Advice::Random);
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get()) + SEARCH_CONTEXTS;
        // A view cannot grow; reserving sizes only its per-thread contexts.
        let contexts = match index.reserve_capacity_and_threads(index.size(), threads) {
            Ok(()) => threads,
            Err(_) => std::thread::available_parallelism().map_or(1, |n| n.get()),
        };
        Ok(Self {
            index,
            map,
            start,
            end,
            file: file.to_path_buf(),
            sha256,
            verified: AtomicBool::new(false),
            populated: AtomicBool::new(false),
            contexts: Contexts::new(contexts),
        })
    }

    /// Maps the part's pages into the process (`MADV_POPULATE_READ`: from the page cache, or the
    /// file), so that searches do not fault each node they visit in one at a time.
    fn populate(&self) -> Result<(), String> {
        let failed = |e: std::io::Error| format!("mapping {} in: {e}", self.file.display());
        // Sequential while it is read in, random again for the searches: under the random advice
        // parts not in the page cache are read a page per fault (four parts, 1.09 GiB: 19.4 s
        // here, against 0.82 s with this; docs/performance.md "after a restart").
        self.map.advise(memmap2::Advice::Sequential).map_err(failed)?;
        #[cfg(target_os = "linux")]
        let populated = self.map.advise(memmap2::Advice::PopulateRead).map_err(failed);
        #[cfg(not(target_os = "linux"))]
        let populated = self.map.advise(memmap2::Advice::WillNeed).map_err(failed);
        self.map.advise(memmap2::Advice::Random).map_err(failed)?;
        populated
    }

    /// Unmaps the part's pages from the process (they stay in the file and the page cache).
    fn release(&self) {
        // SAFETY: MADV_DONTNEED on a shared read-only file mapping drops the process's page
        // table entries only; the next read maps the file's (unchanged) bytes in again, so a
        // search running beside it reads the same values (as `rows.rs` releases rows).
        if let Err(e) = unsafe { self.map.unchecked_advise(memmap2::UncheckedAdvice::DontNeed) } {
            tracing::debug!(error = %e, "releasing a mapped graph part failed");
        }
    }
}

/// One session's graph. Rows `0..covered()` are in it: the sealed parts' rows (in order, each a
/// mapped file), then the live part's, in memory. Only the store's indexer adds (in row order)
/// and seals; searches only read.
pub struct Graph {
    /// The live part: rows `live_start..covered()`.
    ///
    /// usearch's `reserve` reallocates the nodes, contexts and vector table that additions and
    /// searches read, and must not run beside them (its documentation: "no update or search
    /// operations should be running during this operation"); growing the graph while a query
    /// searched it crashed the server (SIGSEGV in CI). Growing takes this lock for writing,
    /// every other call for reading. Sealing takes it for writing too, while it moves the live
    /// rows into a sealed part, so a search holding it sees every row once.
    index: RwLock<Index>,
    /// The sealed parts, in row order, ending at `live_start`.
    sealed: RwLock<Vec<Arc<Sealed>>>,
    live_start: AtomicUsize,
    /// Calls inside the live part at once, at most the contexts it reserved.
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
    /// Bytes of the sealed parts searches are estimated to have mapped in since their pages were
    /// last released (at `sealed_resident`).
    touched: AtomicUsize,
    params: GraphParams,
}

impl Graph {
    /// How usearch compares and stores rows of this scalar: f16 rows are unit length, so their
    /// inner product is the cosine; i8 rows are scaled by `to_i8`, so only the cosine is.
    fn kinds(scalar: GraphScalar) -> (MetricKind, ScalarKind) {
        match scalar {
            GraphScalar::F16 => (MetricKind::IP, ScalarKind::F16),
            GraphScalar::I8 => (MetricKind::Cos, ScalarKind::I8),
        }
    }

    /// Refuses a graph file whose header names another scalar or metric than its record: its
    /// bytes would be read as the wrong values (the graph is then rebuilt from the rows).
    fn check_kinds(file: &Path, meta: &IndexMetadata, scalar: GraphScalar) -> Result<(), String> {
        if (meta.metric, meta.quantization) != Self::kinds(scalar) {
            return Err(format!("{}: not a {} graph", file.display(), scalar.as_str()));
        }
        Ok(())
    }

    fn options(dims: usize, params: &GraphParams) -> IndexOptions {
        let (metric, quantization) = Self::kinds(params.scalar);
        IndexOptions {
            dimensions: dims,
            metric,
            quantization,
            connectivity: params.connectivity,
            expansion_add: params.expansion_add,
            expansion_search: params.expansion_search,
            multi: false,
        }
    }

    /// A new, empty live part with its contexts reserved.
    fn live_index(dims: usize, params: &GraphParams, context_count: usize) -> Result<Index, String> {
        let index =
            Index::new(&Self::options(dims, params)).map_err(|e| format!("creating the approximate index: {e}"))?;
        // Contexts from the start: a search of the empty graph needs one too.
        index
            .reserve_capacity_and_threads(1024, context_count)
            .map_err(|e| format!("reserving the approximate index: {e}"))?;
        Ok(index)
    }

    pub fn new(row_dim: usize, params: GraphParams) -> Result<Self, String> {
        let dims = if params.dims == 0 || params.dims > row_dim { row_dim } else { params.dims };
        let context_count = params.threads.max(1) + SEARCH_CONTEXTS;
        let index = Self::live_index(dims, &params, context_count)?;
        let memory = AtomicUsize::new(index.memory_usage());
        Ok(Self {
            index: RwLock::new(index),
            sealed: RwLock::new(Vec::new()),
            live_start: AtomicUsize::new(0),
            contexts: Contexts::new(context_count),
            context_count,
            dims,
            covered: AtomicUsize::new(0),
            memory,
            touched: AtomicUsize::new(0),
            params,
        })
    }

    pub fn dims(&self) -> usize {
        self.dims
    }

    /// Changes the search-time settings (expansion, candidates per result).
    pub fn tune(&mut self, expansion_search: usize, candidates_per_result: usize) {
        self.index.get_mut().change_expansion_search(expansion_search);
        for s in self.sealed.get_mut().iter() {
            s.index.change_expansion_search(expansion_search);
        }
        self.params.expansion_search = expansion_search;
        self.params.candidates_per_result = candidates_per_result;
    }

    pub fn params(&self) -> GraphParams {
        self.params
    }

    /// The live part's expansions (when adding, when searching), as its usearch index holds them.
    pub fn expansions(&self) -> (usize, usize) {
        let index = self.index.read();
        (index.expansion_add(), index.expansion_search())
    }

    /// Rows `0..covered()` are in the graph.
    pub fn covered(&self) -> usize {
        self.covered.load(Ordering::Acquire)
    }

    /// Bytes the graph holds in the process's own memory (its live part), as of its last
    /// addition (safe beside additions and searches). Sealed parts are mapped files:
    /// [`Graph::sealed_bytes`].
    pub fn memory_bytes(&self) -> usize {
        self.memory.load(Ordering::Relaxed)
    }

    /// Sealed parts (row ranges) and the bytes of their files.
    pub fn sealed_parts(&self) -> Vec<(std::ops::Range<usize>, usize)> {
        self.sealed.read().iter().map(|s| (s.start..s.end, s.map.len())).collect()
    }

    /// Bytes of the sealed parts' files (mapped, not held).
    pub fn sealed_bytes(&self) -> usize {
        self.sealed.read().iter().map(|s| s.map.len()).sum()
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
        let live_start = self.live_start.load(Ordering::Acquire);
        let serial_end = live_start + SERIAL_ROWS;
        if start < serial_end && start + n > serial_end {
            // The serial part first, then the rest on every thread.
            let split = (serial_end - start) * self.dims;
            self.add_rows(start, &reduced[..split])?;
            return self.add_rows(serial_end, &reduced[split..]);
        }
        if start != self.covered() {
            return Err(format!("rows from {start} added to a graph covering {}", self.covered()));
        }
        // Concurrent inserts into a small graph link it worse (measured: 111 Corridor rows on two
        // threads lost 1.3% of recall@5 in a one-off probe); one thread until it has grown.
        let threads = if start < serial_end { 1 } else { self.params.threads.clamp(1, n.max(1)) };
        let want = start + n - live_start;
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
                    let mut bytes = Vec::new();
                    for i in (t..n).step_by(threads) {
                        let row = &reduced[i * self.dims..(i + 1) * self.dims];
                        let added = match self.params.scalar {
                            GraphScalar::F16 => index.add((start + i) as u64, row),
                            GraphScalar::I8 => {
                                to_i8(row, &mut bytes);
                                index.add((start + i) as u64, &bytes)
                            }
                        };
                        if let Err(e) = added {
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
        self.covered.store(start + n, Ordering::Release);
        Ok(())
    }

    /// Up to `count` rows near `query` (already reduced) among those `allow` passes, best first
    /// by the graph's (reduced, i8 or f16) scores: every part searched, the best `count` of all kept.
    pub fn search(
        &self,
        query: &[f32],
        count: usize,
        allow: impl Fn(usize) -> bool + Sync,
    ) -> Result<Vec<usize>, String> {
        self.search_parts(query, count, 1, allow, |_| true)
    }

    /// The parts' row ranges: the sealed ones in order, then the live one.
    pub fn parts(&self) -> Vec<std::ops::Range<usize>> {
        let _live = self.index.read();
        let mut out: Vec<_> = self.sealed.read().iter().map(|s| s.start..s.end).collect();
        out.push(self.live_start.load(Ordering::Acquire)..self.covered());
        out
    }

    /// As [`Graph::search`], through the parts whose row range `take` accepts only (the caller
    /// scans the others' rows itself: a filter that passes few of a part's rows is faster
    /// scanned than searched through), the parts split across up to `threads` threads.
    pub fn search_parts(
        &self,
        query: &[f32],
        count: usize,
        threads: usize,
        allow: impl Fn(usize) -> bool + Sync,
        take: impl Fn(std::ops::Range<usize>) -> bool,
    ) -> Result<Vec<usize>, String> {
        let covered = self.covered();
        // The live part's lock first: sealing holds it while it moves rows into a sealed part.
        let index = self.index.read();
        let sealed = self.sealed.read().clone();
        let live_start = self.live_start.load(Ordering::Acquire);
        // None: the live part.
        let mut jobs: Vec<Option<&Sealed>> = Vec::new();
        if live_start < covered && take(live_start..covered) {
            jobs.push(None);
        }
        jobs.extend(sealed.iter().filter(|s| take(s.start..s.end)).map(|s| Some(&**s)));
        let allow = &allow;
        let index = &*index;
        let mut query_i8 = Vec::new();
        if self.params.scalar == GraphScalar::I8 {
            to_i8(query, &mut query_i8);
        }
        let query_i8 = &query_i8[..];
        let scalar = self.params.scalar;
        let search = move |index: &Index, allow: &dyn Fn(u64) -> bool| match scalar {
            GraphScalar::F16 => index.filtered_search(query, count, allow),
            GraphScalar::I8 => index.filtered_search(query_i8, count, allow),
        };
        let search_one = move |job: &Option<&Sealed>| -> Result<Vec<(f32, u64)>, String> {
            let found = match job {
                None => {
                    let _context = self.contexts.take();
                    search(index, &|key| (key as usize) < covered && allow(key as usize))
                }
                Some(part) => {
                    let _context = part.contexts.take();
                    search(&part.index, &|key| allow(key as usize))
                }
            }
            .map_err(Self::search_failed)?;
            Ok(found.distances.into_iter().zip(found.keys).collect())
        };
        let results: Vec<Result<Vec<(f32, u64)>, String>> = if threads > 1 && jobs.len() > 1 {
            let per = jobs.len().div_ceil(threads);
            std::thread::scope(|s| {
                let handles: Vec<_> = jobs
                    .chunks(per)
                    .map(|chunk| s.spawn(move || chunk.iter().map(search_one).collect::<Vec<_>>()))
                    .collect();
                handles
                    .into_iter()
                    .flat_map(|h| h.join().unwrap_or_else(|_| vec![Err("a graph search thread panicked".to_string())]))
                    .collect()
            })
        } else {
            jobs.iter().map(search_one).collect()
        };
        let searched_sealed = jobs.iter().filter(|j| j.is_some()).count();
        self.touched_sealed(&sealed, searched_sealed);
        let mut all = Vec::new();
        for r in results {
            all.extend(r?);
        }
        if searched_sealed > 0 {
            all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        }
        Ok(all.into_iter().take(count).map(|(_, k)| k as usize).collect())
    }

    /// Counts a search's pages of the sealed parts (an upper bound: a page per link of each node
    /// kept, per part); each time that count passes `sealed_resident` bytes, reads how much of
    /// the parts is mapped in (their mappings' `Rss` in /proc/self/smaps: searches revisit the
    /// same nodes, so the count overstates it several times) and unmaps every part's pages when
    /// that is over the bound.
    fn touched_sealed(&self, sealed: &[Arc<Sealed>], searched: usize) {
        let bytes = searched * self.params.expansion_search * self.params.connectivity * PAGE;
        if self.touched.fetch_add(bytes, Ordering::Relaxed) + bytes <= self.params.sealed_resident {
            return;
        }
        self.touched.store(0, Ordering::Relaxed);
        let Some(dir) = sealed.first().and_then(|s| s.file.parent()) else { return };
        if super::rows::mapped_bytes(dir) > self.params.sealed_resident {
            sealed.iter().for_each(|s| s.release());
        }
    }

    fn search_failed(e: impl std::fmt::Display) -> String {
        format!("searching the approximate index: {e}")
    }

    /// Rows in the live part.
    pub fn live_rows(&self) -> usize {
        self.covered() - self.live_start.load(Ordering::Acquire)
    }

    /// Seals the live part once it holds `seal_rows` rows: writes it to a file in `dir`, maps that
    /// file as a sealed part and starts an empty live part. The rows sealed, if it did. Only the
    /// indexer calls it, between its additions.
    pub fn seal_if_due(&self, dir: &Path) -> Result<Option<std::ops::Range<usize>>, String> {
        let (start, end) = (self.live_start.load(Ordering::Acquire), self.covered());
        if self.params.seal_rows == 0 || end - start < self.params.seal_rows {
            return Ok(None);
        }
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        let file = dir.join(format!("{start}-{end}.usearch"));
        let tmp = file.with_extension("usearch.tmp");
        let tmp_str = tmp.to_str().ok_or_else(|| format!("{}: not a UTF-8 path", tmp.display()))?;
        self.index.read().save(tmp_str).map_err(|e| format!("saving the approximate index: {e}"))?;
        std::fs::File::open(&tmp).and_then(|f| f.sync_all()).map_err(|e| format!("{}: {e}", tmp.display()))?;
        let sha256 = sha256_file(&tmp)?;
        std::fs::rename(&tmp, &file).map_err(|e| format!("{}: {e}", file.display()))?;
        let _ = std::fs::File::open(dir).and_then(|d| d.sync_all());
        let part = Sealed::open(&file, (start, end), (self.dims, self.params.scalar), sha256, None)?;
        part.index.change_expansion_search(self.params.expansion_search);
        part.verified.store(true, Ordering::Release);
        let fresh = Self::live_index(self.dims, &self.params, self.context_count)?;
        let mut live = self.index.write();
        self.sealed.write().push(Arc::new(part));
        *live = fresh;
        self.live_start.store(end, Ordering::Release);
        self.memory.store(live.memory_usage(), Ordering::Relaxed);
        Ok(Some(start..end))
    }

    /// Maps one sealed part's pages in that was not yet (the store's indexer calls it each turn),
    /// when all the sealed parts fit within their resident bound: the first searches after a
    /// seal or a restart then find every node mapped instead of faulting thousands in each.
    /// Parts over the bound are left to the searches, which map in what they visit (and
    /// `touched_sealed` unmaps it). True when it mapped a part in.
    pub fn populate_next(&self) -> bool {
        let sealed = self.sealed.read().clone();
        if sealed.iter().map(|s| s.map.len()).sum::<usize>() > self.params.sealed_resident {
            return false;
        }
        let Some(part) = sealed.iter().find(|s| !s.populated.swap(true, Ordering::AcqRel)) else { return false };
        match part.populate() {
            Ok(()) => true,
            Err(e) => {
                tracing::debug!(error = %e, "a sealed part was not mapped in ahead (searches map it in)");
                false
            }
        }
    }

    /// Unmaps every sealed part's pages from the process, as a restart finds them (mapped in only
    /// where the load read them); `populate_next` maps them in again.
    pub fn release_sealed(&self) {
        for part in self.sealed.read().iter() {
            part.release();
            part.populated.store(false, Ordering::Release);
        }
    }

    /// Hashes the first sealed part not hashed since it was mapped, against its record: Ok(true)
    /// when it did and they match, Ok(false) when none was left, Err(why) when they differ (the
    /// graph must not be trusted: it is rebuilt). Only the indexer calls it, a part per turn.
    pub fn verify_next(&self) -> Result<bool, String> {
        let part = self.sealed.read().iter().find(|s| !s.verified.load(Ordering::Acquire)).cloned();
        let Some(part) = part else { return Ok(false) };
        let sha = sha256_file(&part.file)?;
        if sha != part.sha256 {
            return Err(format!("{}: checksum mismatch (file {sha}, record {})", part.file.display(), part.sha256));
        }
        part.verified.store(true, Ordering::Release);
        Ok(true)
    }
}

/// What a saved graph must match to be used, written beside it (`<file>.json`) after the graph
/// file itself, so a graph file without its record, or with another's, is never trusted. The file
/// holds the live part; the sealed parts are files of their own in [`parts_dir`], named by their
/// rows and never written again.
#[derive(Debug, PartialEq, Serialize, Deserialize)]
struct SavedGraph {
    rows: usize,
    dims: usize,
    row_dim: usize,
    connectivity: usize,
    /// How the rows are stored (records written before i8 graphs: f16).
    #[serde(default)]
    scalar: GraphScalar,
    /// SHA-256 of the graph file (the live part).
    sha256: String,
    /// The first row of the live part (records written before graphs were sealed: 0).
    #[serde(default)]
    live_start: usize,
    /// The sealed parts, in row order, ending at `live_start`.
    #[serde(default)]
    sealed: Vec<SavedPart>,
}

#[derive(Debug, PartialEq, Serialize, Deserialize)]
struct SavedPart {
    start: usize,
    end: usize,
    bytes: u64,
    sha256: String,
}

/// The folder of a graph file's sealed parts (`<session>.parts/` beside `<session>.usearch`).
pub fn parts_dir(path: &Path) -> PathBuf {
    path.with_extension("parts")
}

fn part_file(dir: &Path, rows: &std::ops::Range<usize>) -> PathBuf {
    dir.join(format!("{}-{}.usearch", rows.start, rows.end))
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
    /// Only the indexer calls it, between its additions (and seals).
    pub fn save(&self, path: &Path, row_dim: usize) -> Result<usize, String> {
        let rows = self.covered();
        let live_start = self.live_start.load(Ordering::Acquire);
        let sealed = self
            .sealed
            .read()
            .iter()
            .map(|s| SavedPart { start: s.start, end: s.end, bytes: s.map.len() as u64, sha256: s.sha256.clone() })
            .collect();
        let tmp = path.with_extension("usearch.tmp");
        let tmp_str = tmp.to_str().ok_or_else(|| format!("{}: not a UTF-8 path", tmp.display()))?;
        self.index.read().save(tmp_str).map_err(|e| format!("saving the approximate index: {e}"))?;
        std::fs::File::open(&tmp).and_then(|f| f.sync_all()).map_err(|e| format!("{}: {e}", tmp.display()))?;
        let record = SavedGraph {
            rows,
            dims: self.dims,
            row_dim,
            connectivity: self.params.connectivity,
            scalar: self.params.scalar,
            sha256: sha256_file(&tmp)?,
            live_start,
            sealed,
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
    /// `row_dim`-d rows holding at least the rows it covers; why not, otherwise. The live part is
    /// hashed and read into memory; the sealed parts are mapped, checked by their header and
    /// length here, and hashed in full later ([`Graph::verify_next`]), so that a restart does not
    /// read a large map's graph before it answers.
    pub fn load(path: &Path, row_dim: usize, params: GraphParams, rows_held: usize) -> Result<Self, String> {
        let json = std::fs::read(record_path(path)).map_err(|e| format!("no record beside the graph file: {e}"))?;
        let saved: SavedGraph = serde_json::from_slice(&json).map_err(|e| format!("unreadable record: {e}"))?;
        // A graph keeps the scalar it was built with (a server whose setting changed does not
        // rebuild its graphs: new ones take the setting), so its new rows are stored alike.
        let params = GraphParams { scalar: saved.scalar, ..params };
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
        let dir = parts_dir(path);
        let mut next = 0;
        for part in &saved.sealed {
            if part.start != next || part.end <= part.start {
                return Err(format!("sealed rows {}..{} do not follow row {next}", part.start, part.end));
            }
            let file = part_file(&dir, &(part.start..part.end));
            let sealed = Sealed::open(
                &file,
                (part.start, part.end),
                (graph.dims, params.scalar),
                part.sha256.clone(),
                Some(part.bytes),
            )?;
            sealed.index.change_expansion_search(params.expansion_search);
            graph.sealed.get_mut().push(Arc::new(sealed));
            next = part.end;
        }
        if saved.live_start != next || saved.rows < next {
            return Err(format!("the live part starts at row {}; the sealed ones end at {next}", saved.live_start));
        }
        let sha = sha256_file(path)?;
        if sha != saved.sha256 {
            return Err(format!("checksum mismatch (file {sha}, record {})", saved.sha256));
        }
        let path_str = path.to_str().ok_or_else(|| format!("{}: not a UTF-8 path", path.display()))?;
        let meta = Index::metadata(path_str).map_err(|e| format!("{}: not a graph file: {e}", path.display()))?;
        Self::check_kinds(path, &meta, params.scalar)?;
        let context_count = graph.context_count;
        let index = graph.index.get_mut();
        index.load(path_str).map_err(|e| format!("loading: {e}"))?;
        if index.size() != saved.rows - next || index.dimensions() != graph.dims {
            return Err(format!(
                "holds {} rows of {}-d; its record says {}",
                index.size(),
                index.dimensions(),
                saved.rows - next
            ));
        }
        // Loading sizes the contexts by the machine's threads; this graph counts its own.
        index
            .reserve_capacity_and_threads(index.capacity().max(index.size()).max(1024), context_count)
            .map_err(|e| format!("reserving the approximate index: {e}"))?;
        // Frames added from now on are linked and searched at this server's settings, not the
        // ones the file was built with.
        index.change_expansion_add(params.expansion_add);
        index.change_expansion_search(params.expansion_search);
        graph.memory.store(index.memory_usage(), Ordering::Relaxed);
        graph.live_start.store(next, Ordering::Release);
        graph.covered.store(saved.rows, Ordering::Release);
        // Files of parts the record does not name (sealed after it was written, before a crash).
        let named: Vec<PathBuf> = graph.sealed.get_mut().iter().map(|s| s.file.clone()).collect();
        if let Ok(entries) = std::fs::read_dir(&dir) {
            for e in entries.flatten() {
                if !named.contains(&e.path()) {
                    let _ = std::fs::remove_file(e.path());
                }
            }
        }
        Ok(graph)
    }

    /// Whether the graph holds `row` as `reduced` (that row from [`Graph::reduce`]): equal to its
    /// rounding (f16), or to its bytes within one (i8); None if it does not hold the row.
    pub fn holds(&self, row: usize, reduced: &[f32]) -> Option<bool> {
        fn get<T: usearch::VectorType + Default + Clone>(graph: &Graph, row: usize) -> Option<Vec<T>> {
            let mut out = vec![T::default(); graph.dims];
            let got = match graph.sealed.read().iter().find(|s| (s.start..s.end).contains(&row)) {
                Some(part) => part.index.get(row as u64, &mut out),
                None => graph.index.read().get(row as u64, &mut out),
            };
            matches!(got, Ok(1)).then_some(out)
        }
        match self.params.scalar {
            GraphScalar::F16 => {
                let got: Vec<f32> = get(self, row)?;
                Some(reduced.iter().zip(&got).all(|(a, b)| (a - b).abs() <= 2e-3))
            }
            GraphScalar::I8 => {
                let got: Vec<i8> = get(self, row)?;
                let mut want = Vec::new();
                to_i8(reduced, &mut want);
                Some(want.iter().zip(&got).all(|(a, b)| (i16::from(*a) - i16::from(*b)).abs() <= 1))
            }
        }
    }
}
