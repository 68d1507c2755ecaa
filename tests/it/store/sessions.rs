//! Map sessions on a real sled database, with descriptors of real Corridor frames.
use crate::common::*;
use loopd::index::query::{LoopQuery, Match, Pose, Scope};
use loopd::index::Storage;
use loopd::model::network::Variant;
use loopd::store::record::FrameHeader;
use loopd::store::{NewFrame, Store, StoreError};
use std::sync::OnceLock;

/// Corridor `query/` and `ref/` descriptors (ImageNet backbone, 224x224 input), embedded once.
type Traversals = (Vec<Vec<f32>>, Vec<Vec<f32>>);

fn corridor() -> &'static Traversals {
    static D: OnceLock<Traversals> = OnceLock::new();
    D.get_or_init(|| {
        let cfg = loopd::model::config::ModelConfig::default();
        let (model, _) =
            loopd::model::Model::load(&weights(), cfg, tch::Device::Cpu, loopd::model::device::DType::F32).unwrap();
        let embed = |dir: &str| -> Vec<Vec<f32>> {
            let inputs: Vec<tch::Tensor> = (0..111)
                .map(|i| {
                    let bytes = std::fs::read(data(&format!("corridor/{dir}/{i:07}.jpg"))).unwrap();
                    loopd::model::preprocess::prepare(&bytes, &Default::default(), &model.config.preprocess).unwrap()
                })
                .collect();
            inputs
                .chunks(37)
                .flat_map(|c| loopd::model::rows(&model.descriptors(c, Variant::BACKBONE).unwrap()).unwrap())
                .collect()
        };
        (embed("query"), embed("ref"))
    })
}

/// The store's calls by session name (the service looks a session up once and passes it on).
async fn add(store: &Store, session: &str, frames: Vec<NewFrame>) -> Result<Vec<u64>, StoreError> {
    store.add_frames(&store.session(session)?, frames).await
}

async fn search(store: &Store, session: &str, d: Vec<f32>, q: &LoopQuery) -> Result<Vec<Match>, StoreError> {
    store.query(&store.session(session)?, d, q).await
}

/// A query by a stored frame, as the service makes it: its descriptor, itself excluded.
async fn query_frame(store: &Store, session: &str, id: u64, q: &LoopQuery) -> Result<Vec<Match>, StoreError> {
    let s = store.session(session)?;
    let d = s.descriptor(id)?;
    store.query(&s, d, &LoopQuery { exclude_frame: Some(id), ..q.clone() }).await
}

fn stored_frame(store: &Store, session: &str, id: u64) -> Result<(FrameHeader, Vec<f32>), StoreError> {
    store.session(session)?.frame(id)
}

fn frame(id: Option<u64>, robot: &str, t: f64, d: &[f32]) -> NewFrame {
    NewFrame {
        frame_id: id,
        robot_id: robot.into(),
        timestamp: t,
        pose: Some(Pose { x: t, y: 0.0, z: 0.0, qx: 0.0, qy: 0.0, qz: 0.0, qw: 1.0 }),
        metadata: Some(serde_json::json!({ "camera": "fisheye" })),
        descriptor: d.to_vec(),
        features: None,
        thumbnail: None,
        idempotency_key: None,
    }
}

async fn two_robot_session(store: &Store, id: &str, storage: Storage) {
    let (query, reference) = corridor();
    store.create_session(Some(id.into()), session("corridor", storage)).await.unwrap();
    let refs: Vec<NewFrame> =
        reference.iter().enumerate().map(|(i, d)| frame(Some(i as u64), "ref", i as f64, d)).collect();
    add(store, id, refs).await.unwrap();
    let qs: Vec<NewFrame> =
        query.iter().enumerate().map(|(i, d)| frame(Some(1000 + i as u64), "query", 500.0 + i as f64, d)).collect();
    add(store, id, qs).await.unwrap();
}

