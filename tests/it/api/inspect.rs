//! What the loop inspector reads (issue #18), against the real server on loopback with real
//! gRPC and HTTP clients, on the desk frames (slambook2: 10.png revisits 1.png): thumbnails kept
//! per frame when the session asks for them (the same JPEG over both APIs), frames listed page by
//! page, the similarity matrix agreeing with the scores answered, and the inlier matches of a
//! verified loop kept with it. Bad input gets 400 / 404 with a reason.
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

async fn get(http: &reqwest::Client, url: String) -> (u16, Value) {
    let r = http.get(url).send().await.unwrap();
    (r.status().as_u16(), r.json().await.unwrap_or(Value::Null))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thumbnails_frames_similarity_and_inliers_as_the_inspector_reads_them() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path()).await;
    let mut g = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    let http = reqwest::Client::new();
    let base = format!("http://{}/v1/sessions", server.http_addr);
    let made = http.post(&base).json(&json!({ "id": "desk", "storage": "f32", "thumbnails": true })).send().await;
    let made: Value = made.unwrap().json().await.unwrap();
    assert_eq!(made["thumbnails"], true, "{made}");
    let plain = g.create_session(pb::CreateSessionRequest { id: "plain".into(), ..Default::default() }).await;
    assert!(!plain.unwrap().into_inner().thumbnails);

    // The ten desk frames, each answered with up to 3 verified candidates.
    let mut ids = Vec::new();
    let mut answered = std::collections::HashMap::new();
    for i in 1..=10 {
        let a = g.add_and_query(desk_frame("desk", i)).await.unwrap().into_inner();
        for m in &a.matches {
            answered.insert((a.frame_id, m.frame_id), m.score);
        }
        ids.push(a.frame_id);
    }
    g.add_frame(desk_frame("plain", 1)).await.unwrap();

    // Thumbnails: a 160x120 JPEG per frame, the same bytes over HTTP and gRPC.
    for &id in &ids {
        let r = http.get(format!("{base}/desk/frames/{id}/thumbnail")).send().await.unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.headers()["content-type"], "image/jpeg");
        let jpeg = r.bytes().await.unwrap();
        let t = image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg).unwrap();
        assert_eq!((t.width(), t.height()), (160, 120));
        let over_grpc = g.get_thumbnail(pb::GetThumbnailRequest { session_id: "desk".into(), frame_id: id }).await;
        assert_eq!(over_grpc.unwrap().into_inner().jpeg.to_vec(), jpeg.to_vec());
    }
    let (st, v) = get(&http, format!("{base}/plain/frames/0/thumbnail")).await;
    assert_eq!(st, 404, "{v}");
    assert!(v["error"].as_str().unwrap().contains("keeps no thumbnails"), "{v}");
    let (st, v) = get(&http, format!("{base}/desk/frames/999/thumbnail")).await;
    assert_eq!(st, 404, "{v}");
    let missing = g.get_thumbnail(pb::GetThumbnailRequest { session_id: "desk".into(), frame_id: 999 }).await;
    assert_eq!(missing.unwrap_err().code(), tonic::Code::NotFound);

    // Frames, page by page: every frame once, in id order, with its header.
    let mut listed = Vec::new();
    let mut after = String::new();
    loop {
        let (st, page) = get(&http, format!("{base}/desk/frames?limit=3{after}")).await;
        assert_eq!(st, 200, "{page}");
        let frames = page["frames"].as_array().unwrap();
        assert!(frames.len() <= 3);
        listed.extend(frames.iter().map(|f| (f["frame_id"].as_u64().unwrap(), f["timestamp"].as_f64().unwrap())));
        match page["next"].as_u64() {
            Some(n) => after = format!("&after={n}"),
            None => break,
        }
    }
    let expected: Vec<(u64, f64)> = ids.iter().zip(1..).map(|(&id, t)| (id, t as f64)).collect();
    assert_eq!(listed, expected);
    for bad in ["limit=x", "after=-1", "colour=red"] {
        assert_eq!(get(&http, format!("{base}/desk/frames?{bad}")).await.0, 400, "{bad}");
    }

    // The similarity matrix: symmetric, ones on the diagonal, each answered score in its cell.
    let (st, m) = get(&http, format!("{base}/desk/similarity?size=10")).await;
    assert_eq!(st, 200, "{m}");
    let frame_ids: Vec<u64> = m["frame_ids"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()).collect();
    assert_eq!(frame_ids, ids);
    let values: Vec<f64> = m["values"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert_eq!(values.len(), 100);
    let at = |q: u64, r: u64| {
        let (i, j) = (ids.iter().position(|&x| x == q).unwrap(), ids.iter().position(|&x| x == r).unwrap());
        values[i * 10 + j]
    };
    for &a in &ids {
        assert!((at(a, a) - 1.0).abs() < 1e-3);
        for &b in &ids {
            assert_eq!(at(a, b), at(b, a));
        }
    }
    for (&(q, r), &score) in &answered {
        assert!((at(q, r) - score as f64).abs() < 2e-3, "{q}->{r}: matrix {} answered {score}", at(q, r));
    }
    let (st, small) = get(&http, format!("{base}/desk/similarity?size=4")).await;
    assert_eq!(st, 200);
    let spread: Vec<u64> = small["frame_ids"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()).collect();
    assert_eq!(spread, [ids[0], ids[3], ids[6], ids[9]], "evenly along the ids, both ends");
    for bad in ["size=0", "size=1025", "size=many"] {
        let (st, v) = get(&http, format!("{base}/desk/similarity?{bad}")).await;
        assert_eq!(st, 400, "{bad}: {v}");
    }
    assert_eq!(get(&http, format!("{base}/nosuch/similarity")).await.0, 404);

    // The revisit 10.png -> 1.png is verified, and its inlier matches are kept with it: as many
    // as it has inliers (at most 100), inside both pictures, the same over gRPC.
    let (query, first) = (ids[9], ids[0]);
    let (st, loops) = get(&http, format!("{base}/desk/loops?limit=1000")).await;
    assert_eq!(st, 200);
    let kept = loops["loops"].as_array().unwrap();
    let revisit = kept.iter().find(|l| l["query_frame"] == query && l["match_frame"] == first).expect("10 -> 1 kept");
    assert_eq!(revisit["verified"], true, "{revisit}");
    let inliers = revisit["inliers"].as_u64().unwrap() as usize;
    let shown = revisit["inlier_matches"].as_array().unwrap();
    assert!(inliers >= 30, "{revisit}");
    assert_eq!(shown.len(), inliers.min(100));
    for m in shown {
        let m: Vec<f64> = m.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        assert!(m.len() == 4 && m.iter().all(|v| (0.0..=1.0).contains(v)), "{m:?}");
    }
    let unverified = kept.iter().filter(|l| l["verified"] == false);
    assert!(unverified.clone().all(|l| l.get("inlier_matches").is_none()), "only verified loops carry matches");
    let grpc_loops =
        g.list_loops(pb::ListLoopsRequest { session_id: "desk".into(), limit: 1000, ..Default::default() });
    let grpc_loops = grpc_loops.await.unwrap().into_inner().loops;
    let same = grpc_loops.iter().find(|l| l.query_frame == query && l.match_frame == first).unwrap();
    assert_eq!(same.inlier_matches.len(), shown.len());
    assert!((same.inlier_matches[0].query_x as f64 - shown[0][0].as_f64().unwrap()).abs() < 1e-6);

    // Thumbnails go with their session.
    assert_eq!(http.delete(format!("{base}/desk")).send().await.unwrap().status(), 204);
    let r = http.post(&base).json(&json!({ "id": "desk", "thumbnails": true })).send().await.unwrap();
    assert_eq!(r.status(), 201);
    // The same frame id again, as a descriptor: no picture, and the old one is gone.
    let dim = made["dim"].as_u64().unwrap() as usize;
    let frame = json!({ "robot_id": "desk", "timestamp": 1, "frame_id": ids[0], "descriptor": vec![1.0f32; dim] });
    assert_eq!(http.post(format!("{base}/desk/frames")).json(&frame).send().await.unwrap().status(), 201);
    let (st, v) = get(&http, format!("{base}/desk/frames/{}/thumbnail", ids[0])).await;
    assert_eq!(st, 404, "{v}");
    assert!(v["error"].as_str().unwrap().contains("no thumbnail"), "{v}");
    server.shutdown().await.unwrap();
}
