//! A session's rows and frame records kept across restarts (issue #33: a node holding a large
//! map ready in seconds, not after reading every frame back from sled).
//!
//! With the sled backend and mapped rows, a session writes its rows to `<data-dir>/rows/<id>.rows`
//! (the file its index maps, `index::rows`) and each frame's record (id, robot, time, pose,
//! idempotency key, bytes on disk) to `<id>.frames`, in the order the frames became searchable.
//! Every `--rows-checkpoint-frames` frames (50,000), and at most a minute after the session last grew, the indexer
//! makes both files durable and then writes `<id>.json` (a checkpoint: frames covered, the
//! records' length and SHA-256, and `tail_from`, the lowest frame id that may be on disk but not
//! covered). At start a session with a checkpoint that checks out (format, dimension, storage,
//! file lengths, the records' checksum, and 16 sampled frames equal to sled's) takes the covered
//! rows as they are and reads from sled only the frames from `tail_from` on; anything else is
//! rebuilt from sled, which stays the only source of truth.
//!
//! What keeps `tail_from` right: a frame id is claimed (`Kept::claim`) before it is written to
//! sled and stays "in flight" until it is searchable or taken back, so a checkpoint's `tail_from`
//! is at most the lowest id in flight and at most the next free id. A client frame id below the
//! next free id (frames out of order) removes the checkpoint before it is written, so until the
//! next checkpoint a restart reads the session from sled in full.
use super::record::{decode_frame, frame_key};
use super::{SessionMeta, Trees};
use crate::index::query::Pose;
use crate::index::{SessionIndex, Storage};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Read, Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::time::{Duration, Instant};

/// A checkpoint at least every `SearchConfig::checkpoint_frames` new frames, and at most this long after the session last grew.
const SAVE_INTERVAL: Duration = Duration::from_secs(60);

/// Frames of a checkpoint compared with sled's at start.
const SAMPLES: usize = 16;

const FORMAT: u32 = 1;

#[derive(Serialize, Deserialize)]
struct Checkpoint {
    format: u32,
    frames: usize,
    dim: usize,
    storage: Storage,
    /// Length and SHA-256 of the records of the covered frames.
    records_bytes: u64,
    records_sha256: String,
    /// Frames with ids from here on may be in sled and not covered.
    tail_from: u64,
    /// The session's bytes on disk (sled keys and values) of the covered frames.
    bytes_on_disk: u64,
}

/// A frame's record as kept.
pub(super) struct Record {
    pub id: u64,
    pub bytes: u32,
    pub robot: String,
    pub timestamp: f64,
    pub pose: Option<Pose>,
    pub key: Option<String>,
}

/// The open files of a session's kept rows, and its frames in flight.
pub(super) struct Kept {
    dir: PathBuf,
    id: String,
    records: BufWriter<File>,
    hasher: Sha256,
    records_bytes: u64,
    frames: usize,
    saved_frames: usize,
    saved_at: Instant,
    /// Bumped when frames out of order remove the checkpoint.
    generation: u64,
    /// Frame ids claimed and not yet searchable or taken back (with a count: a failed write's
    /// id may be claimed again).
    in_flight: BTreeMap<u64, usize>,
    /// Set when writing the records failed: no more checkpoints (a restart reads sled).
    broken: bool,
    /// Frames between checkpoints.
    every: usize,
}

/// The three files of a session.
fn paths(dir: &Path, id: &str) -> [PathBuf; 3] {
    ["rows", "frames", "json"].map(|ext| dir.join(format!("{id}.{ext}")))
}

/// Removes a session's kept files (a deleted session; an old mapping stays readable).
pub(super) fn remove(dir: &Path, id: &str) {
    for p in paths(dir, id) {
        let _ = std::fs::remove_file(p);
    }
}

/// Removes kept files of sessions the store does not hold (a delete cut short by a crash).
pub(super) fn remove_others(dir: &Path, held: &std::collections::HashSet<String>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().to_string();
        let Some((id, ext)) = name.rsplit_once('.') else { continue };
        let id = id.split_once(".tmp-").map_or(id, |(id, _)| id);
        let orphan = matches!(ext, "rows" | "frames" | "json") && !held.contains(id);
        if orphan || name.contains(".tmp-") || name.ends_with(".json.tmp") {
            tracing::info!(file = %name, "removing a kept rows file no session holds");
            let _ = std::fs::remove_file(e.path());
        }
    }
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> String + '_ {
    move |e| format!("{}: {e}", path.display())
}

