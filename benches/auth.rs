//! What keys cost on the request path (issue #13): AddAndQuery over gRPC against two servers
//! side by side in one run, one without keys and one with an admin key and a tenant (key check,
//! tenant id mapping, quota bucket), interleaved call by call so machine drift hits both.
//! Descriptor frames (no forward pass), so the difference is not buried under inference.
//! env: LOOPD_BENCH_CALLS (per server, default 3000), LOOPD_BENCH_FRAMES (map size, default 2000)
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::auth::AuthConfig;
use loopd::engine::EngineConfig;
use loopd::model::config::ModelConfig;
use loopd::model::device::DType;
use loopd::model::Model;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use std::time::{Duration, Instant};

const ADMIN: &str = "admin-key-for-the-auth-bench-0123456789";

fn env(name: &str, default: usize) -> usize {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

type WithKey = Box<dyn FnMut(tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> + Send>;

async fn start(dir: &std::path::Path, keys: bool) -> anyhow::Result<RunningServer> {
    let model = Model::new(ModelConfig::default(), tch::Device::Cpu, DType::F32)?;
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 1, warm_up: false, ..Default::default() },
        auth: AuthConfig { admin_key: keys.then(|| ADMIN.to_string()), ..Default::default() },
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, model).await
}

fn frame(i: usize, dim: usize) -> pb::AddFrameRequest {
    pb::AddFrameRequest {
        session_id: "bench".into(),
        robot_id: "r".into(),
        timestamp: Some(i as f64),
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
            values: (0..dim).map(|k| ((k * 31 + i * 17) % 101) as f32 - 50.0).collect(),
            ..Default::default()
        })),
        options: Some(pb::QueryOptions { k: Some(5), ..Default::default() }),
        ..Default::default()
    }
}

async fn client(
    addr: std::net::SocketAddr,
    key: Option<String>,
) -> anyhow::Result<LoopdClient<tonic::service::interceptor::InterceptedService<tonic::transport::Channel, WithKey>>> {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))?.connect().await?;
    let header = key.map(|k| format!("Bearer {k}").parse::<tonic::metadata::MetadataValue<_>>()).transpose()?;
    let add: WithKey = Box::new(move |mut req| {
        if let Some(h) = &header {
            req.metadata_mut().insert("authorization", h.clone());
        }
        Ok(req)
    });
    Ok(LoopdClient::with_interceptor(channel, add))
}

fn pct(v: &mut [Duration], p: f64) -> f64 {
    v.sort();
    v[((v.len() - 1) as f64 * p) as usize].as_secs_f64() * 1e6
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let (calls, frames) = (env("LOOPD_BENCH_CALLS", 3000), env("LOOPD_BENCH_FRAMES", 2000));
    let (d1, d2) = (tempfile::tempdir()?, tempfile::tempdir()?);
    let open = start(d1.path(), false).await?;
    let keyed = start(d2.path(), true).await?;
    let dim = open.service.engine().info().dim;
    // A tenant with a rate limit far above the bench's, so its bucket is checked on every call.
    let tenant: serde_json::Value = reqwest::Client::new()
        .post(format!("http://{}/v1/tenants", keyed.http_addr))
        .bearer_auth(ADMIN)
        .json(&serde_json::json!({ "name": "bench", "limits": { "rate": 1e6 } }))
        .send()
        .await?
        .json()
        .await?;
    let key = tenant["key"].as_str().unwrap_or_default().to_string();
    let mut a = client(open.grpc_addr, None).await?;
    let mut b = client(keyed.grpc_addr, Some(key)).await?;
    for c in [&mut a, &mut b] {
        c.create_session(pb::CreateSessionRequest { id: "bench".into(), ..Default::default() }).await?;
        for i in 0..frames {
            c.add_frame(frame(i, dim)).await?;
        }
    }
    let (mut ta, mut tb) = (Vec::with_capacity(calls), Vec::with_capacity(calls));
    for i in 0..calls {
        for (c, t) in [(&mut a, &mut ta), (&mut b, &mut tb)] {
            let s = Instant::now();
            c.add_and_query(frame(frames + i, dim)).await?;
            t.push(s.elapsed());
        }
        // The other server goes first next time (each keeps its own timings).
        std::mem::swap(&mut a, &mut b);
        std::mem::swap(&mut ta, &mut tb);
    }
    if calls % 2 == 1 {
        std::mem::swap(&mut ta, &mut tb); // back to: ta the server without keys
    }
    let (a50, b50, a99, b99) = (pct(&mut ta, 0.5), pct(&mut tb, 0.5), pct(&mut ta, 0.99), pct(&mut tb, 0.99));
    println!("AddAndQuery over gRPC, descriptor frames, {frames}-frame map, {calls} calls each, interleaved");
    println!("| server | p50 µs | p99 µs |");
    println!("|---|---:|---:|");
    println!("| no keys | {a50:.0} | {a99:.0} |");
    println!("| tenant key (+ key check, id mapping, rate bucket) | {b50:.0} | {b99:.0} |");
    println!("| keys / no keys | {:.3} | {:.3} |", b50 / a50, b99 / a99);
    open.shutdown().await?;
    keyed.shutdown().await?;
    Ok(())
}
