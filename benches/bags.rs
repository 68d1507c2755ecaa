//! Reading bags into frames: loopd's reader (`loopd::bags::frames`, what a bag upload runs) against
//! what a user would otherwise run to take the images out, rosbags with Pillow for raw images
//! (benches/py/bag_read.py), on the same bags of real frames (corridor JPEGs as CompressedImage,
//! the desk PNGs as raw rgb8), MCAP (zstd chunks) and ROS 1 (lz4 or none).
//!
//! env: LOOPD_BENCH_REPS (repetitions, median reported; default 5)
use loopd::bags::{frames, Limits, Selection};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

const TOPIC: &str = "/robot1/cam/image_raw";

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn bag_file(p: &Path) -> PathBuf {
    if p.is_dir() {
        std::fs::read_dir(p)
            .expect("bag folder")
            .filter_map(|e| e.ok().map(|e| e.path()))
            .find(|f| f.extension().is_some_and(|x| x == "mcap"))
            .expect("an .mcap in the folder")
    } else {
        p.to_path_buf()
    }
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let python = root.join(".venv/bin/python");
    let script = root.join("benches/py/bag_read.py");
    let reps: usize = std::env::var("LOOPD_BENCH_REPS").ok().and_then(|v| v.parse().ok()).unwrap_or(5);
    let dir = tempfile::tempdir().expect("temp dir");
    let made = Command::new(&python).arg(&script).arg("make").arg(dir.path()).status().expect("python");
    assert!(made.success(), "making the bags failed");
    let limits = Limits { max_frames: 100_000, max_chunk_bytes: 256 << 20 };
    println!(
        "| bag | frames | MB | loopd ms | loopd frames/s | rosbags+Pillow ms | rosbags frames/s | loopd speed-up |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for (name, topic) in [
        ("corridor-jpeg-zstd", format!("{TOPIC}/compressed")),
        ("corridor-jpeg.bag", format!("{TOPIC}/compressed")),
        ("desk-rgb8-zstd", TOPIC.to_string()),
        ("desk-rgb8-lz4.bag", TOPIC.to_string()),
    ] {
        let path = dir.path().join(name);
        let bytes = std::fs::read(bag_file(&path)).expect("bag");
        let sel = Selection { topics: vec![topic.clone()], ..Selection::default() };
        let mut ours = Vec::new();
        let mut n = 0;
        for _ in 0..reps {
            let t = Instant::now();
            n = frames(&[&bytes], &sel, &limits).expect("loopd reads the bag").len();
            ours.push(t.elapsed().as_secs_f64());
        }
        let out = Command::new(&python).arg(&script).arg("read").arg(&path).arg(&topic).arg(reps.to_string()).output();
        let peer: serde_json::Value = serde_json::from_slice(&out.expect("python").stdout).expect("peer output");
        let theirs: Vec<f64> = peer["seconds"].as_array().expect("seconds").iter().filter_map(|v| v.as_f64()).collect();
        assert_eq!(peer["frames"].as_u64(), Some(n as u64), "both read the same frames");
        let (a, b) = (median(ours), median(theirs));
        println!(
            "| {name} | {n} | {:.1} | {:.1} | {:.0} | {:.1} | {:.0} | {:.2}x |",
            bytes.len() as f64 / 1e6,
            a * 1e3,
            n as f64 / a,
            b * 1e3,
            n as f64 / b,
            b / a
        );
    }
}
