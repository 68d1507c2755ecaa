//! Verified loops through the real server on 127.0.0.1 (HTTP and gRPC clients) on real frames,
//! and `loopd eval --verify geometric` giving the server's verified matches.
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use serde_json::{json, Value};

async fn start(dir: &std::path::Path) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

fn image(path: &str) -> Vec<u8> {
    std::fs::read(data(path)).unwrap()
}

/// The desk loop (10.png closes on 1.png): each frame sent as a robot sends keyframes, the loop
/// verified with many inliers, by image, by stored frame, and by `loopd eval` the same way.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_desk_loop_is_verified_and_eval_agrees_with_the_server() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path()).await;
    let http = reqwest::Client::new();
    let url = |p: &str| format!("http://{}{p}", server.http_addr);
    let r = http.post(url("/v1/sessions")).json(&json!({ "id": "desk", "storage": "f32" })).send().await.unwrap();
    assert_eq!(r.status(), 201);
    // The protocol of `loopd eval --exclude 2`: each frame queries the frames before its last two.
    let mut answers = Vec::new();
    for i in 1..=10 {
        let form = reqwest::multipart::Form::new()
            .part("image", reqwest::multipart::Part::bytes(image(&format!("slambook2-ch11/{i}.png"))))
            .text("robot_id", "cam")
            .text("timestamp", i.to_string())
            .text("options", r#"{"k": 1, "exclude_last_frames": 2}"#);
        let r = http.post(url("/v1/sessions/desk/add_and_query")).multipart(form).send().await.unwrap();
        assert_eq!(r.status(), 200);
        answers.push(r.json::<Value>().await.unwrap());
    }
    let loop_answer = &answers[9]["matches"][0];
    assert_eq!(loop_answer["frame_id"], answers[0]["frame_id"], "{}", answers[9]);
    let v = &loop_answer["verification"];
    assert_eq!(v["verified"], true, "{v}");
    assert!(v["inliers"].as_u64().unwrap() >= 60, "{v}");
    assert!(v["inlier_ratio"].as_f64().unwrap() > 0.3, "{v}");
    assert!(v.get("relative_pose").is_none(), "no camera, no pose: {v}");

    // `loopd eval` on the same frames: the same best match and the same inliers, query by query.
    let gt = root().join("tests/gt/desk.csv");
    let out = tokio::task::spawn_blocking(move || {
        loopd_bin()
            .args(["eval", "--sequence", data("slambook2-ch11").to_str().unwrap(), "--gt", gt.to_str().unwrap()])
            .args(["--exclude", "2", "--verify", "geometric", "--json", "--cache-dir"])
            .arg(tempfile::tempdir().unwrap().keep())
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["recall_at_100_precision"], 1.0, "{report}");
    let best = report["best"].as_array().unwrap();
    for (i, answer) in answers.iter().enumerate() {
        let server_best = answer["matches"].as_array().unwrap().first();
        match (server_best, best[i].as_array()) {
            (None, None) => {}
            (Some(m), Some(e)) => {
                assert_eq!(m["frame_id"], e[0], "query {i}: server {m}, eval {e:?}");
                let server_inliers = match &m["verification"] {
                    v if v["verified"] == true => v["inliers"].as_f64().unwrap(),
                    _ => 0.0,
                };
                let eval_inliers = e[1].as_f64().map(|s| if s > 1.5 { (s - 1.0).floor() } else { 0.0 }).unwrap();
                assert_eq!(server_inliers, eval_inliers, "query {i}: server {m}, eval {e:?}");
            }
            (s, e) => panic!("query {i}: server {s:?}, eval {e:?}"),
        }
    }

    // Query by the stored loop frame over gRPC: its stored features verify the loop again.
    let mut grpc = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    let by_frame = pb::QueryRequest {
        session_id: "desk".into(),
        robot_id: "cam".into(),
        content: Some(pb::query_request::Content::FrameId(answers[9]["frame_id"].as_u64().unwrap())),
        options: Some(pb::QueryOptions { k: Some(2), ..Default::default() }),
        ..Default::default()
    };
    let m = grpc.query(by_frame).await.unwrap().into_inner().matches;
    assert_eq!(m[0].frame_id, answers[0]["frame_id"].as_u64().unwrap());
    let v = m[0].verification.as_ref().unwrap();
    assert!(v.verified && v.inliers >= 60 && v.reason.is_empty(), "{v:?}");
    // A descriptor query has no image to check with: it says so, and still ranks by cosine.
    let d: Value =
        http.post(url("/v1/embed")).body(image("slambook2-ch11/10.png")).send().await.unwrap().json().await.unwrap();
    let r: Value = post_json(
        &http,
        url("/v1/sessions/desk/query"),
        &json!({ "descriptor": d["descriptor"], "options": { "k": 1 } }),
    )
    .await;
    let v = &r["matches"][0]["verification"];
    assert_eq!(v["verified"], false);
    assert!(v["reason"].as_str().unwrap().contains("no image"), "{v}");
    // Switched off per query: no verification at all.
    let r: Value = post_json(
        &http,
        url("/v1/sessions/desk/query"),
        &json!({ "descriptor": d["descriptor"], "options": { "k": 1, "verify": false } }),
    )
    .await;
    assert!(r["matches"][0].get("verification").is_none(), "{r}");
    server.shutdown().await.unwrap();
}

/// EuRoC loops with the camera's intrinsics: verified with a relative rotation close to the
/// ground truth's (37.5 degrees between left_img_1 and left_img_0).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn euroc_loops_carry_the_relative_pose_over_grpc() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path()).await;
    let mut grpc = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    let camera = pb::Camera {
        fx: 458.654,
        fy: 457.296,
        cx: 367.215,
        cy: 248.375,
        distortion: vec![-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0],
        depth_scale: None,
        stereo: None,
    };
    grpc.create_session(pb::CreateSessionRequest { id: "euroc".into(), camera: Some(camera), ..Default::default() })
        .await
        .unwrap();
    let frame = |i: usize| pb::AddFrameRequest {
        session_id: "euroc".into(),
        robot_id: "mav".into(),
        timestamp: Some(i as f64),
        content: Some(pb::add_frame_request::Content::Image(image(&format!("euroc-lcd/left_img_{i}.png")).into())),
        options: Some(pb::QueryOptions { k: Some(2), ..Default::default() }),
        ..Default::default()
    };
    let first = grpc.add_frame(frame(0)).await.unwrap().into_inner().frame_id;
    let other = grpc.add_frame(frame(2)).await.unwrap().into_inner().frame_id;
    let answer = grpc.add_and_query(frame(1)).await.unwrap().into_inner();
    assert_eq!(answer.matches[0].frame_id, first);
    let v = answer.matches[0].verification.as_ref().unwrap();
    assert!(v.verified, "{v:?}");
    let p = v.relative_pose.as_ref().expect("a verified loop with a camera has a pose");
    let angle = 2.0 * p.qw.clamp(-1.0, 1.0).acos().to_degrees();
    assert!((angle - 37.5).abs() < 4.0, "relative rotation {angle:.1} degrees, ground truth 37.5");
    let t = (p.tx * p.tx + p.ty * p.ty + p.tz * p.tz).sqrt();
    assert!((t - 1.0).abs() < 1e-6, "unit translation direction, got |t| = {t}");
    // The non-loop candidate is checked and rejected, with its reason.
    let rejected = answer.matches.iter().find(|m| m.frame_id == other).unwrap();
    let v = rejected.verification.as_ref().unwrap();
    assert!(!v.verified && !v.reason.is_empty() && v.relative_pose.is_none(), "{v:?}");
    server.shutdown().await.unwrap();
}

