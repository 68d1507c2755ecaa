//! Soak run (issue #14; not in CI): the real `loopd serve` process under mixed traffic from many
//! robots into many sessions for a long time, reporting per window: throughput, p99 latency,
//! server RSS, open files, and disk (sled's folder against the live data the sessions report),
//! with sessions dropped and remade as a fleet does, so compaction has work to do.
//! Prints a table and draws docs/img/soak.png.
//! env: LOOPD_SOAK_MINUTES (default 30), LOOPD_SOAK_ROBOTS (default 16), LOOPD_SOAK_SESSIONS
//!      (default 4), LOOPD_SOAK_WINDOW_SECS (default 30), LOOPD_SOAK_PLOT (default docs/img/soak.png)
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use parking_lot::Mutex;
use plotters::prelude::*;
use rand::{Rng, SeedableRng};
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

fn env<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).map(|a| a.port()).expect("a free port")
}

fn dir_bytes(p: &Path) -> u64 {
    std::fs::read_dir(p)
        .map(|rd| {
            rd.flatten()
                .map(|e| match e.metadata() {
                    Ok(m) if m.is_dir() => dir_bytes(&e.path()),
                    Ok(m) => m.len(),
                    Err(_) => 0,
                })
                .sum()
        })
        .unwrap_or(0)
}

fn rss_mib(pid: u32) -> f64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let kb =
        s.lines().find_map(|l| l.strip_prefix("VmRSS:")).and_then(|v| v.trim().trim_end_matches(" kB").parse().ok());
    kb.unwrap_or(0.0) / 1024.0
}

fn open_files(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd")).map(|d| d.count()).unwrap_or(0)
}

#[derive(Default)]
struct Window {
    ok: usize,
    failed: usize,
    latencies: Vec<Duration>,
}

struct Row {
    minute: f64,
    per_s: f64,
    failed: usize,
    p50_ms: f64,
    p99_ms: f64,
    rss_mib: f64,
    files: usize,
    disk_mib: f64,
    live_mib: f64,
}

async fn robot(
    r: usize,
    url: String,
    sessions: usize,
    dim: usize,
    images: Arc<Vec<Vec<u8>>>,
    w: Arc<Mutex<Window>>,
    stop: Arc<AtomicBool>,
) {
    let mut rng = rand::rngs::StdRng::seed_from_u64(r as u64);
    let Ok(mut c) = LoopdClient::connect(url).await else { return };
    let mut n = 0usize;
    while !stop.load(Ordering::Relaxed) {
        n += 1;
        let session = format!("soak-{}", (r + n / 200) % sessions);
        let t = Instant::now();
        // One frame in four an image (embedded on the server), the rest descriptors; every
        // fifth request a query of a stored frame.
        let result = if n.is_multiple_of(5) {
            let req = pb::QueryRequest {
                session_id: session,
                robot_id: format!("robot-{r}"),
                content: Some(pb::query_request::Content::Descriptor(pb::Descriptor {
                    values: (0..dim).map(|_| rng.random_range(-1.0f32..1.0)).collect(),
                    ..Default::default()
                })),
                options: Some(pb::QueryOptions { k: Some(5), ..Default::default() }),
                ..Default::default()
            };
            c.query(req).await.map(drop)
        } else {
            let content = if n.is_multiple_of(4) {
                pb::add_frame_request::Content::Image(images[(r * 31 + n) % images.len()].clone().into())
            } else {
                pb::add_frame_request::Content::Descriptor(pb::Descriptor {
                    values: (0..dim).map(|_| rng.random_range(-1.0f32..1.0)).collect(),
                    ..Default::default()
                })
            };
            let req = pb::AddFrameRequest {
                session_id: session,
                robot_id: format!("robot-{r}"),
                timestamp: Some(n as f64 * 0.2),
                content: Some(content),
                options: Some(pb::QueryOptions { k: Some(5), ..Default::default() }),
                ..Default::default()
            };
            c.add_and_query(req).await.map(drop)
        };
        let took = t.elapsed();
        {
            let mut w = w.lock();
            match result {
                Ok(()) => {
                    w.ok += 1;
                    w.latencies.push(took);
                }
                Err(_) => w.failed += 1,
            }
        }
        // About 5 requests per second per robot, as a keyframe stream.
        tokio::time::sleep(Duration::from_millis(200).saturating_sub(took)).await;
    }
}

