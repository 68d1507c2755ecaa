//! Offline sequence jobs through the real server: a long job whose frames are embedded, have
//! their features extracted and their thumbnails made ahead of the frame being checked.
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::verify::pool::VerifyConfig;
use serde_json::{json, Value};
use std::time::Duration;

/// The Corridor's two traversals (ref, then query: 222 frames) as one job on a server with one
/// verification worker, as many frames in flight as the engine batches (8), and thumbnails: the
/// frames ahead extract features on the same worker the frame being checked needs. The job
/// must end (an earlier runner left the worker to a frame ahead that it did not poll, and the
/// job stopped for good, as `loopd ingest` of the same frames did in CI) and find revisits.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_long_verified_job_with_thumbnails_on_one_worker_finishes_and_finds_the_revisits() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 32, warm_up: false, ..Default::default() },
        verify: VerifyConfig { workers: 1, ..Default::default() },
        ..ServerConfig::on_loopback(dir.path().to_path_buf())
    };
    let server = RunningServer::start(cfg, shipped_model()).await.unwrap();
    let base = format!("http://{}", server.http_addr);
    let http = reqwest::Client::new();
    let r = http.post(format!("{base}/v1/sessions")).json(&json!({ "id": "corridor", "thumbnails": true })).send();
    assert_eq!(r.await.unwrap().status(), 201);
    // Every first candidate is a loop (min_confidence 0): the revisits are the descriptor's and
    // the checks', whatever the loop confidence makes of 160x120 frames.
    let mut form = reqwest::multipart::Form::new().text("order", "name").text("min_confidence", "0");
    for (traversal, prefix) in [("ref", "a"), ("query", "b")] {
        for i in 0..111 {
            let image = std::fs::read(data(&format!("corridor/{traversal}/{i:07}.jpg"))).unwrap();
            let part = reqwest::multipart::Part::bytes(image).file_name(format!("{prefix}{i:03}.jpg"));
            form = form.part("image", part);
        }
    }
    let r = http.post(format!("{base}/v1/sessions/corridor/sequences")).multipart(form).send().await.unwrap();
    assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
    let job: Value = r.json().await.unwrap();
    let url = format!("{base}{}", job["status_url"].as_str().unwrap());
    let started = std::time::Instant::now();
    let (mut status, mut last_done, mut progressed) = (Value::Null, 0, started);
    while progressed.elapsed() < Duration::from_secs(120) {
        status = http.get(&url).send().await.unwrap().json().await.unwrap();
        let done = status["done"].as_u64().unwrap();
        if done > last_done {
            (last_done, progressed) = (done, std::time::Instant::now());
        }
        if status["state"] != "running" {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert_eq!(status["state"], "done", "no frame done for 120 s: {status}");
    assert_eq!((status["done"].as_u64(), status["errors"].as_array().map(Vec::len)), (Some(222), Some(0)), "{status}");
    // Its loops are second-traversal frames revisiting the first, most of them the revisit
    // gt.csv names (query i sees reference frames near i).
    let truth = corridor_truth();
    let loops = status["loops"].as_array().unwrap();
    let revisits = loops
        .iter()
        .filter(|l| {
            let (q, m) = (l["query_name"].as_str().unwrap(), l["match_name"].as_str().unwrap());
            let (q, m): (usize, usize) = (q[1..4].parse().unwrap(), m[1..4].parse().unwrap());
            l["query_name"].as_str().unwrap().starts_with('b')
                && l["match_name"].as_str().unwrap().starts_with('a')
                && truth.get(&q).is_some_and(|t| t.contains(&m))
        })
        .count();
    assert!(revisits >= 10, "{revisits} of {} loops are Corridor revisits: {status}", loops.len());
    let thumbs = http.get(format!("{base}/v1/sessions/corridor")).send().await.unwrap();
    assert_eq!(thumbs.json::<Value>().await.unwrap()["frames"], 222);
}