/// A new empty file put in place of `path` (a rename: a mapping of the old file stays valid).
fn fresh_file(path: &Path) -> Result<File, String> {
    static NEXT: AtomicUsize = AtomicUsize::new(0);
    let tmp = path.with_extension(format!(
        "{}.tmp-{}-{}",
        path.extension().and_then(|e| e.to_str()).unwrap_or(""),
        std::process::id(),
        NEXT.fetch_add(1, Relaxed)
    ));
    let file = std::fs::OpenOptions::new().read(true).write(true).create_new(true).open(&tmp).map_err(io(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io(path))?;
    Ok(file)
}

impl Kept {
    /// New, empty kept files for a session (any old checkpoint removed first); returns the rows
    /// file for the index.
    pub(super) fn create(dir: &Path, id: &str, every: usize) -> Result<(Self, File), String> {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let [rows, frames, json] = paths(dir, id);
        match std::fs::remove_file(&json) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io(&json)(e)),
            _ => {}
        }
        let rows = fresh_file(&rows)?;
        let records = fresh_file(&frames)?;
        Ok((Self::over(dir, id, records, Sha256::new(), 0, 0, every), rows))
    }

    fn over(
        dir: &Path,
        id: &str,
        records: File,
        hasher: Sha256,
        records_bytes: u64,
        frames: usize,
        every: usize,
    ) -> Self {
        Self {
            dir: dir.to_path_buf(),
            id: id.to_string(),
            records: BufWriter::with_capacity(1 << 16, records),
            hasher,
            records_bytes,
            frames,
            saved_frames: frames,
            saved_at: Instant::now(),
            generation: 0,
            in_flight: BTreeMap::new(),
            broken: false,
            every: every.max(1),
        }
    }

    /// Claims frame ids before they are written to sled: `client` ids as given, else the next
    /// free ids (`next`). Returns the id.
    pub(super) fn claim(&mut self, client: Option<u64>, next: &std::sync::atomic::AtomicU64) -> u64 {
        let id = match client {
            Some(id) => {
                if id < next.load(Relaxed) {
                    self.invalidate();
                }
                next.fetch_max(id.saturating_add(1), Relaxed);
                id
            }
            None => next.fetch_add(1, Relaxed),
        };
        *self.in_flight.entry(id).or_default() += 1;
        id
    }

    /// The frames are searchable now, or were taken back.
    pub(super) fn settled(&mut self, ids: impl IntoIterator<Item = u64>) {
        for id in ids {
            if let std::collections::btree_map::Entry::Occupied(mut e) = self.in_flight.entry(id) {
                *e.get_mut() -= 1;
                if *e.get() == 0 {
                    e.remove();
                }
            }
        }
    }

    /// Frames out of order: a restart must not trust the checkpoint (it would miss them).
    fn invalidate(&mut self) {
        self.generation += 1;
        let json = &paths(&self.dir, &self.id)[2];
        match std::fs::remove_file(json) {
            Ok(()) => {
                tracing::info!(session = %self.id, "frames out of order: the kept rows' checkpoint is removed until the next one")
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                tracing::warn!(session = %self.id, error = %e, "removing the kept rows' checkpoint failed; no more checkpoints");
                self.broken = true;
            }
        }
    }

    /// Appends the record of the frame whose row the index appended last.
    pub(super) fn append(&mut self, r: &Record) {
        if self.broken {
            return;
        }
        let bytes = encode(r);
        if let Err(e) = self.records.write_all(&bytes) {
            tracing::warn!(session = %self.id, error = %e, "writing frame records failed; the session is read from sled at the next start");
            self.invalidate();
            self.broken = true;
            return;
        }
        self.hasher.update(&bytes);
        self.records_bytes += bytes.len() as u64;
        self.frames += 1;
    }
}

