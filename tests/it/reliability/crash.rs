//! Crash test (issue #14): the real `loopd serve` process under eight concurrent clients (gRPC
//! AddFrame, AddAndQuery and StreamFrames, HTTP frames, session create/delete, offline sequence
//! jobs), killed with SIGKILL at random moments and restarted on the same data directory, 8
//! times (LOOPD_CRASH_CYCLES: more). Every acknowledged frame must be there after each restart and, at the end, searchable
//! with its descriptor bit-identical; acknowledged deletes stay deleted; acknowledged jobs still
//! answer. Restart times are printed.
use crate::common::proc::Loopd;
use crate::common::*;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use parking_lot::Mutex;
use rand::{Rng, SeedableRng};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Kill -9 cycles: 8 in CI (about 70 s), more with LOOPD_CRASH_CYCLES.
fn cycles() -> usize {
    std::env::var("LOOPD_CRASH_CYCLES").ok().and_then(|v| v.parse().ok()).unwrap_or(8)
}
const SESSION: &str = "crash";

#[derive(Clone, Debug)]
struct Acked {
    robot: String,
    timestamp: f64,
    /// What the store must hold bit for bit (descriptor frames: the client's values normalised
    /// and rounded to f16 as the store does).
    descriptor: Option<Vec<f32>>,
}

#[derive(Default)]
struct Ledger {
    frames: BTreeMap<(String, u64), Acked>,
    /// Frames acknowledged since the last check.
    fresh: Vec<(String, u64)>,
    deleted: BTreeSet<String>,
    jobs: Vec<String>,
}

type Shared = Arc<Mutex<Ledger>>;

fn corridor(i: usize) -> Vec<u8> {
    std::fs::read(data(&format!("corridor/ref/{:07}.jpg", i % 111))).unwrap()
}

fn ack(ledger: &Shared, session: &str, id: u64, robot: &str, timestamp: f64, descriptor: Option<Vec<f32>>) {
    let mut l = ledger.lock();
    let key = (session.to_string(), id);
    let previous = l.frames.insert(key.clone(), Acked { robot: robot.into(), timestamp, descriptor });
    assert!(previous.is_none(), "frame {key:?} acknowledged twice");
    l.fresh.push(key);
}

fn random_descriptor(rng: &mut rand::rngs::StdRng, dim: usize) -> Vec<f32> {
    (0..dim).map(|_| rng.random_range(-1.0f32..1.0)).collect()
}

fn image_frame(robot: &str, t: f64, i: usize) -> pb::AddFrameRequest {
    pb::AddFrameRequest {
        session_id: SESSION.into(),
        robot_id: robot.into(),
        timestamp: Some(t),
        content: Some(pb::add_frame_request::Content::Image(corridor(i).into())),
        options: Some(pb::QueryOptions { k: Some(3), ..Default::default() }),
        ..Default::default()
    }
}

