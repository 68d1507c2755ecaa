//! Models brought as TorchScript (issue #39): exported here with the venv's torch
//! (tests/reference/script_models.py), checked with `loopd models check` on real images, and
//! compared with PyTorch on the same pixels.
use crate::common::*;
use loopd::model::script::ScriptModel;
use std::path::Path;
use std::process::Output;

const IMAGES: [&str; 5] =
    ["slambook2-ch11/1.png", "slambook2-ch11/10.png", "photos/dog.jpg", "photos/tokyo_db.png", "photos/scream.jpg"];

fn python(args: &[&std::ffi::OsStr]) -> Output {
    std::process::Command::new(root().join(".venv/bin/python"))
        .arg(root().join("tests/reference/script_models.py"))
        .args(args)
        .output()
        .expect("running the .venv python")
}

fn export(dir: &Path) {
    let out = python(&["export".as_ref(), dir.as_os_str()]);
    assert!(out.status.success(), "exporting the test models: {}", String::from_utf8_lossy(&out.stderr));
}

fn check(model: &Path, save: Option<&Path>) -> Output {
    let mut c = loopd_bin();
    c.arg("models").arg("check").arg(model);
    for i in IMAGES {
        c.arg("--image").arg(data(i));
    }
    if let Some(s) = save {
        c.arg("--save").arg(s);
    }
    c.output().expect("running loopd")
}

#[test]
fn torchscript_models_give_pytorchs_descriptors_on_real_images() {
    let dir = tempfile::tempdir().unwrap();
    export(dir.path());
    let mut ids = Vec::new();
    for (name, dim) in [("small-resnet", 512), ("small-bgr", 256)] {
        let model = dir.path().join(name);
        let saved = dir.path().join(format!("{name}.out"));
        let out = check(&model, Some(&saved));
        let stdout = String::from_utf8_lossy(&out.stdout);
        eprintln!("{stdout}{}", String::from_utf8_lossy(&out.stderr));
        assert!(out.status.success(), "loopd models check {name} failed");
        let id = stdout.lines().find_map(|l| l.strip_prefix("descriptor id ")).expect("a descriptor id line");
        assert!(id.starts_with(&format!("script-{name}-")), "{id}");
        ids.push(id.to_string());
        // PyTorch, on loopd's input for each image: the same unit descriptor, and the same input
        // from the same resized pixels by the manifest's channel order, scale, mean and std.
        let cmp = python(&["compare".as_ref(), model.as_os_str(), saved.as_os_str()]);
        let report = String::from_utf8_lossy(&cmp.stdout);
        eprintln!("{name} against PyTorch: {report}{}", String::from_utf8_lossy(&cmp.stderr));
        assert!(cmp.status.success(), "{name}: loopd and PyTorch differ by more than 1e-5");
        let report: serde_json::Value = serde_json::from_str(report.trim()).unwrap();
        let rows = report.as_object().unwrap();
        assert_eq!(rows.len(), IMAGES.len());
        assert!(rows.values().all(|r| r["dim"] == dim));
        // In process, the library gives the CLI's descriptor id and unit rows of the stated size.
        let m = ScriptModel::load(&model, tch::Device::Cpu).unwrap();
        assert_eq!(m.descriptor_id(), ids[ids.len() - 1]);
        let img =
            loopd::model::preprocess::decode(&std::fs::read(data(IMAGES[0])).unwrap(), &Default::default()).unwrap();
        let d = m.descriptors(&[m.to_input(&img)]).unwrap();
        assert_eq!(d.size(), vec![1, dim]);
        assert!((f64::try_from(d.norm()).unwrap() - 1.0).abs() < 1e-5);
    }
    assert_ne!(ids[0], ids[1]);
    // The same file with another resize is another descriptor space.
    let manifest = dir.path().join("small-resnet/model.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    std::fs::write(&manifest, text.replace("\"width\": 320", "\"width\": 352")).unwrap();
    let other = ScriptModel::load(&dir.path().join("small-resnet"), tch::Device::Cpu).unwrap();
    assert_ne!(other.descriptor_id(), ids[0]);
}

#[test]
fn a_broken_model_or_manifest_is_refused_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    export(dir.path());
    let refused = |model: &Path, why: &str| {
        let out = check(model, None);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{} was accepted", model.display());
        assert!(stderr.contains(why), "{}: expected {why:?} in {stderr}", model.display());
    };
    refused(&dir.path().join("wrong-dim"), "returned a tensor of shape [1, 512]; its manifest says [N, 128]");
    refused(&dir.path().join("nan"), "not finite");
    refused(&dir.path().join("missing"), "model.json");
    // Manifest errors, each on a copy of a good model.
    let bad = |name: &str, edit: &dyn Fn(&mut serde_json::Value)| {
        let d = dir.path().join(name);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::copy(dir.path().join("small-resnet/model.pt"), d.join("model.pt")).unwrap();
        let mut m: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("small-resnet/model.json")).unwrap()).unwrap();
        edit(&mut m);
        std::fs::write(d.join("model.json"), m.to_string()).unwrap();
        d
    };
    refused(&bad("unknown-field", &|m| m["input"]["mean_rgb"] = serde_json::json!([0, 0, 0])), "not a model manifest");
    refused(&bad("zero-std", &|m| m["input"]["std"] = serde_json::json!([0.2, 0.0, 0.2])), "std positive");
    refused(&bad("tiny", &|m| m["input"]["width"] = serde_json::json!(8)), "each side must be 32 to 4096 pixels");
    refused(&bad("bad name", &|m| m["name"] = serde_json::json!("a/b")), "letters, digits");
    refused(&bad("outside", &|m| m["file"] = serde_json::json!("../small-resnet/model.pt")), "inside the model folder");
    let not_ts = bad("not-torchscript", &|_| {});
    std::fs::write(not_ts.join("model.pt"), b"not a zip archive").unwrap();
    refused(&not_ts, "not a TorchScript file libtorch can load");
    // A model that says it normalises but does not.
    refused(
        &bad("claims-normalized", &|m| m["normalized"] = serde_json::json!(true)),
        "the manifest says the output is normalised",
    );
}
