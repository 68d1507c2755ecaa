//! Map sessions on disk (sled, or the PostgreSQL cluster's log with sled as its cache), each with
//! its search index (`crate::index`) filled from its records.
mod backend;
mod cluster;
mod cluster_jobs;
pub mod disk;
pub mod durability;
mod embedded;
pub mod health;
mod indexer;
mod kept;
pub mod keys;
pub mod loops;
mod operations;
mod owners;
pub mod pg;
mod pg_connect;
mod pg_db;
mod pg_jobs;
mod pg_members;
mod pg_writer;
pub use owners::{ClusterView, HeldSession, Membership};
mod error;
pub mod record;
mod records;
mod reopen;
mod rules;
mod session;
pub use error::StoreError;
use rules::{check_new_frame, new_meta};
pub use rules::{new_session_id, robot_id_error};
use session::insert_new;

use crate::index::query::{self, LoopQuery, Match, Pose};
use crate::index::{normalize, SessionIndex, Storage};
use backend::dispatch;
pub use cluster::tracking_staleness;
use disk::Disk;
use health::Health;
use operations::Operations as _;
use parking_lot::{MappedRwLockReadGuard, Mutex, RwLock, RwLockReadGuard};
use record::{decode_frame, encode_frame, frame_key, key_frame, FrameHeader, SessionMeta};
use serde::Serialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::Semaphore;

/// Largest frame id a client may choose: server-assigned ids count up from the highest stored id
/// and must never wrap around.
pub const MAX_CLIENT_FRAME_ID: u64 = (1 << 63) - 1;

/// A frame to add. `frame_id` None: the session assigns the next free id.
#[derive(Clone, Debug)]
pub struct NewFrame {
    pub frame_id: Option<u64>,
    pub robot_id: String,
    pub timestamp: f64,
    pub pose: Option<Pose>,
    pub metadata: Option<serde_json::Value>,
    pub descriptor: Vec<f32>,
    /// Local features for verification, opaque to the store (kept beside the frame, written and
    /// removed with it, never read at start-up).
    pub features: Option<Vec<u8>>,
    /// A small picture of the frame for people (sessions with thumbnails on); kept like features.
    pub thumbnail: Option<Vec<u8>>,
    /// The client's idempotency key: a write that repeats a stored frame's key stores nothing
    /// and answers that frame's id (`keys.rs`).
    pub idempotency_key: Option<String>,
}

/// A session to create: everything of its metadata but the id and the creation time.
#[derive(Clone, Debug)]
pub struct NewSession {
    pub name: String,
    pub dim: usize,
    /// The descriptor space of what it will hold.
    pub descriptor_id: String,
    pub storage: Storage,
    pub default_query: LoopQuery,
    pub camera: Option<record::Camera>,
    /// Keep a thumbnail of each frame (for the loop inspector).
    pub thumbnails: bool,
    pub index: crate::index::graph::IndexKind,
    /// The served model's name (None: the server's default).
    pub model: Option<String>,
}

/// What a session holds, for listings.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct SessionInfo {
    #[serde(flatten)]
    pub meta: SessionMeta,
    pub frames: usize,
    pub robots: Vec<String>,
    pub bytes_on_disk: u64,
    /// The server's own memory for the session: frame records, the approximate index's graph,
    /// and the rows when kept in memory (`--rows-in-memory`; mapped rows are the page cache's).
    pub bytes_in_memory: usize,
    /// Frames the approximate index covers (the newest others are searched exactly until the
    /// indexer adds them); absent while the session searches exactly.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub approximate_frames: Option<usize>,
}

/// A session's trees in the open database; None while the store reopens it.
struct Trees {
    frames: sled::Tree,
    features: sled::Tree,
    /// Loop candidates answered for its frames (`loops.rs`).
    loops: sled::Tree,
    /// Thumbnails of its frames (JPEG), by frame key.
    thumbs: sled::Tree,
}

