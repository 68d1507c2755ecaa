//! A session's own operations on what this node holds: search over its index, the frames,
//! features, thumbnails and trails read back from its sled trees, and its figures. Writes go
//! through the store (`Store::add_frames`), which checks them first.
use super::*;

impl Session {
    /// Ranked matches for a descriptor (normalised here); blocking: the store runs it on its
    /// search pool.
    pub fn search(&self, mut descriptor: Vec<f32>, q: &LoopQuery, threads: usize) -> Result<Vec<Match>, StoreError> {
        if descriptor.len() != self.meta.dim {
            return Err(StoreError::InvalidArgument(format!(
                "query descriptor has {} values; session '{}' holds {}-d descriptors",
                descriptor.len(),
                self.meta.id,
                self.meta.dim
            )));
        }
        q.validate()?;
        normalize(&mut descriptor)?;
        Ok(self.index.read().search(&descriptor, q, threads))
    }

    /// The frame's stored local features, if it has any (searchable frames only).
    pub fn features(&self, frame_id: u64) -> Result<Option<sled::IVec>, StoreError> {
        if !self.index.read().contains(frame_id) {
            return Err(StoreError::FrameNotFound(self.meta.id.clone(), frame_id));
        }
        Ok(self.trees()?.features.get(frame_key(frame_id))?)
    }

    /// The frame's stored thumbnail, if it has one (searchable frames only).
    pub fn thumbnail(&self, frame_id: u64) -> Result<Option<sled::IVec>, StoreError> {
        if !self.index.read().contains(frame_id) {
            return Err(StoreError::FrameNotFound(self.meta.id.clone(), frame_id));
        }
        Ok(self.trees()?.thumbs.get(frame_key(frame_id))?)
    }

    /// A searchable frame's descriptor as the index holds it.
    pub fn descriptor(&self, frame_id: u64) -> Result<Vec<f32>, StoreError> {
        let d = self.index.read().descriptor(frame_id);
        d.ok_or_else(|| StoreError::FrameNotFound(self.meta.id.clone(), frame_id))
    }

    /// Each descriptor's similarity statistics over the frames a query may match
    /// (`SessionIndex::row_stats`).
    pub fn row_stats(&self, descriptors: &[Vec<f32>], q: &query::LoopQuery) -> Vec<(f32, f32)> {
        self.index.read().row_stats(descriptors, q)
    }

    /// Each frame's place: its robot and its position on that robot's trajectory.
    pub fn places(&self, frames: &[u64]) -> Vec<(u32, usize)> {
        let index = self.index.read();
        frames.iter().map(|&id| index.place(id).unwrap_or((u32::MAX, 0))).collect()
    }

    /// What sequence verification needs of the map: for each candidate, its place (robot,
    /// position in its trajectory) and the descriptors of its last `n` frames up to it; and the
    /// `history` robot's newest `n` stored frames (oldest first).
    #[allow(clippy::type_complexity)]
    pub fn trails(
        &self,
        candidates: &[u64],
        n: usize,
        history: Option<&str>,
    ) -> (Vec<(u32, usize)>, Vec<Vec<Vec<f32>>>, Vec<Vec<f32>>) {
        let index = self.index.read();
        let places = candidates.iter().map(|&id| index.place(id).unwrap_or((u32::MAX, 0))).collect();
        let trails = candidates.iter().map(|&id| index.trail(id, n)).collect();
        let tail = history.map_or_else(Vec::new, |r| index.robot_tail(r, n));
        (places, trails, tail)
    }

    /// Candidates sequence verification adds: the frames the past votes for (see
    /// `index::SessionIndex::voted`), scored against `query` under the query's filters. The past is
    /// the robot's newest `n` frames, or the `n` frames before `stored`. `query` is of unit length.
    pub fn voted(&self, query: &[f32], q: &LoopQuery, stored: Option<u64>, n: usize, skip: &[u64]) -> Vec<Match> {
        let index = self.index.read();
        let votes = index.votes(q.robot_id.as_deref(), stored, n);
        let ids: Vec<u64> =
            index.voted(&votes).into_iter().filter(|id| !skip.contains(id) && Some(*id) != stored).collect();
        index.score_frames(query, &ids, q)
    }