/// Drops the oldest-numbered session and makes it again, every few minutes: sled must reuse the
/// space.
async fn churn(url: String, sessions: usize, every: Duration, stop: Arc<AtomicBool>) {
    let Ok(mut c) = LoopdClient::connect(url).await else { return };
    let mut k = 0;
    let start = Instant::now();
    let mut next = every;
    while !stop.load(Ordering::Relaxed) {
        // Short naps: the run's end is noticed at once.
        tokio::time::sleep(Duration::from_millis(200)).await;
        if start.elapsed() < next {
            continue;
        }
        next += every;
        let id = format!("soak-{}", k % sessions);
        let _ = c.delete_session(pb::DeleteSessionRequest { id: id.clone() }).await;
        let _ = c.create_session(pb::CreateSessionRequest { id, ..Default::default() }).await;
        k += 1;
    }
}

fn plot(rows: &[Row], path: &Path) -> anyhow::Result<()> {
    loopd::eval::plots::png(path, (1100, 800), |root| panels(rows, root))
}

fn panels(rows: &[Row], root: &loopd::eval::plots::Canvas<'_>) -> anyhow::Result<()> {
    root.fill(&WHITE)?;
    let areas = root.split_evenly((2, 2));
    let end = rows.last().map_or(1.0, |r| r.minute).max(1.0);
    type Series<'a> = Vec<(&'a str, Box<dyn Fn(&Row) -> f64>)>;
    let panels: Vec<(&str, Series)> = vec![
        ("requests/s", vec![("answered", Box::new(|r: &Row| r.per_s))]),
        ("latency (ms)", vec![("p50", Box::new(|r: &Row| r.p50_ms)), ("p99", Box::new(|r: &Row| r.p99_ms))]),
        (
            "server memory (MiB) and open files",
            vec![("RSS MiB", Box::new(|r: &Row| r.rss_mib)), ("open files", Box::new(|r: &Row| r.files as f64))],
        ),
        (
            "disk (MiB)",
            vec![("sled folder", Box::new(|r: &Row| r.disk_mib)), ("live data", Box::new(|r: &Row| r.live_mib))],
        ),
    ];
    for (area, (title, series)) in areas.iter().zip(panels) {
        let top = rows.iter().flat_map(|r| series.iter().map(move |(_, f)| f(r))).fold(1.0f64, f64::max) * 1.15;
        let mut chart = ChartBuilder::on(area)
            .caption(title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(30)
            .y_label_area_size(50)
            .build_cartesian_2d(0.0..end, 0.0..top)?;
        chart.configure_mesh().x_desc("minutes").draw()?;
        for (i, (name, f)) in series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(rows.iter().map(|r| (r.minute, f(r))), color.stroke_width(2)))?
                .label(*name)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 15, y)], color));
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
    }
    Ok(())
}