pub struct Session {
    pub meta: SessionMeta,
    trees: RwLock<Option<Trees>>,
    index: RwLock<SessionIndex>,
    next_id: AtomicU64,
    bytes: AtomicU64,
    /// In a cluster: the session's table in the log (0 with sled) and the last `seq` applied
    /// here; the lock orders the applies.
    tbl: i64,
    applied: tokio::sync::Mutex<i64>,
    /// In a cluster: the log's primary epoch it was loaded under (see `PgLog::epoch`).
    epoch: u64,
    /// In a cluster: when a request last used it (ms since the Unix epoch), so that a node evicts
    /// only sessions it neither owns nor serves (`owners.rs`).
    used: AtomicU64,
    /// Where its approximate index is saved, and how much of it was last (`indexer.rs`).
    graph_file: parking_lot::Mutex<indexer::GraphFile>,
    /// Idempotency keys of its frames, and of writes in flight (`keys.rs`).
    keys: parking_lot::Mutex<keys::Keys>,
    /// Its rows and frame records kept across restarts, and the frame ids in flight
    /// (`kept.rs`); None in a cluster's cache and with rows in memory. Locked after `index`.
    kept: parking_lot::Mutex<Option<kept::Kept>>,
    /// Frames taken from the kept files when it loaded (0: all read from sled).
    restored: usize,
}

/// Whether a loading session's rows are kept in files across restarts (`kept.rs`).
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Keep {
    /// No (a cluster node's cache: the log is the truth, and the cache is dropped at start).
    No,
    /// In new files (a new session).
    Fresh,
    /// From the files the last run kept, where they check out (a store opening).
    Restore,
}

pub struct Store {
    dir: PathBuf,
    /// The open database; None while a reopen replaces it.
    disk: RwLock<Option<Disk>>,
    health: Arc<Health>,
    sessions: Arc<RwLock<HashMap<String, Arc<Session>>>>,
    /// Serialises session creation and deletion (not frame writes) and reopens.
    admin: Mutex<()>,
    search_threads: usize,
    /// Searches running at once on blocking threads (never on the async executor).
    search_slots: Arc<Semaphore>,
    search: SearchConfig,
    /// Where the truth lives, chosen once at open (`backend.rs`): sled here, or the cluster's
    /// replicated log with the sled folder as this node's cache of it (`cluster.rs`).
    backend: backend::Backend,
}

/// A write whose flush failed: not stored, and the store refuses writes until it recovers.
fn not_durable(e: String) -> StoreError {
    StoreError::Unavailable(format!("storage failed ({e}); not stored, retry later"))
}

/// A session's local trees are closed: the store reopens after a storage failure, or (cluster)
/// the session's copy here is being replaced, e.g. after the primary changed.
fn reopening() -> StoreError {
    StoreError::Unavailable("this node's copy of the session is being reopened or reloaded; retry later".into())
}

fn session_tree_name(id: &str) -> String {
    format!("session/{id}")
}

fn features_tree_name(id: &str) -> String {
    format!("features/{id}")
}

fn loops_tree_name(id: &str) -> String {
    format!("loops/{id}")
}

fn thumbs_tree_name(id: &str) -> String {
    format!("thumbs/{id}")
}

/// Every tree a session owns: what deleting it drops.
fn trees_of(id: &str) -> [String; 4] {
    [session_tree_name(id), features_tree_name(id), loops_tree_name(id), thumbs_tree_name(id)]
}

/// Where loop searches run.
#[derive(Clone, Copy, Debug)]
pub struct SearchConfig {
    /// A libtorch device (the model's GPU) holding a copy of every session's rows; None: the
    /// host SIMD kernels.
    pub device: Option<tch::Device>,
    /// Sessions smaller than this search on the host even with a device (round-trip cost).
    pub device_min_rows: usize,
    /// Searches running at once (each on a blocking thread); more wait their turn.
    pub max_concurrent: usize,
    /// The approximate index's shape, and when `auto` sessions switch to it.
    pub graph: crate::index::graph::GraphParams,
    /// Each session's rows in a file under `<data-dir>/rows/` mapped into memory, at most this
    /// many bytes of them kept in the process (`index/rows.rs`); None: rows in memory.
    pub rows_resident: Option<usize>,
    /// With mapped rows, a session's rows and frame records are kept across restarts and
    /// checkpointed each time it has grown by this many frames (and at most a minute after it
    /// last grew), so a restart reads only the frames after the checkpoint from sled
    /// (`kept.rs`).
    pub checkpoint_frames: usize,
}