/// One client's traffic until the server dies (its first transport error ends it).
async fn client(role: usize, s: Arc<Loopd>, ledger: Shared, dim: usize, cycle: usize, stop: Arc<AtomicBool>) {
    let mut rng = rand::rngs::StdRng::seed_from_u64((cycle * 100 + role) as u64);
    let robot = format!("r{role}");
    let Ok(mut g) = LoopdClient::connect(s.grpc_url()).await else { return };
    let http = reqwest::Client::new();
    let mut n = 0usize;
    while !stop.load(Ordering::Relaxed) {
        n += 1;
        let t = (cycle * 100_000 + n) as f64;
        let ok = match role {
            0 | 1 => {
                let req = image_frame(&robot, t, n + role * 37);
                let id = if role == 0 {
                    g.add_frame(req).await.map(|r| r.into_inner().frame_id)
                } else {
                    g.add_and_query(req).await.map(|r| r.into_inner().frame_id)
                };
                id.map(|id| ack(&ledger, SESSION, id, &robot, t, None)).is_ok()
            }
            2 => {
                // A stream of five frames; each answer acknowledges its frame.
                let frames: Vec<_> = (0..5).map(|k| image_frame(&robot, t + k as f64 / 10.0, n * 5 + k)).collect();
                let times: Vec<f64> = frames.iter().map(|f| f.timestamp.unwrap_or_default()).collect();
                match g.stream_frames(tokio_stream::iter(frames)).await {
                    Ok(answers) => {
                        let mut answers = answers.into_inner();
                        let mut k = 0;
                        while let Ok(Some(a)) = answers.message().await {
                            assert_eq!(a.error, "", "a stream frame failed");
                            ack(&ledger, SESSION, a.frame_id, &robot, times[k], None);
                            k += 1;
                        }
                        k == 5
                    }
                    Err(_) => false,
                }
            }
            3 => {
                let url = format!("{}/v1/sessions/{SESSION}/frames?robot_id={robot}&timestamp={t}", s.http_url());
                match http.post(url).body(corridor(n + 71)).send().await {
                    Ok(r) if r.status().is_success() => {
                        let v: serde_json::Value = r.json().await.unwrap();
                        ack(&ledger, SESSION, v["frame_id"].as_u64().unwrap(), &robot, t, None);
                        true
                    }
                    _ => false,
                }
            }
            4 | 5 => {
                let d = random_descriptor(&mut rng, dim);
                // As the store keeps it: normalised, then in the session's f16 (the default).
                let mut expected = d.clone();
                loopd::index::normalize(&mut expected).unwrap();
                let expected: Vec<f32> = expected.iter().map(|&v| half::f16::from_f32(v).to_f32()).collect();
                let id = if role == 4 {
                    let req = pb::AddFrameRequest {
                        session_id: SESSION.into(),
                        robot_id: robot.clone(),
                        timestamp: Some(t),
                        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
                            values: d,
                            ..Default::default()
                        })),
                        ..Default::default()
                    };
                    g.add_frame(req).await.ok().map(|r| r.into_inner().frame_id)
                } else {
                    let body = serde_json::json!({ "robot_id": robot, "timestamp": t, "descriptor": d });
                    let url = format!("{}/v1/sessions/{SESSION}/frames", s.http_url());
                    match http.post(url).json(&body).send().await {
                        Ok(r) if r.status().is_success() => {
                            r.json::<serde_json::Value>().await.unwrap()["frame_id"].as_u64()
                        }
                        _ => None,
                    }
                };
                id.map(|id| ack(&ledger, SESSION, id, &robot, t, Some(expected))).is_some()
            }
            6 => {
                // Sessions made, filled and deleted: a kill may land inside a delete.
                let id = format!("tmp-{cycle}-{n}");
                let made = g.create_session(pb::CreateSessionRequest { id: id.clone(), ..Default::default() }).await;
                if made.is_err() {
                    return;
                }
                for k in 0..3 {
                    let req = pb::AddFrameRequest {
                        session_id: id.clone(),
                        robot_id: robot.clone(),
                        timestamp: Some(t + k as f64),
                        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
                            values: random_descriptor(&mut rng, dim),
                            ..Default::default()
                        })),
                        ..Default::default()
                    };
                    if g.add_frame(req).await.is_err() {
                        return;
                    }
                }
                match g.delete_session(pb::DeleteSessionRequest { id: id.clone() }).await {
                    Ok(_) => {
                        ledger.lock().deleted.insert(id);
                        true
                    }
                    Err(_) => false,
                }
            }
            _ => {
                // An offline sequence job: a tar of real frames; the kill may land inside it.
                let mut tar = tar::Builder::new(Vec::new());
                for k in 0..12 {
                    let img = corridor(n * 12 + k);
                    let mut h = tar::Header::new_gnu();
                    h.set_size(img.len() as u64);
                    h.set_mode(0o644);
                    h.set_cksum();
                    tar.append_data(&mut h, format!("{k:03}.jpg"), img.as_slice()).unwrap();
                }
                let body = tar.into_inner().unwrap();
                let url = format!("{}/v1/sessions/{SESSION}/sequences", s.http_url());
                let r = http.post(url).header("content-type", "application/x-tar").body(body).send().await;
                match r {
                    Ok(r) if r.status() == 202 || r.status() == 200 => {
                        let v: serde_json::Value = r.json().await.unwrap();
                        ledger.lock().jobs.push(v["job_id"].as_str().unwrap().to_string());
                        // Let it run before the next (one job at a time per client).
                        tokio::time::sleep(Duration::from_millis(1500)).await;
                        true
                    }
                    Ok(r) if r.status() == 429 => true,
                    _ => false,
                }
            }
        };
        if !ok {
            return;
        }
    }
}

