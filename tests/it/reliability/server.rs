//! Defects a fleet harness found (issue #14), each a test against the real server on loopback:
//! shutdown with open streams, gRPC latency of larger answers, a tar header claiming a terabyte,
//! one status per size limit on both APIs, and decode memory bounded in bytes.
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::model::preprocess::{decode, ImageError, ImageLimits};
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use std::time::{Duration, Instant};

const LIMITS: ImageLimits =
    ImageLimits { max_bytes: 4 << 20, max_pixels: 40_000_000, min_side: 16, max_decode_bytes: 2 << 20 };

async fn start(dir: &std::path::Path, grace: Duration) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        limits: LIMITS,
        shutdown_grace: grace,
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

/// SIGTERM's path with a robot streaming and another holding an idle stream open: both streams
/// end with UNAVAILABLE after their acknowledged frames, shutdown finishes well inside the grace
/// time, and every acknowledged frame is there after a restart.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_streams_and_keeps_every_acknowledged_frame() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), Duration::from_secs(30)).await;
    let mut c = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    c.create_session(pb::CreateSessionRequest { id: "s".into(), ..Default::default() }).await.unwrap();
    // An idle robot: one frame, then the stream stays open.
    let (idle_tx, idle_rx) = tokio::sync::mpsc::channel(4);
    idle_tx.send(corridor_frame("s", "idle", 0)).await.unwrap();
    let mut idle = c.stream_frames(tokio_stream::wrappers::ReceiverStream::new(idle_rx)).await.unwrap().into_inner();
    assert_eq!(idle.message().await.unwrap().unwrap().error, "");
    // A robot streaming at 4 fps, without end.
    let (busy_tx, busy_rx) = tokio::sync::mpsc::channel(4);
    let feeder = tokio::spawn(async move {
        for i in 1.. {
            if busy_tx.send(corridor_frame("s", "busy", i)).await.is_err() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    });
    let mut busy = c.stream_frames(tokio_stream::wrappers::ReceiverStream::new(busy_rx)).await.unwrap().into_inner();
    let mut acknowledged = 1; // the idle robot's frame
    for _ in 0..3 {
        assert_eq!(busy.message().await.unwrap().unwrap().error, "");
        acknowledged += 1;
    }
    let t = Instant::now();
    let stopping = tokio::spawn(server.shutdown());
    // Both streams end with UNAVAILABLE, the busy one possibly after a last acknowledged frame.
    let end = loop {
        match busy.message().await {
            Ok(Some(a)) => {
                assert_eq!(a.error, "");
                acknowledged += 1;
            }
            other => break other,
        }
    };
    assert_eq!(end.unwrap_err().code(), tonic::Code::Unavailable);
    assert_eq!(idle.message().await.unwrap_err().code(), tonic::Code::Unavailable);
    tokio::time::timeout(Duration::from_secs(15), stopping).await.expect("shutdown hung").unwrap().unwrap();
    let took = t.elapsed();
    assert!(took < Duration::from_secs(10), "shutdown took {took:?} with streams open (grace 30 s)");
    feeder.abort();
    drop(idle_tx);
    let server = start(dir.path(), Duration::from_secs(5)).await;
    let info = server.service.store.session("s").unwrap().info();
    assert_eq!(info.frames, acknowledged, "every acknowledged frame, nothing else");
    server.shutdown().await.unwrap();
}