/// The folder (under the data directory) sessions' row files are made in.
const ROWS_DIR: &str = "rows";

/// The default of [`SearchConfig::checkpoint_frames`].
pub const CHECKPOINT_FRAMES: usize = 50_000;

/// The default of [`SearchConfig::rows_resident`]: 1 GiB per session.
pub const ROWS_RESIDENT: usize = 1 << 30;

impl Default for SearchConfig {
    fn default() -> Self {
        Self {
            device: None,
            device_min_rows: 4096,
            max_concurrent: cores(),
            graph: Default::default(),
            rows_resident: Some(ROWS_RESIDENT),
            checkpoint_frames: CHECKPOINT_FRAMES,
        }
    }
}

fn cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}

impl Store {
    /// Opens (or creates) the database and rebuilds every session's index from it; searches
    /// run on the host.
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        Self::open_with(dir, SearchConfig::default())
    }

    /// As [`Store::open`], with searches where `search` says.
    pub fn open_with(dir: &Path, search: SearchConfig) -> Result<Self, StoreError> {
        Self::open_dir(dir, search, backend::Backend::Sled(embedded::Sled))
    }

    /// Opens the folder; with a cluster log, the sessions cached there from an earlier run are
    /// dropped (the log is the authority) and loaded again from it on first use.
    fn open_dir(dir: &Path, search: SearchConfig, backend: backend::Backend) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(|e| StoreError::Storage(format!("{}: {e}", dir.display())))?;
        let graphs = dir.join(indexer::GRAPH_DIR);
        std::fs::create_dir_all(&graphs).map_err(|e| StoreError::Storage(format!("{}: {e}", graphs.display())))?;
        let rows = dir.join(ROWS_DIR);
        let health = Arc::new(Health::default());
        let disk = Disk::open(dir, health.clone())?;
        let t = Instant::now();
        let mut sessions = HashMap::new();
        let mut frames = 0;
        let sled_is_cache = match &backend {
            backend::Backend::Sled(b) => b.sled_is_cache(),
            backend::Backend::Cluster(b) => b.sled_is_cache(),
        };
        if sled_is_cache {
            for key in disk.sessions.iter().keys() {
                let key = key?;
                for tree in trees_of(&String::from_utf8_lossy(&key)) {
                    disk.db.drop_tree(tree)?;
                }
                disk.sessions.remove(key)?;
            }
        }
        for entry in disk.sessions.iter() {
            let (_, v) = entry?;
            let meta: SessionMeta = serde_json::from_slice(&v).map_err(|e| StoreError::Storage(e.to_string()))?;
            let session = Session::load(&disk.db, meta, search, &graphs, &rows, Keep::Restore)?;
            let index = session.index.read();
            index.upload();
            frames += index.len();
            drop(index);
            sessions.insert(session.meta.id.clone(), Arc::new(session));
        }
        kept::remove_others(&rows, &sessions.keys().cloned().collect());
        tracing::info!(
            sessions = sessions.len(),
            frames,
            elapsed_ms = t.elapsed().as_millis() as u64,
            search_device = search.device.map_or_else(|| "host".to_string(), |d| format!("{d:?}")),
            "indexes rebuilt from sled"
        );
        let sessions = Arc::new(RwLock::new(sessions));
        indexer::spawn(Arc::downgrade(&sessions));
        Ok(Self {
            dir: dir.to_path_buf(),
            disk: RwLock::new(Some(disk)),
            health,
            sessions,
            admin: Mutex::new(()),
            search_threads: cores(),
            search_slots: Arc::new(Semaphore::new(search.max_concurrent.max(1))),
            search,
            backend,
        })
    }

    /// Creates a session; `id` None: the store picks one.
    pub async fn create_session(&self, id: Option<String>, new: NewSession) -> Result<SessionMeta, StoreError> {
        let meta = new_meta(id, new)?;
        self.health.writable()?;
        dispatch!(async self, create_session(self, meta))
    }

    /// Whether other nodes serve the same sessions (the cluster's log), so that a request this
    /// node cannot serve may go to another.
    pub fn is_shared(&self) -> bool {
        matches!(self.backend, backend::Backend::Cluster(_))
    }

    pub fn session(&self, id: &str) -> Result<Arc<Session>, StoreError> {
        self.sessions.read().get(id).cloned().ok_or_else(|| StoreError::SessionNotFound(id.into()))
    }

    pub fn list(&self) -> Vec<SessionInfo> {
        let mut v: Vec<SessionInfo> = self.sessions.read().values().map(|s| s.info()).collect();
        v.sort_by(|a, b| a.meta.created.total_cmp(&b.meta.created).then(a.meta.id.cmp(&b.meta.id)));
        v
    }

    /// Deletes the session and its frames from disk and memory.
    pub async fn delete_session(&self, id: &str) -> Result<(), StoreError> {
        self.health.writable()?;
        dispatch!(async self, delete_session(self, id))
    }

    /// Takes the session out of memory and drops its trees (not yet durable); false: there was
    /// none.
    fn remove_local(&self, id: &str) -> Result<bool, StoreError> {
        let _admin = self.admin.lock();
        self.remove_locked(id)
    }

    /// As [`Store::remove_local`], the admin lock held by the caller.
    fn remove_locked(&self, id: &str) -> Result<bool, StoreError> {
        // Nothing is taken out of memory while the database is away (a reopen).
        drop(self.disk()?);
        let removed = self.sessions.write().remove(id);
        let Some(removed) = removed else { return Ok(false) };
        self.drop_trees(id, &removed)?;
        indexer::remove_saved(&removed);
        // Retired first (under its lock): a checkpoint under way does not write its file again.
        if let Some(k) = removed.kept.lock().as_mut() {
            k.retire();
        }
        kept::remove(&self.rows_dir(), id);
        Ok(true)
    }

    /// Drops a session taken out of `sessions` from disk (the admin lock held by the caller).
    fn drop_trees(&self, id: &str, removed: &Session) -> Result<(), StoreError> {
        let disk = self.disk()?;
        // Its handles go first: sled drops a tree's contents once no handle holds it.
        removed.trees.write().take();
        self.note(disk.sessions.remove(id.as_bytes()))?;
        for tree in trees_of(id) {
            self.note(disk.db.drop_tree(tree))?;
        }
        Ok(())
    }

    /// Adds frames; acknowledged (returns their ids) once they are on disk. A frame becomes
    /// searchable right after its flush, on the flusher, whether or not the caller still waits:
    /// a dropped request cannot leave a frame on disk that the index does not know.
    pub async fn add_frames(&self, s: &Arc<Session>, frames: Vec<NewFrame>) -> Result<Vec<u64>, StoreError> {
        self.add_frames_keeping(s, frames, Vec::new()).await
    }

    /// As [`Store::add_frames`], with the loop candidates answered for them (each by its query
    /// frame's position in `frames`, [`loops::KeptLoops`]) kept with them: exactly when the
    /// frames are.
    pub async fn add_frames_keeping(
        &self,
        s: &Arc<Session>,
        frames: Vec<NewFrame>,
        loops: loops::KeptLoops,
    ) -> Result<Vec<u64>, StoreError> {
        self.health.writable()?;
        let mut prepared = Vec::with_capacity(frames.len());
        for mut f in frames {
            check_new_frame(s, &f)?;
            normalize(&mut f.descriptor)?;
            prepared.push(f);
        }
        let held = match s.claim_key(&prepared)? {
            keys::Claim::Stored(id) => return Ok(vec![id]),
            keys::Claim::Held(guard) => Some(guard),
            keys::Claim::Unkeyed => None,
        };
        dispatch!(async self, add_frames(self, s, prepared, loops, held))
    }

    /// Inserts the frames (all or none) and returns their ids and bytes on disk; not yet
    /// durable. Their ids stay claimed (`Session::claim`) until the caller settles them; on an
    /// error they are settled here.
    fn write_frames(s: &Session, prepared: &[NewFrame]) -> Result<(Vec<u64>, Vec<u64>), StoreError> {
        let mut claimed = Vec::with_capacity(prepared.len());
        let written = Self::write_claimed(s, prepared, &mut claimed);
        if written.is_err() {
            s.settle(&claimed);
        }
        written
    }

    fn write_claimed(
        s: &Session,
        prepared: &[NewFrame],
        claimed: &mut Vec<u64>,
    ) -> Result<(Vec<u64>, Vec<u64>), StoreError> {
        let trees = s.trees()?;
        let mut written = Vec::with_capacity(prepared.len());
        let mut sizes = Vec::with_capacity(prepared.len());
        for f in prepared {
            let value = encode_frame(&f.header(), &f.descriptor, s.meta.storage);
            let id = match f.frame_id {
                Some(id) => {
                    claimed.push(s.claim(Some(id)));
                    if !insert_new(&trees.frames, id, &value)? {
                        // All or nothing: take back what this call already wrote.
                        for &done in &written {
                            trees.frames.remove(frame_key(done))?;
                            trees.features.remove(frame_key(done))?;
                            trees.thumbs.remove(frame_key(done))?;
                        }
                        return Err(StoreError::FrameExists(s.meta.id.clone(), id));
                    }
                    s.next_id.fetch_max(id + 1, Relaxed);
                    id
                }
                None => loop {
                    let id = s.claim(None);
                    claimed.push(id);
                    if insert_new(&trees.frames, id, &value)? {
                        break id;
                    }
                },
            };
            if let Some(features) = &f.features {
                trees.features.insert(frame_key(id), features.as_slice())?;
            }
            if let Some(thumbnail) = &f.thumbnail {
                trees.thumbs.insert(frame_key(id), thumbnail.as_slice())?;
            }
            sizes.push((8 + value.len()) as u64);
            written.push(id);
        }
        Ok((written, sizes))
    }

    /// Ranked matches for a descriptor (normalised here), searched on a blocking thread of the
    /// bounded search pool so a large scan never stalls the async executor.
    pub async fn query(&self, s: &Arc<Session>, descriptor: Vec<f32>, q: &LoopQuery) -> Result<Vec<Match>, StoreError> {
        let permit = self.search_slots.clone().acquire_owned().await.map_err(|_| StoreError::Stopped)?;
        let (s, q, threads) = (s.clone(), q.clone(), self.search_threads);
        tokio::task::spawn_blocking(move || {
            let _permit = permit;
            s.search(descriptor, &q, threads)
        })
        .await
        .map_err(|e| StoreError::Storage(format!("search worker failed: {e}")))?
    }

    async fn durable(&self) -> Result<(), StoreError> {
        let flushed = self.disk()?.commit.durable_then(None);
        flushed.await.map_err(not_durable)
    }

    /// The open database, or Unavailable while a reopen replaces it (never waits for one).
    /// Where sessions' approximate indexes are saved (`indexer.rs`).
    fn graph_dir(&self) -> PathBuf {
        self.dir.join(indexer::GRAPH_DIR)
    }

    /// Where sessions' row files are made (unlinked at once: the folder looks empty).
    fn rows_dir(&self) -> PathBuf {
        self.dir.join(ROWS_DIR)
    }

    fn disk(&self) -> Result<MappedRwLockReadGuard<'_, Disk>, StoreError> {
        let guard = self.disk.try_read().ok_or_else(reopening)?;
        RwLockReadGuard::try_map(guard, Option::as_ref).map_err(|_| reopening())
    }

    /// Passes a write's result on, first marking the store failed on an I/O error: sled fails
    /// every write after one until a reopen.
    fn note<T>(&self, r: Result<T, impl Into<StoreError>>) -> Result<T, StoreError> {
        let r = r.map_err(Into::into);
        if let Err(StoreError::Storage(e)) = &r {
            self.health.fail(e);
        }
        r
    }

    /// Why writes are refused now, if they are (readiness reports it).
    pub fn failure(&self) -> Option<String> {
        self.health.failure()
    }

    /// Names of the session trees on disk (a deleted session's tree is gone).
    pub fn session_trees(&self) -> Vec<String> {
        let Ok(disk) = self.disk() else { return Vec::new() };
        disk.db
            .tree_names()
            .iter()
            .filter_map(|n| std::str::from_utf8(n).ok()?.strip_prefix("session/").map(str::to_string))
            .collect()
    }

    /// Everything flushed (used at shutdown).
    pub fn flush(&self) -> Result<(), StoreError> {
        self.disk()?.db.flush()?;
        Ok(())
    }
}