#[tokio::test]
async fn everything_survives_a_reopen_with_the_same_scores() {
    let dir = tempfile::tempdir().unwrap();
    let q = LoopQuery { k: 5, robot_id: Some("query".into()), scope: Scope::OtherRobots, ..Default::default() };
    let mut before = Vec::new();
    {
        let store = Store::open(dir.path()).unwrap();
        two_robot_session(&store, "f16", Storage::F16).await;
        two_robot_session(&store, "f32", Storage::F32).await;
        for s in ["f16", "f32"] {
            for i in [0usize, 40, 110] {
                before.push(search(&store, s, corridor().0[i].clone(), &q).await.unwrap());
            }
        }
        assert_eq!(store.list().len(), 2);
    } // dropped: the database is closed
    let store = Store::open(dir.path()).unwrap();
    let mut after = Vec::new();
    for s in ["f16", "f32"] {
        for i in [0usize, 40, 110] {
            after.push(search(&store, s, corridor().0[i].clone(), &q).await.unwrap());
        }
    }
    assert_eq!(before, after, "matches and scores changed across a reopen");
    assert!(before.iter().all(|m| m.len() == 5 && m.iter().all(|x| x.robot_id == "ref")));
    let info = store.list();
    assert_eq!(info.iter().map(|i| i.frames).collect::<Vec<_>>(), vec![222, 222]);
    assert_eq!(info[0].robots, vec!["ref".to_string(), "query".to_string()]);
    assert!(info[0].bytes_on_disk < info[1].bytes_on_disk, "f16 must take less disk than f32");
    // Stored records come back whole.
    let (h, d) = stored_frame(&store, "f32", 1040).unwrap();
    assert_eq!((h.robot_id.as_str(), h.timestamp), ("query", 540.0));
    assert_eq!(h.metadata, Some(serde_json::json!({ "camera": "fisheye" })));
    let dot: f32 = d.iter().zip(&corridor().0[40]).map(|(a, b)| a * b).sum();
    assert!(dot > 0.99999);
    // The f16 session's scores are within f16 rounding of the f32 session's.
    for (a, b) in before[..3].iter().zip(&before[3..]) {
        for (x, y) in a.iter().zip(b) {
            assert!((x.score - y.score).abs() < 2e-3, "{} vs {}", x.score, y.score);
        }
    }
}

#[tokio::test]
async fn corridor_query_frames_find_their_reference_frames() {
    // Real ground truth: top-1 of most query frames is one of gt.csv's reference frames.
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    two_robot_session(&store, "c", Storage::F16).await;
    let gt = std::fs::read_to_string(data("corridor/gt.csv")).unwrap();
    let (mut hits, mut total) = (0, 0);
    for line in gt.lines().skip(1) {
        let (q, refs) = line.split_once(',').unwrap();
        let q: usize = q.trim().parse().unwrap();
        let refs: Vec<u64> = refs.split_whitespace().map(|r| r.parse().unwrap()).collect();
        let opts = LoopQuery { k: 1, robot_id: Some("query".into()), scope: Scope::OtherRobots, ..Default::default() };
        let m = query_frame(&store, "c", 1000 + q as u64, &opts).await.unwrap();
        total += 1;
        hits += refs.contains(&m[0].frame_id) as usize;
    }
    assert_eq!(total, 111);
    // Measured 62/111 (0.56) for the plain ImageNet backbone at 224x224.
    assert!(hits as f64 / total as f64 > 0.45, "recall@1 {hits}/{total}");
}

