//! The approximate index through the real server (both sessions of a pair on one server on
//! loopback): a session created `approximate`, with every query sent through its graph
//! (`--approx-exact-below 0`), answers as an `exact` session holding the same frames, on every
//! real set of ../shared/data (desk, EuRoC, Corridor, a Nordland validation stretch), and every
//! query option keeps its meaning. Descriptors come from the server's own model (`/v1/embed`).
use crate::common::*;
use loopd::api::server::ServerConfig;
use loopd::index::graph::GraphParams;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use loopd::store::SearchConfig;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use tonic::transport::Channel;

/// A real set: its frames in order, each with the robot that took it.
struct Set {
    name: &'static str,
    frames: Vec<(String, PathBuf)>,
}

fn sorted_images(dir: &str, prefix: &str) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(data(dir))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            let name = p.file_name().unwrap().to_string_lossy();
            loopd::files::is_image(&name) && name.starts_with(prefix)
        })
        .collect();
    files.sort_by_cached_key(|p| loopd::files::natural_key(&p.file_name().unwrap().to_string_lossy()));
    files
}

fn sets() -> Vec<Set> {
    let robot = |r: &str, files: Vec<PathBuf>| files.into_iter().map(|p| (r.to_string(), p)).collect::<Vec<_>>();
    let nordland =
        |season: &str| robot(season, sorted_images(&format!("nordland-64x32/{season}"), "")[2000..2100].to_vec());
    vec![
        Set { name: "desk", frames: robot("desk", sorted_images("slambook2-ch11", "")) },
        Set { name: "euroc", frames: robot("euroc", sorted_images("euroc-lcd", "left_img_")) },
        Set {
            name: "corridor",
            frames: [
                robot("ref", sorted_images("corridor/ref", "")),
                robot("query", sorted_images("corridor/query", "")),
            ]
            .concat(),
        },
        // Places 2000..2100 of the validation range the heads were selected on (docs/training.md).
        Set { name: "nordland", frames: [nordland("summer"), nordland("winter")].concat() },
    ]
}

/// The server's descriptor of each image (the model it serves; nothing stored), in the files'
/// order. Eight requests in flight, so that the engine batches them as it batches a fleet's
/// frames: one at a time, each forward pass was a batch of one.
async fn embed(http: &str, files: &[PathBuf]) -> Vec<Vec<f32>> {
    use futures::StreamExt;
    let client = reqwest::Client::new();
    let url = format!("{http}/v1/embed");
    futures::stream::iter(files)
        .map(|f| {
            let request = client.post(&url).body(std::fs::read(f).unwrap());
            async move {
                let r = request.send().await.unwrap();
                assert_eq!(r.status(), 200, "{}", f.display());
                let v: serde_json::Value = r.json().await.unwrap();
                v["descriptor"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect::<Vec<f32>>()
            }
        })
        .buffered(8)
        .collect()
        .await
}

async fn create(c: &mut LoopdClient<Channel>, id: &str, index: pb::IndexKind) {
    let req = pb::CreateSessionRequest { id: id.into(), name: id.into(), index: index as i32, ..Default::default() };
    c.create_session(req).await.unwrap();
}

/// Adds the frames (robot, descriptor) in order, frame i at time i; returns their ids.
async fn add(c: &mut LoopdClient<Channel>, id: &str, frames: &[(String, Vec<f32>)]) -> Vec<u64> {
    let mut ids = Vec::new();
    for (i, (robot, d)) in frames.iter().enumerate() {
        let req = pb::AddFrameRequest {
            session_id: id.into(),
            robot_id: robot.clone(),
            timestamp: Some(i as f64),
            content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
                values: d.clone(),
                ..Default::default()
            })),
            ..Default::default()
        };
        ids.push(c.add_frame(req).await.unwrap().into_inner().frame_id);
    }
    ids
}

