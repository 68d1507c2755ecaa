//! A full disk (issue #14, defect 4), on a small tmpfs the test mounts (root needed, as in CI):
//! writes fail with a clear error while readiness and gRPC health say not ready and queries go
//! on; once space is back the server takes writes again without a restart. Then the disk is
//! filled again and the process killed with SIGKILL while it is full: after space returns and it
//! restarts, every acknowledged frame is there.
use crate::common::proc::Loopd;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

/// A tmpfs mounted for the test, unmounted when dropped.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(at: &Path, bytes: u64) -> Self {
        std::fs::create_dir_all(at).unwrap();
        let out = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(at)
            .output()
            .expect("running mount");
        assert!(
            out.status.success(),
            "this test mounts a small tmpfs to fill it and needs root (CI runs as root): {}",
            String::from_utf8_lossy(&out.stderr)
        );
        Self(at.to_path_buf())
    }

    /// Fills what is left with a file (removed by `free`).
    fn fill(&self) {
        use std::io::Write;
        let mut f = std::fs::File::create(self.0.join("filler")).unwrap();
        let chunk = vec![0xa5u8; 64 << 10];
        for size in [chunk.len(), 4096, 1] {
            while f.write_all(&chunk[..size]).and_then(|_| f.flush()).is_ok() {}
        }
    }

    fn free(&self) {
        std::fs::remove_file(self.0.join("filler")).unwrap();
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

struct Robot {
    http: reqwest::Client,
    url: String,
    n: usize,
    acked: Vec<u64>,
}

impl Robot {
    /// One descriptor frame; its HTTP status (200: acknowledged and recorded) and error message.
    async fn add(&mut self, dim: usize) -> (u16, String) {
        self.n += 1;
        let d: Vec<f32> = (0..dim).map(|i| ((i * 7 + self.n * 13) % 101) as f32 - 50.0).collect();
        let body = serde_json::json!({ "robot_id": "r", "timestamp": self.n as f64, "descriptor": d });
        let r = self.http.post(format!("{}/v1/sessions/s/frames", self.url)).json(&body).send().await.unwrap();
        // 201 Created counts as 200 here: acknowledged.
        let status = if r.status().is_success() { 200 } else { r.status().as_u16() };
        if status == 503 {
            assert_eq!(r.headers()["retry-after"], "1", "a 503 says when to come back");
        }
        let v: serde_json::Value = r.json().await.unwrap();
        if status == 200 {
            self.acked.push(v["frame_id"].as_u64().unwrap());
        }
        (status, v["error"].as_str().unwrap_or_default().to_string())
    }

    /// Writes until one fails (the disk is full); returns the statuses after the first failure.
    async fn until_refused(&mut self, dim: usize) -> Vec<(u16, String)> {
        for _ in 0..2000 {
            let (status, error) = self.add(dim).await;
            if status != 200 {
                let mut after = vec![(status, error)];
                for _ in 0..5 {
                    after.push(self.add(dim).await);
                }
                return after;
            }
        }
        panic!("2000 writes to a full disk all succeeded");
    }
}

async fn health(s: &Loopd) -> ServingStatus {
    let channel = tonic::transport::Endpoint::from_shared(s.grpc_url()).unwrap().connect().await.unwrap();
    let mut c = HealthClient::new(channel);
    let r = c.check(HealthCheckRequest { service: String::new() }).await.unwrap().into_inner();
    ServingStatus::try_from(r.status).unwrap()
}

async fn ready(s: &Loopd) -> u16 {
    reqwest::get(format!("{}/readyz", s.http_url())).await.unwrap().status().as_u16()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_refuses_writes_then_recovers_without_losing_acknowledged_frames() {
    let dir = tempfile::tempdir().unwrap();
    let disk = Tmpfs::mount(&dir.path().join("mnt"), 48 << 20);
    let data = disk.0.join("data");
    let retry = ["--storage-retry-secs", "0.5"];
    let (server, _) = Loopd::start(&data, &retry).await;
    let dim = server.dim().await;
    let http = reqwest::Client::new();
    let r = http.post(format!("{}/v1/sessions", server.http_url())).json(&serde_json::json!({ "id": "s" }));
    assert_eq!(r.send().await.unwrap().status(), 201);
    let mut robot = Robot { http: http.clone(), url: server.http_url(), n: 0, acked: Vec::new() };
    for _ in 0..50 {
        assert_eq!(robot.add(dim).await.0, 200);
    }

    // Full: writes fail with 503 and a message naming the failure (later ones without trying).
    disk.fill();
    let refused = robot.until_refused(dim).await;
    eprintln!("first refusals on a full disk: {refused:?}");
    assert!(refused.iter().all(|(s, e)| *s == 503 && e.contains("No space left")), "{refused:?}");
    assert_eq!(ready(&server).await, 503);
    tokio::time::sleep(Duration::from_millis(300)).await; // health follows within a tick (0.1 s)
    assert_eq!(health(&server).await, ServingStatus::NotServing);
    // Reads and searches go on.
    let q = serde_json::json!({ "robot_id": "q", "descriptor": vec![1.0f32; dim], "options": { "k": 3 } });
    let r = http.post(format!("{}/v1/sessions/s/query", server.http_url())).json(&q).send().await.unwrap();
    assert_eq!(r.status(), 200, "queries work while writes are refused");

    // Space back: writes succeed again within a few retries, no restart.
    disk.free();
    let t = Instant::now();
    while ready(&server).await != 200 {
        if t.elapsed() > Duration::from_secs(20) {
            let log = std::fs::read_to_string(&server.log).unwrap();
            panic!("not ready 20 s after space came back; log tail:\n{}", &log[log.len().saturating_sub(3000)..]);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    eprintln!("ready again {:.2?} after space came back", t.elapsed());
    assert_eq!(health(&server).await, ServingStatus::Serving);
    for _ in 0..20 {
        assert_eq!(robot.add(dim).await.0, 200, "writes after recovery");
    }
    // After a clean restart the disk holds exactly the acknowledged frames: the reopen took
    // off disk what had been written but never acknowledged.
    server.stop().await;
    let (server, _) = Loopd::start(&data, &retry).await;
    let frames = |v: serde_json::Value| v["frames"].as_u64().unwrap() as usize;
    let info = http.get(format!("{}/v1/sessions/s", server.http_url())).send().await.unwrap();
    assert_eq!(frames(info.json().await.unwrap()), robot.acked.len(), "exactly the acknowledged frames");
    let mut robot = Robot { url: server.http_url(), ..robot };

    // Full again, and the process killed while it is: after space returns and a restart,
    // every acknowledged frame is there.
    disk.fill();
    robot.until_refused(dim).await;
    server.kill();
    disk.free();
    let (server, took) = Loopd::start(&data, &retry).await;
    eprintln!("restarted in {took:.2?} after a kill -9 on a full disk");
    for id in &robot.acked {
        let r = http.get(format!("{}/v1/sessions/s/frames/{id}", server.http_url())).send().await.unwrap();
        assert_eq!(r.status(), 200, "acknowledged frame {id} lost");
    }
    let info = http.get(format!("{}/v1/sessions/s", server.http_url())).send().await.unwrap();
    let stored = frames(info.json().await.unwrap());
    // A frame answered with an error may have reached the disk before the process died (sled
    // writes in the background); an acknowledged one is never missing.
    assert!(stored >= robot.acked.len(), "{stored} stored < {} acknowledged", robot.acked.len());
    robot.url = server.http_url();
    assert_eq!(robot.add(dim).await.0, 200);
    eprintln!("{} frames acknowledged across two full disks and a kill -9, all there", robot.acked.len());
    server.stop().await;
}
