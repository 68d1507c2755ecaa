//! The indexer: one background thread per store that adds each session's new rows to its
//! approximate index (`index::graph`), in row order, outside the session's lock, so writers and
//! searches never wait for the graph. Searches scan exactly the rows it has not reached yet.
//! It also saves each graph to `<data-dir>/graphs/<session>.usearch` as it grows, so a restart
//! loads it (checked against its record and the session's rows) and adds only the rows after it;
//! a missing, stale or corrupt file is removed and the graph rebuilt from the rows.
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
    let due = covered >= file.saved_rows + params.save_rows.max(1)
        || (covered > file.saved_rows && file.saved_at.elapsed() >= SAVE_INTERVAL);
    // A deleted session (its trees gone) is not saved again.
    if !due || s.trees.read().is_none() {
        return;
    }
    let t = Instant::now();
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

/// Rows taken from one session per turn, so that one large build does not starve the others.
const ROWS_PER_TURN: usize = 8192;

/// Pause when no session has rows waiting.
const IDLE: Duration = Duration::from_millis(20);

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
            super::kept::checkpoint_if_due(&s);
            let pending = s.index.read().pending(ROWS_PER_TURN);
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