/// Waits until the session's approximate index covers all its frames (the indexer runs in the
/// background); fails if the session reports none.
async fn indexed(c: &mut LoopdClient<Channel>, id: &str) {
    let t = Instant::now();
    loop {
        let s = c.get_session(pb::GetSessionRequest { id: id.into() }).await.unwrap().into_inner();
        assert_eq!(s.index, pb::IndexKind::Approximate as i32);
        let covered = s.approximate_frames.expect("an approximate session reports the frames its index covers");
        if covered == s.frames {
            return;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "{id}: {covered} of {} frames indexed after 60 s", s.frames);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

async fn query(
    c: &mut LoopdClient<Channel>,
    id: &str,
    robot: &str,
    content: pb::query_request::Content,
    o: &pb::QueryOptions,
    at: Option<f64>,
) -> Vec<pb::Match> {
    let req = pb::QueryRequest {
        session_id: id.into(),
        robot_id: robot.into(),
        content: Some(content),
        options: Some(pb::QueryOptions { verify: Some(false), ..*o }),
        timestamp: at,
        depth: Default::default(),
        right: Default::default(),
    };
    c.query(req).await.unwrap().into_inner().matches
}

fn ids(m: &[pb::Match]) -> Vec<u64> {
    m.iter().map(|m| m.frame_id).collect()
}

/// `auto` sessions of this file's server switch to the approximate index at this size.
const AUTO_FRAMES: usize = 150;

/// One server for this file's tests: the shipped model, every approximate query through the graph.
async fn server() -> (String, String) {
    static S: std::sync::OnceLock<(String, String)> = std::sync::OnceLock::new();
    S.get_or_init(|| {
        let config = |dir| ServerConfig {
            search: SearchConfig {
                graph: GraphParams { exact_below: 0, exact_share: 0.0, min_frames: AUTO_FRAMES, ..Default::default() },
                ..Default::default()
            },
            ..ServerConfig::on_loopback(dir)
        };
        background_server(config, shipped_model)
    })
    .clone()
}

/// A set and its frames: (robot, the server's descriptor).
type Embedded = (Set, Vec<(String, Vec<f32>)>);

/// Every real set, as an exact and an approximate session holding the same frames.
async fn pairs() -> &'static Vec<Embedded> {
    static P: tokio::sync::OnceCell<Vec<Embedded>> = tokio::sync::OnceCell::const_new();
    P.get_or_init(|| async {
        let (grpc, http) = server().await;
        let mut c = LoopdClient::connect(grpc).await.unwrap();
        let mut out = Vec::new();
        for set in sets() {
            let files: Vec<PathBuf> = set.frames.iter().map(|(_, p)| p.clone()).collect();
            let descriptors = embed(&http, &files).await;
            let frames: Vec<(String, Vec<f32>)> = set.frames.iter().map(|(r, _)| r.clone()).zip(descriptors).collect();
            create(&mut c, &format!("{}-exact", set.name), pb::IndexKind::Exact).await;
            create(&mut c, &format!("{}-approx", set.name), pb::IndexKind::Approximate).await;
            let a = add(&mut c, &format!("{}-exact", set.name), &frames).await;
            let b = add(&mut c, &format!("{}-approx", set.name), &frames).await;
            assert_eq!(a, b, "both sessions number the frames alike");
            assert_eq!(a, (0..frames.len() as u64).collect::<Vec<_>>(), "frame i has id i");
            indexed(&mut c, &format!("{}-approx", set.name)).await;
            out.push((set, frames));
        }
        out
    })
    .await
}

/// Each stored frame's best match (and its top 5) is the same in both sessions of every set.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn approximate_and_exact_sessions_find_the_same_best_loops_on_every_real_set() {
    let (grpc, _) = server().await;
    let mut c = LoopdClient::connect(grpc).await.unwrap();
    for (set, frames) in pairs().await {
        let o = pb::QueryOptions { k: Some(5), ..Default::default() };
        let (mut same_best, mut found, mut want) = (0, 0, 0);
        for (i, (robot, _)) in frames.iter().enumerate() {
            let content = || pb::query_request::Content::FrameId(i as u64);
            let exact = query(&mut c, &format!("{}-exact", set.name), robot, content(), &o, None).await;
            let approx = query(&mut c, &format!("{}-approx", set.name), robot, content(), &o, None).await;
            assert!(!exact.is_empty());
            same_best += (exact[0].frame_id == approx[0].frame_id) as usize;
            // Exact scores: what the approximate session answers is re-scored on the stored rows.
            for m in &approx {
                let e = exact.iter().find(|e| e.frame_id == m.frame_id);
                assert!(e.is_none_or(|e| (e.score - m.score).abs() < 1e-6), "{}: {m:?} vs {e:?}", set.name);
            }
            found += ids(&exact).iter().filter(|id| ids(&approx).contains(id)).count();
            want += exact.len();
        }
        assert_eq!(same_best, frames.len(), "{}: the same best match for every frame", set.name);
        let recall = found as f64 / want as f64;
        assert!(recall >= 0.99, "{}: recall@5 against exact {recall}", set.name);
    }
}

