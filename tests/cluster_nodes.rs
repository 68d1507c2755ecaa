//! loopd nodes on one cluster log (issue #17, `serve --cluster`): two real servers on loopback
//! over the PostgreSQL primary + synchronous standby of `scripts/pg-replicated` (which runs these;
//! `--ignored`: they need that database), beside one plain sled server, all with the ImageNet
//! model. Asserted: any node serves any session (images, features and thumbnails written through
//! one node serve verification and the inspector through the other); read-after-ack across
//! nodes, 1,000 times; the cluster answers the same top-k ids, order and scores as one sled node
//! given the same sequence; duplicate ids, deletes and re-creations seen by every node; and with
//! the primary stopped, writes answer UNAVAILABLE / 503 with Retry-After while queries go on from
//! the nodes' indexes (flagged stale), and writes resume once it is back.
mod common;
use common::{data, imagenet_model};
use loopd::api::server::{ClusterConfig, RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::pb::{self, loopd_client::LoopdClient};
use std::process::Command;
use std::time::{Duration, Instant};
use tonic::Code;

type Client = LoopdClient<tonic::transport::Channel>;

fn env(name: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| panic!("{name} is unset: run these through scripts/pg-replicated"))
}

/// A server on loopback: a node of the cluster, or (`cluster` false) a plain sled server.
async fn node(dir: &std::path::Path, cluster: bool) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        cluster: cluster.then(|| ClusterConfig { url: env("LOOPD_PG_URL"), connections: 8, unreplicated: false }),
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

async fn client(s: &RunningServer) -> Client {
    LoopdClient::connect(format!("http://{}", s.grpc_addr)).await.unwrap()
}

async fn create(g: &mut Client, id: &str, thumbnails: bool) {
    let r = pb::CreateSessionRequest { id: id.into(), thumbnails, ..Default::default() };
    g.create_session(r).await.unwrap();
}

/// `pg_ctl` on the primary (as the postgres user, as the script started it).
fn primary(action: &str) {
    let dir = env("LOOPD_PG_PRIMARY");
    let mut c = Command::new("runuser");
    c.args(["-u", "postgres", "--"]).arg(format!("{}/pg_ctl", env("LOOPD_PG_BIN"))).args(["-D", &dir, "-w"]);
    match action {
        "stop" => c.args(["stop", "-m", "fast"]),
        _ => c.args(["start", "-l", &format!("{dir}.log")]),
    };
    assert!(c.status().unwrap().success(), "pg_ctl {action} on the primary");
}

fn desk(session: &str, i: usize) -> pb::AddFrameRequest {
    let image = std::fs::read(data(&format!("slambook2-ch11/{i}.png"))).unwrap();
    pb::AddFrameRequest {
        session_id: session.into(),
        robot_id: "desk".into(),
        timestamp: Some(i as f64),
        content: Some(pb::add_frame_request::Content::Image(image.into())),
        options: Some(pb::QueryOptions { k: Some(3), verify: Some(true), ..Default::default() }),
        ..Default::default()
    }
}

fn descriptor_frame(session: &str, robot: &str, t: f64, d: &[f32], id: Option<u64>) -> pb::AddFrameRequest {
    pb::AddFrameRequest {
        session_id: session.into(),
        robot_id: robot.into(),
        timestamp: Some(t),
        frame_id: id,
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor { values: d.to_vec() })),
        ..Default::default()
    }
}

/// A query with no exclusion window and no verification: what the index holds, ranked.
fn query(session: &str, content: pb::query_request::Content, k: u32) -> pb::QueryRequest {
    pb::QueryRequest {
        session_id: session.into(),
        content: Some(content),
        options: Some(pb::QueryOptions {
            k: Some(k),
            verify: Some(false),
            exclude_last_frames: Some(0),
            exclude_last_seconds: Some(0.0),
            ..Default::default()
        }),
        ..Default::default()
    }
}

fn by_descriptor(d: &[f32]) -> pb::query_request::Content {
    pb::query_request::Content::Descriptor(pb::Descriptor { values: d.to_vec() })
}

/// Ids and score bits of an answer, in order.
fn ranked(matches: &[pb::Match]) -> Vec<(u64, u32)> {
    matches.iter().map(|m| (m.frame_id, m.score.to_bits())).collect()
}

async fn frames_in(g: &mut Client, id: &str) -> Result<u64, Code> {
    g.get_session(pb::GetSessionRequest { id: id.into() }).await.map(|s| s.into_inner().frames).map_err(|e| e.code())
}

