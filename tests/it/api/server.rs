//! The real server on 127.0.0.1 (both APIs, temporary data directory) driven by a tonic
//! client and a real HTTP client, on real frames.
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::model::preprocess::ImageLimits;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use std::time::Duration;

struct Server {
    grpc: String,
    http: String,
}

/// One server for the whole test binary (the model loads once), on its own runtime so it
/// outlives each test's runtime.
async fn server() -> &'static Server {
    static S: std::sync::OnceLock<Server> = std::sync::OnceLock::new();
    S.get_or_init(|| {
        let config = |dir| ServerConfig {
            engine: EngineConfig { max_batch: 16, max_delay: Duration::from_millis(5), ..Default::default() },
            limits: ImageLimits { max_bytes: 2 << 20, ..Default::default() },
            max_jobs: 2,
            ..ServerConfig::on_loopback(dir)
        };
        let (grpc, http) = background_server(config, imagenet_model);
        Server { grpc, http }
    })
}

fn jpeg(path: &str) -> bytes::Bytes {
    std::fs::read(data(path)).unwrap().into()
}

fn frame_req(session: &str, robot: &str, t: f64, image: bytes::Bytes, scope: pb::Scope) -> pb::AddFrameRequest {
    pb::AddFrameRequest {
        session_id: session.into(),
        robot_id: robot.into(),
        timestamp: Some(t),
        content: Some(pb::add_frame_request::Content::Image(image)),
        options: Some(pb::QueryOptions { k: Some(3), scope: scope as i32, ..Default::default() }),
        ..Default::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn two_robots_stream_the_corridor_and_the_second_finds_the_first() {
    let s = server().await;
    let mut client = LoopdClient::connect(s.grpc.clone()).await.unwrap();
    client
        .create_session(pb::CreateSessionRequest {
            id: "corridor".into(),
            name: "office corridor".into(),
            ..Default::default()
        })
        .await
        .unwrap();
    // Robot "mapper" drives the reference traversal, robot "visitor" the query traversal.
    let stream_robot = |robot: &'static str, dir: &'static str| {
        let mut client = client.clone();
        async move {
            let frames: Vec<pb::AddFrameRequest> = (0..111)
                .map(|i| {
                    frame_req(
                        "corridor",
                        robot,
                        i as f64 * 0.5,
                        jpeg(&format!("corridor/{dir}/{i:07}.jpg")),
                        pb::Scope::OtherRobots,
                    )
                })
                .collect();
            let mut answers = client.stream_frames(tokio_stream::iter(frames)).await.unwrap().into_inner();
            let mut out = Vec::new();
            while let Some(a) = answers.message().await.unwrap() {
                assert_eq!(a.error, "", "frame failed: {}", a.error);
                out.push(a);
            }
            out
        }
    };
    let mapper = stream_robot("mapper", "ref").await;
    assert_eq!(mapper.len(), 111);
    assert!(mapper.iter().all(|a| a.matches.is_empty()), "no other robot had mapped yet");
    let visitor = stream_robot("visitor", "query").await;
    assert_eq!(visitor.len(), 111);
    let ref_id: std::collections::HashMap<u64, usize> =
        mapper.iter().enumerate().map(|(i, a)| (a.frame_id, i)).collect();
    let mut hits = 0;
    for (q, refs) in corridor_truth() {
        let a = &visitor[q];
        assert_eq!(a.matches.len(), 3);
        assert!(a.matches.iter().all(|m| m.robot_id == "mapper"));
        hits += refs.contains(&ref_id[&a.matches[0].frame_id]) as usize;
    }
    // Plain ImageNet features reach 0.56 recall@1 here (tests/it/store/sessions.rs).
    assert!(hits >= 50, "visitor's top-1 is a ground-truth reference frame for only {hits}/111 frames");
    let session = client.get_session(pb::GetSessionRequest { id: "corridor".into() }).await.unwrap().into_inner();
    assert_eq!(session.frames, 222);
    assert_eq!(session.robots, vec!["mapper".to_string(), "visitor".to_string()]);
}

fn code<T>(r: Result<tonic::Response<T>, tonic::Status>) -> tonic::Code {
    match r {
        Ok(_) => panic!("expected an error status"),
        Err(s) => s.code(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn grpc_errors_carry_the_right_codes_and_the_server_keeps_serving() {
    let s = server().await;
    let mut c = LoopdClient::connect(s.grpc.clone()).await.unwrap();
    c.create_session(pb::CreateSessionRequest { id: "errors".into(), ..Default::default() }).await.unwrap();
    assert_eq!(
        code(c.create_session(pb::CreateSessionRequest { id: "errors".into(), ..Default::default() }).await),
        tonic::Code::AlreadyExists
    );
    assert_eq!(code(c.get_session(pb::GetSessionRequest { id: "nope".into() }).await), tonic::Code::NotFound);
    let garbage = frame_req("errors", "r", 0.0, bytes::Bytes::from_static(b"GIF89a not really"), pb::Scope::All);
    let status = c.add_frame(garbage).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    assert!(status.message().contains("image"), "{}", status.message());
    let short = pb::AddFrameRequest {
        session_id: "errors".into(),
        robot_id: "r".into(),
        timestamp: Some(0.0),
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
            values: vec![0.5; 10],
            ..Default::default()
        })),
        ..Default::default()
    };
    let status = c.add_frame(short).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    assert!(status.message().contains("10 values"), "{}", status.message());
    let empty = pb::AddFrameRequest { session_id: "errors".into(), robot_id: "r".into(), ..Default::default() };
    assert_eq!(code(c.add_frame(empty).await), tonic::Code::InvalidArgument);
    let unknown = frame_req("nope", "r", 0.0, jpeg("slambook2-ch11/1.png"), pb::Scope::All);
    assert_eq!(code(c.add_frame(unknown).await), tonic::Code::NotFound);
    let mut ok = frame_req("errors", "r", 0.0, jpeg("slambook2-ch11/1.png"), pb::Scope::All);
    ok.frame_id = Some(42);
    assert_eq!(c.add_frame(ok.clone()).await.unwrap().into_inner().frame_id, 42);
    assert_eq!(code(c.add_frame(ok).await), tonic::Code::AlreadyExists);
    let missing = pb::QueryRequest {
        session_id: "errors".into(),
        content: Some(pb::query_request::Content::FrameId(7)),
        ..Default::default()
    };
    assert_eq!(code(c.query(missing).await), tonic::Code::NotFound);
    // A bad frame inside a stream is answered in the stream, which goes on.
    let frames = vec![
        frame_req("errors", "s", 1.0, bytes::Bytes::from_static(b"junk"), pb::Scope::All),
        frame_req("errors", "s", 2.0, jpeg("slambook2-ch11/1.png"), pb::Scope::All),
    ];
    let mut answers = c.stream_frames(tokio_stream::iter(frames)).await.unwrap().into_inner();
    let first = answers.message().await.unwrap().unwrap();
    assert_eq!(first.error_code, tonic::Code::InvalidArgument as i32);
    let second = answers.message().await.unwrap().unwrap();
    assert_eq!(second.error, "");
    assert_eq!(second.matches[0].frame_id, 42, "the same desk image stored before is the best match");
    assert!(second.matches[0].score > 0.999);
    // Standard health service answers SERVING.
    let mut health = tonic_health::pb::health_client::HealthClient::new(
        tonic::transport::Channel::from_shared(s.grpc.clone()).unwrap().connect().await.unwrap(),
    );
    let h = health.check(tonic_health::pb::HealthCheckRequest { service: "loopd.v1.Loopd".into() }).await.unwrap();
    assert_eq!(h.into_inner().status, tonic_health::pb::health_check_response::ServingStatus::Serving as i32);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn http_sessions_frames_queries_and_errors() {
    let s = server().await;
    let http = reqwest::Client::new();
    let url = |p: &str| format!("{}{p}", s.http);
    assert_eq!(http.get(url("/healthz")).send().await.unwrap().status(), 200);
    let info: serde_json::Value = http.get(url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["dim"], 2048);
    let r = http
        .post(url("/v1/sessions"))
        .json(&serde_json::json!({ "id": "desk", "name": "desk", "storage": "f32" }))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    // Raw body with fields in the query string.
    let r = http
        .post(url("/v1/sessions/desk/frames?robot_id=cam&timestamp=1.0"))
        .body(jpeg("slambook2-ch11/1.png").to_vec())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let first: serde_json::Value = r.json().await.unwrap();
    // Multipart form with a pose.
    let form = reqwest::multipart::Form::new()
        .part("image", reqwest::multipart::Part::bytes(jpeg("slambook2-ch11/5.png").to_vec()).file_name("5.png"))
        .text("robot_id", "cam")
        .text("timestamp", "5.0")
        .text("pose", r#"{"x":1,"y":2,"z":0,"qx":0,"qy":0,"qz":0,"qw":1}"#);
    assert_eq!(http.post(url("/v1/sessions/desk/frames")).multipart(form).send().await.unwrap().status(), 201);
    // add_and_query with the loop frame 10.png finds frame 1.png first.
    let form = reqwest::multipart::Form::new()
        .part("image", reqwest::multipart::Part::bytes(jpeg("slambook2-ch11/10.png").to_vec()).file_name("10.png"))
        .text("robot_id", "cam")
        .text("timestamp", "10.0")
        .text("options", r#"{"k": 2}"#);
    let r: serde_json::Value =
        http.post(url("/v1/sessions/desk/add_and_query")).multipart(form).send().await.unwrap().json().await.unwrap();
    assert_eq!(r["matches"][0]["frame_id"], first["frame_id"], "{r}");
    // Query by stored frame id, JSON body.
    let q: serde_json::Value = post_json(
        &http,
        url("/v1/sessions/desk/query"),
        &serde_json::json!({ "frame_id": r["frame_id"], "options": { "k": 1 } }),
    )
    .await;
    assert_eq!(q["matches"][0]["frame_id"], first["frame_id"]);
    // k at the limit by a stored frame: every other frame, not "k = 1001 exceeds the limit".
    let r = http
        .post(url("/v1/sessions/desk/query"))
        .json(&serde_json::json!({ "frame_id": first["frame_id"], "options": { "k": 1000 } }))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let all: serde_json::Value = r.json().await.unwrap();
    let ids: Vec<&serde_json::Value> = all["matches"].as_array().unwrap().iter().map(|m| &m["frame_id"]).collect();
    assert_eq!(ids.len(), 2, "{all}");
    assert!(!ids.contains(&&first["frame_id"]));
    let frame: serde_json::Value = http
        .get(url(&format!("/v1/sessions/desk/frames/{}", first["frame_id"])))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(frame["robot_id"], "cam");
    let listed: serde_json::Value = http.get(url("/v1/sessions")).send().await.unwrap().json().await.unwrap();
    assert!(listed["sessions"].as_array().unwrap().iter().any(|x| x["id"] == "desk" && x["frames"] == 3));

    // Bad requests: the right code, a message, and the server keeps serving.
    let expect = |code: u16| {
        move |r: reqwest::Response| {
            assert_eq!(r.status().as_u16(), code, "{:?}", r.url().path());
            r
        }
    };
    let post_raw = |path: &str, body: Vec<u8>| http.post(url(path)).body(body).send();
    let unknown = post_raw("/v1/sessions/nope/frames?robot_id=a&timestamp=0", jpeg("slambook2-ch11/1.png").to_vec())
        .await
        .unwrap();
    let body: serde_json::Value = expect(404)(unknown).json().await.unwrap();
    assert!(body["error"].as_str().unwrap().contains("nope"));
    let garbage = post_raw("/v1/sessions/desk/frames?robot_id=a&timestamp=0", b"not an image".to_vec()).await.unwrap();
    expect(400)(garbage);
    let wrong_len = http
        .post(url("/v1/sessions/desk/frames"))
        .json(&serde_json::json!({ "robot_id": "a", "timestamp": 0, "descriptor": [1.0, 2.0] }))
        .send()
        .await
        .unwrap();
    let body: serde_json::Value = expect(400)(wrong_len).json().await.unwrap();
    assert!(body["error"].as_str().unwrap().contains("2 values"));
    let missing =
        post_raw("/v1/sessions/desk/frames?timestamp=0", jpeg("slambook2-ch11/1.png").to_vec()).await.unwrap();
    expect(400)(missing);
    let big = post_raw("/v1/embed", vec![0u8; 3 << 20]).await.unwrap();
    expect(413)(big);
    // Over the body limit (8 MiB) on the sequence route, inside a form part: 413 like every other
    // route. Just over, so the client has sent it all when the answer comes.
    let huge = reqwest::multipart::Form::new()
        .part("image", reqwest::multipart::Part::bytes(vec![0u8; (8 << 20) + (64 << 10)]).file_name("big.png"));
    expect(413)(http.post(url("/v1/sessions/desk/sequences")).multipart(huge).send().await.unwrap());
    // Ids that are not ids.
    for bad in ["robot_id=a%0Ab&timestamp=0", "robot_id=a%00&timestamp=0", "robot_id=a&timestamp=NaN"] {
        let r = post_raw(&format!("/v1/sessions/desk/frames?{bad}"), jpeg("slambook2-ch11/1.png").to_vec());
        expect(400)(r.await.unwrap());
    }
    for id in [".", ".."] {
        let r = http.post(url("/v1/sessions")).json(&serde_json::json!({ "id": id })).send().await.unwrap();
        expect(400)(r);
    }
    // The descriptor id names the variant that computed the descriptor.
    let embed = |q: &'static str| {
        let (http, u) = (http.clone(), url(&format!("/v1/embed{q}")));
        async move {
            let r = http.post(u).body(jpeg("slambook2-ch11/1.png").to_vec()).send().await.unwrap();
            let v: serde_json::Value = r.json().await.unwrap();
            v["descriptor_id"].as_str().unwrap().to_string()
        }
    };
    let (full, plain) = (embed("").await, embed("?attention=false&fusion=false").await);
    assert_ne!(full, plain);
    assert!(full.contains("+att+fus") && !plain.contains("+att") && !plain.contains("+fus"), "{full} {plain}");
    assert_eq!(info["descriptor_id"], full.as_str());
    let dup = http.post(url("/v1/sessions")).json(&serde_json::json!({ "id": "desk" })).send().await.unwrap();
    expect(409)(dup);
    let bad_json =
        http.post(url("/v1/sessions")).header("content-type", "application/json").body("{").send().await.unwrap();
    expect(400)(bad_json);
    assert_eq!(http.get(url("/healthz")).send().await.unwrap().status(), 200);
    let metrics = http.get(url("/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains("loopd_engine_images_total{model=\"loopd\"}"), "{metrics}");
    assert_eq!(http.delete(url("/v1/sessions/desk")).send().await.unwrap().status(), 204);
    assert_eq!(http.get(url("/v1/sessions/desk")).send().await.unwrap().status(), 404);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn offline_sequence_job_finds_the_desk_loop() {
    let s = server().await;
    let http = reqwest::Client::new();
    let url = |p: &str| format!("{}{p}", s.http);
    http.post(url("/v1/sessions")).json(&serde_json::json!({ "id": "desk-seq" })).send().await.unwrap();
    // Sent shuffled; order=name puts them back as 1, 2, ..., 10.
    // Every first candidate scoring 0.8 (no confidence floor): the plain backbone's descriptors.
    let mut form =
        reqwest::multipart::Form::new().text("order", "name").text("min_score", "0.8").text("min_confidence", "0");
    for i in [3, 10, 1, 7, 2, 9, 4, 6, 8, 5] {
        let part = reqwest::multipart::Part::bytes(jpeg(&format!("slambook2-ch11/{i}.png")).to_vec())
            .file_name(format!("{i}.png"));
        form = form.part("image", part);
    }
    let r = http.post(url("/v1/sessions/desk-seq/sequences")).multipart(form).send().await.unwrap();
    assert_eq!(r.status(), 202);
    let job: serde_json::Value = r.json().await.unwrap();
    let status_url = url(job["status_url"].as_str().unwrap());
    let status = loop {
        let st: serde_json::Value = http.get(&status_url).send().await.unwrap().json().await.unwrap();
        if st["state"] != "running" {
            break st;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert_eq!(status["state"], "done", "{status}");
    assert_eq!(status["done"], 10);
    let loops = status["loops"].as_array().unwrap();
    let best = loops.iter().max_by(|a, b| a["score"].as_f64().partial_cmp(&b["score"].as_f64()).unwrap()).unwrap();
    assert_eq!((best["query_name"].as_str(), best["match_name"].as_str()), (Some("10.png"), Some("1.png")), "{status}");
    assert_eq!(http.get(url("/v1/jobs/job-999")).send().await.unwrap().status(), 404);
    // The same session evaluated live over gRPC: frame ids 0..9 are the sequence in name order.
    let grpc = s.grpc.trim_start_matches("http://").to_string();
    let gt = root().join("tests/gt/desk.csv");
    let out = tokio::task::spawn_blocking(move || {
        loopd_bin()
            .args([
                "eval",
                "--server",
                &grpc,
                "--session",
                "desk-seq",
                "--gt",
                gt.to_str().unwrap(),
                "--exclude",
                "2",
                "--json",
            ])
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!((report["frames"].as_u64(), report["positives"].as_u64()), (Some(10), Some(1)), "{report}");
    assert_eq!(report["recall_at_1"], 1.0, "{report}");
}

/// A server on `dir` whose model takes `size`x`size` inputs.
async fn server_at(dir: &std::path::Path, size: u32) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model_at(size, size)).await.unwrap()
}

/// A session keeps the descriptor space it was made in. A server restarted with another input
/// size refuses images for it over both APIs, naming both ids, and the session works again once
/// its own model serves it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn images_for_a_session_of_another_model_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let http = reqwest::Client::new();
    let add_image = |server: &RunningServer| {
        let u = format!("http://{}/v1/sessions/space/frames?robot_id=r&timestamp=1", server.http_addr);
        http.post(u).body(jpeg("slambook2-ch11/1.png").to_vec()).send()
    };
    let a = server_at(dir.path(), 224).await;
    let created = http
        .post(format!("http://{}/v1/sessions", a.http_addr))
        .json(&serde_json::json!({ "id": "space" }))
        .send()
        .await
        .unwrap();
    assert_eq!(created.status(), 201);
    let space_a = created.json::<serde_json::Value>().await.unwrap()["descriptor_id"].as_str().unwrap().to_string();
    assert_eq!(add_image(&a).await.unwrap().status(), 201);
    a.shutdown().await.unwrap();

    let b = server_at(dir.path(), 112).await;
    let space_b = b.service.engine().info().descriptor_id.clone();
    assert_ne!(space_a, space_b);
    let refused = add_image(&b).await.unwrap();
    assert_eq!(refused.status(), 409);
    let msg = refused.json::<serde_json::Value>().await.unwrap()["error"].as_str().unwrap().to_string();
    assert!(msg.contains(&space_a) && msg.contains(&space_b), "{msg}");
    let mut grpc = LoopdClient::connect(format!("http://{}", b.grpc_addr)).await.unwrap();
    let req = frame_req("space", "r", 2.0, jpeg("slambook2-ch11/2.png"), pb::Scope::All);
    assert_eq!(code(grpc.add_frame(req.clone()).await), tonic::Code::FailedPrecondition);
    assert_eq!(code(grpc.add_and_query(req).await), tonic::Code::FailedPrecondition);
    let query = pb::QueryRequest {
        session_id: "space".into(),
        content: Some(pb::query_request::Content::Image(jpeg("slambook2-ch11/2.png"))),
        ..Default::default()
    };
    assert_eq!(code(grpc.query(query).await), tonic::Code::FailedPrecondition);
    let info: serde_json::Value =
        http.get(format!("http://{}/v1/sessions/space", b.http_addr)).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["frames"], 1, "nothing was added by the refused requests");
    b.shutdown().await.unwrap();

    let a = server_at(dir.path(), 224).await;
    assert_eq!(add_image(&a).await.unwrap().status(), 201);
    a.shutdown().await.unwrap();
}
