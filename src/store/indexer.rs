//! The indexer: one background thread per store that adds each session's new rows to its
//! approximate index (`index::graph`), in row order, outside the session's lock, so writers and
//! searches never wait for the graph. Searches scan exactly the rows it has not reached yet.
//! It also saves each graph to `<data-dir>/graphs/<session>.usearch` as it grows, so a restart
//! loads it (checked against its record and the session's rows) and adds only the rows after it;
//! a missing, stale or corrupt file is removed and the graph rebuilt from the rows. Once a graph's
//! live part holds `seal_rows` rows the indexer seals it into `<session>.parts/` (a file mapped,
//! not held: `Graph::seal_if_due`), and it hashes each part mapped at start, one per turn, in the
//! background: a part that fails is removed with the rest of the graph, which is rebuilt.
use super::Session;
use crate::index::graph::Graph;
use crate::index::SessionIndex;
use parking_lot::RwLock;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};

/// Folder of the data directory the graphs are saved in.
pub(super) const GRAPH_DIR: &str = "graphs";

/// A graph saved at least this often while it grows (besides every `save_rows` rows).
const SAVE_INTERVAL: Duration = Duration::from_secs(60);

/// Where a session's graph is saved and how much of it was.
pub(super) struct GraphFile {
    path: PathBuf,
    saved_rows: usize,
    saved_at: Instant,
}

/// The session's saved graph, adopted by `index` if it checks out; a file that does not is
/// removed (and logged), and the graph is rebuilt from the rows.
pub(super) fn open_saved(index: &mut SessionIndex, graphs: &Path, session: &str) -> GraphFile {
    let path = graphs.join(format!("{session}.usearch"));
    let mut file = GraphFile { path, saved_rows: 0, saved_at: Instant::now() };
    let exists = file.path.exists();
    if index.graph().is_none() || !exists {
        if exists {
            remove_files(&file.path);
        }
        return file;
    }
    let t = Instant::now();
    let loaded =
        Graph::load(&file.path, index.dim(), index.graph_params(), index.len()).and_then(|g| index.adopt_graph(g));
    match loaded {
        Ok(rows) => {
            file.saved_rows = rows;
            tracing::info!(
                session,
                rows,
                frames = index.len(),
                elapsed_ms = t.elapsed().as_millis() as u64,
                "approximate index loaded; the frames after it are added in the background"
            );
        }
        Err(why) => {
            tracing::warn!(session, file = %file.path.display(), %why, "approximate index file rejected; rebuilding it from the session's frames");
            remove_files(&file.path);
        }
    }
    file
}

fn remove_files(path: &Path) {
    for p in [path.to_path_buf(), path.with_extension("json")] {
        let _ = std::fs::remove_file(p);
    }
    let _ = std::fs::remove_dir_all(crate::index::graph::parts_dir(path));
}

/// Removes a deleted session's saved graph.
pub(super) fn remove_saved(session: &Session) {
    remove_files(&session.graph_file.lock().path);
}

/// Saves the session's graph if it has grown enough since it was last saved.
fn save_if_due(s: &Session) {
    let Some(graph) = s.index.read().graph() else { return };
    let mut file = s.graph_file.lock();
    let covered = graph.covered();
    let params = s.index.read().graph_params();
    let seal = params.seal_rows > 0 && graph.live_rows() >= params.seal_rows;
    let due = seal
        || covered >= file.saved_rows + params.save_rows.max(1)
        || (covered > file.saved_rows && file.saved_at.elapsed() >= SAVE_INTERVAL);
    // A deleted session (its trees gone) is not saved again.
    if !due || s.trees.read().is_none() {
        return;
    }
    let t = Instant::now();
    if seal {
        seal_now(s, &graph, &file.path);
    }
    match graph.save(&file.path, s.meta.dim) {
        Ok(rows) => {
            tracing::info!(session = %s.meta.id, rows, elapsed_ms = t.elapsed().as_millis() as u64, "approximate index saved");
            file.saved_rows = rows;
        }
        Err(e) => {
            tracing::warn!(session = %s.meta.id, error = %e, "approximate index not saved (a restart rebuilds it)")
        }
    }
    file.saved_at = Instant::now();
}

