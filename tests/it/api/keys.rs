//! Idempotency keys through the real server (`loopd serve` as a process, sled): a write sent
//! again with its key stores nothing and answers the first write's frame id, over gRPC and HTTP,
//! across a restart and a SIGKILL; a key reused for another frame, or malformed, is refused.
use crate::common::proc::Loopd;
use crate::common::*;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use tonic::transport::Channel;

async fn frames(c: &mut LoopdClient<Channel>, id: &str) -> u64 {
    c.get_session(pb::GetSessionRequest { id: id.into() }).await.unwrap().into_inner().frames
}

/// Corridor reference frame `i` at time `i`, with `key`.
fn keyed(i: usize, key: &str) -> pb::AddFrameRequest {
    pb::AddFrameRequest { idempotency_key: key.into(), ..corridor_frame("s", "robot", i) }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_write_sent_again_with_its_idempotency_key_is_stored_once() {
    let dir = tempfile::tempdir().unwrap();
    let flags = ["--heads", loopd::cli::DEFAULT_HEADS];
    let (s, _) = Loopd::start(dir.path(), &flags).await;
    let mut c = LoopdClient::connect(s.grpc_url()).await.unwrap();
    c.create_session(pb::CreateSessionRequest { id: "s".into(), name: "s".into(), ..Default::default() })
        .await
        .unwrap();
    let mut first = Vec::new();
    for i in 0..6 {
        first.push(c.add_and_query(keyed(i, &format!("corridor-{i}"))).await.unwrap().into_inner());
    }
    assert_eq!(frames(&mut c, "s").await, 6);
    // Frame 5 again, as a robot retries a write whose answer it lost: the first id, nothing
    // stored, and the answer does not name the frame itself.
    let again = c.add_and_query(keyed(5, "corridor-5")).await.unwrap().into_inner();
    assert_eq!(again.frame_id, first[5].frame_id);
    assert!(again.matches.iter().all(|m| m.frame_id != again.frame_id), "{:?}", again.matches);
    assert_eq!(
        again.matches.iter().map(|m| m.frame_id).collect::<Vec<_>>(),
        first[5].matches.iter().map(|m| m.frame_id).collect::<Vec<_>>()
    );
    assert_eq!(c.add_frame(keyed(2, "corridor-2")).await.unwrap().into_inner().frame_id, first[2].frame_id);
    assert_eq!(frames(&mut c, "s").await, 6);
    // The key of another frame: refused, nothing stored.
    let e = c.add_frame(keyed(7, "corridor-2")).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::AlreadyExists, "{e:?}");
    assert!(e.message().contains("idempotency key 'corridor-2' stored frame"), "{}", e.message());
    // Malformed keys.
    for bad in ["a key".to_string(), "x".repeat(129), "é".into()] {
        let e = c.add_frame(keyed(8, &bad)).await.unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument, "{bad}: {e:?}");
        assert!(e.message().contains("idempotency_key must be 1 to 128 visible ASCII"), "{}", e.message());
    }
    assert_eq!(frames(&mut c, "s").await, 6);
    // Two writes with one key at once: one frame; each answer is its id or "in progress".
    let (mut c1, mut c2) = (c.clone(), c.clone());
    let (a, b) = tokio::join!(c1.add_frame(keyed(9, "both")), c2.add_frame(keyed(9, "both")));
    let ids: Vec<u64> = [a, b]
        .into_iter()
        .filter_map(|r| match r {
            Ok(r) => Some(r.into_inner().frame_id),
            Err(e) => {
                assert_eq!(e.code(), tonic::Code::Unavailable, "{e:?}");
                assert!(e.message().contains("in progress"), "{}", e.message());
                None
            }
        })
        .collect();
    assert!(!ids.is_empty() && ids.iter().all(|&i| i == ids[0]), "{ids:?}");
    assert_eq!(frames(&mut c, "s").await, 7);
    // HTTP: a JSON write and its repeat.
    let http = reqwest::Client::new();
    let url = format!("{}/v1/sessions/s/frames", s.http_url());
    let d: Vec<f32> = vec![0.5; s.dim().await];
    let body = serde_json::json!({"robot_id": "web", "timestamp": 100.0, "descriptor": d, "idempotency_key": "h-1"});
    let r1 = http.post(&url).json(&body).send().await.unwrap();
    assert_eq!(r1.status(), 201);
    let r1: serde_json::Value = r1.json().await.unwrap();
    let r2 = http.post(&url).json(&body).send().await.unwrap();
    assert_eq!(r2.status(), 201);
    let r2: serde_json::Value = r2.json().await.unwrap();
    assert_eq!(r1["frame_id"], r2["frame_id"]);
    let bad = serde_json::json!({"robot_id": "web", "timestamp": 101.0, "descriptor": d, "idempotency_key": ""});
    let r = http.post(&url).json(&bad).send().await.unwrap();
    assert_eq!(r.status(), 400);
    assert_eq!(frames(&mut c, "s").await, 8);
    // SIGKILL, then a restart: keys come back with their frames.
    s.kill();
    let (s, _) = Loopd::start(dir.path(), &flags).await;
    let mut c = LoopdClient::connect(s.grpc_url()).await.unwrap();
    assert_eq!(frames(&mut c, "s").await, 8);
    assert_eq!(c.add_frame(keyed(3, "corridor-3")).await.unwrap().into_inner().frame_id, first[3].frame_id);
    let r: serde_json::Value = http
        .post(format!("{}/v1/sessions/s/frames", s.http_url()))
        .json(&body)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(r["frame_id"], r1["frame_id"]);
    assert_eq!(frames(&mut c, "s").await, 8);
    // A new key still stores a new frame.
    let new = c.add_frame(keyed(10, "corridor-10")).await.unwrap().into_inner().frame_id;
    assert!(first.iter().all(|f| f.frame_id != new));
    assert_eq!(frames(&mut c, "s").await, 9);
    s.stop().await;
}