fn encode(r: &Record) -> Vec<u8> {
    let mut out = Vec::with_capacity(64 + r.robot.len());
    out.extend_from_slice(&r.id.to_le_bytes());
    out.extend_from_slice(&r.bytes.to_le_bytes());
    out.extend_from_slice(&r.timestamp.to_le_bytes());
    out.push(u8::from(r.pose.is_some()) | (u8::from(r.key.is_some()) << 1));
    if let Some(p) = &r.pose {
        for v in [p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out.extend_from_slice(&(r.robot.len() as u32).to_le_bytes());
    out.extend_from_slice(r.robot.as_bytes());
    if let Some(k) = &r.key {
        out.extend_from_slice(&(k.len() as u32).to_le_bytes());
        out.extend_from_slice(k.as_bytes());
    }
    out
}

/// Reads the records written by [`encode`].
struct Reader<'a>(&'a [u8]);

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        if self.0.len() < n {
            return Err("frame records end inside a record".into());
        }
        let (head, rest) = self.0.split_at(n);
        self.0 = rest;
        Ok(head)
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().map_err(|_| "short")?))
    }
    fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().map_err(|_| "short")?))
    }
    fn f64(&mut self) -> Result<f64, String> {
        Ok(f64::from_bits(self.u64()?))
    }
    fn string(&mut self) -> Result<String, String> {
        let n = self.u32()? as usize;
        String::from_utf8(self.take(n)?.to_vec()).map_err(|_| "a frame record's text is not UTF-8".to_string())
    }
    fn record(&mut self) -> Result<Record, String> {
        let id = self.u64()?;
        let bytes = self.u32()?;
        let timestamp = self.f64()?;
        let flags = self.take(1)?[0];
        let pose = if flags & 1 != 0 {
            let mut v = [0f64; 7];
            for x in &mut v {
                *x = self.f64()?;
            }
            Some(Pose { x: v[0], y: v[1], z: v[2], qx: v[3], qy: v[4], qz: v[5], qw: v[6] })
        } else {
            None
        };
        let robot = self.string()?;
        let key = if flags & 2 != 0 { Some(self.string()?) } else { None };
        Ok(Record { id, bytes, robot, timestamp, pose, key })
    }
}

/// A session brought back from its kept files.
pub(super) struct Restored {
    pub index: SessionIndex,
    pub kept: Kept,
    pub records: Vec<Record>,
    pub tail_from: u64,
    pub bytes_on_disk: u64,
}

/// The session's kept rows and records, if its checkpoint checks out (else why not).
pub(super) fn restore(
    dir: &Path,
    meta: &SessionMeta,
    resident: usize,
    every: usize,
    trees: &Trees,
) -> Result<Restored, String> {
    let [rows_path, frames_path, json_path] = paths(dir, &meta.id);
    let json = match std::fs::read(&json_path) {
        Ok(j) => j,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err("no checkpoint".into()),
        Err(e) => return Err(io(&json_path)(e)),
    };
    let c: Checkpoint = serde_json::from_slice(&json).map_err(|e| format!("checkpoint: {e}"))?;
    if c.format != FORMAT || c.dim != meta.dim || c.storage != meta.storage {
        return Err(format!(
            "checkpoint of format {} for {}-d {:?} rows (this server: format {FORMAT}, session {}-d {:?})",
            c.format, c.dim, c.storage, meta.dim, meta.storage
        ));
    }
    let mut records_file =
        std::fs::OpenOptions::new().read(true).write(true).open(&frames_path).map_err(io(&frames_path))?;
    let mut bytes = Vec::new();
    (&mut records_file).take(c.records_bytes).read_to_end(&mut bytes).map_err(io(&frames_path))?;
    if bytes.len() as u64 != c.records_bytes {
        return Err(format!("frame records hold {} bytes; the checkpoint covers {}", bytes.len(), c.records_bytes));
    }
    let mut hasher = Sha256::new();
    hasher.update(&bytes);
    let sha = format!("{:x}", hasher.clone().finalize());
    if sha != c.records_sha256 {
        return Err(format!("frame records' checksum {sha} differs from the checkpoint's {}", c.records_sha256));
    }
    let mut reader = Reader(&bytes);
    let mut records = Vec::with_capacity(c.frames);
    while !reader.0.is_empty() {
        records.push(reader.record()?);
    }
    if records.len() != c.frames {
        return Err(format!("{} frame records; the checkpoint covers {}", records.len(), c.frames));
    }
    drop(bytes);
    let rows_file = std::fs::OpenOptions::new().read(true).write(true).open(&rows_path).map_err(io(&rows_path))?;
    let need = (c.frames * c.dim * c.storage.bytes_per_value()) as u64;
    let have = rows_file.metadata().map_err(io(&rows_path))?.len();
    if have < need {
        return Err(format!("rows file holds {have} bytes; the checkpoint covers {need}"));
    }
    let frames = records.iter().map(|r| (r.id, r.robot.as_str(), r.timestamp, r.pose));
    let index = SessionIndex::with_file(meta.dim, meta.storage, rows_file, resident, frames).map_err(io(&rows_path))?;
    // Sampled frames must be sled's, row and record.
    let n = records.len();
    let picks = (0..SAMPLES.min(n)).map(|i| i * n / SAMPLES.min(n)).chain(n.checked_sub(1));
    for i in picks {
        let r = &records[i];
        let v = trees.frames.get(frame_key(r.id)).map_err(|e| e.to_string())?;
        let v = v.ok_or_else(|| format!("frame {} of the checkpoint is not in sled", r.id))?;
        let (h, d) = decode_frame(&v)?;
        let row = index.descriptor(r.id);
        if h.robot_id != r.robot || h.timestamp.to_bits() != r.timestamp.to_bits() || row.as_deref() != Some(&d[..]) {
            return Err(format!("frame {} differs from sled's", r.id));
        }
        if (8 + v.len()) as u32 != r.bytes {
            return Err(format!("frame {}'s size differs from sled's", r.id));
        }
    }
    records_file.set_len(c.records_bytes).map_err(io(&frames_path))?;
    records_file.seek(std::io::SeekFrom::End(0)).map_err(io(&frames_path))?;
    let kept = Kept::over(dir, &meta.id, records_file, hasher, c.records_bytes, n, every);
    Ok(Restored { index, kept, records, tail_from: c.tail_from, bytes_on_disk: c.bytes_on_disk })
}