#[tokio::test]
async fn deletion_gives_back_disk_and_memory() {
    let dir = tempfile::tempdir().unwrap();
    {
        let store = Store::open(dir.path()).unwrap();
        two_robot_session(&store, "gone", Storage::F16).await;
        two_robot_session(&store, "kept", Storage::F16).await;
        assert_eq!(store.session_trees().len(), 2);
        store.delete_session("gone").await.unwrap();
        assert_eq!(store.delete_session("gone").await, Err(StoreError::SessionNotFound("gone".into())));
        assert!(matches!(
            search(&store, "gone", corridor().0[0].clone(), &LoopQuery::default()).await,
            Err(StoreError::SessionNotFound(_))
        ));
        assert_eq!(store.session_trees(), vec!["kept".to_string()]);
    }
    let store = Store::open(dir.path()).unwrap();
    assert_eq!(store.list().iter().map(|s| s.meta.id.clone()).collect::<Vec<_>>(), vec!["kept".to_string()]);
    assert_eq!(store.session_trees(), vec!["kept".to_string()]);
    assert_eq!(store.list()[0].frames, 222, "deleting one session touched another");
}

#[tokio::test]
async fn exclusion_window_skips_the_robots_own_recent_frames() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    let (query, _) = corridor();
    store.create_session(Some("w".into()), session("w", Storage::F16)).await.unwrap();
    // One robot driving the corridor: frame i at time 0.5 * i.
    let frames: Vec<NewFrame> = query.iter().enumerate().map(|(i, d)| frame(None, "r1", 0.5 * i as f64, d)).collect();
    let ids = add(&store, "w", frames).await.unwrap();
    assert_eq!(ids, (0..111).collect::<Vec<u64>>(), "auto ids are consecutive");
    let last = query[110].clone();
    // Without a window the newest frame matches itself and its neighbours.
    let plain =
        search(&store, "w", last.clone(), &LoopQuery { k: 3, robot_id: Some("r1".into()), ..Default::default() })
            .await
            .unwrap();
    assert_eq!(plain[0].frame_id, 110);
    let by_frames = LoopQuery { k: 20, robot_id: Some("r1".into()), exclude_last_frames: 10, ..Default::default() };
    let m = search(&store, "w", last.clone(), &by_frames).await.unwrap();
    assert_eq!(m.len(), 20);
    assert!(m.iter().all(|x| x.frame_id < 101), "{:?}", m.iter().map(|x| x.frame_id).collect::<Vec<_>>());
    let by_time = LoopQuery { k: 20, robot_id: Some("r1".into()), exclude_last_seconds: 10.0, ..Default::default() };
    let m = search(&store, "w", last.clone(), &by_time).await.unwrap();
    assert!(m.iter().all(|x| x.timestamp <= 55.0 - 10.0));
    // Another robot is not affected by r1's window.
    let other = LoopQuery { k: 3, robot_id: Some("r2".into()), exclude_last_frames: 10, ..Default::default() };
    assert_eq!(search(&store, "w", last.clone(), &other).await.unwrap()[0].frame_id, 110);
    // Ranges
    let ranged =
        LoopQuery { k: 50, frame_id_range: Some((10, 20)), time_range: Some((6.0, 100.0)), ..Default::default() };
    let m = search(&store, "w", last, &ranged).await.unwrap();
    assert_eq!(m.iter().map(|x| x.frame_id).min(), Some(12));
    assert_eq!(m.len(), 9);
}

