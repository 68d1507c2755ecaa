//! A database failover under two loopd nodes (issue #17, `serve --cluster`): the PostgreSQL
//! primary and synchronous standby of `scripts/pg-replicated`, which runs this last (`--ignored`:
//! it needs that database, and it leaves the standby promoted). The nodes' URL names both servers
//! with `target_session_attrs=read-write`.
//!
//! The case a cache gets wrong: with the standby stopped, a frame written through A commits on the
//! primary and waits there for a standby. Its connection is terminated while it waits (as a
//! pooler or a shutdown does): the write fails, never acknowledged, but the primary keeps the
//! local commit and shows it, so node B reads the frame and answers with it. The primary then dies
//! and the standby, which never had the frame, is promoted. Asserted: the write is never
//! acknowledged; B and A then answer without the frame and hold exactly the acknowledged ones;
//! and writes are refused while the new primary has no synchronous standby. Then the old primary
//! starts again, writable on its old timeline: the nodes refuse it rather than serve its frames.
use crate::common::pg::{env, pg_ctl, psql};
use crate::common::{data, imagenet_model};
use loopd::api::server::{ClusterConfig, RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::pb::{self, loopd_client::LoopdClient};
use std::time::{Duration, Instant};
use tonic::Code;

type Client = LoopdClient<tonic::transport::Channel>;

async fn node(dir: &std::path::Path, url: &str) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        // One probe of the log, at start: this test needs a write that reaches the primary in the
        // moment between the standby's loss and the node's next probe (which would refuse it at
        // once, `a_write_past_the_deadline_is_unavailable_and_a_gone_standby_refuses_writes_at_once`),
        // so that the write waits for a standby there.
        cluster: Some(ClusterConfig {
            connections: 4,
            tenant_refresh: Duration::from_secs(3600),
            ..ClusterConfig::new(url)
        }),
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

fn frame(t: f64, d: &[f32], id: u64) -> pb::AddFrameRequest {
    pb::AddFrameRequest {
        session_id: "failover".into(),
        robot_id: "r0".into(),
        timestamp: Some(t),
        frame_id: Some(id),
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
            values: d.to_vec(),
            ..Default::default()
        })),
        ..Default::default()
    }
}

/// The ids a descriptor query answers (no exclusion window, no verification), and whether the
/// node flagged the answer stale.
async fn answer(g: &mut Client, d: &[f32]) -> Result<(Vec<u64>, bool), Code> {
    let r = pb::QueryRequest {
        session_id: "failover".into(),
        content: Some(pb::query_request::Content::Descriptor(pb::Descriptor {
            values: d.to_vec(),
            ..Default::default()
        })),
        options: Some(pb::QueryOptions {
            k: Some(20),
            verify: Some(false),
            exclude_last_frames: Some(0),
            exclude_last_seconds: Some(0.0),
            ..Default::default()
        }),
        ..Default::default()
    };
    let r = g.query(r).await.map_err(|e| e.code())?;
    let stale = r.metadata().get("loopd-stale").is_some();
    Ok((r.into_inner().matches.iter().map(|m| m.frame_id).collect(), stale))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "needs scripts/pg-replicated (PostgreSQL primary + synchronous standby); promotes the standby"]