fn percentile(v: &mut [Duration], p: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort();
    v[((v.len() - 1) as f64 * p) as usize].as_secs_f64() * 1e3
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let minutes: f64 = env("LOOPD_SOAK_MINUTES", 30.0);
    let robots: usize = env("LOOPD_SOAK_ROBOTS", 16);
    let sessions: usize = env("LOOPD_SOAK_SESSIONS", 4);
    let window = Duration::from_secs_f64(env("LOOPD_SOAK_WINDOW_SECS", 30.0));
    let plot_path = PathBuf::from(env("LOOPD_SOAK_PLOT", "docs/img/soak.png".to_string()));
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let data = tempfile::tempdir()?;
    let (grpc, http) = (free_port(), free_port());
    let mut child: Child = std::process::Command::new(env!("CARGO_BIN_EXE_loopd"))
        .current_dir(&root)
        .args(["serve", "--data-dir"])
        .arg(data.path())
        .args(["--grpc-addr", &format!("127.0.0.1:{grpc}"), "--http-addr", &format!("127.0.0.1:{http}")])
        .env("LOOPD_DEVICE", "cpu")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()?;
    let pid = child.id();
    let url = format!("http://127.0.0.1:{grpc}");
    let info_url = format!("http://127.0.0.1:{http}");
    let t0 = Instant::now();
    let mut c = loop {
        if let Ok(c) = LoopdClient::connect(url.clone()).await {
            if reqwest::get(format!("{info_url}/readyz")).await.is_ok_and(|r| r.status() == 200) {
                break c;
            }
        }
        anyhow::ensure!(t0.elapsed() < Duration::from_secs(120), "loopd did not start");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let info: serde_json::Value = reqwest::get(format!("{info_url}/v1/info")).await?.json().await?;
    let dim = info["dim"].as_u64().unwrap_or(2048) as usize;
    for s in 0..sessions {
        c.create_session(pb::CreateSessionRequest { id: format!("soak-{s}"), ..Default::default() }).await?;
    }
    let shared = root.join("../shared/data/corridor/ref");
    let images: Arc<Vec<Vec<u8>>> =
        Arc::new((0..111).map(|i| std::fs::read(shared.join(format!("{i:07}.jpg")))).collect::<Result<_, _>>()?);
    let stop = Arc::new(AtomicBool::new(false));
    let w = Arc::new(Mutex::new(Window::default()));
    let mut tasks: Vec<_> = (0..robots)
        .map(|r| tokio::spawn(robot(r, url.clone(), sessions, dim, images.clone(), w.clone(), stop.clone())))
        .collect();
    tasks.push(tokio::spawn(churn(url.clone(), sessions, Duration::from_secs(180), stop.clone())));

    let total = Duration::from_secs_f64(minutes * 60.0);
    let bar = indicatif::ProgressBar::new(total.as_secs());
    let start = Instant::now();
    let mut rows = Vec::new();
    println!(
        "{:>7} {:>9} {:>7} {:>8} {:>8} {:>8} {:>6} {:>9} {:>9}",
        "minute", "req/s", "failed", "p50 ms", "p99 ms", "RSS MiB", "files", "disk MiB", "live MiB"
    );
    while start.elapsed() < total {
        tokio::time::sleep(window).await;
        let mut cur = std::mem::take(&mut *w.lock());
        let list: serde_json::Value = reqwest::get(format!("{info_url}/v1/sessions")).await?.json().await?;
        let live: u64 =
            list["sessions"].as_array().map_or(0, |a| a.iter().filter_map(|s| s["bytes_on_disk"].as_u64()).sum());
        let row = Row {
            minute: start.elapsed().as_secs_f64() / 60.0,
            per_s: cur.ok as f64 / window.as_secs_f64(),
            failed: cur.failed,
            p50_ms: percentile(&mut cur.latencies, 0.5),
            p99_ms: percentile(&mut cur.latencies, 0.99),
            rss_mib: rss_mib(pid),
            files: open_files(pid),
            disk_mib: dir_bytes(data.path()) as f64 / (1 << 20) as f64,
            live_mib: live as f64 / (1 << 20) as f64,
        };
        bar.suspend(|| {
            println!(
                "{:>7.1} {:>9.1} {:>7} {:>8.1} {:>8.1} {:>8.0} {:>6} {:>9.1} {:>9.1}",
                row.minute,
                row.per_s,
                row.failed,
                row.p50_ms,
                row.p99_ms,
                row.rss_mib,
                row.files,
                row.disk_mib,
                row.live_mib
            )
        });
        bar.set_position(start.elapsed().as_secs());
        rows.push(row);
    }
    bar.finish_and_clear();
    stop.store(true, Ordering::Relaxed);
    for t in tasks {
        let _ = t.await;
    }
    plot(&rows, &plot_path)?;
    println!("plot: {}", plot_path.display());
    let _ = child.kill();
    let _ = child.wait();
    Ok(())
}