#[tokio::test]
async fn scopes_with_three_robots() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    two_robot_session(&store, "s", Storage::F32).await;
    let (query, _) = corridor();
    let third: Vec<NewFrame> = query
        .iter()
        .take(20)
        .enumerate()
        .map(|(i, d)| frame(Some(5000 + i as u64), "third", 900.0 + i as f64, d))
        .collect();
    add(&store, "s", third).await.unwrap();
    let ask = |scope| LoopQuery { k: 50, robot_id: Some("query".into()), scope, ..Default::default() };
    let d = query[5].clone();
    let same = search(&store, "s", d.clone(), &ask(Scope::SameRobot)).await.unwrap();
    assert!(same.iter().all(|m| m.robot_id == "query") && same.len() == 50);
    let other = search(&store, "s", d.clone(), &ask(Scope::OtherRobots)).await.unwrap();
    assert!(other.iter().all(|m| m.robot_id != "query"));
    assert!(other.iter().any(|m| m.robot_id == "ref") && other.iter().any(|m| m.robot_id == "third"));
    assert_eq!(other[0].robot_id, "third", "the identical frame of the third robot ranks first");
    let all = search(&store, "s", d.clone(), &ask(Scope::All)).await.unwrap();
    assert!(all.windows(2).all(|w| w[0].score >= w[1].score), "ranked best first");
    let robots: std::collections::HashSet<_> = all.iter().map(|m| m.robot_id.as_str()).collect();
    assert_eq!(robots.len(), 3);
    let stranger = LoopQuery { k: 5, robot_id: Some("nobody".into()), scope: Scope::SameRobot, ..Default::default() };
    assert!(search(&store, "s", d.clone(), &stranger).await.unwrap().is_empty());
    let strict = LoopQuery { k: 50, min_score: 0.999, ..Default::default() };
    assert!(search(&store, "s", d, &strict).await.unwrap().iter().all(|m| m.score >= 0.999));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_writers_lose_nothing() {
    let dir = tempfile::tempdir().unwrap();
    {
        let store = std::sync::Arc::new(Store::open(dir.path()).unwrap());
        store.create_session(Some("c".into()), session("c", Storage::F16)).await.unwrap();
        let (query, reference) = corridor();
        let tasks: Vec<_> = (0..8)
            .map(|w| {
                let store = store.clone();
                tokio::spawn(async move {
                    let mut ids = Vec::new();
                    for i in 0..50 {
                        let d = if w % 2 == 0 { &query[(w * 13 + i) % 111] } else { &reference[(w * 7 + i) % 111] };
                        // one frame per call, as a robot sends them
                        ids.extend(
                            add(&store, "c", vec![frame(None, &format!("robot{w}"), i as f64, d)]).await.unwrap(),
                        );
                    }
                    ids
                })
            })
            .collect();
        let mut ids = Vec::new();
        for t in tasks {
            ids.extend(t.await.unwrap());
        }
        ids.sort();
        ids.dedup();
        assert_eq!(ids.len(), 400, "duplicate or lost frame ids");
        assert_eq!(store.list()[0].frames, 400);
        assert_eq!(store.list()[0].robots.len(), 8);
    }
    let store = Store::open(dir.path()).unwrap();
    assert_eq!(store.list()[0].frames, 400, "not all acknowledged frames were durable");
}

#[tokio::test]
async fn bad_writes_get_clear_errors_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    let (query, _) = corridor();
    store.create_session(Some("b".into()), session("b", Storage::F16)).await.unwrap();
    let again = store.create_session(Some("b".into()), session("b", Storage::F16)).await;
    assert_eq!(again, Err(StoreError::SessionExists("b".into())));
    let bad_id = store.create_session(Some("no spaces/".into()), session("x", Storage::F16)).await;
    assert!(matches!(bad_id, Err(StoreError::InvalidArgument(_))));
    add(&store, "b", vec![frame(Some(7), "r", 0.0, &query[0])]).await.unwrap();
    // A batch with a taken id is refused whole: its other frame is not stored either.
    let batch = vec![frame(Some(8), "r", 1.0, &query[1]), frame(Some(7), "r", 2.0, &query[2])];
    assert_eq!(add(&store, "b", batch).await, Err(StoreError::FrameExists("b".into(), 7)));
    assert!(matches!(stored_frame(&store, "b", 8), Err(StoreError::FrameNotFound(_, 8))));
    let short = add(&store, "b", vec![frame(None, "r", 0.0, &query[0][..100])]).await;
    assert!(matches!(&short, Err(StoreError::InvalidArgument(m)) if m.contains("100 values")), "{short:?}");
    let mut nan = query[3].clone();
    nan[5] = f32::NAN;
    assert!(matches!(add(&store, "b", vec![frame(None, "r", 0.0, &nan)]).await, Err(StoreError::InvalidArgument(_))));
    assert!(matches!(
        add(&store, "nope", vec![frame(None, "r", 0.0, &query[0])]).await,
        Err(StoreError::SessionNotFound(_))
    ));
    assert!(matches!(
        search(&store, "b", vec![0.0; 2048], &LoopQuery::default()).await,
        Err(StoreError::InvalidArgument(_))
    ));
    assert!(matches!(
        search(&store, "b", query[0].clone(), &LoopQuery { k: 5000, ..Default::default() }).await,
        Err(StoreError::InvalidArgument(_))
    ));
    assert!(matches!(query_frame(&store, "b", 99, &LoopQuery::default()).await, Err(StoreError::FrameNotFound(_, 99))));
    // The stored frame is untouched.
    assert_eq!(store.list()[0].frames, 1);
    let m = search(&store, "b", query[0].clone(), &LoopQuery::default()).await.unwrap();
    assert_eq!((m.len(), m[0].frame_id), (1, 7));
}