async fn after_a_failover_no_node_serves_a_frame_the_new_primary_lacks() {
    let url = format!(
        "postgres://postgres@127.0.0.1:{},127.0.0.1:{}/loopd?target_session_attrs=read-write",
        env("LOOPD_PG_PRIMARY_PORT"),
        env("LOOPD_PG_STANDBY_PORT")
    );
    let dirs: Vec<_> = (0..2).map(|_| tempfile::tempdir().unwrap()).collect();
    let (a, b) = (node(dirs[0].path(), &url).await, node(dirs[1].path(), &url).await);
    let mut ga = LoopdClient::connect(format!("http://{}", a.grpc_addr)).await.unwrap();
    let mut gb = LoopdClient::connect(format!("http://{}", b.grpc_addr)).await.unwrap();

    // Real descriptors: 6 corridor frames embedded by A; frames 0..5 acknowledged.
    let http = reqwest::Client::new();
    let mut descriptors: Vec<Vec<f32>> = Vec::new();
    for i in 0..6 {
        let image = std::fs::read(data(&format!("corridor/ref/{:07}.jpg", i * 10))).unwrap();
        let r = http.post(format!("http://{}/v1/embed", a.http_addr)).body(image).send().await.unwrap();
        let v: serde_json::Value = r.json().await.unwrap();
        descriptors.push(serde_json::from_value(v["descriptor"].clone()).unwrap());
    }
    ga.create_session(pb::CreateSessionRequest { id: "failover".into(), ..Default::default() }).await.unwrap();
    for (i, d) in descriptors.iter().take(5).enumerate() {
        ga.add_frame(frame(i as f64, d, i as u64)).await.unwrap();
    }
    let (acked, _) = answer(&mut gb, &descriptors[5]).await.unwrap();
    assert_eq!(acked.len(), 5);

    // The standby stops: frame 777 commits on the primary and waits there for a standby, not
    // acknowledged. Its connection is then terminated (as a pooler or a shutdown would): the write
    // fails, but the primary keeps its local commit, visible from then on.
    let (primary, standby) = (env("LOOPD_PG_PRIMARY"), env("LOOPD_PG_STANDBY"));
    pg_ctl(&standby, &["stop", "-m", "fast"]);
    let pending = tokio::spawn({
        let mut ga = ga.clone();
        let d = descriptors[5].clone();
        async move { ga.add_frame(frame(5.0, &d, 777)).await }
    });
    let t = Instant::now();
    while psql("SELECT count(*) FROM pg_stat_activity WHERE wait_event = 'SyncRep'") != "1" {
        assert!(t.elapsed() < Duration::from_secs(20), "the write never waited for a standby");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(!pending.is_finished(), "frame 777 was acknowledged without a synchronous standby");
    psql("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE wait_event = 'SyncRep'");
    let failed = tokio::time::timeout(Duration::from_secs(30), pending).await.expect("the write ends").unwrap();
    assert_eq!(failed.map(|_| ()).unwrap_err().code(), Code::Unavailable, "never acknowledged");
    // B reads frame 777 from the primary and answers with it.
    let (ids, _) = answer(&mut gb, &descriptors[5]).await.unwrap();
    assert!(ids.contains(&777), "B answers with the frame the primary holds: {ids:?}");

    // The primary dies; the standby, which never had frame 777, is promoted.
    pg_ctl(&primary, &["stop", "-m", "immediate"]);
    pg_ctl(&standby, &["start", "-l", &format!("{standby}.log")]);
    pg_ctl(&standby, &["promote"]);

    // Both nodes answer from the new primary, without frame 777, once they reach it.
    for (name, g) in [("B", &mut gb), ("A", &mut ga)] {
        let t = Instant::now();
        let ids = loop {
            match answer(g, &descriptors[5]).await {
                Ok((ids, false)) => break ids,
                Ok((_, true)) | Err(Code::Unavailable) => {}
                Err(code) => panic!("{name}: {code:?}"),
            }
            assert!(t.elapsed() < Duration::from_secs(30), "{name} did not reach the new primary in 30 s");
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        assert!(!ids.contains(&777), "{name} still serves frame 777, which the new primary lacks: {ids:?}");
        let mut sorted = ids.clone();
        sorted.sort();
        assert_eq!(sorted, [0, 1, 2, 3, 4], "{name} holds exactly the acknowledged frames");
        let by_id = pb::QueryRequest {
            session_id: "failover".into(),
            content: Some(pb::query_request::Content::FrameId(777)),
            ..Default::default()
        };
        assert_eq!(g.query(by_id).await.unwrap_err().code(), Code::NotFound, "{name}: frame 777");
    }
    // The new primary has no synchronous standby: writes are refused, not acknowledged at risk.
    let refused = ga.add_frame(frame(6.0, &descriptors[5], 6)).await.map(|_| ()).unwrap_err();
    assert_eq!(refused.code(), Code::Unavailable);
    assert!(refused.message().contains("synchronous standby"), "{}", refused.message());

    // Fencing (issue #34): the old primary starts again, writable on its old timeline and still
    // holding frame 777, first in the nodes' URL. Their connections to the new primary are cut,
    // so their next ones reach the old primary: each node refuses it (a timeline older than it
    // has seen) instead of taking it as a primary change and serving frame 777 again.
    pg_ctl(&primary, &["start", "-l", &format!("{primary}.log")]);
    let new_primary = format!("postgres://postgres@127.0.0.1:{}/loopd", env("LOOPD_PG_STANDBY_PORT"));
    let cut = "SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity \
               WHERE backend_type = 'client backend' AND pid <> pg_backend_pid()";
    let out = std::process::Command::new("psql").args([&new_primary, "-tAc", cut]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(5) {
        for (name, g) in [("B", &mut gb), ("A", &mut ga)] {
            match answer(g, &descriptors[5]).await {
                Ok((ids, _)) => assert!(!ids.contains(&777), "{name} took the old primary: it serves frame 777"),
                Err(Code::Unavailable) => {}
                Err(code) => panic!("{name}: {code:?}"),
            }
        }
        match ga.add_frame(frame(7.0, &descriptors[5], 7)).await {
            Err(e) if e.code() == Code::Unavailable => {}
            other => panic!("a write with the old primary back answered {other:?}"),
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    pg_ctl(&primary, &["stop", "-m", "fast"]);
}