/// Seals the graph's live part into a mapped file (before a save, so the record written next names
/// the part). The indexer adds at most `seal_rows` rows to a live part: each part holds that many.
fn seal_now(s: &Session, graph: &Graph, path: &Path) {
    let t = Instant::now();
    match graph.seal_if_due(&crate::index::graph::parts_dir(path)) {
        Ok(Some(rows)) => tracing::info!(
            session = %s.meta.id,
            from = rows.start,
            to = rows.end,
            elapsed_ms = t.elapsed().as_millis() as u64,
            "approximate index: rows sealed into a mapped file"
        ),
        Ok(None) => {}
        Err(e) => {
            tracing::warn!(session = %s.meta.id, error = %e, "approximate index: sealing failed (the rows stay in memory)")
        }
    }
}

/// Hashes one sealed part mapped at start; a part that fails its record is removed with the
/// whole graph, which is rebuilt from the rows.
fn verify_one(s: &Session) {
    let Some(graph) = s.index.read().graph() else { return };
    // A deleted session's files are gone; nothing to check.
    if s.trees.read().is_none() {
        return;
    }
    match graph.verify_next() {
        Ok(_) => {}
        Err(why) => {
            let mut file = s.graph_file.lock();
            tracing::warn!(session = %s.meta.id, %why, "approximate index file rejected; rebuilding it from the session's frames");
            remove_files(&file.path);
            file.saved_rows = 0;
            s.index.write().rebuild_graph();
        }
    }
}

/// Maps one sealed part of the session's graph in ahead of its searches, when the parts fit
/// their bound (`Graph::populate_next`); outside the session's lock: it reads up to a part.
fn populate_one(s: &Session) {
    let graph = s.index.read().graph();
    if let Some(graph) = graph {
        graph.populate_next();
    }
}

/// Rows taken from one session per turn, so that one large build does not starve the others.
const ROWS_PER_TURN: usize = 8192;

/// Pause when no session has rows waiting.
const IDLE: Duration = Duration::from_millis(20);

/// Rows to add to a session's graph this turn: up to the end of its live part (sealed earlier in
/// the turn when full; one that could not be sealed grows on, and is sealed larger later).
/// It takes the index the caller has locked: taking the session's lock again inside one held
/// for reading would wait forever behind a writer queued between the two (parking_lot's locks
/// are fair), and that writer (a frame's publish on the flusher) with it, and every write after.
fn rows_this_turn(index: &SessionIndex) -> usize {
    let Some(graph) = index.graph() else { return ROWS_PER_TURN };
    match graph.params().seal_rows.saturating_sub(graph.live_rows()) {
        0 => ROWS_PER_TURN,
        room => ROWS_PER_TURN.min(room),
    }
}

type Sessions = RwLock<HashMap<String, Arc<Session>>>;

/// Starts the indexer; it ends when the store (the owner of `sessions`) is dropped.
pub(super) fn spawn(sessions: Weak<Sessions>) {
    let run = move || loop {
        let Some(map) = sessions.upgrade() else { return };
        let list: Vec<Arc<Session>> = map.read().values().cloned().collect();
        drop(map);
        let mut added = false;
        for s in list {
            save_if_due(&s);
            verify_one(&s);
            populate_one(&s);
            super::kept::checkpoint_if_due(&s);
            let pending = {
                let index = s.index.read();
                index.pending(rows_this_turn(&index))
            };
            if let Some(p) = pending {
                added = true;
                let rows = p.reduced.len() / p.graph.dims().max(1);
                if let Err(e) = p.graph.add_rows(p.start, &p.reduced) {
                    tracing::error!(session = %s.meta.id, error = %e, "approximate index: adding rows failed");
                    std::thread::sleep(IDLE * 50);
                } else if p.start == 0 || (p.start + rows) % (ROWS_PER_TURN * 16) < rows {
                    tracing::info!(session = %s.meta.id, rows = p.start + rows, "approximate index: rows added");
                }
            }
        }
        if !added {
            std::thread::sleep(IDLE);
        }
    };
    if let Err(e) = std::thread::Builder::new().name("loopd-indexer".into()).spawn(run) {
        tracing::error!(error = %e, "the approximate indexer could not start; sessions search exactly");
    }
}
