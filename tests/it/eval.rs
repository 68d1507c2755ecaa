//! Ground-truth loading (the paper's four matrices) and `loopd eval` end to end on real data.
use crate::common::*;
use loopd::eval::gt::GroundTruth;

#[test]
fn the_four_ground_truth_matrices_load_and_agree_with_their_csv_lists() {
    for (mat, csv, pairs) in [
        ("city_GT_final.mat", "CC_1237_knzhang.csv", 8_321),
        ("NewCollegeGroundTruth.mat", "NC_2146_oxford_original.csv", 14_832),
        ("groundTruth_KITTI00.mat", "KITTI00_4541_knzhang_ICRA18.csv", 31_922),
        ("kitti02GroundTruth.mat", "KITTI02_4661_knzhang.csv", 4_037),
    ] {
        let m = GroundTruth::from_mat(&data(&format!("groundtruth/{mat}")), None).unwrap();
        let c = GroundTruth::from_csv(&data(&format!("groundtruth/{csv}"))).unwrap();
        assert_eq!(m.pairs(), pairs, "{mat}");
        assert_eq!(m, c, "{mat} and {csv} disagree");
    }
    // New College, one camera: every second row and column.
    let nc = GroundTruth::from_mat(&data("groundtruth/NewCollegeGroundTruth.mat"), None).unwrap();
    let left = GroundTruth::from_mat(&data("groundtruth/NewCollegeGroundTruth.mat"), Some(0)).unwrap();
    let expected = nc
        .loops
        .iter()
        .flat_map(|(&q, rs)| rs.iter().map(move |&r| (q, r)))
        .filter(|(q, r)| q % 2 == 0 && r % 2 == 0)
        .count();
    assert_eq!(left.pairs(), expected);
    assert!(left.loops.keys().all(|&q| q < 1073));
}

fn eval_json(args: &[&str]) -> serde_json::Value {
    let out = loopd_bin().arg("eval").args(args).arg("--json").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn eval_on_the_desk_frames_finds_the_loop_writes_figures_and_caches() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, gt) = (data("slambook2-ch11"), root().join("tests/gt/desk.csv"));
    let cache = dir.path().join("cache");
    let out = dir.path().join("out");
    let args = [
        "--sequence",
        seq.to_str().unwrap(),
        "--gt",
        gt.to_str().unwrap(),
        "--exclude",
        "2",
        "--cache-dir",
        cache.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    let r = eval_json(&args);
    assert_eq!(r["positives"], 1);
    assert_eq!(r["queries"], 10);
    assert_eq!(r["recall_at_1"], 1.0, "{r}");
    assert!(r["recall_at_100_precision"].as_f64().unwrap() == 1.0, "{r}");
    assert!(r["pr_curve"].as_array().unwrap().len() >= 2);
    for f in ["report.json", "pr_curve.png", "similarity.png"] {
        let bytes = std::fs::read(out.join(f)).unwrap();
        assert!(bytes.len() > 100, "{f}");
    }
    assert!(image::open(out.join("similarity.png")).unwrap().width() == 10);
    // Rerun with other search settings: descriptors come from the cache (no weights needed).
    let cached = std::fs::read_dir(&cache).unwrap().count();
    assert_eq!(cached, 1);
    let out2 = loopd_bin()
        .arg("eval")
        .args(&args[..4])
        .args(["--exclude", "8", "--cache-dir", cache.to_str().unwrap(), "--json"])
        .env("RUST_LOG", "info")
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out2.stderr).contains("descriptors from cache"));
    let r2: serde_json::Value = serde_json::from_slice(&out2.stdout).unwrap();
    assert_eq!(r2["exclude"], 8);
}

#[test]
fn eval_two_traversals_of_the_corridor() {
    let r = eval_json(&[
        "--sequence",
        data("corridor/ref").to_str().unwrap(),
        "--query-sequence",
        data("corridor/query").to_str().unwrap(),
        "--gt",
        data("corridor/gt.csv").to_str().unwrap(),
        "--cache-dir",
        process_cache().to_str().unwrap(),
    ]);
    assert_eq!((r["queries"].as_u64(), r["positives"].as_u64()), (Some(111), Some(111)));
    // The store test measured recall@1 0.56 with the same backbone features.
    let r1 = r["recall_at_1"].as_f64().unwrap();
    assert!((0.5..0.65).contains(&r1), "{r}");
    let ap = r["average_precision"].as_f64().unwrap();
    assert!(ap > 0.0 && ap <= r1 + 1e-9, "{r}");
}

/// `loopd eval --depth --poses` on tum-desk: the verified loops get metric poses from the depth
/// images and each is scored against the ground-truth camera poses.
#[test]
fn eval_scores_metric_loop_poses_against_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let desk = data("rgbd-slambook2/tum-desk");
    let (color, depth, poses) = (desk.join("color"), desk.join("depth"), desk.join("pose.txt"));
    let gt = root().join("tests/gt/tum-desk.csv");
    let cache = dir.path().join("cache");
    let path = |p: &std::path::PathBuf| p.to_str().unwrap().to_string();
    let mut args: Vec<String> =
        ["--sequence", &path(&color), "--gt", &path(&gt), "--exclude", "0"].into_iter().map(String::from).collect();
    args.extend(["--verify", "geometric", "--intrinsics", "518,519,325.5,253.5", "--cache-dir"].map(String::from));
    args.push(path(&cache));
    let without: Vec<&str> = args.iter().map(String::as_str).collect();
    let r = eval_json(&without);
    assert!(r.get("pose_errors").is_none(), "no depth, no poses: {r}");
    args.extend(["--depth".to_string(), path(&depth), "--poses".to_string(), path(&poses)]);
    let with: Vec<&str> = args.iter().map(String::as_str).collect();
    let r = eval_json(&with);
    let errors = r["pose_errors"].as_array().unwrap();
    assert!(errors.len() >= 3, "{r}");
    for e in errors {
        eprintln!("{e}");
        assert!(e["translation_m"].as_f64().unwrap() < 0.10, "{e}");
        assert!(e["rotation_deg"].as_f64().unwrap() < 2.0, "{e}");
        assert!(e["distance_m"].as_f64().unwrap() > 0.1, "{e}");
    }
    assert_eq!(r["recall_at_100_precision"], 1.0, "{r}");
}
