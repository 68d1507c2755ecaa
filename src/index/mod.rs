//! Search, a layer of its own: one session's descriptors, contiguous in memory, searched exactly
//! (cosine = dot of unit rows), with the sequence helpers (trails, votes) that read the same rows.
//! `query` holds the query options and results, `kernels` the host SIMD dot products, `device`
//! the rows mirrored on a libtorch device, `graph` the approximate index (an HNSW graph) that
//! large sessions search instead of every row (`approx` the search over it). It imports no other layer of loopd: persistence
//! (`store`) fills it from its records and asks it, verification reads its matches.
mod approx;
pub use approx::Pending;
mod batch;
pub mod device;
pub mod graph;
pub mod kernels;
pub mod query;
pub mod rows;
mod select;
use select::{Filter, TopK};

use device::{DeviceRows, HostRows};
use graph::{Graph, GraphParams, IndexKind};
use kernels::{dots_f16, dots_f32};
use ordered_float::OrderedFloat;
use query::{LoopQuery, Match, Pose, Scope};
use serde::{Deserialize, Serialize};
use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::sync::Arc;

/// How a session keeps its descriptors (on disk and in memory).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum Storage {
    /// Half the bytes, twice the search speed; cosine error ~1e-3.
    #[default]
    F16,
    F32,
}

impl Storage {
    pub fn bytes_per_value(self) -> usize {
        match self {
            Storage::F16 => 2,
            Storage::F32 => 4,
        }
    }
}

/// Why a descriptor cannot be searched (the store and the service answer it as a bad argument).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct InvalidDescriptor(pub &'static str);

/// Unit length, finite values: cosine similarity is then a dot product.
pub fn normalize(descriptor: &mut [f32]) -> Result<(), InvalidDescriptor> {
    if descriptor.iter().any(|v| !v.is_finite()) {
        return Err(InvalidDescriptor("descriptor has non-finite values"));
    }
    // f64: squares of large f32 values would overflow to infinity.
    let norm = descriptor.iter().map(|&v| (v as f64) * (v as f64)).sum::<f64>().sqrt();
    if !norm.is_finite() || norm < 1e-12 {
        return Err(InvalidDescriptor("descriptor is all zeros (or its norm is out of range)"));
    }
    descriptor.iter_mut().for_each(|v| *v = (*v as f64 / norm) as f32);
    Ok(())
}

enum Rows {
    F16(rows::Column<u16>),
    F32(rows::Column<f32>),
}

impl Rows {
    fn new(storage: Storage, mapping: Option<rows::Mapping<'_>>) -> Self {
        match storage {
            Storage::F16 => Rows::F16(rows::Column::new(mapping)),
            Storage::F32 => Rows::F32(rows::Column::new(mapping)),
        }
    }
}

/// A stored frame's record beside its row. Kept small: a map of 10^7 frames holds 10^7 of them
/// in memory (48 bytes each; the pose boxed, since many robots send none, and the votes a boxed
/// slice, where an inline pose and a `Vec` made it 112).
#[derive(Clone, Debug)]
pub struct FrameMeta {
    pub frame_id: u64,
    pub robot: u32,
    pub timestamp: f64,
    pub pose: Option<Box<Pose>>,
    /// The best matches this frame's own query found when it was added (sequence verification's
    /// candidate votes); memory only, empty after a restart.
    pub votes: Box<[u64]>,
}

pub struct SessionIndex {
    dim: usize,
    rows: Rows,
    frames: Vec<FrameMeta>,
    robots: Vec<String>,
    robot_ids: HashMap<String, u32>,
    /// Row of each frame id.
    by_frame: HashMap<u64, usize>,
    /// Frame ids of each robot, ascending (its "last N frames" are the N highest ids).
    by_robot: Vec<Vec<u64>>,
    /// Set when searches run on a libtorch device (the model's GPU); None: the host kernels.
    device: Option<DeviceSearch>,
    /// Exact, approximate, or approximate from `graph_params.min_frames` on.
    kind: IndexKind,
    graph_params: GraphParams,
    /// The approximate index once the session uses one (filled by the store's indexer).
    graph: Option<Arc<Graph>>,
}

