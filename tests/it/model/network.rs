//! The descriptor network on real ImageNet weights and real photos.
use crate::common::*;
use loopd::model::config::ModelConfig;
use loopd::model::device::DType;
use loopd::model::network::Variant;
use loopd::model::weights::{named_tensors, WeightFile};
use loopd::model::{rows, tfjs, Model};
use tch::{Device, Tensor};

#[test]
fn import_consumes_every_keras_array_and_fills_every_backbone_tensor() {
    let dir = root().join("weights/pkg/package/ResNet50");
    let imported = tfjs::import(&dir).expect("import");
    // 53 convs (kernel + bias) + 53 batch norms (4 arrays) + fc (2) = 320; import fails on any unmapped array.
    assert_eq!(imported.keras_arrays, 320);
    assert_eq!(imported.shard_bytes, 25_636_712 * 4, "ResNet50 has 25,636,712 float32 parameters");
    let model = Model::new(ModelConfig::default(), Device::Cpu, DType::F32).unwrap();
    let vars = model.var_store().variables();
    let backbone: Vec<_> = vars.keys().filter(|k| !k.starts_with("attention.") && !k.starts_with("fusion.")).collect();
    assert_eq!(imported.tensors.len(), backbone.len(), "one file tensor per backbone variable");
    for (name, t) in &imported.tensors {
        let var = vars.get(name).unwrap_or_else(|| panic!("{name} is not a model variable"));
        assert_eq!(var.size(), t.size(), "{name}");
    }
    // The written file carries exactly those tensors, values and metadata.
    let file = WeightFile::read(&weights()).unwrap();
    assert_eq!(file.metadata.get("stride_layout").map(String::as_str), Some("v1"));
    assert_eq!(file.tensors.len(), imported.tensors.len());
    for (name, t) in &file.tensors {
        let (_, fresh) = imported.tensors.iter().find(|(n, _)| n == name).unwrap();
        assert_eq!(f64::try_from((t - fresh).abs().max()).unwrap(), 0.0, "{name}");
    }
}

#[test]
fn nothing_is_left_random_after_loading() {
    // Two loads under different seeds must give the same descriptors: every tensor
    // that matters came from the file, and the heads start as the exact identity.
    tch::manual_seed(1);
    let a = imagenet_model();
    tch::manual_seed(2);
    let b = imagenet_model();
    let inputs: Vec<Tensor> = photo_inputs(&a).into_iter().take(2).collect();
    for v in Variant::ALL {
        let da = a.descriptors(&inputs, v).unwrap();
        let db = b.descriptors(&inputs, v).unwrap();
        assert_eq!(f64::try_from((da - db).abs().max()).unwrap(), 0.0, "{}", v.name());
    }
}

#[test]
fn untrained_attention_and_fusion_are_the_identity() {
    let model = imagenet_model();
    let inputs = photo_inputs(&model);
    let plain = model.descriptors(&inputs, Variant::BACKBONE).unwrap();
    for v in Variant::ALL {
        let d = model.descriptors(&inputs, v).unwrap();
        assert_eq!(f64::try_from((&d - &plain).abs().max()).unwrap(), 0.0, "{} differs from the backbone", v.name());
    }
    // and that descriptor is a unit vector
    let norms = plain.norm_scalaropt_dim(2, [1i64].as_slice(), false);
    assert!(f64::try_from((norms - 1.0).abs().max()).unwrap() < 1e-5);
}

#[test]
fn tokyo_pair_is_the_most_similar_pair() {
    let model = imagenet_model();
    let d = rows(&model.descriptors(&photo_inputs(&model), Variant::FULL).unwrap()).unwrap();
    let cos = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
    let (db, q) = (
        PHOTOS.iter().position(|p| *p == "tokyo_db.png").unwrap(),
        PHOTOS.iter().position(|p| *p == "tokyo_query.jpg").unwrap(),
    );
    let pair = cos(&d[db], &d[q]);
    for (i, name) in PHOTOS.iter().enumerate() {
        if i == db || i == q {
            continue;
        }
        for t in [db, q] {
            let other = cos(&d[t], &d[i]);
            assert!(pair > other, "tokyo pair {pair:.4} not above {} vs {name} {other:.4}", PHOTOS[t]);
        }
    }
}

fn top1(image: &str) -> String {
    let out = loopd_bin().args(["classify", data(&format!("photos/{image}")).to_str().unwrap()]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.lines().count(), 5, "top-5, one per line: {text}");
    text.lines().next().unwrap().split('\t').next().unwrap().to_string()
}

#[test]
fn classify_names_the_dog_and_the_eagle() {
    let dog = top1("dog.jpg");
    assert!(["malamute", "Eskimo_dog", "Siberian_husky"].contains(&dog.as_str()), "dog.jpg top-1 is {dog}");
    assert_eq!(top1("eagle.jpg"), "bald_eagle");
}

