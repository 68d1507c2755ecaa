//! Kept loops (issue #18) against the real server on loopback, over real gRPC and HTTP clients,
//! on corridor frames: every candidate answered for a stored frame is listed exactly (pairs,
//! ranks, scores), filters and pages cut the same list, verdicts are recorded and survive a
//! re-answer and a restart, and bad input gets 400 / 404.
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use serde_json::{json, Value};
use std::collections::BTreeMap;

async fn start(dir: &std::path::Path) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

fn frame(part: &str, robot: &str, i: usize, scope: pb::Scope) -> pb::AddFrameRequest {
    let image = std::fs::read(data(&format!("corridor/{part}/{i:07}.jpg"))).unwrap();
    pb::AddFrameRequest {
        session_id: "hall".into(),
        robot_id: robot.into(),
        timestamp: Some(i as f64 + if part == "query" { 1000.0 } else { 0.0 }),
        content: Some(pb::add_frame_request::Content::Image(image.into())),
        options: Some(pb::QueryOptions {
            k: Some(3),
            scope: scope as i32,
            exclude_last_frames: Some(2),
            verify: Some(false),
            ..Default::default()
        }),
        ..Default::default()
    }
}

async fn list(http: &reqwest::Client, base: &str, query: &str) -> (u16, Value) {
    let r = http.get(format!("{base}/v1/sessions/hall/loops?{query}")).send().await.unwrap();
    (r.status().as_u16(), r.json().await.unwrap())
}