    /// Records the best matches of the query a frame was added with.
    pub fn set_votes(&self, frame_id: u64, votes: Vec<u64>) {
        self.index.write().set_votes(frame_id, votes);
    }

    /// Claims a frame id before it is written to sled (`kept.rs`): a client's id as given,
    /// else the next free one.
    pub(super) fn claim(&self, client: Option<u64>) -> u64 {
        match self.kept.lock().as_mut() {
            Some(k) => k.claim(client, &self.next_id),
            None => client.unwrap_or_else(|| self.next_id.fetch_add(1, Relaxed)),
        }
    }

    /// Claimed ids that are searchable now, or were taken back.
    pub(super) fn settle(&self, ids: &[u64]) {
        if let Some(k) = self.kept.lock().as_mut() {
            k.settled(ids.iter().copied());
        }
    }

    /// Makes `frames` searchable (their rows appended to the index, their records kept) and
    /// counts their bytes on disk; the caller holds the index's lock.
    pub(super) fn publish(&self, index: &mut SessionIndex, frames: &[NewFrame], ids: &[u64], sizes: &[u64]) {
        let mut kept = self.kept.lock();
        for ((f, &id), &size) in frames.iter().zip(ids).zip(sizes) {
            index.push(id, &f.robot_id, f.timestamp, f.pose, &f.descriptor);
            if let Some(k) = kept.as_mut() {
                let key = f.idempotency_key.clone();
                let robot = f.robot_id.clone();
                k.append(&kept::Record { id, bytes: size as u32, robot, timestamp: f.timestamp, pose: f.pose, key });
            }
            self.bytes.fetch_add(size, Relaxed);
        }
        if let Some(k) = kept.as_mut() {
            k.settled(ids.iter().copied());
        }
    }

    /// Takes a frame that was never acknowledged back off disk, with the loops kept for it.
    pub(super) fn remove(&self, frame_id: u64) -> Result<(), StoreError> {
        let trees = self.trees()?;
        trees.frames.remove(frame_key(frame_id))?;
        trees.features.remove(frame_key(frame_id))?;
        trees.thumbs.remove(frame_key(frame_id))?;
        for key in trees.loops.scan_prefix(frame_key(frame_id)).keys() {
            trees.loops.remove(key?)?;
        }
        Ok(())
    }

