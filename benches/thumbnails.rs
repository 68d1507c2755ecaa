//! Thumbnails for the loop inspector: loopd's (`loopd::inspect::thumbnail::make`, what a session
//! with thumbnails runs per frame) against Pillow doing the same (benches/py/thumbnail.py: decode,
//! long side to 160 px, JPEG quality 80), on the same real frames, one thread each.
//!
//! env: LOOPD_BENCH_REPS (repetitions, median reported; default 5)
use loopd::inspect::thumbnail::make;
use loopd::model::preprocess::ImageLimits;
use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let data = std::env::var("LOOPD_SHARED_DATA").map(PathBuf::from).unwrap_or_else(|_| root.join("../shared/data"));
    let reps: usize = std::env::var("LOOPD_BENCH_REPS").ok().and_then(|v| v.parse().ok()).unwrap_or(5);
    let limits = ImageLimits::default();
    println!("| frames | count | mean thumbnail bytes | loopd ms/frame | Pillow ms/frame | loopd speed-up |");
    println!("|---|---:|---:|---:|---:|---:|");
    let sets = [
        ("desk 640x480 PNG", "slambook2-ch11", "png"),
        ("photos JPEG (352x448 to 3264x2448)", "photos", "jpg"),
        ("corridor 160x120 JPEG (kept as is)", "corridor/ref", "jpg"),
    ];
    for (name, dir, ext) in sets {
        let mut files: Vec<PathBuf> = std::fs::read_dir(data.join(dir))
            .expect("real frames in ../shared/data")
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == ext))
            .collect();
        files.sort();
        let bytes: Vec<Vec<u8>> = files.iter().map(|f| std::fs::read(f).expect("frame")).collect();
        let mut ours = Vec::new();
        let mut size = 0;
        for _ in 0..reps {
            let t = Instant::now();
            size = bytes.iter().map(|b| make(b, &limits).expect("thumbnail").len()).sum::<usize>();
            ours.push(t.elapsed().as_secs_f64());
        }
        let out = Command::new(root.join(".venv/bin/python"))
            .arg(root.join("benches/py/thumbnail.py"))
            .arg(reps.to_string())
            .args(&files)
            .output()
            .expect("python");
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let peer: f64 = String::from_utf8_lossy(&out.stdout).trim().parse().expect("seconds");
        let (n, ours) = (bytes.len() as f64, median(ours));
        println!(
            "| {name} | {} | {} | {:.2} | {:.2} | {:.2}x |",
            bytes.len(),
            size / bytes.len(),
            ours * 1e3 / n,
            peer * 1e3 / n,
            peer / ours
        );
    }
}
