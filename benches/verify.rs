//! Geometric verification: what it finds on real frames and what it costs, side by side.
//!
//! 1. Inliers on the desk (TUM RGB-D) and EuRoC pairs, with the EuRoC rotation error.
//! 2. Cost per piece at 640x480: extraction, one check with the scan matcher and with OpenCV's
//!    BFMatcher (the peer a user would pick), and K=5 candidates (one loop, four non-loops).
//! 3. The real server: add_and_query p50/p99 and frames/s for 1 and 8 robots, verification on and
//!    off, alternating in one run.
//!
//! env: LOOPD_BENCH_SECONDS (per server cell, default 8), LOOPD_BENCH_ROUNDS (default 200)
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::engine::EngineConfig;
use loopd::model::config::ModelConfig;
use loopd::model::device::DType;
use loopd::model::preprocess::ImageLimits;
use loopd::model::Model;
use loopd::pb;
use loopd::verify::features::{from_image_bytes, FeatureParams, Features};
use loopd::verify::geometric::{verify, Intrinsics, Matcher, VerifyParams};
use nalgebra::{Matrix3, Quaternion, UnitQuaternion};
use std::path::PathBuf;
use std::time::{Duration, Instant};

fn data(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data").join(rel)
}

fn features(rel: &str) -> Features {
    let bytes = std::fs::read(data(rel)).expect("real frame");
    from_image_bytes(&bytes, &ImageLimits::default(), &FeatureParams::default()).expect("features")
}