/// Every query option, against the Corridor's two robots (ref: frames 0..111 at times 0..111,
/// query: frames 111..222 at times 111..222) in a session whose every query goes through the
/// graph: the same answer as the exact session, each match allowed by the option.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_query_option_is_honoured_by_the_approximate_index() {
    let (grpc, _) = server().await;
    let mut c = LoopdClient::connect(grpc).await.unwrap();
    let (_, frames) = pairs().await.iter().find(|(s, _)| s.name == "corridor").unwrap();
    assert_eq!(frames.len(), 222);
    type Allowed = Box<dyn Fn(&pb::Match) -> bool>;
    // k = 5: the graph's 104 candidates are fewer than the session's 222 frames.
    let all = || pb::QueryOptions { k: Some(5), ..Default::default() };
    let cases: Vec<(&str, &str, pb::QueryOptions, Option<f64>, Allowed)> = vec![
        (
            "same robot",
            "ref",
            pb::QueryOptions { scope: pb::Scope::SameRobot as i32, ..all() },
            None,
            Box::new(|m| m.robot_id == "ref"),
        ),
        (
            "other robots",
            "ref",
            pb::QueryOptions { scope: pb::Scope::OtherRobots as i32, ..all() },
            None,
            Box::new(|m| m.robot_id != "ref"),
        ),
        (
            "exclude last frames",
            "query",
            pb::QueryOptions { exclude_last_frames: Some(60), ..all() },
            None,
            Box::new(|m| m.robot_id != "query" || m.frame_id < 222 - 60),
        ),
        (
            "exclude last seconds",
            "query",
            pb::QueryOptions { exclude_last_seconds: Some(80.0), ..all() },
            Some(200.0),
            Box::new(|m| m.robot_id != "query" || m.timestamp <= 120.0),
        ),
        (
            "time range",
            "ref",
            pb::QueryOptions { time_from: Some(40.0), time_to: Some(150.0), ..all() },
            None,
            Box::new(|m| (40.0..=150.0).contains(&m.timestamp)),
        ),
        (
            "frame id range",
            "ref",
            pb::QueryOptions { frame_id_from: Some(100), frame_id_to: Some(130), ..all() },
            None,
            Box::new(|m| (100..=130).contains(&m.frame_id)),
        ),
        ("k at its limit", "ref", pb::QueryOptions { k: Some(1000), ..all() }, None, Box::new(|_| true)),
    ];
    for (name, robot, o, at, allowed) in cases {
        for q in [0usize, 37, 111, 150, 221] {
            let d = pb::query_request::Content::Descriptor(pb::Descriptor {
                values: frames[q].1.clone(),
                ..Default::default()
            });
            let exact = query(&mut c, "corridor-exact", robot, d.clone(), &o, at).await;
            let approx = query(&mut c, "corridor-approx", robot, d, &o, at).await;
            assert!(!exact.is_empty(), "{name}");
            assert!(approx.iter().all(&allowed), "{name}, frame {q}: {:?}", ids(&approx));
            assert_eq!(ids(&approx), ids(&exact), "{name}, frame {q}");
            if name == "k at its limit" {
                assert_eq!(approx.len(), 222, "every frame, ranked");
            }
        }
    }
    // A stored frame's query never returns the frame itself.
    for q in [0u64, 111, 221] {
        let o = all();
        let approx = query(&mut c, "corridor-approx", "ref", pb::query_request::Content::FrameId(q), &o, None).await;
        let exact = query(&mut c, "corridor-exact", "ref", pb::query_request::Content::FrameId(q), &o, None).await;
        assert!(!ids(&approx).contains(&q), "frame {q} found itself");
        assert_eq!(ids(&approx), ids(&exact), "stored frame {q}");
    }
}

