//! loopd nodes on one cluster log (issue #17, `serve --cluster`): two real servers on loopback
//! over the PostgreSQL primary + synchronous standby of `scripts/pg-replicated` (which runs these;
//! `--ignored`: they need that database), beside one plain sled server, all with the ImageNet
//! model. Asserted: any node serves any session (images, features and thumbnails written through
//! one node serve verification and the inspector through the other); read-after-ack across
//! nodes, 1,000 times; the cluster answers the same top-k ids, order and scores as one sled node
//! given the same sequence; duplicate ids, deletes and re-creations seen by every node; and with
//! the primary stopped, writes answer UNAVAILABLE / 503 with Retry-After while queries go on from
//! the nodes' indexes (flagged stale), readiness (/readyz, gRPC health) turns false, and writes
//! and readiness resume once it is back.
use crate::common::pg::{env, server};
use crate::common::{data, desk_frame, imagenet_model};
use loopd::api::server::{ClusterConfig, RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::pb::{self, loopd_client::LoopdClient};
use std::process::Command;
use std::time::{Duration, Instant};
use tonic::Code;

type Client = LoopdClient<tonic::transport::Channel>;

/// A server on loopback: a node of the cluster, or (`cluster` false) a plain sled server.
async fn node(dir: &std::path::Path, cluster: bool) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        cluster: cluster.then(|| ClusterConfig { connections: 8, ..ClusterConfig::new(&env("LOOPD_PG_URL")) }),
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

const ADMIN: &str = "admin-key-for-the-cluster-tests-0123456789";

/// A cluster node with keys required (the admin key set).
async fn keyed_node(dir: &std::path::Path) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        cluster: Some(ClusterConfig { connections: 4, ..ClusterConfig::new(&env("LOOPD_PG_URL")) }),
        auth: loopd::auth::AuthConfig { admin_key: Some(ADMIN.into()), ..Default::default() },
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

/// Removes the tenants from the log at the end (pass or fail): keys would be required by every
/// node started on it afterwards.
struct ForgetTenants;

impl Drop for ForgetTenants {
    fn drop(&mut self) {
        let _ = Command::new("psql").args([&env("LOOPD_PG_URL"), "-tAc", "DELETE FROM loopd_tenants"]).status();
    }
}

/// Polls `url` with `key` until it answers `status` (within 10 s); the time it took.
async fn until_status(http: &reqwest::Client, url: &str, key: &str, status: u16) -> Duration {
    let t = Instant::now();
    loop {
        let r = http.get(url).bearer_auth(key).send().await.unwrap();
        if r.status() == status {
            return t.elapsed();
        }
        assert!(t.elapsed() < Duration::from_secs(10), "{url} answered {} for 10 s, not {status}", r.status());
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A node's readiness as the balancer sees it: `/readyz`'s status and gRPC health's (1 SERVING,
/// 2 NOT_SERVING).
async fn readiness(s: &RunningServer) -> (u16, i32) {
    let http = reqwest::get(format!("http://{}/readyz", s.http_addr)).await.unwrap().status().as_u16();
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", s.grpc_addr)).unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.connect().await.unwrap());
    let grpc = health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.unwrap();
    (http, grpc.into_inner().status)
}

/// Waits (at most 15 s) until `s` reports `want` (see [`readiness`]).
async fn until_readiness(s: &RunningServer, want: (u16, i32)) {
    let t = Instant::now();
    loop {
        let now = readiness(s).await;
        if now == want {
            return;
        }
        assert!(t.elapsed() < Duration::from_secs(15), "readiness {now:?} for 15 s, not {want:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn client(s: &RunningServer) -> Client {
    LoopdClient::connect(format!("http://{}", s.grpc_addr)).await.unwrap()
}

async fn create(g: &mut Client, id: &str, thumbnails: bool) {
    let r = pb::CreateSessionRequest { id: id.into(), thumbnails, ..Default::default() };
    g.create_session(r).await.unwrap();
}

fn descriptor_frame(session: &str, robot: &str, t: f64, d: &[f32], id: Option<u64>) -> pb::AddFrameRequest {
    pb::AddFrameRequest {
        session_id: session.into(),
        robot_id: robot.into(),
        timestamp: Some(t),
        frame_id: id,
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
            values: d.to_vec(),
            ..Default::default()
        })),
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
    pb::query_request::Content::Descriptor(pb::Descriptor { values: d.to_vec(), ..Default::default() })
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

    // Images through A (embedded, features and thumbnails kept, each answered with its
    // candidates); B verifies the revisit 10.png -> 1.png against the features A stored, and
    // serves A's thumbnails.
    create(&mut ga, "desk", true).await;
    let mut desk_ids = Vec::new();
    for i in 1..=9 {
        desk_ids.push(ga.add_and_query(desk_frame("desk", i)).await.unwrap().into_inner().frame_id);
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
    let revisit = gb.add_and_query(desk_frame("desk", 10)).await.unwrap().into_inner();
    let best = &revisit.matches[0];
    let inliers = best.verification.as_ref().map_or(0, |v| v.inliers);
    assert_eq!(best.frame_id, desk_ids[0], "10.png revisits 1.png: {:?}", revisit.matches);
    assert!(inliers >= 30, "verified through B with A's features: {inliers} inliers");
    assert_eq!(frames_in(&mut ga, "desk").await, Ok(10), "A holds the frame written through B");

    // Kept loops go into the log with their frames: both nodes list the same ones. A verdict
    // given through A shows through B, and stays when B answers the loop again.
    let http = reqwest::Client::new();
    let (base_a, base_b) =
        (format!("http://{}/v1/sessions/desk", a.http_addr), format!("http://{}/v1/sessions/desk", b.http_addr));
    let listing = |base: &str| {
        let (http, url) = (http.clone(), format!("{base}/loops?limit=1000"));
        async move {
            let v: serde_json::Value = http.get(url).send().await.unwrap().json().await.unwrap();
            v["loops"].as_array().unwrap().clone()
        }
    };
    let (from_a, from_b) = (listing(&base_a).await, listing(&base_b).await);
    assert_eq!(from_a, from_b, "the same kept loops through both nodes");
    let pair = |l: &serde_json::Value| (l["query_frame"].as_u64().unwrap(), l["match_frame"].as_u64().unwrap());
    let kept = from_a.iter().find(|l| pair(l) == (revisit.frame_id, desk_ids[0])).expect("10 -> 1 kept");
    assert_eq!(kept["verified"], true, "{kept}");
    assert_eq!(kept["inliers"].as_u64(), Some(inliers as u64));
    assert!(from_a.iter().any(|l| l["query_robot"] == "desk" && pair(l).0 == desk_ids[8]), "loops kept through A");
    let verdict = format!("{base_a}/loops/{}/{}/verdict", revisit.frame_id, desk_ids[0]);
    let r = http.post(verdict).json(&serde_json::json!({ "accepted": false })).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let judged = |loops: &[serde_json::Value]| {
        loops.iter().find(|l| pair(l) == (revisit.frame_id, desk_ids[0])).cloned().expect("10 -> 1 listed")
    };
    assert_eq!(judged(&listing(&base_b).await)["verdict"]["accepted"], false, "A's verdict through B");
    let again = pb::QueryRequest {
        session_id: "desk".into(),
        content: Some(pb::query_request::Content::FrameId(revisit.frame_id)),
        options: Some(pb::QueryOptions { k: Some(3), verify: Some(true), ..Default::default() }),
        ..Default::default()
    };
    gb.query(again).await.unwrap();
    let after = judged(&listing(&base_a).await);
    assert!(after["found"].as_f64() > kept["found"].as_f64(), "answered again through B: {after}");
    assert_eq!(after["verdict"]["accepted"], false, "the verdict stays: {after}");

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
    // The cluster's answers are the sled server's: ids, order and scores. Node C starts now and
    // loads the session on its first request (two pages of the log's tail).
    let dir_c = tempfile::tempdir().unwrap();
    let c = node(dir_c.path(), true).await;
    let mut gc = client(&c).await;
    for d in &descriptors {
        let q = query("ping", by_descriptor(d), 10);
        let on_sled = ranked(&gs.query(q.clone()).await.unwrap().into_inner().matches);
        assert_eq!(on_sled.len(), 10);
        assert_eq!(ranked(&gc.query(q.clone()).await.unwrap().into_inner().matches), on_sled, "node C");
        assert_eq!(ranked(&ga.query(q.clone()).await.unwrap().into_inner().matches), on_sled, "node A");
        assert_eq!(ranked(&gb.query(q).await.unwrap().into_inner().matches), on_sled, "node B");
    }
    assert_eq!(frames_in(&mut gc, "ping").await, Ok(1000));

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

/// Issue #34, item 3, through real servers: a frame sent with an idempotency key through one
/// node and sent again through the other (a client that failed over) is stored once, and both
/// answers name the same frame; the second node holds it after the replay.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby)"]
async fn a_frame_sent_again_with_its_key_through_another_node_is_stored_once() {
    let dirs: Vec<_> = (0..2).map(|_| tempfile::tempdir().unwrap()).collect();
    let (a, b) = (node(dirs[0].path(), true).await, node(dirs[1].path(), true).await);
    let (mut ga, mut gb) = (client(&a).await, client(&b).await);
    create(&mut ga, "keyed-nodes", false).await;
    let d = corridor_descriptors(&a, 3).await;
    let keyed = |i: usize, key: &str| pb::AddFrameRequest {
        idempotency_key: key.into(),
        ..descriptor_frame("keyed-nodes", "r1", i as f64, &d[i], None)
    };
    let mut ids = Vec::new();
    for i in 0..3 {
        let key = format!("r1-{i}");
        let first = ga.add_and_query(keyed(i, &key)).await.unwrap().into_inner();
        let again = gb.add_and_query(keyed(i, &key)).await.unwrap().into_inner();
        assert_eq!(first.frame_id, again.frame_id, "frame {i} through the other node");
        assert!(again.matches.iter().all(|m| m.frame_id != first.frame_id), "the replay matched itself");
        ids.push(first.frame_id);
    }
    // And back through the first node, with the second node's answer lost.
    let again = ga.add_frame(keyed(1, "r1-1")).await.unwrap().into_inner();
    assert_eq!(again.frame_id, ids[1]);
    assert_eq!((frames_in(&mut ga, "keyed-nodes").await, frames_in(&mut gb, "keyed-nodes").await), (Ok(3), Ok(3)));
    let reused = gb.add_frame(keyed(2, "r1-0")).await.unwrap_err();
    assert_eq!(reused.code(), Code::AlreadyExists, "{reused:?}");
    ga.delete_session(pb::DeleteSessionRequest { id: "keyed-nodes".into() }).await.unwrap();
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
    until_readiness(&b, (200, 1)).await;

    server("LOOPD_PG_PRIMARY", "stop");
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
    // Not ready (the balancer sends calls to nodes that can write, if any), and says why.
    until_readiness(&b, (503, 2)).await;
    let why = reqwest::get(format!("http://{}/readyz", b.http_addr)).await.unwrap().text().await.unwrap();
    assert!(why.contains("not ready") && why.contains("database"), "{why}");

    server("LOOPD_PG_PRIMARY", "start");
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
    until_readiness(&b, (200, 1)).await;
    ga.delete_session(pb::DeleteSessionRequest { id: "outage".into() }).await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby)"]
async fn keys_issued_or_revoked_through_one_node_hold_on_every_node() {
    let _forget = ForgetTenants;
    let dirs: Vec<_> = (0..2).map(|_| tempfile::tempdir().unwrap()).collect();
    let (a, b) = (keyed_node(dirs[0].path()).await, keyed_node(dirs[1].path()).await);
    let (base_a, base_b) = (format!("http://{}/v1", a.http_addr), format!("http://{}/v1", b.http_addr));
    let http = reqwest::Client::new();
    let issue = |base: String, name: &'static str| {
        let http = http.clone();
        async move {
            let r = http.post(format!("{base}/tenants")).bearer_auth(ADMIN).json(&serde_json::json!({ "name": name }));
            let v: serde_json::Value = r.send().await.unwrap().json().await.unwrap();
            v["key"].as_str().unwrap_or_else(|| panic!("no key: {v}")).to_string()
        }
    };
    // A key issued through A works through B within the refresh (1 s here).
    let key = issue(base_a.clone(), "fleet-a").await;
    let took = until_status(&http, &format!("{base_b}/sessions"), &key, 200).await;
    assert!(took < Duration::from_secs(3), "B took {took:?} to take A's key");
    // The tenant's session, created through B, is its own through A; another tenant's key (issued
    // through B) does not see it.
    let made = http.post(format!("{base_b}/sessions")).bearer_auth(&key).json(&serde_json::json!({ "id": "map" }));
    assert_eq!(made.send().await.unwrap().status(), 201);
    assert_eq!(http.get(format!("{base_a}/sessions/map")).bearer_auth(&key).send().await.unwrap().status(), 200);
    let other = issue(base_b.clone(), "fleet-b").await;
    until_status(&http, &format!("{base_a}/sessions"), &other, 200).await;
    assert_eq!(http.get(format!("{base_a}/sessions/map")).bearer_auth(&other).send().await.unwrap().status(), 404);
    let listed = http.get(format!("{base_a}/tenants")).bearer_auth(ADMIN).send().await.unwrap();
    let listed: serde_json::Value = listed.json().await.unwrap();
    assert_eq!(listed["tenants"].as_array().map(Vec::len), Some(2), "{listed}");
    // Revoked through B: refused through A within the refresh.
    assert_eq!(http.delete(format!("{base_a}/sessions/map")).bearer_auth(&key).send().await.unwrap().status(), 204);
    let revoked = http.delete(format!("{base_b}/tenants/fleet-a")).bearer_auth(ADMIN).send().await.unwrap();
    assert_eq!(revoked.status(), 200);
    let took = until_status(&http, &format!("{base_a}/sessions"), &key, 401).await;
    assert!(took < Duration::from_secs(3), "A took {took:?} to refuse the revoked key");
    assert_eq!(http.get(format!("{base_a}/sessions")).bearer_auth(&other).send().await.unwrap().status(), 200);
}

/// A cluster node named `name` for the owners test: members heartbeat every 0.2 s, are gone
/// after 2 s unheard, and a session the node does not own is dropped after 1 s unused.
async fn member_node(dir: &std::path::Path, name: &str) -> RunningServer {
    member_node_keyed(dir, name, None).await
}

/// As [`member_node`], with keys required when `admin` is set.
async fn member_node_keyed(dir: &std::path::Path, name: &str, admin: Option<&str>) -> RunningServer {
    let cfg = ServerConfig {
        auth: loopd::auth::AuthConfig { admin_key: admin.map(String::from), ..Default::default() },
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        cluster: Some(ClusterConfig {
            connections: 4,
            tenant_refresh: Duration::from_millis(200),
            node: name.into(),
            member_ttl: Duration::from_secs(2),
            evict_idle: Some(Duration::from_secs(1)),
            ..ClusterConfig::new(&env("LOOPD_PG_URL"))
        }),
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

/// Every node's `GET /v1/cluster`, by node name.
async fn views(nodes: &[&RunningServer]) -> Vec<serde_json::Value> {
    let mut out = Vec::new();
    for n in nodes {
        // The admin key (ignored by nodes that require no keys).
        let r = reqwest::Client::new().get(format!("http://{}/v1/cluster", n.http_addr)).bearer_auth(ADMIN);
        let r = r.send().await.unwrap();
        assert_eq!(r.status(), 200);
        out.push(r.json().await.unwrap());
    }
    out
}

/// The nodes holding `session` in `views`: (node, owner, frames).
fn holders(views: &[serde_json::Value], session: &str) -> Vec<(String, bool, u64)> {
    let mut out = Vec::new();
    for v in views {
        for h in v["held"].as_array().unwrap().iter().filter(|h| h["session"] == session) {
            out.push((v["node"].as_str().unwrap().to_string(), h["owner"] == true, h["frames"].as_u64().unwrap()));
        }
    }
    out.sort();
    out
}

/// Polls the nodes' views until `want` holds (within 20 s); the last views otherwise, in the panic.
async fn until_views(nodes: &[&RunningServer], what: &str, want: impl Fn(&[serde_json::Value]) -> bool) {
    let t = Instant::now();
    loop {
        let now = views(nodes).await;
        if want(&now) {
            return;
        }
        assert!(t.elapsed() < Duration::from_secs(20), "not within 20 s: {what}; views: {now:#?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Owners (issue #17): each session is held warm by two live members before any request for it;
/// a node that does not own a session drops it once unused; when an owner leaves, the remaining
/// member loads its sessions without a request; a member that stops heartbeating is gone after
/// the ttl; and every node answers every session all along (a non-owner loads it: the fallback).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby)"]
async fn sessions_are_held_warm_by_two_live_members() {
    // Nodes of earlier tests stopped without leaving; their rows would count until the ttl.
    crate::common::pg::psql("DELETE FROM loopd_members");
    let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    let mut nodes = Vec::new();
    for (i, d) in dirs.iter().enumerate() {
        nodes.push(member_node(d.path(), &format!("node-{i}")).await);
    }
    let descriptors = corridor_descriptors(&nodes[0], 8).await;
    let sessions: Vec<String> = (0..6).map(|i| format!("owned-{i}")).collect();
    // All written through node 0, which owns only some of them.
    let mut g0 = client(&nodes[0]).await;
    for (i, id) in sessions.iter().enumerate() {
        create(&mut g0, id, false).await;
        for (t, d) in descriptors.iter().take(i + 2).enumerate() {
            g0.add_frame(descriptor_frame(id, "r0", t as f64, d, None)).await.unwrap();
        }
    }
    let members = |views: &[serde_json::Value], want: &[&str]| {
        views
            .iter()
            .all(|v| v["members"].as_array().unwrap().iter().map(|m| m.as_str().unwrap()).eq(want.iter().copied()))
    };
    // Two owners each, both holding every frame; nobody else holds it.
    let warm = |views: &[serde_json::Value]| {
        sessions.iter().enumerate().all(|(i, id)| {
            let h = holders(views, id);
            h.len() == 2 && h.iter().all(|(_, owner, frames)| *owner && *frames == i as u64 + 2)
        })
    };
    let all = [&nodes[0], &nodes[1], &nodes[2]];
    until_views(&all, "3 members, each session held by its 2 owners only", |v| {
        members(v, &["node-0", "node-1", "node-2"]) && warm(v)
    })
    .await;
    // Its own sessions only (a failed test before may have left some).
    let own = |h: &&serde_json::Value| h["session"].as_str().unwrap().starts_with("owned-");
    let per_node: Vec<usize> =
        views(&all).await.iter().map(|v| v["held"].as_array().unwrap().iter().filter(own).count()).collect();
    assert_eq!(per_node.iter().sum::<usize>(), 12, "6 sessions x 2 owners spread over 3 nodes: {per_node:?}");

    // The fallback: each session answered through a node that does not own it (loaded on
    // demand, then dropped again once unused).
    for id in &sessions {
        let owners: Vec<String> = holders(&views(&all).await, id).into_iter().map(|h| h.0).collect();
        let other = (0..3).find(|i| !owners.contains(&format!("node-{i}"))).unwrap();
        let mut g = client(&nodes[other]).await;
        let best = g.query(query(id, by_descriptor(&descriptors[1]), 1)).await.unwrap().into_inner().matches;
        assert_eq!(best[0].frame_id, 1, "{id} through node-{other}, not an owner");
        let h = holders(&views(&all).await, id);
        assert!(
            h.contains(&(format!("node-{other}"), false, (h[0].2))),
            "{id} held by node-{other} after a query: {h:?}"
        );
    }
    until_views(&all, "non-owners dropped the sessions they served", |v| warm(v)).await;

    // An owner leaves (a clean stop): the two left own and hold every session, loaded before any
    // request.
    let gone = nodes.remove(1);
    gone.shutdown().await.unwrap();
    let left = [&nodes[0], &nodes[1]];
    until_views(&left, "2 members, both holding every session", |v| members(v, &["node-0", "node-2"]) && warm(v)).await;

    // A member that stops heartbeating ("ghost": a row nobody refreshes) owns some sessions
    // until the ttl: a node it displaces drops them, yet each stays warm on the other owner and
    // answered through both; after the ttl both hold every session again.
    crate::common::pg::psql("INSERT INTO loopd_members (node, seen, since) VALUES ('ghost', now(), now())");
    until_views(&left, "the ghost counted: sessions it owns held by their one live owner only", |v| {
        let held: Vec<Vec<(String, bool, u64)>> = sessions.iter().map(|id| holders(v, id)).collect();
        members(v, &["ghost", "node-0", "node-2"])
            && held.iter().all(|h| !h.is_empty() && h.iter().all(|(_, owner, _)| *owner))
            && held.iter().any(|h| h.len() == 1)
    })
    .await;
    for n in left {
        let mut g = client(n).await;
        for id in &sessions {
            let best = g.query(query(id, by_descriptor(&descriptors[0]), 1)).await.unwrap().into_inner().matches;
            assert_eq!(best[0].frame_id, 0, "{id} answered while the ghost owns it");
        }
    }
    until_views(&left, "the ghost gone after the ttl; both hold every session", |v| {
        members(v, &["node-0", "node-2"]) && warm(v)
    })
    .await;
    let mut g = client(&nodes[0]).await;
    for id in &sessions {
        g.delete_session(pb::DeleteSessionRequest { id: id.clone() }).await.unwrap();
    }
    until_views(&left, "deleted sessions dropped everywhere", |v| {
        v.iter().all(|v| !v["held"].as_array().unwrap().iter().any(|h| own(&h)))
    })
    .await;
    for n in nodes {
        n.shutdown().await.unwrap();
    }
}

/// A tenant's frame limit counts its frames on every node (issue #17): a node that never loaded
/// one of the tenant's sessions still counts its frames, from the log.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby)"]
async fn a_tenants_frame_limit_counts_its_frames_on_every_node() {
    let _forget = ForgetTenants;
    let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    let mut nodes = Vec::new();
    for (i, d) in dirs.iter().enumerate() {
        nodes.push(member_node_keyed(d.path(), &format!("limit-{i}"), Some(ADMIN)).await);
    }
    // Nodes of earlier tests that stopped without leaving (these three heartbeat again at once).
    crate::common::pg::psql("DELETE FROM loopd_members");
    let http = reqwest::Client::new();
    let base = |n: &RunningServer| format!("http://{}/v1", n.http_addr);
    let r = http.post(format!("{}/tenants", base(&nodes[0]))).bearer_auth(ADMIN);
    let r = r.json(&serde_json::json!({ "name": "small", "limits": { "max_frames": 3 } })).send().await.unwrap();
    assert_eq!(r.status(), 201);
    let key = r.json::<serde_json::Value>().await.unwrap()["key"].as_str().unwrap().to_string();
    for n in &nodes {
        until_status(&http, &format!("{}/sessions", base(n)), &key, 200).await;
    }
    let dim = http.get(format!("{}/info", base(&nodes[0]))).bearer_auth(&key).send().await.unwrap();
    let dim = dim.json::<serde_json::Value>().await.unwrap()["dim"].as_u64().unwrap() as usize;
    let post = |n: &RunningServer, path: &str, body: serde_json::Value| {
        http.post(format!("{}{path}", base(n))).bearer_auth(&key).json(&body).send()
    };
    let frame =
        |t: usize| serde_json::json!({ "robot_id": "r", "timestamp": t, "descriptor": vec![t as f32 + 1.0; dim] });
    // "m1" gets 2 frames through one of its owners; the node that does not own it never loads it.
    assert_eq!(post(&nodes[0], "/sessions", serde_json::json!({ "id": "m1" })).await.unwrap().status(), 201);
    let all: Vec<&RunningServer> = nodes.iter().collect();
    until_views(&all, "small/m1 held by its 2 owners", |v| holders(v, "small/m1").len() == 2).await;
    let owners: Vec<String> = holders(&views(&all).await, "small/m1").into_iter().map(|h| h.0).collect();
    let (owner, other) = (
        (0..3).find(|i| owners.contains(&format!("limit-{i}"))).unwrap(),
        (0..3).find(|i| !owners.contains(&format!("limit-{i}"))).unwrap(),
    );
    for t in 0..2 {
        assert_eq!(post(&nodes[owner], "/sessions/m1/frames", frame(t)).await.unwrap().status(), 201);
    }
    // Through the other node, into another session: one more fits, the next is refused.
    let x = &nodes[other];
    assert_eq!(post(x, "/sessions", serde_json::json!({ "id": "m2" })).await.unwrap().status(), 201);
    assert_eq!(post(x, "/sessions/m2/frames", frame(2)).await.unwrap().status(), 201);
    assert!(holders(&views(&all).await, "small/m1").iter().all(|h| h.0 != format!("limit-{other}")));
    let r = post(x, "/sessions/m2/frames", frame(3)).await.unwrap();
    let status = r.status();
    let body: serde_json::Value = r.json().await.unwrap();
    assert_eq!(status, 429, "limit-{other} took a 4th frame for a tenant limited to 3: {body}");
    assert!(body["error"].as_str().unwrap().contains("stores 3 frames"), "{body}");
    for id in ["m1", "m2"] {
        let r = http.delete(format!("{}/sessions/{id}", base(x))).bearer_auth(&key).send().await.unwrap();
        assert_eq!(r.status(), 204);
    }
    for n in nodes {
        n.shutdown().await.unwrap();
    }
}

/// Posts the ten desk frames as a sequence job into `session` through `node`; the job's id.
async fn desk_job(http: &reqwest::Client, node: &RunningServer, session: &str) -> String {
    let url = format!("http://{}/v1/sessions", node.http_addr);
    let r = http.post(&url).json(&serde_json::json!({ "id": session })).send().await.unwrap();
    assert!(r.status() == 201 || r.status() == 409, "{}", r.status());
    // Every first candidate scoring 0.8 (no confidence floor): the plain backbone's descriptors.
    let mut form =
        reqwest::multipart::Form::new().text("order", "name").text("min_score", "0.8").text("min_confidence", "0");
    for i in 1..=10 {
        let image = std::fs::read(data(&format!("slambook2-ch11/{i}.png"))).unwrap();
        form = form.part("image", reqwest::multipart::Part::bytes(image).file_name(format!("{i}.png")));
    }
    let r = http.post(format!("{url}/{session}/sequences")).multipart(form).send().await.unwrap();
    assert_eq!(r.status(), 202);
    r.json::<serde_json::Value>().await.unwrap()["job_id"].as_str().unwrap().to_string()
}

async fn job_status(http: &reqwest::Client, node: &RunningServer, job: &str) -> (u16, serde_json::Value) {
    let r = http.get(format!("http://{}/v1/jobs/{job}", node.http_addr)).send().await.unwrap();
    (r.status().as_u16(), r.json().await.unwrap_or_default())
}

/// A job's record as a node that died mid-job leaves it in the log (last written a minute ago).
fn leftover_job(id: &str, node: &str) {
    logged_job(id, node, "now() - interval '1 minute'");
}

/// A running job's record in the log, by `node`, last written at `updated` (SQL).
fn logged_job(id: &str, node: &str, updated: &str) {
    let record = serde_json::json!({ "job_id": id, "session_id": "seq-a", "state": "running", "total": 10,
                                     "done": 4, "loops": [], "errors": [] });
    crate::common::pg::psql(&format!(
        "INSERT INTO loopd_jobs (id, n, node, record, updated) VALUES ('{id}', 0, '{node}', '{record}', \
         {updated}) ON CONFLICT (id) DO UPDATE SET node = EXCLUDED.node, record = EXCLUDED.record, \
         updated = EXCLUDED.updated"
    ));
}

/// Sequence jobs in the log (issue #17): a job started through one node is polled through any
/// (running while its node runs it, then its loops); two nodes never give the same job id; a job
/// whose node is gone, or whose node started again, reads as interrupted, and a node that starts
/// again marks its earlier run's jobs interrupted in the log.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby)"]
async fn sequence_jobs_are_answered_through_every_node() {
    let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    let a = member_node(dirs[0].path(), "jobs-a").await;
    let b = member_node(dirs[1].path(), "jobs-b").await;
    let http = reqwest::Client::new();
    let ja = desk_job(&http, &a, "seq-a").await;
    let jb = desk_job(&http, &b, "seq-b").await;
    assert_ne!(ja, jb, "two nodes gave the same job id");
    // Through the other node at once: its node runs it.
    let (code, first) = job_status(&http, &b, &ja).await;
    assert_eq!(code, 200, "{first}");
    assert!(first["state"] == "running" || first["state"] == "done", "{first}");
    let t = Instant::now();
    let done = loop {
        let (_, st) = job_status(&http, &b, &ja).await;
        if st["state"] != "running" {
            break st;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "job {ja} still running through B: {st}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert_eq!(done["state"], "done", "{done}");
    assert_eq!(done["done"], 10);
    let best = done["loops"]
        .as_array()
        .unwrap()
        .iter()
        .max_by(|x, y| x["score"].as_f64().partial_cmp(&y["score"].as_f64()).unwrap())
        .cloned()
        .unwrap_or_default();
    assert_eq!((best["query_name"].as_str(), best["match_name"].as_str()), (Some("10.png"), Some("1.png")), "{done}");
    assert_eq!(job_status(&http, &a, &ja).await.1, done, "A (which ran it) and B answer the same status");
    assert_eq!(job_status(&http, &a, "job-999999999").await.0, 404);

    // Left running by a node that is no member, or by this very node before it started again.
    leftover_job("job-ghost", "ghost");
    leftover_job("job-earlier-b", "jobs-b");
    for (job, node) in [("job-ghost", &a), ("job-ghost", &b), ("job-earlier-b", &b)] {
        let (code, st) = job_status(&http, node, job).await;
        assert_eq!((code, st["state"].as_str(), st["done"].as_u64()), (200, Some("interrupted"), Some(4)), "{job}");
    }
    // Through another member, jobs-b's record says running: jobs-b is live, so it is believed.
    assert_eq!(job_status(&http, &a, "job-earlier-b").await.1["state"], "running");
    // Written just now by a node this one does not see (a heartbeat late for a round): still
    // running, since interrupted is final.
    logged_job("job-recent", "late", "now()");
    assert_eq!(job_status(&http, &a, "job-recent").await.1["state"], "running");
    // A node started again under its name marks them interrupted in the log, for every node.
    leftover_job("job-earlier-c", "jobs-c");
    let c = member_node(dirs[2].path(), "jobs-c").await;
    let state = crate::common::pg::psql("SELECT record->>'state' FROM loopd_jobs WHERE id = 'job-earlier-c'");
    assert_eq!(state, "interrupted");
    crate::common::pg::psql(
        "DELETE FROM loopd_jobs WHERE id IN ('job-ghost', 'job-earlier-b', 'job-earlier-c', 'job-recent')",
    );
    // The next test counts every session's owners.
    for id in ["seq-a", "seq-b"] {
        let r = http.delete(format!("http://{}/v1/sessions/{id}", c.http_addr)).send().await.unwrap();
        assert_eq!(r.status(), 204);
    }
    for n in [a, b, c] {
        n.shutdown().await.unwrap();
    }
}

/// The cluster's nodes are meant to serve the same models (issue #39): a node that lacks a
/// session's model answers its images UNAVAILABLE / 503 naming the model (a load balancer tries
/// another node), while it still stores the session's bare descriptors and answers its queries;
/// the node that serves the model embeds them.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby)"]
async fn a_node_without_a_sessions_model_answers_unavailable_naming_it() {
    let dirs: Vec<_> = (0..2).map(|_| tempfile::tempdir().unwrap()).collect();
    // A serves the shipped heads as a model of a repository beside its default; B does not.
    let repo = tempfile::tempdir().unwrap();
    let folder = repo.path().join("shipped");
    std::fs::create_dir(&folder).unwrap();
    std::os::unix::fs::symlink(crate::common::root().join(loopd::cli::DEFAULT_HEADS), folder.join("heads.safetensors"))
        .unwrap();
    let manifest = serde_json::json!({"name": "shipped", "kind": "builtin", "heads": "heads.safetensors"});
    std::fs::write(folder.join("model.json"), manifest.to_string()).unwrap();
    let cfg = |dir: &std::path::Path, models: Option<&std::path::Path>| ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        cluster: Some(ClusterConfig { connections: 4, ..ClusterConfig::new(&env("LOOPD_PG_URL")) }),
        models_dir: models.map(|m| m.to_path_buf()),
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    let a = RunningServer::start(cfg(dirs[0].path(), Some(repo.path())), imagenet_model()).await.unwrap();
    let b = RunningServer::start(cfg(dirs[1].path(), None), imagenet_model()).await.unwrap();
    let (mut ga, mut gb) = (client(&a).await, client(&b).await);
    let id = "model-on-one-node";
    let _ = ga.delete_session(pb::DeleteSessionRequest { id: id.into() }).await;
    let made = ga
        .create_session(pb::CreateSessionRequest { id: id.into(), model: "shipped".into(), ..Default::default() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(made.model, "shipped");
    let through_a = ga.add_and_query(desk_frame(id, 1)).await.unwrap().into_inner();

    // B: gRPC UNAVAILABLE and HTTP 503, both naming the model and the session.
    let refused = gb.add_and_query(desk_frame(id, 2)).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unavailable, "{refused:?}");
    assert!(refused.message().contains("model 'shipped'") && refused.message().contains(id), "{}", refused.message());
    let form = reqwest::multipart::Form::new().text("robot_id", "desk").text("timestamp", "2").part(
        "image",
        reqwest::multipart::Part::bytes(std::fs::read(data("slambook2-ch11/2.png")).unwrap()).file_name("2.png"),
    );
    let http = reqwest::Client::new();
    let r = http.post(format!("http://{}/v1/sessions/{id}/frames", b.http_addr)).multipart(form).send().await.unwrap();
    assert_eq!(r.status(), 503);
    assert!(r.text().await.unwrap().contains("model 'shipped'"));

    // B still stores the session's bare descriptors (A's embedding) and answers queries by them.
    let e: serde_json::Value = http
        .post(format!("http://{}/v1/embed?model=shipped", a.http_addr))
        .body(std::fs::read(data("slambook2-ch11/10.png")).unwrap())
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let d: Vec<f32> = serde_json::from_value(e["descriptor"].clone()).unwrap();
    assert_eq!(d.len() as u32, made.dim);
    let stored = gb.add_frame(descriptor_frame(id, "desk", 10.0, &d, None)).await.unwrap().into_inner().frame_id;
    let answer = gb.query(query(id, by_descriptor(&d), 2)).await.unwrap().into_inner();
    let mut ids: Vec<u64> = answer.matches.iter().map(|m| m.frame_id).collect();
    ids.sort();
    assert_eq!(ids, [through_a.frame_id, stored], "{:?}", answer.matches);
    assert_eq!(frames_in(&mut ga, id).await, Ok(2));
    ga.delete_session(pb::DeleteSessionRequest { id: id.into() }).await.unwrap();
}