fn pct(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn time(rounds: usize, mut f: impl FnMut()) -> (f64, f64) {
    let mut ms: Vec<f64> = (0..rounds)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    (pct(&mut ms, 0.5), pct(&mut ms, 0.99))
}

/// EuRoC ground-truth rotation of cam0 between two frames (body poses, w x y z; T_BS of cam0).
fn euroc_rotation(q: [f64; 4], c: [f64; 4]) -> UnitQuaternion<f64> {
    let u = |a: [f64; 4]| UnitQuaternion::from_quaternion(Quaternion::new(a[0], a[1], a[2], a[3]));
    let r_bc = UnitQuaternion::from_matrix(&Matrix3::new(
        0.0148655429818,
        -0.999880929698,
        0.00414029679422,
        0.999557249008,
        0.0149672133247,
        0.025715529948,
        -0.0257744366974,
        0.00375618835797,
        0.999660727178,
    ));
    r_bc.inverse() * u(q).inverse() * u(c) * r_bc
}

fn quality() {
    let p = VerifyParams::default();
    let desk: Vec<Features> = (1..=10).map(|i| features(&format!("slambook2-ch11/{i}.png"))).collect();
    println!(
        "\nInliers (matches after ratio 0.8 / RANSAC inliers), {} ORB features",
        FeatureParams::default().max_features
    );
    println!("| pair | loop | matches | inliers | verified |");
    println!("|---|---|--:|--:|---|");
    let row = |name: &str, is_loop: bool, v: &loopd::verify::geometric::Verification| {
        println!("| {name} | {is_loop} | {} | {} | {} |", v.matches, v.inliers, v.verified);
    };
    row("desk 10 -> 1", true, &verify(&desk[9], &desk[0], None, &p));
    for j in 1..9 {
        row(&format!("desk {} -> 1", j + 1), false, &verify(&desk[j], &desk[0], None, &p));
    }
    let k = Intrinsics {
        fx: 458.654,
        fy: 457.296,
        cx: 367.215,
        cy: 248.375,
        dist: Some([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]),
    };
    let poses = [
        [0.338337, 0.608466, -0.535476, 0.478082],
        [0.478634, 0.415595, -0.700197, 0.328505],
        [0.3394, -0.672895, -0.492724, -0.435018],
        [0.39266, -0.590667, -0.58023, -0.400326],
    ];
    let e: Vec<Features> = (0..4).map(|i| features(&format!("euroc-lcd/left_img_{i}.png"))).collect();
    println!("\nEuRoC (essential matrix with the camera's intrinsics)");
    println!("| pair | loop | inliers (F) | inliers (E) | verified | rotation error deg | ground-truth rotation deg |");
    println!("|---|---|--:|--:|---|--:|--:|");
    for (q, c, is_loop) in [(1, 0, true), (3, 2, true), (2, 0, false), (3, 0, false), (2, 1, false), (3, 1, false)] {
        let f = verify(&e[q], &e[c], None, &p);
        let v = verify(&e[q], &e[c], Some(&k), &p);
        let gt = euroc_rotation(poses[q], poses[c]);
        let err = v
            .relative_pose
            .as_ref()
            .map_or("-".to_string(), |r| format!("{:.2}", (r.rotation().inverse() * gt).angle().to_degrees()));
        println!(
            "| left_img_{q} -> left_img_{c} | {is_loop} | {} | {} | {} | {err} | {:.1} |",
            f.inliers,
            v.inliers,
            v.verified,
            gt.angle().to_degrees()
        );
    }
}

fn cost(rounds: usize) {
    let bytes = std::fs::read(data("slambook2-ch11/1.png")).expect("desk frame");
    let q = features("slambook2-ch11/10.png");
    let cands: Vec<Features> = [1, 3, 5, 7, 9].iter().map(|i| features(&format!("slambook2-ch11/{i}.png"))).collect();
    let scan = VerifyParams::default();
    let ocv = VerifyParams { matcher: Matcher::OpenCv, ..VerifyParams::default() };
    println!("\nCost at 640x480 ({rounds} rounds each, ms)");
    println!("| step | p50 | p99 |");
    println!("|---|--:|--:|");
    let (a, b) = time(rounds, || {
        from_image_bytes(&bytes, &ImageLimits::default(), &FeatureParams::default()).expect("features");
    });
    println!("| decode PNG + extract ORB | {a:.2} | {b:.2} |");
    for (name, params) in [("scan matcher", &scan), ("OpenCV BFMatcher", &ocv)] {
        let (a, b) = time(rounds, || {
            verify(&q, &cands[0], None, params);
        });
        println!("| one loop candidate, {name} | {a:.2} | {b:.2} |");
        let (a, b) = time(rounds, || {
            cands.iter().for_each(|c| {
                verify(&q, c, None, params);
            })
        });
        println!("| K=5 candidates (1 loop, 4 not), {name} | {a:.2} | {b:.2} |");
    }
    println!("| stored bytes per frame | {} | |", q.encode().len());
}

async fn server_cell(addr: &str, robots: usize, verify_on: bool, budget: Duration, round: u32) -> (f64, f64, f64) {
    let session = format!("bench-{robots}-{verify_on}-{round}");
    let mut c = pb::loopd_client::LoopdClient::connect(addr.to_string()).await.expect("connect");
    c.create_session(pb::CreateSessionRequest { id: session.clone(), ..Default::default() }).await.expect("session");
    let frames: Vec<bytes::Bytes> =
        (1..=10).map(|i| std::fs::read(data(&format!("slambook2-ch11/{i}.png"))).expect("frame").into()).collect();
    let start = Instant::now();
    let tasks: Vec<_> = (0..robots)
        .map(|r| {
            let (mut c, frames, session) = (c.clone(), frames.clone(), session.clone());
            tokio::spawn(async move {
                let mut lat = Vec::new();
                let mut i = 0usize;
                while start.elapsed() < budget || lat.len() < 2 {
                    let req = pb::AddFrameRequest {
                        session_id: session.clone(),
                        robot_id: format!("robot{r}"),
                        timestamp: Some(i as f64),
                        content: Some(pb::add_frame_request::Content::Image(frames[(i + r) % frames.len()].clone())),
                        options: Some(pb::QueryOptions { k: Some(3), verify: Some(verify_on), ..Default::default() }),
                        ..Default::default()
                    };
                    let t = Instant::now();
                    c.add_and_query(req).await.expect("add_and_query");
                    lat.push(t.elapsed().as_secs_f64() * 1e3);
                    i += 1;
                }
                lat
            })
        })
        .collect();
    let mut all = Vec::new();
    for t in tasks {
        all.extend(t.await.expect("robot"));
    }
    let rate = all.len() as f64 / start.elapsed().as_secs_f64();
    (rate, pct(&mut all, 0.5), pct(&mut all, 0.99))
}

fn server(seconds: u64) -> anyhow::Result<()> {
    let rt = tokio::runtime::Runtime::new()?;
    let dir = tempfile::tempdir()?;
    rt.block_on(async {
        let weights = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("weights/resnet50-imagenet.safetensors");
        let (model, _) = Model::load(&weights, ModelConfig::default(), tch::Device::Cpu, DType::F32)?;
        let cfg = ServerConfig {
            engine: EngineConfig { max_batch: 8, ..Default::default() },
            ..ServerConfig::on_loopback(dir.path().to_path_buf())
        };
        let server = RunningServer::start(cfg, model).await?;
        let addr = format!("http://{}", server.grpc_addr);
        println!("\nServer, add_and_query with 640x480 desk frames over gRPC (ImageNet model on CPU, k=3, K=5)");
        println!("| robots | verification | frames/s | p50 ms | p99 ms |");
        println!("|--:|---|--:|--:|--:|");
        for robots in [1usize, 8] {
            // Alternating so the machine's drift hits both settings.
            for (round, verify_on) in [false, true, false, true].into_iter().enumerate() {
                let (rate, p50, p99) =
                    server_cell(&addr, robots, verify_on, Duration::from_secs(seconds), round as u32).await;
                let on = if verify_on { "on" } else { "off" };
                println!("| {robots} | {on} | {rate:.1} | {p50:.1} | {p99:.1} |");
            }
        }
        server.shutdown().await
    })
}

fn main() -> anyhow::Result<()> {
    let env = |k: &str, d: u64| std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d);
    println!("loopd verification bench, {} cores", std::thread::available_parallelism().map_or(1, |n| n.get()));
    quality();
    cost(env("LOOPD_BENCH_ROUNDS", 200) as usize);
    server(env("LOOPD_BENCH_SECONDS", 8))
}
