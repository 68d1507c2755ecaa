//! Issue #33, restart: a session's rows and frame records kept across restarts (`store/kept.rs`).
//! A reopened store takes the rows its checkpoint covers from the kept files and reads only the
//! frames after it from sled; files that do not check out, and frames written out of order,
//! send it back to sled. On 600 of the Nordland images (raw pixels, 6,144-d f16).
use super::graph::nordland_rows;
use loopd::index::query::{LoopQuery, Scope};
use loopd::index::Storage;
use loopd::store::{NewFrame, NewSession, SearchConfig, Store};
use std::path::Path;
use std::time::{Duration, Instant};

const ID: &str = "nordland";

fn config(checkpoint_frames: usize) -> SearchConfig {
    SearchConfig { checkpoint_frames, ..Default::default() }
}

/// A session of Nordland raw-pixel rows (f16, the default index).
pub(super) fn nordland_session(dim: usize) -> NewSession {
    NewSession {
        name: ID.into(),
        dim,
        descriptor_id: "nordland-pixels".into(),
        storage: Storage::F16,
        default_query: Default::default(),
        camera: None,
        thumbnails: false,
        index: Default::default(),
        model: None,
    }
}

/// Nordland image `i` as a frame: summer and winter are two robots.
pub(super) fn frame(rows: &[Vec<f32>], i: usize) -> NewFrame {
    NewFrame {
        frame_id: Some(i as u64),
        robot_id: if i < 2400 { "summer".into() } else { "winter".into() },
        timestamp: i as f64,
        pose: None,
        metadata: None,
        descriptor: rows[i].clone(),
        features: None,
        thumbnail: None,
        idempotency_key: None,
    }
}

fn picks() -> Vec<usize> {
    (0..4800).step_by(8).collect()
}

/// Best 5 summer frames of every 5th winter frame of `picks`, and the session's frames and bytes.
fn answers(store: &Store, rows: &[Vec<f32>]) -> (Vec<Vec<(u64, u32)>>, usize, u64) {
    let s = store.session(ID).unwrap();
    let opts = LoopQuery { k: 5, robot_id: Some("winter".into()), scope: Scope::OtherRobots, ..Default::default() };
    let winter = picks().into_iter().filter(|&i| i >= 2400).step_by(5);
    let found = winter.map(|i| {
        s.search(rows[i].clone(), &opts, 1).unwrap().iter().map(|m| (m.frame_id, m.score.to_bits())).collect()
    });
    let info = s.info();
    (found.collect(), info.frames, info.bytes_on_disk)
}

/// Frames the session's checkpoint covers (0 without one).
fn checkpointed(dir: &Path) -> usize {
    let Ok(json) = std::fs::read(dir.join(format!("rows/{ID}.json"))) else { return 0 };
    let v: serde_json::Value = serde_json::from_slice(&json).unwrap();
    v["frames"].as_u64().unwrap() as usize
}