#[test]
fn batched_search_matches_single_searches() {
    use loopd::index::SessionIndex;
    let (query, reference) = corridor();
    for storage in [Storage::F16, Storage::F32] {
        let mut index = SessionIndex::new(2048, storage);
        for (i, d) in reference.iter().chain(query.iter()).enumerate() {
            index.push(i as u64, if i < 111 { "ref" } else { "query" }, i as f64, None, d);
        }
        let opts = LoopQuery { k: 7, robot_id: Some("query".into()), exclude_last_frames: 30, ..Default::default() };
        let batch = index.search_batch(&query[..20], &opts, 2);
        for (q, got) in query[..20].iter().zip(&batch) {
            let single = index.search(q, &opts, 2);
            assert_eq!(
                got.iter().map(|m| m.frame_id).collect::<Vec<_>>(),
                single.iter().map(|m| m.frame_id).collect::<Vec<_>>()
            );
            for (a, b) in got.iter().zip(&single) {
                assert!((a.score - b.score).abs() < 1e-4);
            }
        }
        // The same batch on the device path (libtorch on the CPU device here).
        index.search_on(tch::Device::Cpu, 0);
        let on_device = index.search_batch(&query[..20], &opts, 2);
        assert_eq!(index.device_searches(), 1);
        for (d, h) in on_device.iter().zip(&batch) {
            assert_eq!(d.len(), h.len());
            for (a, b) in d.iter().zip(h) {
                assert!((a.score - b.score).abs() < 1e-4);
                assert_eq!(a.frame_id, b.frame_id);
            }
        }
    }
}