/// What a checkpoint is taken from: the session's state under its locks.
pub(super) struct Snapshot {
    checkpoint: Checkpoint,
    rows: File,
    records: File,
    generation: u64,
    json: PathBuf,
}

impl Kept {
    /// Whether a checkpoint is due, given `frames` searchable now.
    pub(super) fn due(&self, frames: usize) -> bool {
        !self.broken
            && (frames >= self.saved_frames.saturating_add(self.every)
                || (frames > self.saved_frames && self.saved_at.elapsed() >= SAVE_INTERVAL))
    }

    /// Takes what a checkpoint of `index` needs (the caller holds the index's lock, so no frame
    /// becomes searchable meanwhile).
    pub(super) fn snapshot(
        &mut self,
        index: &SessionIndex,
        next_id: u64,
        bytes_on_disk: u64,
    ) -> Result<Snapshot, String> {
        if index.len() != self.frames {
            return Err(format!("{} frames searchable, {} records", index.len(), self.frames));
        }
        self.records.flush().map_err(|e| e.to_string())?;
        let Some(rows) = index.rows_file() else {
            // A failed write moved the rows into memory (`index::rows`): nothing to keep.
            self.invalidate();
            self.broken = true;
            return Err("the session's rows moved into memory; no more checkpoints".into());
        };
        let rows = rows.map_err(|e| e.to_string())?;
        let records = self.records.get_ref().try_clone().map_err(|e| e.to_string())?;
        let tail_from = self.in_flight.keys().next().map_or(next_id, |&low| low.min(next_id));
        Ok(Snapshot {
            checkpoint: Checkpoint {
                format: FORMAT,
                frames: self.frames,
                dim: index.dim(),
                storage: index.storage(),
                records_bytes: self.records_bytes,
                records_sha256: format!("{:x}", self.hasher.clone().finalize()),
                tail_from,
                bytes_on_disk,
            },
            rows,
            records,
            generation: self.generation,
            json: paths(&self.dir, &self.id)[2].clone(),
        })
    }

