//! loopd nodes on the cluster log (`serve --cluster`, issue #17) against one sled node, side by
//! side in one run, over gRPC on loopback with 2,048-d f16 descriptors:
//! * durable frames/s from 16 concurrent clients sending one frame per call;
//! * query latency p50/p99 from one client (k = 5, no verification), interleaved between the
//!   two; through the cluster node each query first brings the session up to the log's version;
//! * the cold load of a session: a node that never saw it answering its first request, against
//!   sled rebuilding the same frames' index when it opens.
//!
//! Run through `scripts/pg-replicated bench` (it starts PostgreSQL with a synchronous standby and
//! sets LOOPD_PG_URL). env: LOOPD_BENCH_FRAMES (writes per node, default 4000),
//! LOOPD_BENCH_QUERIES (default 2000), LOOPD_BENCH_COLD_FRAMES (default 100000).
mod common;
use common::{descriptor, frame, meta, new_session, WRITERS};
use indicatif::ProgressBar;
use loopd::api::server::{ClusterConfig, RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::model::config::ModelConfig;
use loopd::model::device::DType;
use loopd::model::Model;
use loopd::pb::{self, loopd_client::LoopdClient};
use loopd::store::pg::{LogConfig, PgLog, Replication};
use loopd::store::{NewFrame, Store};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

type Client = LoopdClient<tonic::transport::Channel>;

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

async fn node(dir: &Path, url: Option<&str>) -> anyhow::Result<RunningServer> {
    let weights = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("weights/resnet50-imagenet.safetensors");
    let (model, _) = Model::load(&weights, ModelConfig::default(), tch::Device::Cpu, DType::F32)?;
    let cfg = ServerConfig {
        engine: EngineConfig { warm_up: false, ..Default::default() },
        cluster: url.map(|u| ClusterConfig { connections: WRITERS, ..ClusterConfig::new(u) }),
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, model).await
}

async fn client(s: &RunningServer) -> anyhow::Result<Client> {
    Ok(LoopdClient::connect(format!("http://{}", s.grpc_addr)).await?)
}

fn add(session: &str, i: usize) -> pb::AddFrameRequest {
    pb::AddFrameRequest {
        session_id: session.into(),
        robot_id: format!("robot{}", i % WRITERS),
        timestamp: Some(i as f64),
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
            values: descriptor(i),
            ..Default::default()
        })),
        ..Default::default()
    }
}

/// Frames/s of `n` frames sent by WRITERS concurrent clients, one frame per call.
async fn write(g: &Client, session: &str, n: usize) -> f64 {
    let t = Instant::now();
    let tasks: Vec<_> = (0..WRITERS)
        .map(|w| {
            let (mut g, session) = (g.clone(), session.to_string());
            tokio::spawn(async move {
                for i in (w..n).step_by(WRITERS) {
                    g.add_frame(add(&session, i)).await.expect("add_frame");
                }
            })
        })
        .collect();
    for t in tasks {
        t.await.expect("writer");
    }
    n as f64 / t.elapsed().as_secs_f64()
}

async fn query(g: &mut Client, session: &str, i: usize) -> Duration {
    let r = pb::QueryRequest {
        session_id: session.into(),
        content: Some(pb::query_request::Content::Descriptor(pb::Descriptor {
            values: descriptor(i),
            ..Default::default()
        })),
        options: Some(pb::QueryOptions { k: Some(5), verify: Some(false), ..Default::default() }),
        ..Default::default()
    };
    let t = Instant::now();
    g.query(r).await.expect("query");
    t.elapsed()
}

fn pct(v: &mut [Duration], p: f64) -> f64 {
    v.sort();
    v[((v.len() - 1) as f64 * p).round() as usize].as_secs_f64() * 1e3
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let (n, queries, cold) = (
        env_usize("LOOPD_BENCH_FRAMES", 4000),
        env_usize("LOOPD_BENCH_QUERIES", 2000),
        env_usize("LOOPD_BENCH_COLD_FRAMES", 100_000),
    );
    let url = std::env::var("LOOPD_PG_URL").map_err(|_| anyhow::anyhow!("run through scripts/pg-replicated bench"))?;
    let dirs = [tempfile::tempdir()?, tempfile::tempdir()?, tempfile::tempdir()?];
    let (cluster, sled) = (node(dirs[0].path(), Some(&url)).await?, node(dirs[1].path(), None).await?);
    let (mut gc, mut gs) = (client(&cluster).await?, client(&sled).await?);
    for g in [&mut gc, &mut gs] {
        g.create_session(pb::CreateSessionRequest { id: "bench".into(), ..Default::default() }).await?;
    }

    println!("| measure | cluster node | sled node | cluster / sled |");
    println!("|---|---:|---:|---:|");
    let (c, s) = (write(&gc, "bench", n).await, write(&gs, "bench", n).await);
    println!("| durable frames/s, {WRITERS} clients x 1 frame per call, {n} frames | {c:.0} | {s:.0} | {:.2} |", c / s);

    let (mut on_cluster, mut on_sled) = (Vec::with_capacity(queries), Vec::with_capacity(queries));
    for i in 0..queries {
        on_cluster.push(query(&mut gc, "bench", i % n).await);
        on_sled.push(query(&mut gs, "bench", i % n).await);
    }
    for (name, p) in [("p50", 0.5), ("p99", 0.99)] {
        let (c, s) = (pct(&mut on_cluster, p), pct(&mut on_sled, p));
        println!("| query {name} ms, {n} frames, k = 5 | {c:.2} | {s:.2} | {:.2} |", c / s);
    }

    // Cold load: the frames go straight to the log (and to a sled folder), then a new node
    // answers its first request on that session, and sled reopens its folder.
    let log = PgLog::connect(&url, LogConfig::new(4, Replication::Synchronous)).await?;
    log.create_session(&meta("cold")).await?;
    let store = Store::open(dirs[2].path())?;
    let session = store.create_session(Some("cold".into()), new_session("cold")).await?;
    let session = store.session(&session.id)?;
    let bar = ProgressBar::new(cold as u64);
    for start in (0..cold).step_by(512) {
        let frames: Vec<NewFrame> = (start..(start + 512).min(cold)).map(frame).collect();
        log.append(&meta("cold"), &frames).await?;
        store.add_frames(&session, frames).await?;
        bar.inc(512);
    }
    bar.finish_and_clear();
    drop((session, store));
    let dir = tempfile::tempdir()?;
    let newcomer = node(dir.path(), Some(&url)).await?;
    let mut gn = client(&newcomer).await?;
    let t = Instant::now();
    let held = gn.get_session(pb::GetSessionRequest { id: "cold".into() }).await?.into_inner().frames;
    let c = t.elapsed().as_secs_f64();
    assert_eq!(held, cold as u64, "the new node holds every frame");
    let t = Instant::now();
    let reopened = Store::open(dirs[2].path())?;
    let s = t.elapsed().as_secs_f64();
    assert_eq!(reopened.session("cold")?.info().frames, cold);
    println!(
        "| cold load s, {cold} frames (first request on a new node / sled open) | {c:.2} | {s:.2} | {:.2} |",
        c / s
    );
    log.delete_session("cold").await?;
    gc.delete_session(pb::DeleteSessionRequest { id: "bench".into() }).await?;
    Ok(())
}