/// The device path (scores and top-k in libtorch) on the CPU device: the same code that runs on
/// the model's GPU. Against the host kernels: same matches, same scores, filters respected, and
/// the device copy follows frames added after earlier searches.
#[tokio::test]
async fn device_search_matches_host_search() {
    use loopd::store::SearchConfig;
    let (query, _) = corridor();
    for storage in [Storage::F32, Storage::F16] {
        let (host_dir, dev_dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        let host = Store::open(host_dir.path()).unwrap();
        let dev = Store::open_with(
            dev_dir.path(),
            SearchConfig { device: Some(tch::Device::Cpu), device_min_rows: 0, ..Default::default() },
        )
        .unwrap();
        let queries = [
            LoopQuery { k: 5, ..Default::default() },
            LoopQuery { k: 5, robot_id: Some("query".into()), exclude_last_frames: 30, ..Default::default() },
            LoopQuery {
                k: 3,
                robot_id: Some("query".into()),
                scope: Scope::SameRobot,
                exclude_last_seconds: 20.0,
                ..Default::default()
            },
            LoopQuery {
                k: 10,
                robot_id: Some("query".into()),
                scope: Scope::OtherRobots,
                min_score: 0.7,
                ..Default::default()
            },
        ];
        let compare = |round: &str| {
            for (qi, q) in queries.iter().enumerate() {
                for d in [&query[3], &query[60], &query[110]] {
                    let a = host.session("c").unwrap().search(d.clone(), q, 2).unwrap();
                    let b = dev.session("c").unwrap().search(d.clone(), q, 2).unwrap();
                    let ids = |m: &[loopd::index::query::Match]| m.iter().map(|m| m.frame_id).collect::<Vec<_>>();
                    // The device only proposes candidates; the host scores them again with the
                    // f32 query, so ranks and scores are the host's, for f16 sessions too.
                    assert_eq!(ids(&a), ids(&b), "{storage:?} {round} query {qi}");
                    for (x, y) in a.iter().zip(&b) {
                        assert!(
                            (x.score - y.score).abs() < 1e-5,
                            "{storage:?} {round} query {qi}: {} vs {}",
                            x.score,
                            y.score
                        );
                        assert_eq!((x.robot_id.as_str(), x.timestamp), (y.robot_id.as_str(), y.timestamp));
                    }
                }
            }
        };
        for s in [&host, &dev] {
            two_robot_session(s, "c", storage).await;
        }
        compare("after the first frames");
        // More frames after the device copy exists: the copy must grow with them.
        for s in [&host, &dev] {
            // Mid-points of neighbouring frames: new descriptors, no exact ties with stored ones.
            let extra: Vec<NewFrame> = query[..41]
                .windows(2)
                .enumerate()
                .map(|(i, w)| {
                    let mid: Vec<f32> = w[0].iter().zip(&w[1]).map(|(a, b)| a + b).collect();
                    frame(Some(5000 + i as u64), "third", 900.0 + i as f64, &mid)
                })
                .collect();
            add(s, "c", extra).await.unwrap();
        }
        compare("after more frames");
        assert_eq!(dev.list()[0].frames, 262);
        // Every query above was answered on the device (none fell back to the host kernels).
        assert_eq!(dev.session("c").unwrap().device_searches(), 2 * 4 * 3);
        assert_eq!(host.session("c").unwrap().device_searches(), 0);
    }
}

/// A write whose caller goes away mid-flush (client disconnect, gRPC deadline) is either wholly
/// there, searchable, counted and visible, or absent: never on disk but unknown to the index.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dropped_write_is_never_a_ghost() {
    let dir = tempfile::tempdir().unwrap();
    let (query, _) = corridor();
    {
        let store = Store::open(dir.path()).unwrap();
        store.create_session(Some("g".into()), session("g", Storage::F16)).await.unwrap();
        let s = store.session("g").unwrap();
        for i in 0..5u64 {
            // Polled once (the frame is written, its flush awaited), then dropped.
            let write = store.add_frames(&s, vec![frame(Some(40 + i), "r", i as f64, &query[i as usize])]);
            let _ = futures::FutureExt::now_or_never(write);
        }
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        while s.info().frames < 5 && std::time::Instant::now() < deadline {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
        assert_eq!(s.info().frames, 5, "frames written by dropped requests never became searchable");
        for i in 0..5u64 {
            let m = query_frame(&store, "g", 40 + i, &LoopQuery { k: 4, ..Default::default() }).await.unwrap();
            assert_eq!(m.len(), 4);
            assert!(stored_frame(&store, "g", 40 + i).is_ok());
            let own = search(&store, "g", query[i as usize].clone(), &LoopQuery::default()).await.unwrap();
            assert_eq!(own[0].frame_id, 40 + i);
        }
        // A client retrying the dropped write learns that it is stored, rather than storing it twice.
        let retry = add(&store, "g", vec![frame(Some(42), "r", 2.0, &query[2])]).await;
        assert_eq!(retry, Err(StoreError::FrameExists("g".into(), 42)));
        let next = add(&store, "g", vec![frame(None, "r", 9.0, &query[9])]).await.unwrap();
        assert_eq!(next, vec![45]);
    }
    let store = Store::open(dir.path()).unwrap();
    assert_eq!(store.list()[0].frames, 6, "what was searchable before the restart is what comes back");
}

/// Equal scores rank the earlier frame first, whichever search thread saw it first
/// (docs/storage.md: "ties: the earlier frame").
#[test]
fn equal_scores_rank_the_earlier_frame_first_with_any_number_of_threads() {
    use loopd::index::SessionIndex;
    let (query, _) = corridor();
    // 6,000 identical rows: enough values for the search to split across threads.
    let mut index = SessionIndex::new(2048, Storage::F16);
    for i in 0..6000u64 {
        index.push(i, "r", i as f64, None, &query[0]);
    }
    for threads in [1, 2, 4] {
        for round in 0..10 {
            let m = index.search(&query[0], &LoopQuery { k: 5, ..Default::default() }, threads);
            let ids: Vec<u64> = m.iter().map(|m| m.frame_id).collect();
            assert_eq!(ids, vec![0, 1, 2, 3, 4], "{threads} threads, round {round}");
        }
    }
}

/// A query by a stored frame takes every k the limit allows and never returns that frame.
#[tokio::test]
async fn a_stored_frame_query_takes_the_full_k_and_excludes_itself() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    two_robot_session(&store, "k", Storage::F16).await;
    let max = LoopQuery { k: loopd::index::query::MAX_K, ..Default::default() };
    let m = query_frame(&store, "k", 1005, &max).await.unwrap();
    assert_eq!(m.len(), 221, "every other frame of the session");
    assert!(m.iter().all(|m| m.frame_id != 1005));
    let over = LoopQuery { k: loopd::index::query::MAX_K + 1, ..Default::default() };
    assert!(
        matches!(query_frame(&store, "k", 1005, &over).await, Err(StoreError::InvalidArgument(m)) if m.contains("k = 1001"))
    );
    let top = query_frame(&store, "k", 1005, &LoopQuery { k: 1, ..Default::default() }).await.unwrap();
    assert_eq!(top.len(), 1);
    assert_ne!(top[0].frame_id, 1005);
}