/// A store in `dir` holding `picks()` of the Nordland rows, checkpointed (the indexer writes the
/// checkpoint within a turn of being due).
async fn filled(dir: &Path, rows: &[Vec<f32>], dim: usize) {
    let store = Store::open_with(dir, config(1)).unwrap();
    store.create_session(Some(ID.into()), nordland_session(dim)).await.unwrap();
    let s = store.session(ID).unwrap();
    // The first ten one at a time under idempotency keys, the rest in batches.
    let picks = picks();
    let (keyed, rest) = picks.split_at(10);
    for &i in keyed {
        let f = NewFrame { idempotency_key: Some(format!("key-{i}")), ..frame(rows, i) };
        store.add_frames(&s, vec![f]).await.unwrap();
    }
    for batch in rest.chunks(100) {
        store.add_frames(&s, batch.iter().map(|&i| frame(rows, i)).collect()).await.unwrap();
    }
    let t = Instant::now();
    while checkpointed(dir) < picks.len() {
        assert!(t.elapsed() < Duration::from_secs(30), "no checkpoint of all frames after 30 s");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The Nordland rows, and a folder holding a checkpointed store of `picks()` of them.
async fn a_checkpointed_store() -> (Vec<Vec<f32>>, tempfile::TempDir) {
    let (rows, dim) = nordland_rows();
    let dir = tempfile::tempdir().unwrap();
    filled(dir.path(), &rows, dim).await;
    (rows, dir)
}

/// The store in `dir` opened again, and its session.
fn reopened(dir: &Path, checkpoint_frames: usize) -> (Store, std::sync::Arc<loopd::store::Session>) {
    let store = Store::open_with(dir, config(checkpoint_frames)).unwrap();
    let s = store.session(ID).unwrap();
    (store, s)
}

#[tokio::test(flavor = "multi_thread")]
async fn a_reopened_store_takes_its_kept_rows_and_reads_only_the_frames_after_the_checkpoint() {
    let (rows, dir) = a_checkpointed_store().await;
    let n = picks().len();

    // Restored from the kept files: the same answers, frames and bytes as a read from sled.
    let (store, s) = reopened(dir.path(), 1_000_000);
    assert_eq!(s.restored_frames(), n);
    let first = answers(&store, &rows);
    assert_eq!(first.1, n);
    // Idempotency keys come back with the records: a repeated write stores nothing.
    let repeat = NewFrame { frame_id: None, idempotency_key: Some("key-8".into()), ..frame(&rows, 8) };
    let again = store.add_frames(&s, vec![repeat]).await.unwrap();
    assert_eq!(again, vec![8]);
    // Frames after the checkpoint (none is written: it is due only every 10^6 frames).
    let tail: Vec<usize> = (4801..4840).step_by(3).map(|i| i % 4800).collect();
    let tail_frames = tail.iter().map(|&i| NewFrame { frame_id: None, ..frame(&rows, i) });
    let ids = store.add_frames(&s, tail_frames.collect()).await.unwrap();
    assert!(ids.iter().all(|&id| id > 4792), "server ids follow the highest: {ids:?}");
    let with_tail = answers(&store, &rows);
    drop((s, store));
    assert_eq!(checkpointed(dir.path()), n, "no checkpoint of the tail");

    let (store, s) = reopened(dir.path(), 1_000_000);
    assert_eq!(s.restored_frames(), n, "the checkpoint's frames from the files");
    assert_eq!(s.info().frames, n + tail.len(), "and the tail from sled");
    for &id in &ids {
        assert!(s.frame(id).is_ok(), "tail frame {id} is back");
    }
    let restored = answers(&store, &rows);
    drop((s, store));

    // Every frame read from sled (rows in memory) answers the same, bit for bit.
    let memory = Store::open_with(dir.path(), SearchConfig { rows_resident: None, ..Default::default() }).unwrap();
    assert_eq!(memory.session(ID).unwrap().restored_frames(), 0);
    let from_sled = answers(&memory, &rows);
    assert_eq!(restored, from_sled);
    assert_eq!(restored, with_tail);
    assert_eq!(first.0.len(), restored.0.len());
    // A run with rows in memory does not keep them: its frames would be missing from the files.
    assert!(!dir.path().join(format!("rows/{ID}.json")).exists());
    drop(memory);

    // Deleting the session removes its kept files.
    let store = Store::open_with(dir.path(), config(1)).unwrap();
    assert!(dir.path().join(format!("rows/{ID}.rows")).exists());
    store.delete_session(ID).await.unwrap();
    let left: Vec<_> = std::fs::read_dir(dir.path().join("rows")).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert!(left.is_empty(), "kept files left after the delete: {left:?}");
}

#[tokio::test(flavor = "multi_thread")]
async fn kept_rows_that_do_not_check_out_are_read_again_from_sled() {
    let (rows, dir) = a_checkpointed_store().await;
    let n = picks().len();
    let good = {
        let store = Store::open_with(dir.path(), config(1)).unwrap();
        assert_eq!(store.session(ID).unwrap().restored_frames(), n);
        answers(&store, &rows)
    };
    let flip = |file: &str, at: u64| {
        use std::os::unix::fs::FileExt;
        let f = std::fs::OpenOptions::new().read(true).write(true).open(dir.path().join("rows").join(file)).unwrap();
        let mut b = [0u8; 1];
        f.read_exact_at(&mut b, at).unwrap();
        f.write_all_at(&[b[0] ^ 0x5a], at).unwrap();
    };
    type Breaks<'a> = [(&'a str, Box<dyn Fn() + 'a>); 4];
    let cases: Breaks = [
        ("a flipped byte in the frame records", Box::new(|| flip(&format!("{ID}.frames"), 40))),
        // The first frame is one of the sampled ones.
        ("a flipped byte in the first row", Box::new(|| flip(&format!("{ID}.rows"), 6))),
        (
            "a rows file cut short",
            Box::new(|| {
                let f =
                    std::fs::OpenOptions::new().write(true).open(dir.path().join(format!("rows/{ID}.rows"))).unwrap();
                f.set_len((n as u64 - 1) * rows[0].len() as u64 * 2).unwrap();
            }),
        ),
        (
            "a checkpoint that is not JSON",
            Box::new(|| std::fs::write(dir.path().join(format!("rows/{ID}.json")), b"{").unwrap()),
        ),
    ];
    for (what, break_it) in cases {
        break_it();
        let store = Store::open_with(dir.path(), config(1)).unwrap();
        let s = store.session(ID).unwrap();
        assert_eq!(s.restored_frames(), 0, "{what}: not restored");
        assert_eq!(answers(&store, &rows), good, "{what}: read from sled instead");
        // The files are written again and checkpointed (every frame: due at once).
        let t = Instant::now();
        while checkpointed(dir.path()) < n {
            assert!(t.elapsed() < Duration::from_secs(30), "{what}: no new checkpoint");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        drop((s, store));
        let store = Store::open_with(dir.path(), config(1)).unwrap();
        assert_eq!(store.session(ID).unwrap().restored_frames(), n, "{what}: the new checkpoint is taken");
    }
}

/// A frame id below the session's highest, written after a checkpoint, lies before the
/// checkpoint's tail: the checkpoint goes before the frame is written, and the next start reads
/// sled in full. Without that the frame would be stored, acknowledged and missing after a restart.
#[tokio::test(flavor = "multi_thread")]
async fn a_frame_written_out_of_order_removes_the_checkpoint_until_the_next() {
    let (rows, dir) = a_checkpointed_store().await;
    let n = picks().len();
    let (store, s) = reopened(dir.path(), 1_000_000);
    assert_eq!(s.restored_frames(), n);
    store.add_frames(&s, vec![frame(&rows, 3)]).await.unwrap();
    drop((s, store));
    let (_store, s) = reopened(dir.path(), 1_000_000);
    assert_eq!(s.info().frames, n + 1, "every acknowledged frame is back after the restart");
    assert_eq!(s.frame(3).map(|f| f.0.timestamp).ok(), Some(3.0), "the out-of-order frame is back");
    assert_eq!(s.restored_frames(), 0, "read from sled in full: the checkpoint was removed");
}