#[test]
fn rust_matches_the_pytorch_reference_with_random_heads() {
    let model = imagenet_model();
    model.randomize(7, true);
    let dir = tempfile::tempdir().unwrap();
    let w = dir.path().join("random-heads.safetensors");
    let mut meta = std::collections::HashMap::new();
    meta.insert("stride_layout".to_string(), "v1".to_string());
    WeightFile::write(&w, &named_tensors(model.var_store()), meta).unwrap();
    // Reload from the file so both implementations see exactly the same numbers.
    let (model, report) = Model::load(&w, ModelConfig::default(), Device::Cpu, DType::F32).unwrap();
    assert!(report.heads_from_file);
    let inputs = photo_inputs(&model);
    let mut expected = Vec::new();
    let plain = model.descriptors(&inputs, Variant::BACKBONE).unwrap();
    for v in Variant::ALL {
        let d = model.descriptors(&inputs, v).unwrap();
        if v != Variant::BACKBONE {
            // random heads are not the identity: the variant must change the descriptor
            assert!(f64::try_from((&d - &plain).abs().max()).unwrap() > 1e-3, "{} equals the backbone", v.name());
        }
        expected.push((v.name().to_string(), d));
    }
    let inp = dir.path().join("inputs.safetensors");
    let exp = dir.path().join("expected.safetensors");
    WeightFile::write(&inp, &[("inputs".to_string(), Tensor::stack(&inputs, 0))], Default::default()).unwrap();
    WeightFile::write(&exp, &expected, Default::default()).unwrap();
    let out = std::process::Command::new(root().join(".venv/bin/python"))
        .arg(root().join("tests/reference/reference.py"))
        .args([&w, &inp, &exp])
        .output()
        .expect("running the .venv python");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("reference: {stdout}{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "PyTorch reference disagrees: {stdout}");
    let report: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(report["max_abs_diff"].as_object().unwrap().len(), 4);
}

#[test]
fn stride_layouts_and_aspect_preserving_resize() {
    use loopd::model::config::{ResizeMode, StrideLayout};
    // Same random weights, the two stride placements: both run, and they differ.
    let mut cfg = ModelConfig::default();
    let v1 = Model::new(cfg.clone(), Device::Cpu, DType::F32).unwrap();
    v1.randomize(11, false);
    cfg.stride_layout = StrideLayout::V15;
    let v15 = Model::new(cfg.clone(), Device::Cpu, DType::F32).unwrap();
    v15.randomize(11, false);
    let inputs = photo_inputs(&v1);
    let (a, b) =
        (v1.descriptors(&inputs[..1], Variant::FULL).unwrap(), v15.descriptors(&inputs[..1], Variant::FULL).unwrap());
    assert_eq!(a.size(), vec![1, 2048]);
    assert!(f64::try_from((a - b).abs().max()).unwrap() > 1e-3);
    // Keep the aspect ratio: a 768x576 photo fits 224x224 as 224x168, and still embeds.
    cfg.preprocess.resize = ResizeMode::Keep;
    let keep = Model::new(cfg, Device::Cpu, DType::F32).unwrap();
    let bytes = std::fs::read(data("photos/dog.jpg")).unwrap();
    let x = loopd::model::preprocess::prepare(&bytes, &Default::default(), &keep.config.preprocess).unwrap();
    assert_eq!(x.size(), vec![3, 168, 224]);
    assert_eq!(keep.descriptors(&[x], Variant::FULL).unwrap().size(), vec![1, 2048]);
}

#[test]
fn half_precision_is_refused_on_cpu_with_a_clear_message() {
    let out = loopd_bin()
        .args(["embed", "--dtype", "f16", "--device", "cpu", data("photos/dog.jpg").to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("needs a CUDA device") && !err.contains("panicked"), "{err}");
}

/// Power-normalised pooling: each value is the square root of average pooling's (the pooled
/// values are non-negative after ReLU), renormalised; the Tokyo pair stays the closest pair.
#[test]
fn square_root_pooling_is_the_root_of_average_pooling() {
    use loopd::model::config::Pooling;
    let gap = imagenet_model();
    let cfg = ModelConfig { pooling: Pooling::GapSqrt, ..ModelConfig::default() };
    let (sqrt, _) = loopd::model::Model::load(&weights(), cfg, tch::Device::Cpu, DType::F32).unwrap();
    assert_ne!(gap.descriptor_id(Variant::FULL), sqrt.descriptor_id(Variant::FULL));
    let inputs = photo_inputs(&gap);
    let a = rows(&gap.descriptors(&inputs, Variant::FULL).unwrap()).unwrap();
    let b = rows(&sqrt.descriptors(&inputs, Variant::FULL).unwrap()).unwrap();
    for (x, y) in a.iter().zip(&b) {
        let root: Vec<f32> = x.iter().map(|v| v.max(0.0).sqrt()).collect();
        let n = root.iter().map(|v| v * v).sum::<f32>().sqrt();
        let max_diff = root.iter().zip(y).map(|(r, y)| (r / n - y).abs()).fold(0f32, f32::max);
        assert!(max_diff < 1e-4, "sqrt pooling differs from the root of average pooling by {max_diff}");
        assert!((y.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-4);
    }
    let cos = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
    let (db, q) = (
        PHOTOS.iter().position(|p| *p == "tokyo_db.png").unwrap(),
        PHOTOS.iter().position(|p| *p == "tokyo_query.jpg").unwrap(),
    );
    let pair = cos(&b[db], &b[q]);
    for i in (0..PHOTOS.len()).filter(|&i| i != db && i != q) {
        assert!(pair > cos(&b[db], &b[i]) && pair > cos(&b[q], &b[i]), "{}", PHOTOS[i]);
    }
}
