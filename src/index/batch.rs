//! Exact search of many queries at once: rows scored a cache-sized block at a time against all
//! queries (host kernels, threads taking blocks in turn), or on the session's device; and the
//! scans and conversions the single search shares.
use super::kernels::{dots_f16, dots_f32, dots_many_f16, dots_many_f32};
use super::query::{self, LoopQuery, Match};
use super::select::{rank_key, Filter, TopK};
use super::Rows;
use super::{SessionIndex, Storage, FAULT_AROUND, PARALLEL_MIN_VALUES};
use std::cmp::Reverse;

impl SessionIndex {
    /// Top-k for many queries at once (same options). Rows are scored a cache-sized block at a
    /// time against all queries with the register-blocked kernel (each row value loaded once per
    /// four queries), threads taking blocks in turn; compute-bound rather than memory-bound.
    pub fn search_batch(&self, queries: &[Vec<f32>], opts: &LoopQuery, threads: usize) -> Vec<Vec<Match>> {
        let k = opts.k.min(query::MAX_K);
        if queries.len() <= 1 || k == 0 || self.frames.is_empty() {
            return queries.iter().map(|q| self.search(q, opts, threads)).collect();
        }
        if self.searches_graph() {
            return self.graph_batch(queries, opts, threads);
        }
        let filter = Filter::new(self, opts);
        let (b, n, dim) = (queries.len(), self.frames.len(), self.dim);
        let flat: Vec<f32> = queries.iter().flat_map(|q| q.iter().copied()).collect();
        if let Some(found) = self.device_top(&flat, opts, k, &filter) {
            return found.into_iter().map(|v| v.into_iter().map(|(s, row)| self.to_match(s, row)).collect()).collect();
        }
        let block = batch_block_rows(dim, self.storage());
        let threads = if n * dim < PARALLEL_MIN_VALUES / 4 { 1 } else { threads };
        let init = || ((0..b).map(|_| TopK::new(k)).collect::<Vec<_>>(), vec![0f32; block * b]);
        let parts = self.scan(block, threads, init, |(heaps, scores), s, e| {
            let out = &mut scores[..(e - s) * b];
            match &self.rows {
                Rows::F16(v) => dots_many_f16(&flat, &v[s * dim..e * dim], dim, out),
                Rows::F32(v) => dots_many_f32(&flat, &v[s * dim..e * dim], dim, out),
            }
            // Counted block by block once read, as the single search's scan (`SessionIndex::search`).
            self.note_read(e - s);
            for (i, row_scores) in out.chunks_exact(b).enumerate() {
                for (heap, &score) in heaps.iter_mut().zip(row_scores) {
                    if score >= opts.min_score && heap.would_take(score, s + i) && filter.allows(s + i) {
                        heap.push(score, s + i);
                    }
                }
            }
        });
        let mut heaps: Vec<TopK> = (0..b).map(|_| TopK::new(k)).collect();
        for (part, _) in parts {
            heaps.iter_mut().zip(part).for_each(|(m, h)| m.merge(h));
        }
        heaps
            .into_iter()
            .map(|h| h.sorted().into_iter().map(|(score, row)| self.to_match(score, row)).collect())
            .collect()
    }