/// An `auto` session searches exactly until it holds `--approx-min-frames` frames, then builds
/// its approximate index and keeps it; its answers stay those of the exact session.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_auto_session_switches_to_the_approximate_index_at_its_size() {
    let (grpc, _) = server().await;
    let mut c = LoopdClient::connect(grpc).await.unwrap();
    let (_, frames) = pairs().await.iter().find(|(s, _)| s.name == "corridor").unwrap();
    let req = pb::CreateSessionRequest { id: "corridor-auto".into(), name: "auto".into(), ..Default::default() };
    let s = c.create_session(req).await.unwrap().into_inner();
    assert_eq!(s.index, pb::IndexKind::Auto as i32, "auto is the default");
    let info = |c: &mut LoopdClient<Channel>| {
        let mut c = c.clone();
        async move { c.get_session(pb::GetSessionRequest { id: "corridor-auto".into() }).await.unwrap().into_inner() }
    };
    add(&mut c, "corridor-auto", &frames[..AUTO_FRAMES - 1]).await;
    assert_eq!(info(&mut c).await.approximate_frames, None, "exact below the size");
    let rest: Vec<(String, Vec<f32>)> = frames[AUTO_FRAMES - 1..].to_vec();
    let mut c2 = c.clone();
    // Frames added after the switch keep their ids (the session numbers them on).
    for (i, (robot, d)) in rest.iter().enumerate() {
        let req = pb::AddFrameRequest {
            session_id: "corridor-auto".into(),
            robot_id: robot.clone(),
            timestamp: Some((AUTO_FRAMES - 1 + i) as f64),
            content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
                values: d.clone(),
                ..Default::default()
            })),
            ..Default::default()
        };
        c2.add_frame(req).await.unwrap();
    }
    let t = Instant::now();
    while info(&mut c).await.approximate_frames != Some(frames.len() as u64) {
        assert!(t.elapsed() < Duration::from_secs(60), "{:?}", info(&mut c).await);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let o = pb::QueryOptions { k: Some(5), ..Default::default() };
    for q in [3u64, 120, 200] {
        let fid = || pb::query_request::Content::FrameId(q);
        let auto = query(&mut c, "corridor-auto", "ref", fid(), &o, None).await;
        let exact = query(&mut c, "corridor-exact", "ref", fid(), &o, None).await;
        assert_eq!(ids(&auto), ids(&exact), "frame {q}");
    }
}

/// Over HTTP: `index` on create, echoed with the session; an unknown kind is a 400 naming it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_sessions_take_and_report_their_index_kind() {
    let (_, http) = server().await;
    let client = reqwest::Client::new();
    let r =
        client.post(format!("{http}/v1/sessions")).json(&serde_json::json!({"id": "h-approx", "index": "approximate"}));
    let r = r.send().await.unwrap();
    assert_eq!(r.status(), 201);
    let v: serde_json::Value = r.json().await.unwrap();
    assert_eq!((v["index"].as_str(), v["approximate_frames"].as_u64()), (Some("approximate"), Some(0)), "{v}");
    let r = client.post(format!("{http}/v1/sessions")).json(&serde_json::json!({"id": "h-bad", "index": "fast"}));
    let r = r.send().await.unwrap();
    assert_eq!(r.status(), 400);
    let body = r.text().await.unwrap();
    assert!(body.contains("index") && body.contains("fast"), "{body}");
    let v: serde_json::Value =
        client.get(format!("{http}/v1/sessions/h-approx")).send().await.unwrap().json().await.unwrap();
    assert_eq!(v["index"], "approximate");
}

