//! Search through the approximate index ([`graph::Graph`]): the graph's candidates among the
//! rows it covers, re-scored exactly on the full rows, plus an exact scan of the rows it does not
//! cover yet. A filter that leaves only a few rows is answered by scanning those rows exactly.
use super::*;

/// Rows of the session sampled to estimate how many rows a query's filter leaves.
const FILTER_SAMPLE: usize = 1024;

/// Candidates the graph returns beyond `candidates_per_result` per result asked for, re-scored
/// on the full rows (docs/storage.md: how many the reduction needs).
const CANDIDATES_EXTRA: usize = 64;

/// What the store's indexer adds next to a session's graph: the graph, the first row and the
/// reduced rows.
pub struct Pending {
    pub graph: Arc<Graph>,
    pub start: usize,
    pub reduced: Vec<f32>,
}

impl SessionIndex {
    /// How this session searches; an `auto` or `approximate` session starts its graph as soon as
    /// it is due (now, if it already holds enough rows).
    pub fn set_index(&mut self, kind: IndexKind, params: GraphParams) {
        self.kind = kind;
        self.graph_params = params;
        if kind == IndexKind::Exact {
            self.graph = None;
        }
        self.start_graph_when_due();
    }

    pub fn index_kind(&self) -> IndexKind {
        self.kind
    }

    pub fn graph_params(&self) -> GraphParams {
        self.graph_params
    }

    /// Changes the graph's search-time settings (benchmarks sweep them on one built graph).
    pub fn tune_graph(&mut self, expansion_search: usize, candidates_per_result: usize) {
        self.graph_params.expansion_search = expansion_search;
        self.graph_params.candidates_per_result = candidates_per_result;
        if let Some(g) = self.graph.as_mut().and_then(Arc::get_mut) {
            g.tune(expansion_search, candidates_per_result);
        }
    }

    /// The session's graph, if it has one (the store saves it).
    pub fn graph(&self) -> Option<Arc<Graph>> {
        self.graph.clone()
    }

    /// Uses a saved graph in place of the empty one this session started, if the rows it holds
    /// are this session's (its first, last and 14 evenly spaced rows compared); why not, otherwise.
    pub fn adopt_graph(&mut self, saved: Graph) -> Result<usize, String> {
        let Some(current) = &self.graph else { return Err("the session does not use the approximate index".into()) };
        if current.covered() > 0 {
            return Err("the session's index is already being built".into());
        }
        let rows = saved.covered();
        if rows > self.frames.len() || saved.dims() != current.dims() {
            return Err(format!(
                "it covers {rows} rows of {}-d; the session holds {}",
                saved.dims(),
                self.frames.len()
            ));
        }
        let (mut row, mut want) = (vec![0f32; self.dim], Vec::new());
        let sample = (0..16).map(|i| i * rows.saturating_sub(1) / 15);
        for r in sample.filter(|_| rows > 0) {
            self.row_into(r, &mut row);
            saved.reduce(&row, &mut want);
            if !saved.holds(r, &want).ok_or_else(|| format!("row {r} is missing"))? {
                return Err(format!("row {r} differs from the session's"));
            }
        }
        self.graph = Some(Arc::new(saved));
        Ok(rows)
    }

    /// Drops the session's graph and starts an empty one (a saved part failed its check): the
    /// indexer builds it again from the rows; searches scan exactly meanwhile.
    pub fn rebuild_graph(&mut self) {
        self.graph = None;
        self.start_graph_when_due();
    }

    /// Rows the approximate index covers (None: the session searches exactly).
    pub fn graph_rows(&self) -> Option<usize> {
        self.graph.as_ref().map(|g| g.covered())
    }

    pub(super) fn start_graph_when_due(&mut self) {
        let due = match self.kind {
            IndexKind::Exact => false,
            IndexKind::Approximate => true,
            IndexKind::Auto => self.frames.len() >= self.graph_params.min_frames,
        };
        if due && self.graph.is_none() {
            match Graph::new(self.dim, self.graph_params) {
                Ok(g) => self.graph = Some(Arc::new(g)),
                Err(e) => {
                    // Searches stay exact (correct, slower); the next frame tries again.
                    tracing::error!(error = %e, "the approximate index could not be created; searching exactly");
                }
            }
        }
    }