    /// Writes the checkpoint once its files are durable (`Snapshot::sync`), unless frames out
    /// of order came meanwhile. Called with the session's kept lock held, so none can come
    /// while it is written.
    pub(super) fn commit(&mut self, snap: Snapshot) -> Result<bool, String> {
        if snap.generation != self.generation || self.broken {
            return Ok(false);
        }
        let tmp = snap.json.with_extension("json.tmp");
        let body = serde_json::to_vec(&snap.checkpoint).map_err(|e| e.to_string())?;
        let mut f = File::create(&tmp).map_err(io(&tmp))?;
        f.write_all(&body).and_then(|_| f.sync_all()).map_err(io(&tmp))?;
        std::fs::rename(&tmp, &snap.json).map_err(io(&snap.json))?;
        File::open(&self.dir).and_then(|d| d.sync_all()).map_err(io(&self.dir))?;
        self.saved_frames = snap.checkpoint.frames;
        self.saved_at = Instant::now();
        Ok(true)
    }

    /// The session is deleted: no more checkpoints (its files are removed after this).
    pub(super) fn retire(&mut self) {
        self.broken = true;
    }

    /// A failed checkpoint: try again after the interval.
    pub(super) fn postpone(&mut self) {
        self.saved_at = Instant::now();
    }
}

impl Snapshot {
    /// Makes the covered rows and records durable (outside the session's locks: slow).
    pub(super) fn sync(&self) -> Result<(), String> {
        self.rows.sync_data().map_err(|e| format!("rows: {e}"))?;
        self.records.sync_data().map_err(|e| format!("frame records: {e}"))
    }

    pub(super) fn frames(&self) -> usize {
        self.checkpoint.frames
    }
}

/// Kept rows restored or begun for a session, as `Session::load` needs them.
pub(super) enum Start {
    /// Not kept (a cluster's cache, rows in memory, or files that could not be made).
    None,
    /// Files begun empty: read every frame from sled.
    Fresh(Box<Kept>, File),
    Restored(Box<Restored>),
}

/// Restores the session's kept rows (`restore`), or begins new files when there are none or
/// they do not check out (logged).
pub(super) fn start(
    dir: &Path,
    meta: &SessionMeta,
    search: &super::SearchConfig,
    trees: &Trees,
    restore_saved: bool,
) -> Start {
    let Some(resident) = search.rows_resident else {
        // Rows in memory this run: frames it adds would be missing from the kept files.
        remove(dir, &meta.id);
        return Start::None;
    };
    let every = search.checkpoint_frames;
    if restore_saved {
        let t = Instant::now();
        match restore(dir, meta, resident, every, trees) {
            Ok(r) => {
                tracing::info!(
                    session = %meta.id,
                    frames = r.records.len(),
                    elapsed_ms = t.elapsed().as_millis() as u64,
                    "kept rows restored; the frames after them are read from sled"
                );
                return Start::Restored(Box::new(r));
            }
            Err(why) if why == "no checkpoint" => {}
            Err(why) => {
                tracing::warn!(session = %meta.id, %why, "kept rows rejected; reading the session from sled")
            }
        }
    }
    match Kept::create(dir, &meta.id, every) {
        Ok((kept, rows)) => Start::Fresh(Box::new(kept), rows),
        Err(e) => {
            tracing::warn!(session = %meta.id, error = %e, "kept rows not created; the session is read from sled at each start");
            Start::None
        }
    }
}

/// Writes a checkpoint of the session's kept rows if one is due (the indexer, every turn).
pub(super) fn checkpoint_if_due(s: &super::Session) {
    // A deleted session (its trees gone), or the store reopening: not now.
    if s.trees.read().is_none() {
        return;
    }
    let snap = {
        let index = s.index.read();
        let mut kept = s.kept.lock();
        let Some(k) = kept.as_mut() else { return };
        if !k.due(index.len()) {
            return;
        }
        k.snapshot(&index, s.next_id.load(Relaxed), s.bytes.load(Relaxed))
    };
    let t = Instant::now();
    let done = snap.and_then(|snap| {
        snap.sync()?;
        let frames = snap.frames();
        match s.kept.lock().as_mut() {
            Some(k) => k.commit(snap).map(|written| written.then_some(frames)),
            None => Ok(None),
        }
    });
    match done {
        Ok(Some(frames)) => tracing::info!(
            session = %s.meta.id,
            frames,
            elapsed_ms = t.elapsed().as_millis() as u64,
            "kept rows checkpointed"
        ),
        Ok(None) => {}
        Err(e) => {
            tracing::warn!(session = %s.meta.id, error = %e, "kept rows not checkpointed (a restart reads more of sled)");
            if let Some(k) = s.kept.lock().as_mut() {
                k.postpone();
            }
        }
    }
}