/// `loopd serve` (a real process) with an approximate session saved as it grows
/// (`--approx-save-frames 1`) and sealed into mapped parts of 64 frames (`--approx-seal-frames`):
/// a restart loads the saved index (its log says so) instead of rebuilding it; SIGKILL right
/// after frames were acknowledged loses none of them and the index catches up; a corrupt index
/// file (the live part, then a sealed part) is detected, removed and rebuilt. Answers stay the
/// exact session's throughout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_saved_index_is_loaded_at_restart_and_a_corrupt_one_is_rebuilt() {
    use crate::common::proc::Loopd;
    let (grpc, _) = server().await;
    let exact = LoopdClient::connect(grpc).await.unwrap();
    let (_, frames) = pairs().await.iter().find(|(s, _)| s.name == "corridor").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let flags = [
        "--heads",
        loopd::cli::DEFAULT_HEADS,
        "--approx-save-frames",
        "1",
        "--approx-exact-below",
        "0",
        "--approx-exact-share",
        "0",
        "--approx-seal-frames",
        "64",
        "--approx-expansion-add",
        "96",
    ];
    let file = dir.path().join("graphs/c.usearch");
    let same_answers = |server: String| {
        let mut exact = exact.clone();
        async move {
            let mut c = LoopdClient::connect(server).await.unwrap();
            let o = pb::QueryOptions { k: Some(5), ..Default::default() };
            for q in [0u64, 60, 111, 180] {
                let fid = || pb::query_request::Content::FrameId(q);
                let a = query(&mut c, "c", "ref", fid(), &o, None).await;
                let e = query(&mut exact, "corridor-exact", "ref", fid(), &o, None).await;
                assert_eq!(ids(&a), ids(&e), "frame {q}");
            }
        }
    };
    let log_has = |s: &Loopd, what: &str| std::fs::read_to_string(&s.log).unwrap().contains(what);
    // Frames 0..200, indexed and saved.
    let (s, _) = Loopd::start(dir.path(), &flags).await;
    let mut c = LoopdClient::connect(s.grpc_url()).await.unwrap();
    create(&mut c, "c", pb::IndexKind::Approximate).await;
    add(&mut c, "c", &frames[..200]).await;
    indexed(&mut c, "c").await;
    let t = Instant::now();
    while !log_has(&s, "\"rows\":200") || !log_has(&s, "approximate index saved") {
        assert!(t.elapsed() < Duration::from_secs(30), "the index of 200 frames was not saved");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    s.kill();
    // Restart: the saved index is loaded; the last 22 frames go in, SIGKILL follows at once.
    let (s, _) = Loopd::start(dir.path(), &flags).await;
    assert!(log_has(&s, "approximate index loaded"), "{}", std::fs::read_to_string(&s.log).unwrap());
    let mut c = LoopdClient::connect(s.grpc_url()).await.unwrap();
    for (i, (robot, d)) in frames.iter().enumerate().skip(200) {
        let req = pb::AddFrameRequest {
            session_id: "c".into(),
            robot_id: robot.clone(),
            timestamp: Some(i as f64),
            content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
                values: d.clone(),
                ..Default::default()
            })),
            ..Default::default()
        };
        assert_eq!(c.add_frame(req).await.unwrap().into_inner().frame_id, i as u64);
    }
    s.kill();
    let (s, _) = Loopd::start(dir.path(), &flags).await;
    let mut c = LoopdClient::connect(s.grpc_url()).await.unwrap();
    assert_eq!(c.get_session(pb::GetSessionRequest { id: "c".into() }).await.unwrap().into_inner().frames, 222);
    indexed(&mut c, "c").await;
    same_answers(s.grpc_url()).await;
    s.stop().await;
    // A corrupt file: detected at start, removed, rebuilt.
    let mut bytes = std::fs::read(&file).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid..mid + 64].iter_mut().for_each(|b| *b ^= 0x5a);
    std::fs::write(&file, bytes).unwrap();
    let (s, _) = Loopd::start(dir.path(), &flags).await;
    assert!(log_has(&s, "approximate index file rejected"), "{}", std::fs::read_to_string(&s.log).unwrap());
    assert!(log_has(&s, "checksum mismatch"));
    let mut c = LoopdClient::connect(s.grpc_url()).await.unwrap();
    indexed(&mut c, "c").await;
    same_answers(s.grpc_url()).await;
    let t = Instant::now();
    while !log_has(&s, "rows sealed into a mapped file") || !log_has(&s, "\"rows\":222") {
        assert!(t.elapsed() < Duration::from_secs(30), "the rebuilt index was not sealed and saved");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    s.stop().await;
    // A corrupt sealed part: its header and length check out, so the start maps it; the indexer
    // hashes it in the background, rejects the index and rebuilds it.
    let part = dir.path().join("graphs/c.parts/64-128.usearch");
    let mut bytes = std::fs::read(&part).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid..mid + 64].iter_mut().for_each(|b| *b ^= 0x5a);
    std::fs::write(&part, bytes).unwrap();
    let (s, _) = Loopd::start(dir.path(), &flags).await;
    assert!(log_has(&s, "approximate index loaded"), "{}", std::fs::read_to_string(&s.log).unwrap());
    let t = Instant::now();
    while !log_has(&s, "64-128.usearch: checksum mismatch") {
        assert!(t.elapsed() < Duration::from_secs(30), "{}", std::fs::read_to_string(&s.log).unwrap());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let mut c = LoopdClient::connect(s.grpc_url()).await.unwrap();
    indexed(&mut c, "c").await;
    same_answers(s.grpc_url()).await;
    s.stop().await;
}