/// Wrong cameras and options are refused with INVALID_ARGUMENT / 400; frames without texture are
/// stored and simply not verified, with the reason.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_verification_input_gets_clear_answers() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path()).await;
    let http = reqwest::Client::new();
    let url = |p: &str| format!("http://{}{p}", server.http_addr);
    for camera in [
        json!({ "fx": 0.0, "fy": 500.0, "cx": 320.0, "cy": 240.0 }),
        json!({ "fx": -1.0, "fy": 500.0, "cx": 320.0, "cy": 240.0 }),
        json!({ "fx": 500.0, "fy": 500.0, "cx": 320.0 }),
    ] {
        let r = http.post(url("/v1/sessions")).json(&json!({ "id": "cam", "camera": camera })).send().await.unwrap();
        assert_eq!(r.status(), 400, "{camera}");
    }
    let mut grpc = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    let bad =
        pb::Camera { fx: f64::NAN, fy: 1.0, cx: 0.0, cy: 0.0, distortion: vec![], depth_scale: None, stereo: None };
    let status = grpc
        .create_session(pb::CreateSessionRequest { id: "cam".into(), camera: Some(bad), ..Default::default() })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    let short =
        pb::Camera { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0, distortion: vec![0.1, 0.2], depth_scale: None, stereo: None };
    let status = grpc
        .create_session(pb::CreateSessionRequest { id: "cam".into(), camera: Some(short), ..Default::default() })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    assert_eq!(http.post(url("/v1/sessions")).json(&json!({ "id": "s" })).send().await.unwrap().status(), 201);
    let send = |path: &str, body: Vec<u8>, options: &str| {
        let form = reqwest::multipart::Form::new()
            .part("image", reqwest::multipart::Part::bytes(body))
            .text("robot_id", "r")
            .text("timestamp", "1")
            .text("options", options.to_string());
        http.post(url(path)).multipart(form).send()
    };
    for options in [r#"{"verify_candidates": 0}"#, r#"{"verify_candidates": 51}"#, r#"{"min_inliers": 5}"#] {
        let r = send("/v1/sessions/s/add_and_query", image("slambook2-ch11/1.png"), options).await.unwrap();
        assert_eq!(r.status(), 400, "{options}");
    }
    // A blank, over-exposed frame: stored, searchable, never verified.
    let mut png = std::io::Cursor::new(Vec::new());
    image::RgbImage::from_pixel(640, 480, image::Rgb([255, 255, 255]))
        .write_to(&mut png, image::ImageFormat::Png)
        .unwrap();
    let blank = png.into_inner();
    let r = send("/v1/sessions/s/add_and_query", blank.clone(), "{}").await.unwrap();
    assert_eq!(r.status(), 200);
    let r: Value = send("/v1/sessions/s/add_and_query", blank, "{}").await.unwrap().json().await.unwrap();
    let v = &r["matches"][0]["verification"];
    assert_eq!(v["verified"], false, "{r}");
    assert!(v["reason"].as_str().unwrap().contains("too few features"), "{v}");
    let info: Value = http.get(url("/v1/sessions/s")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["frames"], 2);
    server.shutdown().await.unwrap();
}