    /// The next rows (at most `max`) the graph does not cover yet, reduced for it; None when it
    /// covers every row or the session has no graph.
    pub fn pending(&self, max: usize) -> Option<Pending> {
        let graph = self.graph.as_ref()?;
        let start = graph.covered();
        let end = self.frames.len().min(start + max);
        if start >= end {
            return None;
        }
        let mut reduced = Vec::with_capacity((end - start) * graph.dims());
        let (mut row, mut out) = (vec![0f32; self.dim], Vec::with_capacity(graph.dims()));
        for r in start..end {
            self.row_into(r, &mut row);
            graph.reduce(&row, &mut out);
            reduced.extend_from_slice(&out);
        }
        self.note_read(end - start);
        Some(Pending { graph: graph.clone(), start, reduced })
    }

    /// Adds every row the graph does not cover yet, here and now (what the indexer does in the
    /// background; `loopd eval`, benchmarks and tests call it to search a complete graph).
    pub fn index_all(&self) -> Result<(), String> {
        while let Some(p) = self.pending(1 << 16) {
            p.graph.add_rows(p.start, &p.reduced)?;
        }
        Ok(())
    }

    fn row_into(&self, row: usize, out: &mut [f32]) {
        let range = row * self.dim..(row + 1) * self.dim;
        match &self.rows {
            Rows::F16(v) => out.iter_mut().zip(&v[range]).for_each(|(o, &b)| *o = half::f16::from_bits(b).to_f32()),
            Rows::F32(v) => out.copy_from_slice(&v[range]),
        }
    }

    /// True when searches go through the graph (it exists and covers at least half the rows).
    pub(super) fn searches_graph(&self) -> bool {
        self.graph.as_ref().is_some_and(|g| g.covered() > 0 && 2 * g.covered() >= self.frames.len())
    }

    /// Top-k (score, row) through the graph, best first; None when this index searches exactly
    /// (no graph yet, or one covering less than half the rows).
    pub(super) fn graph_search(
        &self,
        q: &[f32],
        opts: &LoopQuery,
        k: usize,
        filter: &Filter,
        threads: usize,
    ) -> Option<Vec<(f32, usize)>> {
        // Mostly not in the graph yet (a rebuild after a restart): the exact search, on every
        // core, is faster than the graph plus a one-core scan of the rest.
        if !self.searches_graph() {
            return None;
        }
        let graph = self.graph.as_ref()?;
        let covered = graph.covered().min(self.frames.len());
        let n = self.frames.len();
        let mut heap = TopK::new(k);
        let allowed = self.allowed_estimate(filter);
        if self.few_allowed(allowed, n) {
            return Some(self.subset_scan(q, opts, k, filter, allowed, threads));
        }
        let mut reduced = Vec::with_capacity(graph.dims());
        graph.reduce(q, &mut reduced);
        // The graph ranks by reduced f16 scores: take a margin of candidates and re-score them.
        let count = (graph.params().candidates_per_result * k + CANDIDATES_EXTRA).min(covered);
        // A part of the graph (a sealed file, the live rows) that the filter leaves few rows of is
        // scanned exactly instead, as the whole session is above: a graph search through a
        // filter that passes none of its nodes visits them all (benches/ann.rs: a quarter of the
        // time range over four parts took 692 ms a query).
        let scanned: Vec<std::ops::Range<usize>> = graph
            .parts()
            .into_iter()
            .filter(|r| self.few_allowed(self.allowed_in(filter, r.clone(), FILTER_SAMPLE / 4), r.len()))
            .collect();
        for r in &scanned {
            self.scan_into(q, opts, filter, r.clone(), &mut heap);
        }
        let take = |r: std::ops::Range<usize>| !scanned.contains(&r);
        match graph.search_parts(&reduced, count, threads, |row| filter.allows(row), take) {
            Ok(rows) => {
                for row in rows {
                    let score = self.host_dot(q, row);
                    if score >= opts.min_score {
                        heap.push(score, row);
                    }
                }
            }
            Err(e) => {
                tracing::warn!(error = %e, "approximate search failed; searching exactly");
                return None;
            }
        }
        // Rows the graph does not cover yet: exactly.
        self.scan_into(q, opts, filter, covered..n, &mut heap);
        Some(heap.sorted())
    }

