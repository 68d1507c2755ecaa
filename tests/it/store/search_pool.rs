//! Loop searches run on a bounded pool of blocking threads, never on the request executor:
//! health checks answer promptly while large searches keep every core busy.
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::api::service::CreateSession;
use loopd::engine::EngineConfig;
use loopd::index::Storage;
use loopd::model::network::Variant;
use loopd::store::NewFrame;
use std::time::{Duration, Instant};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[test]
fn health_checks_answer_while_large_searches_run() {
    // The server's own runtime: two request workers, as on a two-core machine.
    let server_rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let client_rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (server, descriptors) = server_rt.block_on(async {
        let cfg = ServerConfig {
            engine: EngineConfig { max_batch: 8, warm_up: false, ..Default::default() },
            ..ServerConfig::on_loopback(dir.path().to_path_buf())
        };
        let server = RunningServer::start(cfg, imagenet_model()).await.unwrap();
        let svc = &server.service;
        let mut descriptors = Vec::new();
        for i in 0..16 {
            let image = std::fs::read(data(&format!("corridor/ref/{:07}.jpg", i * 7))).unwrap();
            descriptors.push(svc.embed(image.into(), Variant::FULL, None).await.unwrap().1);
        }
        let create = CreateSession { id: Some("big".into()), storage: Storage::F32, ..Default::default() };
        svc.create_session(create).await.unwrap();
        // A large map (30,000 keyframes of real descriptors, 240 MB of f32 rows): each search
        // scans it for tens of milliseconds.
        let s = svc.store.session("big").unwrap();
        for chunk in 0..30 {
            let frames = (0..1000)
                .map(|i| NewFrame {
                    frame_id: None,
                    robot_id: format!("r{}", i % 4),
                    timestamp: (chunk * 1000 + i) as f64,
                    pose: None,
                    metadata: None,
                    descriptor: descriptors[i % descriptors.len()].clone(),
                    features: None,
                    thumbnail: None,
                    idempotency_key: None,
                })
                .collect();
            svc.store.add_frames(&s, frames).await.unwrap();
        }
        (server, descriptors)
    });
    let base = format!("http://{}", server.http_addr);
    let (solo, health) = client_rt.block_on(async move {
        let http = reqwest::Client::new();
        let (client, url, descriptors) =
            (http.clone(), format!("{base}/v1/sessions/big/query"), std::sync::Arc::new(descriptors));
        let query = move |i: usize| {
            let (http, url) = (client.clone(), url.clone());
            let body = serde_json::json!({ "descriptor": descriptors[i % descriptors.len()], "options": { "k": 5 } });
            async move {
                let t = Instant::now();
                let r = http.post(url).json(&body).send().await.unwrap();
                assert_eq!(r.status(), 200);
                t.elapsed().as_secs_f64()
            }
        };
        // One search at a time: how long a search takes here.
        let mut solo = Vec::new();
        for i in 0..9 {
            solo.push(query(i).await);
        }
        // Six robots searching back to back for four seconds, and a health probe.
        let stop = Instant::now() + Duration::from_secs(4);
        let load: Vec<_> = (0..6)
            .map(|c| {
                let query = query.clone();
                tokio::spawn(async move {
                    let mut n = 0;
                    while Instant::now() < stop {
                        query(c + n).await;
                        n += 1;
                    }
                    n
                })
            })
            .collect();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let mut health = Vec::new();
        while Instant::now() < stop {
            let t = Instant::now();
            let r = http.get(format!("{base}/healthz")).send().await.unwrap();
            assert_eq!(r.status(), 200);
            health.push(t.elapsed().as_secs_f64());
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
        let searches: usize = futures::future::join_all(load).await.into_iter().map(Result::unwrap).sum();
        assert!(searches > 12, "only {searches} searches ran under load");
        (median(solo), median(health))
    });
    eprintln!("one search alone: {:.1} ms; health check under load: {:.2} ms", solo * 1e3, health * 1e3);
    // On the executor a health check waits for a search to finish; off it, it does not.
    assert!(
        health < solo / 2.0,
        "health checks took {:.1} ms under load; a search alone takes {:.1} ms",
        health * 1e3,
        solo * 1e3
    );
    server_rt.block_on(server.shutdown()).unwrap();
}