/// Sequence verification through the server (two robots on the Corridor, the visitor's frames
/// checked by the frames that led up to them) gives `loopd eval --verify sequence`'s best match
/// for every query frame.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sequence_verification_agrees_with_eval_on_the_corridor() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path()).await;
    let mut grpc = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    grpc.create_session(pb::CreateSessionRequest {
        id: "corridor".into(),
        storage: pb::Storage::F32 as i32,
        ..Default::default()
    })
    .await
    .unwrap();
    let options = pb::QueryOptions {
        k: Some(1),
        scope: pb::Scope::OtherRobots as i32,
        verify: Some(false),
        sequence: Some(true),
        sequence_length: Some(10),
        ..Default::default()
    };
    let stream = |robot: &'static str, dir: &'static str| {
        let mut grpc = grpc.clone();
        async move {
            let frames: Vec<pb::AddFrameRequest> = (0..111)
                .map(|i| pb::AddFrameRequest {
                    session_id: "corridor".into(),
                    robot_id: robot.into(),
                    timestamp: Some(i as f64),
                    content: Some(pb::add_frame_request::Content::Image(
                        image(&format!("corridor/{dir}/{i:07}.jpg")).into(),
                    )),
                    options: Some(options),
                    ..Default::default()
                })
                .collect();
            let mut answers = grpc.stream_frames(tokio_stream::iter(frames)).await.unwrap().into_inner();
            let mut out = Vec::new();
            while let Some(a) = answers.message().await.unwrap() {
                assert_eq!(a.error, "");
                out.push(a);
            }
            out
        }
    };
    let mapper = stream("mapper", "ref").await;
    let visitor = stream("visitor", "query").await;
    let position: std::collections::HashMap<u64, usize> =
        mapper.iter().enumerate().map(|(i, a)| (a.frame_id, i)).collect();
    let gt = data("corridor/gt.csv");
    let out = tokio::task::spawn_blocking(move || {
        loopd_bin()
            .args(["eval", "--sequence", data("corridor/ref").to_str().unwrap()])
            .args(["--query-sequence", data("corridor/query").to_str().unwrap(), "--gt", gt.to_str().unwrap()])
            .args(["--verify", "sequence", "--sequence-length", "10", "--json", "--cache-dir"])
            .arg(process_cache())
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    let best = report["best"].as_array().unwrap();
    let mut same = 0;
    for (i, a) in visitor.iter().enumerate() {
        let m = &a.matches[0];
        let s = m.sequence.as_ref().expect("sequence checked");
        // The history grows up to L; a candidate near the start of its trajectory has less.
        assert!((1..=(i + 1).min(10) as u32).contains(&s.length), "query {i}: {s:?}");
        let e = best[i].as_array().unwrap();
        same += (position[&m.frame_id] as u64 == e[0].as_u64().unwrap()) as usize;
        if position[&m.frame_id] as u64 == e[0].as_u64().unwrap() {
            assert!((s.margin as f64 - e[1].as_f64().unwrap()).abs() < 1e-3, "query {i}: {s:?} vs {e:?}");
        }
    }
    // The same code on the same descriptors: the same best match (f32 sums may break exact ties
    // differently, so allow one in a hundred).
    assert!(same >= 110, "server and eval agree on {same}/111 best matches");
    server.shutdown().await.unwrap();
}