struct DeviceSearch {
    rows: parking_lot::Mutex<DeviceRows>,
    /// Below this many rows the host kernels answer (a device round trip costs more).
    min_rows: usize,
    /// Searches the device answered (a failed one falls back to the host and is not counted).
    answered: std::sync::atomic::AtomicU64,
}

/// Row values (rows x dim) from which a single query is split across threads.
const PARALLEL_MIN_VALUES: usize = 8 << 20;

/// Rows searched per chunk: big enough to amortise, small enough for threads to share work.
const CHUNK_ROWS: usize = 4096;

/// Bytes the kernel maps in around a read fault of a file mapping whose pages are cached (its
/// fault-around window, debugfs `fault_around_bytes`, 64 KB by default): what one scattered read
/// of mapped rows costs the resident bound.
const FAULT_AROUND: usize = 64 << 10;

/// Frames of the map (evenly spaced) a frame's similarity statistics are taken over
/// ([`SessionIndex::row_stats`]).
pub const ROW_SAMPLE: usize = 256;

/// Mean and standard deviation (at least 1e-6) of `values`.
pub fn mean_std(values: impl Iterator<Item = f32>) -> (f32, f32) {
    let (mut n, mut sum, mut sq) = (0usize, 0f64, 0f64);
    for v in values {
        n += 1;
        sum += v as f64;
        sq += (v as f64) * (v as f64);
    }
    if n == 0 {
        return (0.0, 1.0);
    }
    let mean = sum / n as f64;
    let var = (sq / n as f64 - mean * mean).max(0.0);
    (mean as f32, (var.sqrt() as f32).max(1e-6))
}

impl SessionIndex {
    pub fn new(dim: usize, storage: Storage) -> Self {
        Self::with_rows(dim, storage, None)
    }

    /// An index whose rows are in a file mapped into memory (`rows.rs`), or in memory (None).
    pub fn with_rows(dim: usize, storage: Storage, mapping: Option<rows::Mapping<'_>>) -> Self {
        Self {
            dim,
            rows: Rows::new(storage, mapping),
            frames: Vec::new(),
            robots: Vec::new(),
            robot_ids: HashMap::new(),
            by_frame: HashMap::new(),
            by_robot: Vec::new(),
            device: None,
            kind: IndexKind::Exact,
            graph_params: GraphParams::default(),
            graph: None,
        }
    }

    /// An index over rows kept in `file` by the store across restarts (`rows::Column::in_file`):
    /// `frames` describes the file's first rows, in order (frame id, robot, timestamp, pose);
    /// rows after them are cut off, and new frames are appended to the file.
    pub fn with_file<'a>(
        dim: usize,
        storage: Storage,
        file: std::fs::File,
        resident: usize,
        frames: impl ExactSizeIterator<Item = (u64, &'a str, f64, Option<Pose>)>,
    ) -> std::io::Result<Self> {
        let mut index = Self::with_rows(dim, storage, None);
        let values = frames.len() * dim;
        index.rows = match storage {
            Storage::F16 => Rows::F16(rows::Column::in_file(file, values, resident)?),
            Storage::F32 => Rows::F32(rows::Column::in_file(file, values, resident)?),
        };
        for (frame_id, robot_id, timestamp, pose) in frames {
            index.push_meta(frame_id, robot_id, timestamp, pose);
        }
        Ok(index)
    }

    /// A handle on the file the rows are written to (None when they are in memory), to make
    /// them durable with (`File::sync_data`) outside the session's lock.
    pub fn rows_file(&self) -> Option<std::io::Result<std::fs::File>> {
        let file = match &self.rows {
            Rows::F16(v) => v.file(),
            Rows::F32(v) => v.file(),
        };
        file.map(std::fs::File::try_clone)
    }