    /// Top-k (score, row) per query from the device mirror, best first; None when this index
    /// searches on the host or the device failed (logged; the host kernels then answer).
    pub(super) fn device_top(
        &self,
        queries: &[f32],
        opts: &LoopQuery,
        k: usize,
        filter: &Filter,
    ) -> Option<Vec<Vec<(f32, usize)>>> {
        let dev = self.device.as_ref().filter(|d| self.frames.len() >= d.min_rows)?;
        let n = self.frames.len();
        let mut rows = dev.rows.lock();
        // How far a device score may be from the host's: half-precision products and outputs.
        let eps = match self.storage() {
            Storage::F16 => 4e-3,
            Storage::F32 => 1e-4,
        };
        let result = (|| -> Result<_, tch::TchError> {
            rows.sync(self.host_rows())?;
            // Filtered rows (a robot's own recent frames) tend to score highest: fetch past them
            // and widen the fetch until every query has its candidates or nothing is left.
            let mut fetch = (2 * k + opts.exclude_last_frames + 8).min(n);
            loop {
                let tops = rows.top(queries, fetch)?;
                let mut short = false;
                let mut picked = Vec::with_capacity(tops.len());
                for (q, cands) in queries.chunks_exact(self.dim).zip(tops) {
                    // Candidates: allowed rows down to eps below the k-th allowed device score, so
                    // the device's rounding cannot push a true top-k row out...
                    let mut got = Vec::with_capacity(k + 4);
                    let mut cutoff = opts.min_score - eps;
                    let mut complete = cands.len() == n;
                    for &(score, row) in &cands {
                        if score < cutoff {
                            complete = true;
                            break;
                        }
                        if filter.allows(row) {
                            got.push(row);
                            if got.len() == k {
                                cutoff = cutoff.max(score - eps);
                            }
                        }
                    }
                    short |= !complete;
                    // ...then scored again on the host with the f32 query: the same scores, ranks
                    // and ties (earlier frame first) as the host search.
                    let mut exact: Vec<(f32, usize)> = got
                        .into_iter()
                        .map(|row| (self.host_dot(q, row), row))
                        .filter(|&(score, _)| score >= opts.min_score)
                        .collect();
                    exact.sort_by_key(|&(score, row)| Reverse(rank_key(score, row)));
                    exact.truncate(k);
                    picked.push(exact);
                }
                if !short {
                    dev.answered.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    return Ok(picked);
                }
                fetch = (fetch * 4).min(n);
            }
        })();
        result.map_err(|e| tracing::warn!(error = %e, "device search failed; searching on the host")).ok()
    }

    /// Visits all rows in blocks of `block` rows, which up to `threads` workers take in turn from a
    /// shared counter; each worker has its own state (heaps, scratch), returned for merging.
    pub(super) fn scan<S: Send>(
        &self,
        block: usize,
        threads: usize,
        init: impl Fn() -> S + Sync,
        visit: impl Fn(&mut S, usize, usize) + Sync,
    ) -> Vec<S> {
        let n = self.frames.len();
        let blocks = n.div_ceil(block);
        let next = std::sync::atomic::AtomicUsize::new(0);
        let work = || {
            let mut state = init();
            loop {
                let c = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                if c >= blocks {
                    break state;
                }
                visit(&mut state, c * block, ((c + 1) * block).min(n));
            }
        };
        match threads.clamp(1, blocks.max(1)) {
            1 => vec![work()],
            t => std::thread::scope(|sc| {
                let handles: Vec<_> = (0..t).map(|_| sc.spawn(work)).collect();
                handles.into_iter().map(|h| h.join().expect("search thread")).collect()
            }),
        }
    }

    /// The host kernel's score of one stored row.
    pub(super) fn host_dot(&self, q: &[f32], row: usize) -> f32 {
        let mut out = [0f32];
        self.host_dots(q, row, &mut out);
        out[0]
    }

    /// The host kernel's scores of the stored rows `first..first + out.len()`.
    pub(super) fn host_dots(&self, q: &[f32], first: usize, out: &mut [f32]) {
        let range = first * self.dim..(first + out.len()) * self.dim;
        // Mapped rows: a read maps in the kernel's fault-around window around it, more than a
        // short run's own bytes (one re-scored candidate, a robot's frame among others'), so a
        // run counts at least that much against the resident bound.
        let row_bytes = self.dim * self.storage().bytes_per_value();
        self.note_read(out.len().max(FAULT_AROUND.div_ceil(row_bytes)));
        match &self.rows {
            Rows::F16(v) => dots_f16(q, &v[range], out),
            Rows::F32(v) => dots_f32(q, &v[range], out),
        }
    }

    pub fn storage(&self) -> Storage {
        match self.rows {
            Rows::F16(_) => Storage::F16,
            Rows::F32(_) => Storage::F32,
        }
    }

    pub(super) fn to_match(&self, score: f32, row: usize) -> Match {
        let f = &self.frames[row];
        Match {
            frame_id: f.frame_id,
            score,
            robot_id: self.robots[f.robot as usize].clone(),
            timestamp: f.timestamp,
            pose: f.pose.as_deref().copied(),
        }
    }
}

/// Rows per block in batched search: one 1024-value slice of the block (what the kernel sweeps
/// per query tile) stays within ~192 KB of L2.
fn batch_block_rows(dim: usize, storage: Storage) -> usize {
    (192 * 1024 / (dim.min(1024) * storage.bytes_per_value())).clamp(48, 4096)
}