    /// Top-k (score, row) among the rows `filter` allows, exactly: the filter first, then the
    /// kernel over each run of allowed rows (a robot's frames, a time window), blocks on up to
    /// `threads` cores once `allowed` rows are worth them.
    fn subset_scan(
        &self,
        q: &[f32],
        opts: &LoopQuery,
        k: usize,
        filter: &Filter,
        allowed: usize,
        threads: usize,
    ) -> Vec<(f32, usize)> {
        let threads = if allowed * self.dim < PARALLEL_MIN_VALUES { 1 } else { threads };
        let init = || (TopK::new(k), vec![0f32; CHUNK_ROWS]);
        let parts = self.scan(CHUNK_ROWS, threads, init, |(heap, scores), s, e| {
            let mut row = s;
            while row < e {
                if !filter.allows(row) {
                    row += 1;
                    continue;
                }
                let first = row;
                while row < e && filter.allows(row) {
                    row += 1;
                }
                let out = &mut scores[..row - first];
                self.host_dots(q, first, out);
                for (i, &score) in out.iter().enumerate() {
                    if score >= opts.min_score {
                        heap.push(score, first + i);
                    }
                }
            }
        });
        let mut heap = TopK::new(k);
        parts.into_iter().for_each(|(h, _)| heap.merge(h));
        heap.sorted()
    }

    /// True when a filter expected to let `allowed` of `rows` rows through leaves so few that
    /// scanning them exactly beats a graph search (`exact_below`, `exact_share`).
    fn few_allowed(&self, allowed: usize, rows: usize) -> bool {
        let p = &self.graph_params;
        allowed < p.exact_below || (allowed as f32) < p.exact_share * rows as f32
    }

    /// Scores the rows of `rows` the filter allows, one by one, into `heap`.
    fn scan_into(&self, q: &[f32], opts: &LoopQuery, filter: &Filter, rows: std::ops::Range<usize>, heap: &mut TopK) {
        for row in rows.filter(|&row| filter.allows(row)) {
            let score = self.host_dot(q, row);
            if score >= opts.min_score && heap.would_take(score, row) {
                heap.push(score, row);
            }
        }
    }

    /// Rows of `rows` the filter is expected to let through, from up to `samples` evenly spaced
    /// ones.
    fn allowed_in(&self, filter: &Filter, rows: std::ops::Range<usize>, samples: usize) -> usize {
        let n = rows.len();
        if n == 0 {
            return 0;
        }
        let step = n.div_ceil(samples).max(1);
        let (mut seen, mut allowed) = (0usize, 0usize);
        for row in rows.step_by(step) {
            seen += 1;
            allowed += filter.allows(row) as usize;
        }
        allowed * n / seen.max(1)
    }

    /// Rows the filter is expected to let through, from an evenly spaced sample.
    fn allowed_estimate(&self, filter: &Filter) -> usize {
        // A sample that saw none sends the query to the exact scan, which is right for any share.
        self.allowed_in(filter, 0..self.frames.len(), FILTER_SAMPLE)
    }

    /// A batch through the graph: the queries split across `threads`.
    pub(super) fn graph_batch(&self, queries: &[Vec<f32>], opts: &LoopQuery, threads: usize) -> Vec<Vec<Match>> {
        let per = queries.len().div_ceil(threads.max(1));
        std::thread::scope(|s| {
            let parts: Vec<_> = queries
                .chunks(per)
                .map(|chunk| s.spawn(move || chunk.iter().map(|q| self.search(q, opts, 1)).collect::<Vec<_>>()))
                .collect();
            parts.into_iter().flat_map(|h| h.join().expect("search thread")).collect()
        })
    }
}