/// Real descriptors: the first `n` corridor reference frames embedded by `s`.
async fn corridor_descriptors(s: &RunningServer, n: usize) -> Vec<Vec<f32>> {
    let http = reqwest::Client::new();
    let mut out = Vec::new();
    for i in 0..n {
        let image = std::fs::read(data(&format!("corridor/ref/{i:07}.jpg"))).unwrap();
        let r = http.post(format!("http://{}/v1/embed", s.http_addr)).body(image).send().await.unwrap();
        assert_eq!(r.status(), 200);
        let v: serde_json::Value = r.json().await.unwrap();
        out.push(serde_json::from_value(v["descriptor"].clone()).unwrap());
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby)"]
async fn any_node_serves_any_session_and_sees_every_acknowledged_frame() {
    let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    let (a, b, sled) =
        (node(dirs[0].path(), true).await, node(dirs[1].path(), true).await, node(dirs[2].path(), false).await);
    let (mut ga, mut gb, mut gs) = (client(&a).await, client(&b).await, client(&sled).await);

    // Images through A (embedded, features and thumbnails kept); B verifies the revisit
    // 10.png -> 1.png against the features A stored, and serves A's thumbnails.
    create(&mut ga, "desk", true).await;
    let mut desk_ids = Vec::new();
    for i in 1..=9 {
        desk_ids.push(ga.add_frame(desk("desk", i)).await.unwrap().into_inner().frame_id);
    }
    assert_eq!(frames_in(&mut gb, "desk").await, Ok(9), "B holds every frame acknowledged through A");
    for &id in &desk_ids {
        let thumb = |g: &mut Client| {
            let mut g = g.clone();
            async move { g.get_thumbnail(pb::GetThumbnailRequest { session_id: "desk".into(), frame_id: id }).await }
        };
        let (from_a, from_b) = (thumb(&mut ga).await.unwrap().into_inner(), thumb(&mut gb).await.unwrap().into_inner());
        assert!(!from_b.jpeg.is_empty());
        assert_eq!(from_a.jpeg, from_b.jpeg, "frame {id}: the same thumbnail through both nodes");
    }
    let revisit = gb.add_and_query(desk("desk", 10)).await.unwrap().into_inner();
    let best = &revisit.matches[0];
    let inliers = best.verification.as_ref().map_or(0, |v| v.inliers);
    assert_eq!(best.frame_id, desk_ids[0], "10.png revisits 1.png: {:?}", revisit.matches);
    assert!(inliers >= 30, "verified through B with A's features: {inliers} inliers");
    assert_eq!(frames_in(&mut ga, "desk").await, Ok(10), "A holds the frame written through B");

    // Read-after-ack, 1,000 times: each frame acknowledged through A is in B's next answer.
    // The same sequence goes to the sled server, which must assign the same ids.
    let descriptors = corridor_descriptors(&a, 24).await;
    for g in [&mut ga, &mut gs] {
        create(g, "ping", false).await;
    }
    let copies = 1000 / descriptors.len() as u32 + 1;
    for i in 0..1000 {
        let d = &descriptors[i % descriptors.len()];
        let frame = descriptor_frame("ping", &format!("r{}", i % 3), i as f64, d, None);
        let id = ga.add_frame(frame.clone()).await.unwrap().into_inner().frame_id;
        assert_eq!(gs.add_frame(frame).await.unwrap().into_inner().frame_id, id, "the sled server's id");
        let by_id = gb.query(query("ping", pb::query_request::Content::FrameId(id), 1)).await;
        assert!(by_id.is_ok(), "frame {id} acknowledged through A, unknown to B: {:?}", by_id.err());
        let answer = gb.query(query("ping", by_descriptor(d), copies)).await.unwrap().into_inner();
        assert!(answer.matches.iter().any(|m| m.frame_id == id), "frame {id} missing from B's answer");
    }
    // The cluster's answers are the sled server's: ids, order and scores.
    for d in &descriptors {
        let q = query("ping", by_descriptor(d), 10);
        let on_sled = ranked(&gs.query(q.clone()).await.unwrap().into_inner().matches);
        assert_eq!(on_sled.len(), 10);
        assert_eq!(ranked(&ga.query(q.clone()).await.unwrap().into_inner().matches), on_sled, "node A");
        assert_eq!(ranked(&gb.query(q).await.unwrap().into_inner().matches), on_sled, "node B");
    }

    // A frame id stored through one node is refused through the other (exact retries).
    let taken = descriptor_frame("ping", "r0", 2000.0, &descriptors[0], Some(5000));
    gb.add_frame(taken.clone()).await.unwrap();
    assert_eq!(ga.add_frame(taken).await.unwrap_err().code(), Code::AlreadyExists);
    assert_eq!(frames_in(&mut ga, "ping").await, Ok(1001));

    // Deleted and created again through B under the same id while A holds the old one: A serves
    // the new session, not its cache of the old one. Deleted again through B: gone from A.
    gb.delete_session(pb::DeleteSessionRequest { id: "ping".into() }).await.unwrap();
    create(&mut gb, "ping", false).await;
    let id =
        gb.add_frame(descriptor_frame("ping", "r0", 0.0, &descriptors[3], None)).await.unwrap().into_inner().frame_id;
    assert_eq!(frames_in(&mut ga, "ping").await, Ok(1));
    let best = ga.query(query("ping", by_descriptor(&descriptors[3]), 5)).await.unwrap().into_inner().matches;
    assert_eq!(best.iter().map(|m| m.frame_id).collect::<Vec<_>>(), [id]);
    gb.delete_session(pb::DeleteSessionRequest { id: "ping".into() }).await.unwrap();
    assert_eq!(frames_in(&mut ga, "ping").await, Err(Code::NotFound));
    let listed = ga.list_sessions(pb::ListSessionsRequest {}).await.unwrap().into_inner().sessions;
    assert_eq!(listed.iter().map(|s| (s.id.as_str(), s.frames)).collect::<Vec<_>>(), [("desk", 10)]);
    for g in [&mut ga, &mut gb] {
        for id in ["desk", "ping"] {
            let _ = g.delete_session(pb::DeleteSessionRequest { id: id.into() }).await;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby)"]
async fn without_a_primary_writes_are_refused_and_queries_go_on() {
    let dirs: Vec<_> = (0..2).map(|_| tempfile::tempdir().unwrap()).collect();
    let (a, b) = (node(dirs[0].path(), true).await, node(dirs[1].path(), true).await);
    let (mut ga, mut gb) = (client(&a).await, client(&b).await);
    let descriptors = corridor_descriptors(&a, 8).await;
    create(&mut ga, "outage", false).await;
    for (i, d) in descriptors.iter().enumerate() {
        ga.add_frame(descriptor_frame("outage", "r0", i as f64, d, None)).await.unwrap();
    }
    let q = query("outage", by_descriptor(&descriptors[2]), 3);
    let before = ranked(&gb.query(q.clone()).await.unwrap().into_inner().matches);
    assert_eq!(before.len(), 3);

    primary("stop");
    let refused = ga.add_frame(descriptor_frame("outage", "r0", 100.0, &descriptors[0], None)).await;
    let stopped = Instant::now();
    assert_eq!(refused.map(|_| ()).unwrap_err().code(), Code::Unavailable);
    let http = reqwest::Client::new();
    let body = serde_json::json!({ "robot_id": "r0", "timestamp": 101.0, "descriptor": descriptors[1] });
    let r = http.post(format!("http://{}/v1/sessions/outage/frames", b.http_addr)).json(&body).send().await.unwrap();
    assert_eq!(r.status(), 503);
    assert!(r.headers().contains_key("retry-after"), "503 carries Retry-After");
    // Queries answer from the nodes' indexes meanwhile, flagged stale.
    for g in [&mut ga, &mut gb] {
        let answer = g.query(q.clone()).await.unwrap();
        assert_eq!(answer.metadata().get("loopd-stale").map(|v| v.to_str().unwrap()), Some("1"));
        assert_eq!(ranked(&answer.into_inner().matches), before);
    }
    let body = serde_json::json!({ "descriptor": descriptors[2], "options": { "k": 3, "verify": false } });
    let r = http.post(format!("http://{}/v1/sessions/outage/query", b.http_addr)).json(&body).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers().get("x-loopd-stale").map(|v| v.to_str().unwrap()), Some("1"));

    primary("start");
    // Writes resume once the primary (and its synchronous standby) is back.
    let id = loop {
        match ga.add_frame(descriptor_frame("outage", "r0", 102.0, &descriptors[2], None)).await {
            Ok(r) => break r.into_inner().frame_id,
            Err(e) => assert_eq!(e.code(), Code::Unavailable, "{e:?}"),
        }
        assert!(stopped.elapsed() < Duration::from_secs(60), "writes did not resume in 60 s");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let after = gb.query(q).await.unwrap();
    assert!(after.metadata().get("loopd-stale").is_none(), "not stale once the primary is back");
    assert!(after.into_inner().matches.iter().any(|m| m.frame_id == id), "B sees the frame written after the restart");
    assert_eq!(frames_in(&mut gb, "outage").await, Ok(descriptors.len() as u64 + 1), "refused writes left nothing");
    ga.delete_session(pb::DeleteSessionRequest { id: "outage".into() }).await.unwrap();
}