/// A filter that leaves few rows is answered by scanning those rows exactly, on every core: the
/// same top-k, scores and order as the exact search, for every filter option (#33). The graph
/// is forced on and asked to hand every query to the subset scan.
#[test]
fn selective_filters_on_the_approximate_index_scan_the_allowed_rows_exactly() {
    use loopd::index::graph::{GraphParams, IndexKind};
    use loopd::index::SessionIndex;
    let (query, reference) = corridor();
    let build = |kind: IndexKind| {
        let mut index = SessionIndex::new(2048, Storage::F16);
        for (i, d) in reference.iter().chain(query.iter()).enumerate() {
            // The two robots take turns every 25 rows: a filter by robot leaves runs with gaps.
            let robot = if (i / 25) % 2 == 0 { "ref" } else { "query" };
            index.push(i as u64, robot, i as f64, None, d);
        }
        let forced = GraphParams { min_frames: 0, exact_below: usize::MAX, ..Default::default() };
        index.set_index(kind, forced);
        index.index_all().expect("graph");
        index
    };
    let (exact, approx) = (build(IndexKind::Exact), build(IndexKind::Approximate));
    assert_eq!(approx.graph_rows(), Some(222));
    let base = LoopQuery { k: 15, robot_id: Some("query".into()), ..Default::default() };
    let options = [
        LoopQuery { scope: Scope::SameRobot, exclude_last_frames: 30, ..base.clone() },
        LoopQuery { scope: Scope::OtherRobots, ..base.clone() },
        LoopQuery { exclude_last_seconds: 40.0, at_time: Some(200.0), ..base.clone() },
        LoopQuery { time_range: Some((20.5, 130.0)), ..base.clone() },
        LoopQuery { frame_id_range: Some((7, 160)), exclude_frame: Some(9), ..base.clone() },
        LoopQuery { min_score: 0.7, ..base.clone() },
    ];
    assert_same_answers(&exact, &approx, query, &options, "");
}

