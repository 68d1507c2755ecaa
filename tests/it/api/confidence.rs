//! The calibrated loop confidence through the real server (both APIs, kept loops, the export) and
//! offline jobs that verify like online queries, on the desk frames (slambook2: 10.png revisits
//! 1.png) with the shipped model (heads and whitening) and `models/calibration.json`.
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use loopd::verify::confidence::Calibration;
use serde_json::{json, Value};
use std::time::Duration;

async fn shipped_server(dir: &std::path::Path, calibration: Calibration) -> anyhow::Result<RunningServer> {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        max_jobs: 2,
        calibration,
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, shipped_model()).await
}

/// The shipped server with the shipped calibrator: the server, its HTTP base URL, a client.
async fn shipped(dir: &std::path::Path) -> (RunningServer, String, reqwest::Client) {
    let server = shipped_server(dir, Calibration::Shipped(loopd::verify::confidence::SHIPPED.into())).await.unwrap();
    let base = format!("http://{}", server.http_addr);
    (server, base, reqwest::Client::new())
}

fn desk(i: usize) -> bytes::Bytes {
    std::fs::read(data(&format!("slambook2-ch11/{i}.png"))).unwrap().into()
}

async fn run_job(http: &reqwest::Client, base: &str, session: &str, form: reqwest::multipart::Form) -> Value {
    let r = http.post(format!("{base}/v1/sessions/{session}/sequences")).multipart(form).send().await.unwrap();
    assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
    let job: Value = r.json().await.unwrap();
    let url = format!("{base}{}", job["status_url"].as_str().unwrap());
    loop {
        let st: Value = http.get(&url).send().await.unwrap().json().await.unwrap();
        if st["state"] != "running" {
            return st;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

fn desk_form() -> reqwest::multipart::Form {
    let mut form = reqwest::multipart::Form::new().text("order", "name");
    for i in [3, 10, 1, 7, 2, 9, 4, 6, 8, 5] {
        form = form.part("image", reqwest::multipart::Part::bytes(desk(i).to_vec()).file_name(format!("{i}.png")));
    }
    form
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_job_with_default_options_finds_and_verifies_the_desk_loop_and_its_frames_keep_features() {
    let dir = tempfile::tempdir().unwrap();
    let (server, base, http) = shipped(dir.path()).await;
    let info: Value = http.get(format!("{base}/v1/info")).send().await.unwrap().json().await.unwrap();
    let loop_confidence = info["loop_confidence"].as_f64().expect("the shipped model has a calibrator");
    http.post(format!("{base}/v1/sessions")).json(&json!({ "id": "desk" })).send().await.unwrap();
    // No option at all: the job's defaults (verified, calibrated) decide what is a loop.
    let status = run_job(&http, &base, "desk", desk_form()).await;
    assert_eq!((status["state"].as_str(), status["done"].as_u64()), (Some("done"), Some(10)), "{status}");
    let loops = status["loops"].as_array().unwrap();
    let found = loops
        .iter()
        .find(|l| l["query_name"] == "10.png" && l["match_name"] == "1.png")
        .unwrap_or_else(|| panic!("the job did not report 10.png -> 1.png: {status}"));
    assert_eq!(found["verified"], true, "{found}");
    assert!(found["inliers"].as_u64().unwrap() >= 30, "{found}");
    assert!(found["confidence"].as_f64().unwrap() >= loop_confidence, "{found} below {loop_confidence}");
    // Every loop the job reports reaches the loop confidence, and is a real revisit here.
    for l in loops {
        assert!(l["confidence"].as_f64().unwrap() >= loop_confidence, "{l}");
        assert_eq!((l["query_name"].as_str(), l["match_name"].as_str()), (Some("10.png"), Some("1.png")), "{status}");
    }
    // The job's frames keep their features: a later query on 10.png's stored frame verifies.
    let frame_10 = found["query_frame_id"].as_u64().unwrap();
    let r: Value = post_json(
        &http,
        format!("{base}/v1/sessions/desk/query"),
        &json!({ "frame_id": frame_10, "options": { "k": 1, "exclude_last_frames": 0 } }),
    )
    .await;
    let m = &r["matches"][0];
    assert_eq!(m["frame_id"], found["match_frame_id"], "{r}");
    assert_eq!(m["verification"]["verified"], true, "{r}");
    // The same frames through add_and_query, one by one in the same order, give the same loop
    // with the same confidence: the job answers as the server does.
    let mut client = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    client.create_session(pb::CreateSessionRequest { id: "desk-live".into(), ..Default::default() }).await.unwrap();
    let mut live = None;
    for (t, i) in (1..=10).enumerate() {
        let options = pb::QueryOptions {
            k: Some(1),
            exclude_last_frames: Some(3),
            scope: pb::Scope::SameRobot as i32,
            verify: Some(true),
            sequence: Some(true),
            ..Default::default()
        };
        let req = pb::AddFrameRequest {
            session_id: "desk-live".into(),
            robot_id: "sequence".into(),
            timestamp: Some(t as f64),
            content: Some(pb::add_frame_request::Content::Image(desk(i))),
            options: Some(options),
            ..Default::default()
        };
        let a = client.add_and_query(req).await.unwrap().into_inner();
        if i == 10 {
            live = a.matches.first().cloned();
        }
    }
    let live = live.expect("10.png has a candidate");
    assert_eq!(live.frame_id, found["match_frame_id"].as_u64().unwrap());
    let job_confidence = found["confidence"].as_f64().unwrap() as f32;
    // Batches of other sizes round the descriptors a little differently.
    assert!((live.confidence.unwrap() - job_confidence).abs() < 1e-3, "{live:?} vs {found}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn confidence_is_one_number_over_both_apis_kept_loops_and_the_export_and_min_confidence_filters() {
    let dir = tempfile::tempdir().unwrap();
    let (server, base, http) = shipped(dir.path()).await;
    let mut client = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    client.create_session(pb::CreateSessionRequest { id: "c".into(), ..Default::default() }).await.unwrap();
    for i in 1..=10 {
        client.add_frame(desk_frame("c", i)).await.unwrap();
    }
    // Frame 9 is 10.png; a stored-frame query keeps its candidates.
    let q = |min_confidence: Option<f32>| pb::QueryRequest {
        session_id: "c".into(),
        content: Some(pb::query_request::Content::FrameId(9)),
        options: Some(pb::QueryOptions { k: Some(3), min_confidence, ..Default::default() }),
        ..Default::default()
    };
    let grpc = client.query(q(None)).await.unwrap().into_inner().matches;
    assert_eq!(grpc.len(), 3);
    assert_eq!(grpc[0].frame_id, 0, "10.png's first candidate is 1.png: {grpc:?}");
    let c0 = grpc[0].confidence.expect("a calibrated confidence");
    assert!((0.0..=1.0).contains(&c0));
    assert!(grpc.iter().all(|m| m.confidence.unwrap() <= c0), "the verified loop is the most confident: {grpc:?}");
    let h: Value =
        post_json(&http, format!("{base}/v1/sessions/c/query"), &json!({ "frame_id": 9, "options": { "k": 3 } })).await;
    for (g, m) in grpc.iter().zip(h["matches"].as_array().unwrap()) {
        assert_eq!(m["frame_id"].as_u64(), Some(g.frame_id));
        assert_eq!(m["confidence"].as_f64().map(|c| c as f32), g.confidence, "{h}");
    }
    // Kept loops (both APIs) and the export carry the same number.
    let kept: Value = http.get(format!("{base}/v1/sessions/c/loops")).send().await.unwrap().json().await.unwrap();
    let k0 = kept["loops"].as_array().unwrap().iter().find(|l| l["query_frame"] == 9 && l["match_frame"] == 0).unwrap();
    assert_eq!(k0["confidence"].as_f64().map(|c| c as f32), Some(c0), "{k0}");
    let listed = client
        .list_loops(pb::ListLoopsRequest { session_id: "c".into(), ..Default::default() })
        .await
        .unwrap()
        .into_inner()
        .loops;
    let l0 = listed.iter().find(|l| l.query_frame == 9 && l.match_frame == 0).unwrap();
    assert_eq!(l0.confidence, Some(c0));
    let tar = http.get(format!("{base}/v1/sessions/c/export")).send().await.unwrap().bytes().await.unwrap();
    let mut archive = tar::Archive::new(std::io::Cursor::new(tar.to_vec()));
    let mut csv = String::new();
    for e in archive.entries().unwrap() {
        let mut e = e.unwrap();
        if e.path().unwrap().ends_with("loops.csv") {
            std::io::Read::read_to_string(&mut e, &mut csv).unwrap();
        }
    }
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = header.iter().position(|h| *h == "confidence").expect("loops.csv has a confidence column");
    let row =
        csv.lines().skip(1).map(|l| l.split(',').collect::<Vec<_>>()).find(|r| r[0] == "9" && r[1] == "0").unwrap();
    assert_eq!(row[col].parse::<f32>().unwrap(), c0, "{csv}");
    // min_confidence: candidates below it are not returned, over both APIs and in the listing.
    let above = client.query(q(Some(c0))).await.unwrap().into_inner().matches;
    assert_eq!(above.iter().map(|m| m.frame_id).collect::<Vec<_>>(), vec![0]);
    let listed = client
        .list_loops(pb::ListLoopsRequest { session_id: "c".into(), min_confidence: Some(c0), ..Default::default() })
        .await
        .unwrap()
        .into_inner()
        .loops;
    assert!(listed.iter().all(|l| l.confidence.unwrap() >= c0) && listed.iter().any(|l| l.match_frame == 0));
    let r = http
        .post(format!("{base}/v1/sessions/c/query"))
        .json(&json!({ "frame_id": 9, "options": { "min_confidence": 1.5 } }))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400, "min_confidence beyond 1 is refused");
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn a_calibrator_of_another_model_is_refused_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    // A calibration file given on purpose must cover this model: the plain backbone at 112 px
    // has another descriptor space than any calibrator shipped.
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 1, warm_up: false, ..Default::default() },
        calibration: Calibration::File(root().join(loopd::verify::confidence::SHIPPED)),
        ..ServerConfig::on_loopback(dir.path().to_path_buf())
    };
    let e = match RunningServer::start(cfg, imagenet_model_at(112, 112)).await {
        Ok(_) => panic!("a server started with a calibrator of other descriptors"),
        Err(e) => format!("{e:#}"),
    };
    assert!(e.contains("none for this server's descriptors") && e.contains("112x112"), "{e}");
    // The shipped file, not asked for by name: the server starts and answers without confidence,
    // and refuses a min_confidence it cannot apply.
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 1, warm_up: false, ..Default::default() },
        ..ServerConfig::on_loopback(dir.path().to_path_buf())
    };
    let server = RunningServer::start(cfg, imagenet_model_at(112, 112)).await.unwrap();
    let mut client = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    client.create_session(pb::CreateSessionRequest { id: "s".into(), ..Default::default() }).await.unwrap();
    let a = client.add_and_query(desk_frame("s", 1)).await.unwrap().into_inner();
    assert!(a.matches.is_empty());
    let a = client.add_and_query(desk_frame("s", 10)).await.unwrap().into_inner();
    assert!(a.matches.iter().all(|m| m.confidence.is_none()), "{a:?}");
    let mut req = desk_frame("s", 2);
    req.options.as_mut().unwrap().min_confidence = Some(0.5);
    let e = client.add_and_query(req).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::FailedPrecondition, "{e:?}");
    assert!(e.message().contains("min_confidence needs a calibrated confidence"), "{e:?}");
    server.shutdown().await.unwrap();
    // The command line says the same and exits non-zero.
    let out = loopd_bin()
        .args(["serve", "--input-size", "112", "--calibration"])
        .arg(root().join("models/calibration.json"))
        .args(["--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--data-dir"])
        .arg(dir.path().join("cli"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("none for this server's descriptors"), "{err}");
}