/// Oversized inputs: one status per limit on both APIs, a tar entry claiming 2^40 bytes refused
/// without allocating it, decode memory bounded in bytes, small gRPC answers without a 40 ms
/// Nagle/delayed-ACK stall, and the server serving on afterwards.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_inputs_and_latency() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), Duration::from_secs(5)).await;
    let http = reqwest::Client::new();
    let url = |p: &str| format!("http://{}{p}", server.http_addr);
    let mut c = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    c.create_session(pb::CreateSessionRequest { id: "o".into(), ..Default::default() }).await.unwrap();

    // A tar entry whose (GNU base-256) size claims a terabyte, in a 2 KB upload.
    let mut header = tar::Header::new_gnu();
    header.set_path("frame.png").unwrap();
    header.set_size(1 << 40);
    header.set_mode(0o644);
    header.set_cksum();
    let mut body = header.as_bytes().to_vec();
    body.extend([0u8; 1024]);
    let r = http.post(url("/v1/sessions/o/sequences")).header("content-type", "application/x-tar").body(body);
    assert_eq!(r.send().await.unwrap().status(), 400);

    // Just over the image byte limit: 413 over HTTP, OUT_OF_RANGE over gRPC (as tonic answers a
    // message over its own limit).
    let mut big = std::fs::read(data("slambook2-ch11/1.png")).unwrap();
    big.resize((4 << 20) + 1, 0);
    let r = http.post(url("/v1/sessions/o/frames?robot_id=r&timestamp=1")).body(big.clone()).send().await.unwrap();
    assert_eq!(r.status(), 413);
    let mut req = corridor_frame("o", "r", 1);
    req.content = Some(pb::add_frame_request::Content::Image(big.into()));
    assert_eq!(c.add_frame(req).await.unwrap_err().code(), tonic::Code::OutOfRange);
    let mut huge = corridor_frame("o", "r", 1);
    huge.content = Some(pb::add_frame_request::Content::Image(vec![0u8; 5 << 20].into()));
    assert_eq!(c.add_frame(huge).await.unwrap_err().code(), tonic::Code::OutOfRange);

    // A 16-bit RGBA PNG of a real frame, upscaled: 3 MB to send, 9.8 MB to decode (limit 2 MiB),
    // while the frame itself (8-bit RGB, 0.9 MB decoded) is taken.
    let desk = image::load_from_memory(&std::fs::read(data("slambook2-ch11/1.png")).unwrap()).unwrap();
    let wide = image::DynamicImage::ImageRgba16(
        desk.resize_exact(1280, 960, image::imageops::FilterType::Triangle).to_rgba16(),
    );
    let mut png = std::io::Cursor::new(Vec::new());
    wide.write_to(&mut png, image::ImageFormat::Png).unwrap();
    let png = png.into_inner();
    assert!(png.len() < 4 << 20, "the PNG itself ({} bytes) is under the byte limit", png.len());
    let refused = decode(&png, &LIMITS);
    assert!(matches!(refused, Err(ImageError::TooMuchMemory { bytes_per_pixel: 8, .. })), "{refused:?}");
    let r = http.post(url("/v1/sessions/o/frames?robot_id=r&timestamp=1")).body(png.clone()).send().await.unwrap();
    assert_eq!(r.status(), 413);
    let fits = decode(&png, &ImageLimits { max_decode_bytes: 16 << 20, ..LIMITS });
    assert!(fits.is_ok(), "{:?}", fits.err());
    assert!(decode(&std::fs::read(data("slambook2-ch11/1.png")).unwrap(), &LIMITS).is_ok());

    // Answers above 250 bytes over gRPC (k = 10) come back without the ~40 ms stall.
    // Frames as a fleet sends them: a robot id and a pose, so ten matches are about 1 KB.
    for i in 0..12 {
        let mut f = corridor_frame("o", "warehouse-robot-07", i);
        f.pose = Some(pb::Pose { x: i as f64, y: 0.5, z: 0.1, qx: 0.0, qy: 0.0, qz: 0.38, qw: 0.92 });
        c.add_frame(f).await.unwrap();
    }
    let d = c.add_and_query(corridor_frame("o", "r", 50)).await.unwrap();
    assert!(d.into_inner().matches.len() >= 3);
    let query = |i: u64| pb::QueryRequest {
        session_id: "o".into(),
        content: Some(pb::query_request::Content::FrameId(i)),
        options: Some(pb::QueryOptions { k: Some(10), verify: Some(false), ..Default::default() }),
        ..Default::default()
    };
    let mut ms = Vec::new();
    for i in 0..30 {
        let t = Instant::now();
        let r = c.query(query(i % 12)).await.unwrap().into_inner();
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        assert_eq!(r.matches.len(), 10);
    }
    ms.sort_by(f64::total_cmp);
    eprintln!("median {:.2} ms", ms[15]);
    assert!(ms[15] < 20.0, "median gRPC query with k = 10 took {:.1} ms (Nagle + delayed ACK is ~40 ms)", ms[15]);
    assert_eq!(http.get(url("/healthz")).send().await.unwrap().status(), 200);
    server.shutdown().await.unwrap();
}

/// Offline sequence jobs are kept in sled: after a restart a finished job answers with its
/// loops, and new jobs get new ids (no reuse of a kept one).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_jobs_answer_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path(), Duration::from_secs(5)).await;
    let http = reqwest::Client::new();
    let base = format!("http://{}", server.http_addr);
    let r = http.post(format!("{base}/v1/sessions")).json(&serde_json::json!({ "id": "desk" })).send().await.unwrap();
    assert_eq!(r.status(), 201);
    let sequence = || {
        // Every first candidate scoring 0.8 is a loop here (the plain backbone's descriptors).
        let mut form = reqwest::multipart::Form::new().text("min_score", "0.8").text("min_confidence", "0");
        for i in 1..=10 {
            let bytes = std::fs::read(data(&format!("slambook2-ch11/{i}.png"))).unwrap();
            form = form.part("image", reqwest::multipart::Part::bytes(bytes).file_name(format!("{i}.png")));
        }
        form
    };
    let post = |form| http.post(format!("{base}/v1/sessions/desk/sequences")).multipart(form).send();
    let job: serde_json::Value = post(sequence()).await.unwrap().json().await.unwrap();
    let id = job["job_id"].as_str().unwrap().to_string();
    let finished = loop {
        let st: serde_json::Value =
            http.get(format!("{base}/v1/jobs/{id}")).send().await.unwrap().json().await.unwrap();
        if st["state"] != "running" {
            break st;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(finished["state"], "done");
    assert!(!finished["loops"].as_array().unwrap().is_empty(), "{finished}");
    server.shutdown().await.unwrap();

    let server = start(dir.path(), Duration::from_secs(5)).await;
    let base = format!("http://{}", server.http_addr);
    let after: serde_json::Value = http.get(format!("{base}/v1/jobs/{id}")).send().await.unwrap().json().await.unwrap();
    assert_eq!(after, finished, "the same job status after a restart");
    let post = |form| http.post(format!("{base}/v1/sessions/desk/sequences")).multipart(form).send();
    let next: serde_json::Value = post(sequence()).await.unwrap().json().await.unwrap();
    assert_ne!(next["job_id"], finished["job_id"], "a new job gets a new id");
    server.shutdown().await.unwrap();
}