/// Frames acknowledged since the last check are there with their robot and time (image frames
/// all, descriptor frames sampled), the session holds at least every acknowledged frame; every
/// acknowledged delete stayed deleted; every acknowledged job answers, none still "running".
async fn check(s: &Loopd, ledger: &Shared) -> usize {
    let http = reqwest::Client::new();
    let (fresh, deleted, jobs) = {
        let mut l = ledger.lock();
        let fresh: Vec<_> =
            std::mem::take(&mut l.fresh).into_iter().map(|k| (k.clone(), l.frames[&k].clone())).collect();
        (fresh, l.deleted.clone(), l.jobs.clone())
    };
    // Each image frame and one in ten descriptor frames over HTTP (the end reads them all).
    for ((session, id), acked) in fresh.iter().filter(|(k, a)| a.descriptor.is_none() || k.1 % 10 == 0) {
        let r = http.get(format!("{}/v1/sessions/{session}/frames/{id}", s.http_url())).send().await.unwrap();
        assert_eq!(r.status(), 200, "acknowledged frame {session}/{id} lost");
        let v: serde_json::Value = r.json().await.unwrap();
        assert_eq!(v["robot_id"], acked.robot.as_str());
        assert_eq!(v["timestamp"].as_f64(), Some(acked.timestamp));
    }
    let held = ledger.lock().frames.len();
    let r = http.get(format!("{}/v1/sessions/{SESSION}", s.http_url())).send().await.unwrap();
    let stored = r.json::<serde_json::Value>().await.unwrap()["frames"].as_u64().unwrap() as usize;
    assert!(stored >= held, "{held} frames acknowledged, {stored} stored");
    for id in &deleted {
        let r = http.get(format!("{}/v1/sessions/{id}", s.http_url())).send().await.unwrap();
        assert_eq!(r.status(), 404, "deleted session {id} came back");
    }
    for job in &jobs {
        let r = http.get(format!("{}/v1/jobs/{job}", s.http_url())).send().await.unwrap();
        assert_eq!(r.status(), 200, "acknowledged job {job} forgotten");
        let v: serde_json::Value = r.json().await.unwrap();
        let state = v["state"].as_str().unwrap().to_string();
        assert!(["done", "interrupted", "failed"].contains(&state.as_str()), "job {job} is '{state}' after a restart");
    }
    fresh.len()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_under_load_loses_no_acknowledged_frame() {
    let dir = tempfile::tempdir().unwrap();
    let ledger: Shared = Arc::default();
    let mut rng = rand::rngs::StdRng::seed_from_u64(14);
    let mut restarts = Vec::new();
    let mut dim = 0;
    let cycles = cycles();
    // Kept rows checkpointed every 20 frames (`store/kept.rs`): kills land between checkpoints,
    // with frames in flight, and during them; each start takes the last checkpoint and the tail.
    let args = ["--rows-checkpoint-frames", "20"];
    for cycle in 0..cycles {
        let (server, ready) = Loopd::start(dir.path(), &args).await;
        restarts.push(ready);
        if cycle == 0 {
            dim = server.dim().await;
            let mut g = LoopdClient::connect(server.grpc_url()).await.unwrap();
            g.create_session(pb::CreateSessionRequest { id: SESSION.into(), ..Default::default() }).await.unwrap();
        } else {
            let checked = check(&server, &ledger).await;
            eprintln!("cycle {cycle}: restart {ready:.2?}, {checked} frames acknowledged in the last cycle all there");
        }
        let server = Arc::new(server);
        let stop = Arc::new(AtomicBool::new(false));
        let clients: Vec<_> = (0..8)
            .map(|role| tokio::spawn(client(role, server.clone(), ledger.clone(), dim, cycle, stop.clone())))
            .collect();
        tokio::time::sleep(Duration::from_millis(rng.random_range(1000..3500))).await;
        server.kill();
        stop.store(true, Ordering::Relaxed);
        for c in clients {
            c.await.unwrap();
        }
    }
    // The last start: check, stop it cleanly, then read the store itself.
    let (server, ready) = Loopd::start(dir.path(), &args).await;
    restarts.push(ready);
    check(&server, &ledger).await;
    server.stop().await;
    let store = loopd::store::Store::open(dir.path()).unwrap();
    // It took the kept rows of the last clean stop (a checkpoint every 20 frames) and the tail.
    let restored = store.session(SESSION).unwrap().restored_frames();
    assert!(restored > 0, "the session was read from sled in full, not from its kept rows");
    let l = ledger.lock();
    let (mut exact, mut searched) = (0, 0);
    let rt = tokio::runtime::Handle::current();
    for ((session, id), acked) in &l.frames {
        let s = store.session(session).unwrap();
        let (h, stored) = s.frame(*id).unwrap_or_else(|e| panic!("frame {session}/{id}: {e}"));
        assert_eq!((h.robot_id.as_str(), h.timestamp), (acked.robot.as_str(), acked.timestamp));
        if let Some(expected) = &acked.descriptor {
            assert!(stored.iter().zip(expected).all(|(a, b)| a.to_bits() == b.to_bits()), "{id}: descriptor changed");
            exact += 1;
            // Searchable: one in 25 is searched for (each search scans the whole session).
            if exact % 25 == 1 {
                let q = loopd::index::query::LoopQuery { k: 1, ..Default::default() };
                let best = tokio::task::block_in_place(|| rt.block_on(store.query(&s, stored.clone(), &q))).unwrap();
                assert_eq!(best[0].frame_id, *id, "descriptor frame {id} is not its own best match");
                searched += 1;
            }
        }
    }
    let frames = l.frames.len();
    restarts.sort();
    eprintln!(
        "{cycles} kill -9 cycles: {frames} acknowledged frames ({exact} descriptor frames bit-identical, \
         {searched} of them searched for and found first), {} deletes, {} jobs, 0 lost ({restored} frames of the \
         last open from kept rows); restart to ready: min {:.2?}, median {:.2?}, max {:.2?}",
        l.deleted.len(),
        l.jobs.len(),
        restarts[0],
        restarts[restarts.len() / 2],
        restarts[restarts.len() - 1]
    );
    assert!(frames >= 200, "too little traffic to mean anything: {frames} frames");
    assert!(!l.deleted.is_empty() && !l.jobs.is_empty(), "deletes and jobs ran");
}
