//! The real `loopd serve` as a child process on free loopback ports, for tests that kill it.
use std::path::Path;
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

pub struct Loopd {
    child: parking_lot::Mutex<Child>,
    pub grpc: std::net::SocketAddr,
    pub http: std::net::SocketAddr,
    pub log: std::path::PathBuf,
}

impl Loopd {
    /// Starts `loopd serve` on `data_dir` (ports picked by the server, read from its JSON log)
    /// and waits for `/readyz`; returns it and the time from spawn to ready.
    pub async fn start(data_dir: &Path, extra: &[&str]) -> (Self, Duration) {
        let t = Instant::now();
        // Not in the data folder (a test may fill its disk); a fresh name per start.
        let logs = std::env::temp_dir().join("loopd-test-logs");
        std::fs::create_dir_all(&logs).unwrap();
        let log = logs.join(format!("serve-{:016x}.log", rand::random::<u64>()));
        let file = std::fs::File::create(&log).unwrap();
        let child = super::loopd_bin()
            .args(["serve", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--data-dir"])
            .arg(data_dir)
            .args(extra)
            .env("LOOPD_LOG_FORMAT", "json")
            .stdout(Stdio::null())
            .stderr(file)
            .spawn()
            .expect("spawning loopd serve");
        let mut child = child;
        let (grpc, http) = loop {
            if let Some(addrs) = serving_addrs(&log) {
                break addrs;
            }
            if let Ok(Some(status)) = child.try_wait() {
                panic!("loopd serve exited with {status}: {}", std::fs::read_to_string(&log).unwrap_or_default());
            }
            assert!(t.elapsed() < Duration::from_secs(120), "loopd serve did not start in 2 min");
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        let s = Self { child: parking_lot::Mutex::new(child), grpc, http, log };
        let client = reqwest::Client::new();
        loop {
            if let Ok(r) = client.get(format!("{}/readyz", s.http_url())).send().await {
                if r.status() == 200 {
                    break;
                }
            }
            assert!(t.elapsed() < Duration::from_secs(120), "loopd serve not ready in 2 min");
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        (s, t.elapsed())
    }

    pub fn pid(&self) -> u32 {
        self.child.lock().id()
    }

    pub fn grpc_url(&self) -> String {
        format!("http://{}", self.grpc)
    }

    pub fn http_url(&self) -> String {
        format!("http://{}", self.http)
    }

    /// The server's descriptor length.
    pub async fn dim(&self) -> usize {
        let v: serde_json::Value =
            reqwest::get(format!("{}/v1/info", self.http_url())).await.unwrap().json().await.unwrap();
        v["dim"].as_u64().unwrap() as usize
    }

    /// SIGKILL: no shutdown code runs.
    pub fn kill(&self) {
        let mut c = self.child.lock();
        let _ = c.kill();
        let _ = c.wait();
    }

    /// SIGTERM, then waits for the exit (a clean shutdown).
    pub async fn stop(&self) {
        let pid = self.child.lock().id();
        std::process::Command::new("kill").args(["-TERM", &pid.to_string()]).status().unwrap();
        let t = Instant::now();
        loop {
            if let Ok(Some(status)) = self.child.lock().try_wait() {
                assert!(status.success(), "loopd serve exited with {status} after SIGTERM");
                return;
            }
            assert!(t.elapsed() < Duration::from_secs(60), "loopd serve did not stop after SIGTERM");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

impl Drop for Loopd {
    /// Kills a server still running; its log goes unless the test is failing.
    fn drop(&mut self) {
        let mut c = self.child.lock();
        if let Ok(None) = c.try_wait() {
            let _ = c.kill();
            let _ = c.wait();
        }
        if !std::thread::panicking() {
            let _ = std::fs::remove_file(&self.log);
        }
    }
}

/// The addresses from the server's "loopd serving" log line, once it is written.
fn serving_addrs(log: &Path) -> Option<(std::net::SocketAddr, std::net::SocketAddr)> {
    let text = std::fs::read_to_string(log).ok()?;
    text.lines().find_map(|line| {
        let v: serde_json::Value = serde_json::from_str(line).ok()?;
        let f = &v["fields"];
        (f["message"] == "loopd serving")
            .then(|| Some((f["grpc_addr"].as_str()?.parse().ok()?, f["http_addr"].as_str()?.parse().ok()?)))?
    })
}