fn pairs(v: &Value) -> Vec<(u64, u64)> {
    v["loops"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| (l["query_frame"].as_u64().unwrap(), l["match_frame"].as_u64().unwrap()))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_answered_candidate_is_kept_listed_and_judged() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path()).await;
    let mut g = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    g.create_session(pb::CreateSessionRequest { id: "hall".into(), ..Default::default() }).await.unwrap();

    // What the server answered: (query frame, match frame) -> (rank, score, robots).
    let mut answered = BTreeMap::new();
    for (part, robot, n, scope) in
        [("ref", "mapper", 30, pb::Scope::All), ("query", "visitor", 12, pb::Scope::OtherRobots)]
    {
        for i in 0..n {
            let a = g.add_and_query(frame(part, robot, i, scope)).await.unwrap().into_inner();
            for (rank, m) in a.matches.iter().enumerate() {
                answered.insert((a.frame_id, m.frame_id), (rank as u64, m.score, robot, m.robot_id.clone()));
            }
        }
    }
    assert!(answered.len() > 60, "{} candidates answered", answered.len());

    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let (st, all) = list(&http, &base, "limit=1000").await;
    assert_eq!(st, 200, "{all}");
    assert_eq!(pairs(&all), answered.keys().copied().collect::<Vec<_>>(), "every candidate answered, in frame order");
    for l in all["loops"].as_array().unwrap() {
        let key = (l["query_frame"].as_u64().unwrap(), l["match_frame"].as_u64().unwrap());
        let (rank, score, robot, match_robot) = &answered[&key];
        assert_eq!(l["rank"].as_u64().unwrap(), *rank);
        assert!((l["score"].as_f64().unwrap() as f32 - score).abs() < 1e-6);
        assert_eq!(
            (l["query_robot"].as_str().unwrap(), l["match_robot"].as_str().unwrap()),
            (*robot, match_robot.as_str())
        );
        assert_eq!((l["checked"].as_bool(), l["verified"].as_bool()), (Some(false), Some(false)));
    }
    assert!(all["next"].is_null());

    // Pages of 7 put together give the same list.
    let (mut paged, mut after) = (Vec::new(), String::new());
    loop {
        let q = if after.is_empty() { "limit=7".to_string() } else { format!("limit=7&after={after}") };
        let (st, page) = list(&http, &base, &q).await;
        assert_eq!(st, 200);
        assert!(page["loops"].as_array().unwrap().len() <= 7);
        paged.extend(pairs(&page));
        match page["next"].as_str() {
            Some(n) => after = n.to_string(),
            None => break,
        }
    }
    assert_eq!(paged, pairs(&all));

    // Filters cut the same list.
    let visitor: Vec<_> =
        answered.iter().filter(|(_, v)| v.2 == "visitor" || v.3 == "visitor").map(|(k, _)| *k).collect();
    assert_eq!(pairs(&list(&http, &base, "robot=visitor&limit=1000").await.1), visitor);
    let strong: Vec<_> = answered.iter().filter(|(_, v)| v.1 >= 0.8).map(|(k, _)| *k).collect();
    assert_eq!(pairs(&list(&http, &base, "min_score=0.8&limit=1000").await.1), strong);
    let window = list(&http, &base, "time_from=5&time_to=9&limit=1000").await.1;
    assert!(window["loops"]
        .as_array()
        .unwrap()
        .iter()
        .all(|l| (5.0..=9.0).contains(&l["query_time"].as_f64().unwrap())));
    assert_eq!(list(&http, &base, "verified=true").await.1["loops"].as_array().unwrap().len(), 0);

    // The same over gRPC.
    let listed =
        g.list_loops(pb::ListLoopsRequest { session_id: "hall".into(), limit: 1000, ..Default::default() }).await;
    let listed = listed.unwrap().into_inner();
    let grpc_pairs: Vec<_> = listed.loops.iter().map(|l| (l.query_frame, l.match_frame)).collect();
    assert_eq!(grpc_pairs, pairs(&all));
    assert!(listed.next.is_empty());

    // Verdicts: accept one over HTTP with a pose and covariance, reject another over gRPC.
    let (&(q1, m1), _) = answered.iter().find(|(_, v)| v.2 == "visitor").unwrap();
    let mut cov = vec![0.0; 36];
    (0..6).for_each(|i| cov[i * 7] = 0.01);
    let pose = json!({ "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0, "tx": 0.5, "ty": 0.0, "tz": 0.1 });
    let r = http
        .post(format!("{base}/v1/sessions/hall/loops/{q1}/{m1}/verdict"))
        .json(&json!({ "accepted": true, "relative_pose": pose, "covariance": cov }))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let judged: Value = r.json().await.unwrap();
    assert_eq!(judged["verdict"]["accepted"], true);
    assert_eq!(judged["verdict"]["relative_pose"]["tx"], 0.5);
    let (&(q2, m2), _) = answered.iter().find(|(k, v)| v.2 == "mapper" && **k != (q1, m1)).unwrap();
    let rejected = g
        .set_loop_verdict(pb::SetLoopVerdictRequest {
            session_id: "hall".into(),
            query_frame: q2,
            match_frame: m2,
            accepted: false,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert!(!rejected.verdict.unwrap().accepted);

    // A query on a stored frame answers its candidates again: updated, the verdict kept.
    let q = pb::QueryRequest {
        session_id: "hall".into(),
        robot_id: "visitor".into(),
        content: Some(pb::query_request::Content::FrameId(q1)),
        options: Some(pb::QueryOptions {
            k: Some(3),
            scope: pb::Scope::OtherRobots as i32,
            verify: Some(false),
            ..Default::default()
        }),
        ..Default::default()
    };
    let again = g.query(q).await.unwrap().into_inner();
    assert!(again.matches.iter().any(|m| m.frame_id == m1), "the same best candidates");
    let now = list(&http, &base, "limit=1000").await.1;
    let kept = now["loops"].as_array().unwrap().iter().find(|l| l["query_frame"] == q1 && l["match_frame"] == m1);
    let kept = kept.expect("still kept");
    assert_eq!(kept["verdict"]["accepted"], true, "{kept}");
    assert!(kept["found"].as_f64() > judged["found"].as_f64(), "answered again: {kept}");

    // Bad input: 400 / 404 with a message; nothing changes.
    for (path, body, status) in [
        (format!("loops/{q1}/999999/verdict"), json!({ "accepted": true }), 404),
        (format!("loops/{q1}/{m1}/verdict"), json!({ "accepted": true, "covariance": [1.0, 2.0] }), 400),
        (
            format!("loops/{q1}/{m1}/verdict"),
            json!({ "accepted": true, "relative_pose": { "qx": 0, "qy": 0, "qz": 0, "qw": 2, "tx": 0, "ty": 0, "tz": 0 } }),
            400,
        ),
        (format!("loops/x/{m1}/verdict"), json!({ "accepted": true }), 400),
        (format!("loops/{q1}/{m1}/verdict"), json!({ "accept": true }), 400),
    ] {
        let r = http.post(format!("{base}/v1/sessions/hall/{path}")).json(&body).send().await.unwrap();
        assert_eq!(r.status().as_u16(), status, "{path} {body}");
        let v: Value = r.json().await.unwrap();
        assert!(v["error"].as_str().is_some_and(|e| !e.is_empty()), "{v}");
    }
    assert_eq!(list(&http, &base, "after=nope").await.0, 400);
    assert_eq!(list(&http, &base, "colour=red").await.0, 400);
    assert_eq!(http.get(format!("{base}/v1/sessions/nosuch/loops")).send().await.unwrap().status(), 404);
    let before_restart = list(&http, &base, "limit=1000").await.1;

    // The export: every frame, every kept loop with its verdict (no poses here: an empty graph).
    let r = http.get(format!("{base}/v1/sessions/hall/export")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "application/x-tar");
    let bytes = r.bytes().await.unwrap();
    let mut files = BTreeMap::new();
    for entry in tar::Archive::new(bytes.as_ref()).entries().unwrap() {
        let mut e = entry.unwrap();
        let mut text = String::new();
        std::io::Read::read_to_string(&mut e, &mut text).unwrap();
        files.insert(e.path().unwrap().display().to_string(), text);
    }
    let names: Vec<&str> = files.keys().map(String::as_str).collect();
    assert_eq!(names, ["README.txt", "frames.csv", "graph.g2o", "loops.csv"]);
    assert_eq!(files["frames.csv"].lines().count(), 1 + 42);
    let loops_csv: Vec<&str> = files["loops.csv"].lines().collect();
    assert_eq!(loops_csv.len(), 1 + answered.len());
    assert!(loops_csv.iter().any(|l| l.starts_with(&format!("{q1},{m1},")) && l.contains(",accepted,0.5,")));
    assert!(loops_csv.iter().any(|l| l.starts_with(&format!("{q2},{m2},")) && l.contains(",rejected,")));
    assert_eq!(files["graph.g2o"], "", "no frame has a pose");
    let r = http.get(format!("{base}/v1/sessions/hall/export?odometry_sigma_m=-1")).send().await.unwrap();
    assert_eq!(r.status(), 400);

    // Kept across a restart, verdicts included.
    server.shutdown().await.unwrap();
    let server = start(dir.path()).await;
    let base = format!("http://{}", server.http_addr);
    assert_eq!(list(&http, &base, "limit=1000").await.1, before_restart);
    server.shutdown().await.unwrap();
}