    /// The session's trees, or Unavailable while the store reopens (never waits for it).
    pub(super) fn trees(&self) -> Result<MappedRwLockReadGuard<'_, Trees>, StoreError> {
        let guard = self.trees.try_read().ok_or_else(reopening)?;
        RwLockReadGuard::try_map(guard, Option::as_ref).map_err(|_| reopening())
    }

    /// A stored frame: header and descriptor as stored (f16 sessions give f16-rounded values).
    /// Read from the index's view, so a frame is visible here exactly when it is searchable.
    pub fn frame(&self, frame_id: u64) -> Result<(FrameHeader, Vec<f32>), StoreError> {
        let not_found = || StoreError::FrameNotFound(self.meta.id.clone(), frame_id);
        if !self.index.read().contains(frame_id) {
            return Err(not_found());
        }
        let v = self.trees()?.frames.get(frame_key(frame_id))?.ok_or_else(not_found)?;
        decode_frame(&v).map_err(StoreError::Storage)
    }

    /// The session's rows from sled, and its saved approximate index from `graphs` if that
    /// matches them (else it is rebuilt in the background). `keep`: whether its rows are kept in
    /// files across restarts (`kept.rs`; with mapped rows only), and whether to take them from
    /// the files kept by the last run.
    pub(super) fn load(
        db: &sled::Db,
        meta: SessionMeta,
        search: SearchConfig,
        graphs: &Path,
        rows: &Path,
        keep: Keep,
    ) -> Result<Self, StoreError> {
        let trees = Trees::open(db, &meta.id)?;
        let start = match keep {
            Keep::No => kept::Start::None,
            Keep::Fresh | Keep::Restore => kept::start(rows, &meta, &search, &trees, keep == Keep::Restore),
        };
        let mapping = search.rows_resident.map(|resident| crate::index::rows::Mapping { dir: rows, resident });
        let mut keys = super::keys::Keys::default();
        let (mut index, mut kept, mut bytes, tail_from) = match start {
            kept::Start::None => (SessionIndex::with_rows(meta.dim, meta.storage, mapping), None, 0, 0),
            kept::Start::Fresh(kept, file) => {
                let resident = search.rows_resident.unwrap_or(ROWS_RESIDENT);
                let index = SessionIndex::with_file(meta.dim, meta.storage, file, resident, std::iter::empty())
                    .map_err(|e| StoreError::Storage(format!("rows file of session '{}': {e}", meta.id)))?;
                (index, Some(*kept), 0, 0)
            }
            kept::Start::Restored(r) => {
                let r = *r;
                for rec in r.records {
                    if let Some(key) = rec.key {
                        keys.stored(key, rec.id);
                    }
                }
                (r.index, Some(r.kept), r.bytes_on_disk, r.tail_from)
            }
        };
        let restored = index.len();
        if let Some(device) = search.device {
            index.search_on(device, search.device_min_rows);
        }
        index.set_index(meta.index, search.graph);
        // Every frame, or (restored) those from `tail_from` on that the kept rows do not cover.
        for entry in trees.frames.range(frame_key(tail_from)..) {
            let (k, v) = entry?;
            let id = key_frame(&k).ok_or_else(|| StoreError::Storage("bad frame key".into()))?;
            if index.contains(id) {
                continue;
            }
            let (h, d) = decode_frame(&v).map_err(StoreError::Storage)?;
            let FrameHeader { robot_id, timestamp, pose, idempotency_key, .. } = h;
            index.push(id, &robot_id, timestamp, pose, &d);
            let size = (k.len() + v.len()) as u64;
            if let Some(kept) = &mut kept {
                let key = idempotency_key.clone();
                kept.append(&kept::Record { id, bytes: size as u32, robot: robot_id, timestamp, pose, key });
            }
            if let Some(key) = idempotency_key {
                keys.stored(key, id);
            }
            bytes += size;
        }
        let next = index.max_frame_id().map_or(0, |m| m.saturating_add(1));
        let graph_file = indexer::open_saved(&mut index, graphs, &meta.id);
        Ok(Self {
            meta,
            trees: RwLock::new(Some(trees)),
            index: RwLock::new(index),
            next_id: AtomicU64::new(next),
            bytes: AtomicU64::new(bytes),
            tbl: 0,
            applied: tokio::sync::Mutex::new(0),
            epoch: 0,
            used: AtomicU64::new(owners::now_ms()),
            graph_file: parking_lot::Mutex::new(graph_file),
            keys: parking_lot::Mutex::new(keys),
            kept: parking_lot::Mutex::new(kept),
            restored,
        })
    }

    /// Frames taken from the files kept by the last run when the session loaded (`kept.rs`;
    /// 0: every frame was read from the database).
    pub fn restored_frames(&self) -> usize {
        self.restored
    }

    /// Searches of this session answered on the search device (0 when searching on the host).
    pub fn device_searches(&self) -> u64 {
        self.index.read().device_searches()
    }

    pub fn info(&self) -> SessionInfo {
        let index = self.index.read();
        SessionInfo {
            meta: self.meta.clone(),
            frames: index.len(),
            robots: index.robots().to_vec(),
            bytes_on_disk: self.bytes.load(Relaxed),
            bytes_in_memory: index.memory_bytes(),
            approximate_frames: index.graph_rows(),
        }
    }
}

/// Inserts only if the frame id is free (atomic in sled). False: the id is taken.
pub(super) fn insert_new(frames: &sled::Tree, id: u64, value: &[u8]) -> Result<bool, StoreError> {
    Ok(frames.compare_and_swap(frame_key(id), None as Option<&[u8]>, Some(value))?.is_ok())
}

impl Trees {
    pub(super) fn open(db: &sled::Db, id: &str) -> Result<Self, StoreError> {
        Ok(Self {
            frames: db.open_tree(session_tree_name(id))?,
            features: db.open_tree(features_tree_name(id))?,
            loops: db.open_tree(loops_tree_name(id))?,
            thumbs: db.open_tree(thumbs_tree_name(id))?,
        })
    }
}