/// Every 10th query frame under every option, on one and two threads: `approx` gives the exact
/// index's matches in its order with its scores, and finds something unless a minimum score is set.
fn assert_same_answers(
    exact: &loopd::index::SessionIndex,
    approx: &loopd::index::SessionIndex,
    query: &[Vec<f32>],
    options: &[LoopQuery],
    what: &str,
) {
    for (o, opts) in options.iter().enumerate() {
        for (qi, q) in query.iter().enumerate().step_by(10) {
            for threads in [1, 2] {
                let want = exact.search(q, opts, threads);
                let got = approx.search(q, opts, threads);
                let ids = |m: &[Match]| m.iter().map(|m| m.frame_id).collect::<Vec<_>>();
                assert_eq!(ids(&got), ids(&want), "{what}option {o}, query {qi}, {threads} threads");
                assert!(!got.is_empty() || opts.min_score > 0.0, "{what}option {o}, query {qi}: nothing found");
                for (a, b) in got.iter().zip(&want) {
                    assert!(
                        (a.score - b.score).abs() < 1e-5,
                        "{what}option {o}, query {qi}: {} vs {}",
                        a.score,
                        b.score
                    );
                }
            }
        }
    }
}

/// A graph sealed into parts (mapped files of 50 rows, the live part the last 22) answers every
/// filter option as the exact search does: through every part on one or two threads, and with
/// the parts a filter leaves few rows of scanned exactly instead (#33).
#[test]
fn sealed_graph_parts_answer_every_filter_as_the_exact_search() {
    use loopd::index::graph::{parts_dir, GraphParams, IndexKind};
    use loopd::index::SessionIndex;
    let (query, reference) = corridor();
    let dir = tempfile::tempdir().unwrap();
    let build = |kind: IndexKind, params: GraphParams| {
        let mut index = SessionIndex::new(2048, Storage::F16);
        for (i, d) in reference.iter().chain(query.iter()).enumerate() {
            let robot = if (i / 25) % 2 == 0 { "ref" } else { "query" };
            index.push(i as u64, robot, i as f64, None, d);
        }
        index.set_index(kind, params);
        if let Some(graph) = index.graph() {
            let parts = parts_dir(&dir.path().join(format!("{}.usearch", params.exact_share)));
            // As the store's indexer adds: at most a part's rows at a time, sealed when full.
            while let Some(p) = index.pending(params.seal_rows - graph.live_rows()) {
                p.graph.add_rows(p.start, &p.reduced).unwrap();
                graph.seal_if_due(&parts).unwrap();
            }
        }
        index
    };
    let exact = build(IndexKind::Exact, GraphParams::default());
    let base = GraphParams { min_frames: 0, seal_rows: 50, exact_below: 0, exact_share: 0.0, ..Default::default() };
    // Every part through the graph; then parts a filter leaves under 30% of scanned exactly.
    for params in [base, GraphParams { exact_share: 0.3, ..base }] {
        let approx = build(IndexKind::Approximate, params);
        let graph = approx.graph().unwrap();
        assert_eq!(graph.parts(), [0..50, 50..100, 100..150, 150..200, 200..222]);
        let q = LoopQuery { k: 5, robot_id: Some("query".into()), ..Default::default() };
        let options = [
            q.clone(),
            LoopQuery { scope: Scope::SameRobot, exclude_last_frames: 30, ..q.clone() },
            LoopQuery { scope: Scope::OtherRobots, ..q.clone() },
            LoopQuery { exclude_last_seconds: 40.0, at_time: Some(200.0), ..q.clone() },
            LoopQuery { time_range: Some((20.5, 70.0)), ..q.clone() },
            LoopQuery { frame_id_range: Some((7, 160)), exclude_frame: Some(9), ..q.clone() },
            LoopQuery { min_score: 0.7, ..q.clone() },
        ];
        assert_same_answers(&exact, &approx, query, &options, &format!("share {}, ", params.exact_share));
    }
}