    /// Searches on `device` (scores and top-k there) once the session holds `min_rows` rows.
    /// The host rows stay the source of truth; the device copy is topped up before each search.
    pub fn search_on(&mut self, device: tch::Device, min_rows: usize) {
        let rows = DeviceRows::new(device, self.storage() == Storage::F16, self.dim);
        self.device =
            Some(DeviceSearch { rows: parking_lot::Mutex::new(rows), min_rows, answered: Default::default() });
    }

    /// Copies the rows to the search device now (at start-up) rather than at the first query.
    pub fn upload(&self) {
        if let Some(dev) = &self.device {
            if let Err(e) = dev.rows.lock().sync(self.host_rows()) {
                tracing::warn!(error = %e, "copying rows to the search device failed; searching on the host");
            }
        }
    }

    fn host_rows(&self) -> HostRows<'_> {
        match &self.rows {
            Rows::F16(v) => HostRows::F16(v),
            Rows::F32(v) => HostRows::F32(v),
        }
    }

    /// How many searches (a batch counts once) the device has answered.
    pub fn device_searches(&self) -> u64 {
        self.device.as_ref().map_or(0, |d| d.answered.load(std::sync::atomic::Ordering::Relaxed))
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Values per descriptor.
    pub fn dim(&self) -> usize {
        self.dim
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    pub fn contains(&self, frame_id: u64) -> bool {
        self.by_frame.contains_key(&frame_id)
    }

    /// Every frame id, ascending.
    pub fn frame_ids(&self) -> Vec<u64> {
        let mut ids: Vec<u64> = self.frames.iter().map(|f| f.frame_id).collect();
        ids.sort_unstable();
        ids
    }

    pub fn robots(&self) -> &[String] {
        &self.robots
    }

    pub fn max_frame_id(&self) -> Option<u64> {
        self.frames.iter().map(|f| f.frame_id).max()
    }

    pub fn memory_bytes(&self) -> usize {
        let rows = match &self.rows {
            Rows::F16(v) => v.memory_bytes(),
            Rows::F32(v) => v.memory_bytes(),
        };
        rows + self.frames.capacity() * std::mem::size_of::<FrameMeta>() + self.graph_bytes()
    }

    /// The approximate index's memory (0 without one).
    pub fn graph_bytes(&self) -> usize {
        self.graph.as_ref().map_or(0, |g| g.memory_bytes())
    }

    /// Bytes of rows in a file mapped into memory (0 when they are in memory).
    pub fn rows_file_bytes(&self) -> usize {
        match &self.rows {
            Rows::F16(v) => v.file_bytes(),
            Rows::F32(v) => v.file_bytes(),
        }
    }

    /// Whether the rows are in a mapped file.
    pub fn rows_mapped(&self) -> bool {
        match &self.rows {
            Rows::F16(v) => v.is_mapped(),
            Rows::F32(v) => v.is_mapped(),
        }
    }

    /// Counts `rows` rows read (see `rows::Column::note_read`).
    fn note_read(&self, rows: usize) {
        match &self.rows {
            Rows::F16(v) => v.note_read(rows * self.dim),
            Rows::F32(v) => v.note_read(rows * self.dim),
        }
    }

    /// Appends one unit descriptor (the caller has checked dim and uniqueness).
    pub fn push(&mut self, frame_id: u64, robot_id: &str, timestamp: f64, pose: Option<Pose>, descriptor: &[f32]) {
        debug_assert_eq!(descriptor.len(), self.dim);
        match &mut self.rows {
            Rows::F16(v) => v.extend(descriptor.iter().map(|&x| half::f16::from_f32(x).to_bits())),
            Rows::F32(v) => v.extend(descriptor.iter().copied()),
        }
        self.push_meta(frame_id, robot_id, timestamp, pose);
        self.start_graph_when_due();
    }

    /// The frame's record, for the row appended last.
    fn push_meta(&mut self, frame_id: u64, robot_id: &str, timestamp: f64, pose: Option<Pose>) {
        let robot = match self.robot_ids.get(robot_id) {
            Some(&r) => r,
            None => {
                let r = self.robots.len() as u32;
                self.robots.push(robot_id.to_string());
                self.robot_ids.insert(robot_id.to_string(), r);
                self.by_robot.push(Vec::new());
                r
            }
        };
        let row = self.frames.len();
        self.frames.push(FrameMeta { frame_id, robot, timestamp, pose: pose.map(Box::new), votes: Box::default() });
        self.by_frame.insert(frame_id, row);
        let ids = &mut self.by_robot[robot as usize];
        match ids.last() {
            Some(&last) if last > frame_id => {
                let at = ids.partition_point(|&id| id < frame_id);
                ids.insert(at, frame_id);
            }
            _ => ids.push(frame_id),
        }
    }

    /// The frame's robot and its position in that robot's trajectory (frames in id order).
    pub fn place(&self, frame_id: u64) -> Option<(u32, usize)> {
        let robot = self.frames[*self.by_frame.get(&frame_id)?].robot;
        let ids = &self.by_robot[robot as usize];
        Some((robot, ids.partition_point(|&id| id < frame_id)))
    }

    /// Descriptors of the robot's frames up to and including `frame_id`, at most `n`, oldest first.
    pub fn trail(&self, frame_id: u64, n: usize) -> Vec<Vec<f32>> {
        let Some((robot, at)) = self.place(frame_id) else { return Vec::new() };
        let ids = &self.by_robot[robot as usize][..=at];
        ids[ids.len().saturating_sub(n)..].iter().filter_map(|&id| self.descriptor(id)).collect()
    }

    /// Records the best matches of the query a frame was added with.
    pub fn set_votes(&mut self, frame_id: u64, votes: Vec<u64>) {
        if let Some(&row) = self.by_frame.get(&frame_id) {
            self.frames[row].votes = votes.into_boxed_slice();
        }
    }

    /// The frame `steps` positions after `frame_id` on its robot's trajectory.
    pub fn advance(&self, frame_id: u64, steps: usize) -> Option<u64> {
        let (robot, at) = self.place(frame_id)?;
        self.by_robot[robot as usize].get(at + steps).copied()
    }

    /// Candidates the query's past votes for (sequence verification): each earlier frame's own
    /// best matches (`past_votes`, oldest first, the frame just before the query last), moved
    /// forward along their trajectory by how far back that frame is. A place the robot passed L
    /// frames ago is where it would be now if it is retracing it.
    pub fn voted(&self, past_votes: &[Vec<u64>]) -> Vec<u64> {
        let mut out = Vec::new();
        for (back, votes) in past_votes.iter().rev().enumerate() {
            for &id in votes {
                if let Some(now) = self.advance(id, back + 1) {
                    if !out.contains(&now) {
                        out.push(now);
                    }
                }
            }
        }
        out
    }

    /// The votes of a robot's newest `n` frames (or of the `n` frames before `before` on its
    /// trajectory), oldest first.
    pub fn votes(&self, robot_id: Option<&str>, before: Option<u64>, n: usize) -> Vec<Vec<u64>> {
        let ids: &[u64] = match (before.and_then(|id| self.place(id)), robot_id.and_then(|r| self.robot_ids.get(r))) {
            (Some((robot, at)), _) => &self.by_robot[robot as usize][..at],
            (None, Some(&r)) => &self.by_robot[r as usize],
            (None, None) => &[],
        };
        ids[ids.len().saturating_sub(n)..].iter().map(|id| self.frames[self.by_frame[id]].votes.to_vec()).collect()
    }

    /// These frames as matches of `q` under the query's filters (unknown or filtered ids left out).
    pub fn score_frames(&self, q: &[f32], ids: &[u64], opts: &LoopQuery) -> Vec<Match> {
        let filter = Filter::new(self, opts);
        ids.iter()
            .filter_map(|id| {
                let row = *self.by_frame.get(id)?;
                let score = self.host_dot(q, row);
                (filter.allows(row) && score >= opts.min_score).then(|| self.to_match(score, row))
            })
            .collect()
    }

    /// Descriptors of a robot's newest `n` frames, oldest first (none for an unknown robot).
    pub fn robot_tail(&self, robot_id: &str, n: usize) -> Vec<Vec<f32>> {
        let Some(&r) = self.robot_ids.get(robot_id) else { return Vec::new() };
        let ids = &self.by_robot[r as usize];
        ids[ids.len().saturating_sub(n)..].iter().filter_map(|&id| self.descriptor(id)).collect()
    }

    /// Each descriptor's (mean, std) of its similarities to the frames `opts` lets a query
    /// match: to [`ROW_SAMPLE`] of them, evenly spaced in the index (all of them when fewer).
    /// Sequence verification z-scores a history frame's similarities with them.
    pub fn row_stats(&self, descriptors: &[Vec<f32>], opts: &LoopQuery) -> Vec<(f32, f32)> {
        let filter = Filter::new(self, opts);
        let allowed: Vec<usize> = (0..self.frames.len()).filter(|&row| filter.allows(row)).collect();
        let step = allowed.len().div_ceil(ROW_SAMPLE).max(1);
        let rows: Vec<usize> = allowed.into_iter().step_by(step).collect();
        descriptors.iter().map(|d| mean_std(rows.iter().map(|&row| self.host_dot(d, row)))).collect()
    }

    /// The stored descriptor of a frame, as f32.
    pub fn descriptor(&self, frame_id: u64) -> Option<Vec<f32>> {
        let row = *self.by_frame.get(&frame_id)?;
        let range = row * self.dim..(row + 1) * self.dim;
        Some(match &self.rows {
            Rows::F16(v) => v[range].iter().map(|&b| half::f16::from_bits(b).to_f32()).collect(),
            Rows::F32(v) => v[range].to_vec(),
        })
    }

    /// Top-k rows by dot product with `q` that pass the query's filters, best first.
    pub fn search(&self, q: &[f32], opts: &LoopQuery, threads: usize) -> Vec<Match> {
        let filter = Filter::new(self, opts);
        let k = opts.k.min(query::MAX_K);
        if k == 0 || self.frames.is_empty() {
            return Vec::new();
        }
        if let Some(found) = self.graph_search(q, opts, k, &filter, threads) {
            return found.into_iter().map(|(score, row)| self.to_match(score, row)).collect();
        }
        if let Some(mut found) = self.device_top(q, opts, k, &filter) {
            let best = found.pop().unwrap_or_default();
            return best.into_iter().map(|(score, row)| self.to_match(score, row)).collect();
        }
        // Below a few MB of rows, starting threads costs more than it saves.
        let threads = if self.frames.len() * self.dim < PARALLEL_MIN_VALUES { 1 } else { threads };
        let init = || (TopK::new(k), vec![0f32; CHUNK_ROWS]);
        let parts = self.scan(CHUNK_ROWS, threads, init, |(heap, scores), s, e| {
            let out = &mut scores[..e - s];
            match &self.rows {
                Rows::F16(v) => dots_f16(q, &v[s * self.dim..e * self.dim], out),
                Rows::F32(v) => dots_f32(q, &v[s * self.dim..e * self.dim], out),
            }
            // Each block counts once read: a mapped file larger than its resident bound is
            // released as the scan goes, not mapped in whole first (issue #33's 10^7 run: a
            // 9.5 GiB peak of rows against a 512 MiB bound).
            self.note_read(e - s);
            for (i, &score) in out.iter().enumerate() {
                // Score first: the filter is only evaluated for would-be results.
                if score >= opts.min_score && heap.would_take(score, s + i) && filter.allows(s + i) {
                    heap.push(score, s + i);
                }
            }
        });
        let mut heap = TopK::new(k);
        parts.into_iter().for_each(|(h, _)| heap.merge(h));
        heap.sorted().into_iter().map(|(score, row)| self.to_match(score, row)).collect()
    }
}
