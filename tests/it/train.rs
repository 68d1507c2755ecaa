//! `loopd train` on real frames: a step equals PyTorch's, a short run lowers the loss and its heads
//! change the descriptors, the same seed gives the same heads, a stopped run resumes, bad input
//! is refused before any step.
use crate::common::*;
use loopd::engine::{Engine, EngineConfig};
use loopd::model::config::{ModelConfig, Preprocess};
use loopd::model::device::DType;
use loopd::model::network::Variant;
use loopd::model::preprocess::{decode, normalize, resized_rgb, to_input, ImageLimits};
use loopd::model::weights::{named_tensors, WeightFile};
use loopd::model::Model;
use loopd::train::data::{TrainSet, TraversalSource};
use loopd::train::loss::MsParams;
use loopd::train::run::{optimizer, step, train, Recipe, TrainSpec, ValSet, WhitenSpec};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use tch::{Device, Kind, Tensor};

/// Training and `randomize` seed torch's global generator, and building a model draws from it:
/// tests here take turns, so that another test's draws cannot fall between a seed and its use.
static TRAINING: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn turn() -> std::sync::MutexGuard<'static, ()> {
    TRAINING.lock().unwrap_or_else(|e| e.into_inner())
}

fn nordland(season: &str) -> PathBuf {
    data(&format!("nordland-64x32/{season}"))
}

fn recipe(epochs: usize, seed: u64) -> Recipe {
    Recipe {
        epochs,
        places_per_batch: 4,
        views: 2,
        lr: 1e-2,
        weight_decay: 1e-4,
        warmup_steps: 2,
        clip_norm: 1.0,
        seed,
        steps_per_epoch: None,
        patience: 0,
        train_layer4: false,
        augment_labelled: false,
        loss: MsParams::default(),
        autocast: loopd::model::device::DType::F32,
    }
}

/// Nordland places 0..24 (summer and winter) at their native 64x32: seconds per epoch on CPU.
fn tiny_spec(out: &Path, epochs: usize, seed: u64) -> TrainSpec {
    let mut set = TrainSet::default();
    set.add_traversal(&TraversalSource {
        sequence: nordland("summer"),
        query_sequence: Some(nordland("winter")),
        gt: "aligned".into(),
        camera: None,
        tolerance: 2,
        range: Some(0..24),
        filter: None,
    })
    .unwrap();
    let mut config = ModelConfig::default();
    config.preprocess.width = 64;
    config.preprocess.height = 32;
    TrainSpec {
        weights: weights(),
        init_heads: None,
        val_config: config.clone(),
        config,
        device: Device::Cpu,
        set,
        val: vec![ValSet {
            name: "nordland-val".into(),
            sequence: nordland("summer"),
            query_sequence: Some(nordland("winter")),
            gt: "aligned".into(),
            tolerance: 2,
            exclude: 0,
            range: Some(2000..2040),
            filter: None,
        }],
        out: out.to_path_buf(),
        name: None,
        recipe: recipe(epochs, seed),
        whiten: None,
        resume: false,
        cache_dir: None,
    }
}

fn tensors(path: &Path) -> Vec<(String, Tensor)> {
    let mut t = WeightFile::read(path).unwrap().tensors;
    t.sort_by(|a, b| a.0.cmp(&b.0));
    t
}

#[test]
fn a_short_training_lowers_the_loss_and_its_heads_change_the_descriptors() {
    let _turn = turn();
    let dir = tempfile::tempdir().unwrap();
    let mut spec = tiny_spec(dir.path(), 8, 1);
    spec.whiten = Some(WhitenSpec { dim: Some(16), frames: 48, shrink: 0.1 });
    let out = train(&spec).unwrap();
    let losses: Vec<f64> = out.state.losses.iter().map(|l| l.1).collect();
    assert_eq!(losses.len(), 8 * 6, "24 places / 4 per batch = 6 steps per epoch");
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (first, last) = (mean(&losses[..6]), mean(&losses[losses.len() - 6..]));
    eprintln!("loss first epoch {first:.4}, last epoch {last:.4}");
    assert!(last < 0.85 * first, "loss did not fall: {first} -> {last}");
    assert_eq!(out.state.validation.len(), 9, "epoch 0 (before training) and 8 epochs validated");
    for f in ["heads.safetensors", "checkpoint.safetensors", "state.json", "loss.png", "validation.png"] {
        assert!(dir.path().join(f).is_file(), "{f} missing");
    }
    // The heads file loads on top of the backbone and changes what it computes.
    let load = |heads: Option<&Path>| {
        let mut cfg = ModelConfig::default();
        cfg.preprocess = Preprocess { width: 64, height: 32, ..cfg.preprocess };
        let (mut m, _) = Model::load(&weights(), cfg, Device::Cpu, DType::F32).unwrap();
        if let Some(h) = heads {
            m.load_heads(h).unwrap();
        }
        m
    };
    let (plain, trained) = (load(None), load(Some(&out.heads)));
    assert_eq!(trained.dim(), 16, "whitened to 16 dimensions");
    let best = dir.path().join("best.safetensors");
    let unwhitened = load(Some(&best));
    assert_eq!(unwhitened.dim(), 2048);
    let x = to_input(
        &decode(&std::fs::read(nordland("winter").join("images-20100.png")).unwrap(), &ImageLimits::default()).unwrap(),
        &plain.config.preprocess,
    );
    let (a, b) = (
        plain.descriptors(std::slice::from_ref(&x), Variant::FULL).unwrap(),
        unwhitened.descriptors(&[x], Variant::FULL).unwrap(),
    );
    if out.state.best_epoch > 0 {
        assert!(f64::try_from((a - b).abs().max()).unwrap() > 1e-4, "trained heads left the descriptor unchanged");
    }
    // Its own descriptor space: sessions of the identity heads refuse it, and the id names it.
    let id = trained.descriptor_id(Variant::FULL);
    assert!(id.contains("-h") && id != plain.descriptor_id(Variant::FULL), "{id}");
    let engine =
        Engine::start(trained, EngineConfig { warm_up: false, ..Default::default() }, ImageLimits::default()).unwrap();
    assert!(!engine.info().compatible(&plain.descriptor_id(Variant::FULL)));
    assert_eq!(engine.info().dim, 16);
    // The heads file carries only heads and whitening, with its metadata.
    let file = WeightFile::read(&out.heads).unwrap();
    assert!(file
        .tensors
        .iter()
        .all(|(n, _)| n.starts_with("attention.") || n.starts_with("fusion.") || n.starts_with("whiten.")));
    for k in ["backbone_sha256", "datasets", "recipe", "seed", "steps", "validation"] {
        assert!(file.metadata.contains_key(k), "metadata {k} missing");
    }
}

#[test]
fn the_same_seed_gives_the_same_heads_and_a_resumed_run_continues() {
    let _turn = turn();
    let (a, b, c) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let mut spec = tiny_spec(a.path(), 2, 5);
    spec.val.clear();
    train(&spec).unwrap();
    spec.out = b.path().to_path_buf();
    train(&spec).unwrap();
    let (ta, tb) =
        (tensors(&a.path().join("checkpoint.safetensors")), tensors(&b.path().join("checkpoint.safetensors")));
    assert_eq!(ta.len(), tb.len());
    for ((n, x), (_, y)) in ta.iter().zip(&tb) {
        assert!(x.equal(y), "{n} differs between two runs with seed 5");
    }
    // Another seed trains other heads.
    spec.out = c.path().to_path_buf();
    spec.recipe.seed = 6;
    spec.recipe.epochs = 1;
    train(&spec).unwrap();
    // Stopped after epoch 1 of 2, resumed: it continues at epoch 2 and step 6.
    spec.recipe.epochs = 2;
    spec.resume = true;
    let out = train(&spec).unwrap();
    assert_eq!(out.state.epochs_done, 2);
    assert_eq!(out.state.losses.len(), 12);
    assert_eq!(out.state.losses[6].0, 6, "the resumed run numbers its steps on");
}

/// The heads' starting values come from the seed alone, whatever else draws from libtorch's
/// global generator meanwhile (another thread's model load did, and the same seed trained other
/// heads), in the ranges the layers' own initialisers draw from; zero-initialised ones stay zero.
#[test]
fn the_heads_starting_values_come_from_the_seed_alone() {
    let heads = |m: &Model| -> Vec<(String, Tensor)> {
        named_tensors(m.var_store()).into_iter().filter(|(n, _)| n.starts_with("attention.")).collect()
    };
    let a = imagenet_model();
    a.seed_heads(5);
    let _ = Tensor::randn([1000], (Kind::Float, Device::Cpu));
    let b = imagenet_model();
    let _ = Tensor::randn([1000], (Kind::Float, Device::Cpu));
    b.seed_heads(5);
    let c = imagenet_model();
    c.seed_heads(6);
    let (ha, hb, hc) = (heads(&a), heads(&b), heads(&c));
    assert!(!ha.is_empty());
    let (mut drawn, mut zero) = (0, 0);
    for (((n, x), (_, y)), (_, z)) in ha.iter().zip(&hb).zip(&hc) {
        assert!(x.equal(y), "{n}: the same seed gave other starting values");
        let max = f64::try_from(x.abs().max()).unwrap();
        if max == 0.0 {
            // The last layers (the identity at the start) and the convolutions' biases.
            zero += 1;
            assert!(z.equal(x), "{n}");
            continue;
        }
        drawn += 1;
        assert!(!x.equal(z), "{n}: seeds 5 and 6 gave the same values");
        let size = x.size();
        let bound = if size.len() >= 2 {
            (6.0 / size.iter().skip(1).product::<i64>() as f64).sqrt()
        } else {
            let w = ha.iter().find(|(m, _)| *m == n.replace(".bias", ".weight")).unwrap();
            1.0 / (w.1.size()[1] as f64).sqrt()
        };
        // Uniform within the bound: nothing past it, and the largest of many draws close to it.
        assert!(max <= bound && (x.numel() < 64 || max > 0.8 * bound), "{n}: max {max}, bound {bound}");
    }
    assert!(drawn > 0 && zero > 0, "{drawn} drawn, {zero} zero");
}

/// One Rust step (loss, clipped gradients, AdamW update) equals the PyTorch reference's.
#[test]
fn one_training_step_equals_the_pytorch_reference() {
    let _turn = turn();
    let dir = tempfile::tempdir().unwrap();
    let w = dir.path().join("weights.safetensors");
    let mut cfg = ModelConfig::default();
    cfg.preprocess.width = 64;
    cfg.preprocess.height = 64;
    // Two real places, two views each: the desk loop (1.png, 10.png) and an EuRoC loop.
    let files =
        ["slambook2-ch11/1.png", "slambook2-ch11/10.png", "euroc-lcd/left_img_0.png", "euroc-lcd/left_img_1.png"];
    let inputs: Vec<Tensor> = files
        .iter()
        .map(|f| {
            let img = decode(&std::fs::read(data(f)).unwrap(), &ImageLimits::default()).unwrap();
            normalize(&resized_rgb(&img, &cfg.preprocess), cfg.preprocess.normalization)
        })
        .collect();
    let x = Tensor::stack(&inputs, 0);
    let same = Tensor::from_slice(&[0i64, 0, 1, 1]);
    let same = same.unsqueeze(1).eq_tensor(&same.unsqueeze(0)).to_kind(Kind::Float);
    let pos = &same - Tensor::eye(4, (Kind::Float, Device::Cpu));
    let neg = 1.0 - &same;
    let r = Recipe { lr: 1e-3, clip_norm: 0.5, ..recipe(1, 0) };
    // Random heads, so that every head tensor gets a gradient. Some draws mine no pair from
    // these four images (loss 0, nothing to compare; seen twice in CI with seed 9): the next
    // seed is drawn then.
    let (model, opt, params, loss) = (9..25)
        .find_map(|seed| {
            let model = imagenet_model_at(64, 64);
            model.randomize(seed, true);
            let meta = HashMap::from([("stride_layout".to_string(), "v1".to_string())]);
            WeightFile::write(&w, &named_tensors(model.var_store()), meta).unwrap();
            let (model, _) = Model::load(&w, cfg.clone(), Device::Cpu, DType::F32).unwrap();
            let (mut opt, params) = optimizer(&model, &r).unwrap();
            let loss = step(&model, &mut opt, &params, &x, &pos, &neg, &r, r.lr).unwrap();
            (loss > 0.0).then_some((model, opt, params, loss))
        })
        .expect("16 draws of random heads, none with a positive loss");
    drop((opt, params));
    let mut expected = vec![("loss".to_string(), Tensor::from_slice(&[loss as f32]))];
    for (name, t) in model.var_store().variables() {
        if name.starts_with("attention.") || name.starts_with("fusion.") {
            expected.push((format!("grad.{name}"), t.grad()));
            expected.push((format!("after.{name}"), t.detach()));
        }
    }
    let p = &r.loss;
    let hyper = [r.lr, r.weight_decay, r.clip_norm, p.alpha, p.beta, p.lambda, p.epsilon].map(|v| v as f32);
    let batch = dir.path().join("batch.safetensors");
    let exp = dir.path().join("expected.safetensors");
    WeightFile::write(
        &batch,
        &[("inputs".into(), x), ("pos".into(), pos), ("neg".into(), neg), ("hyper".into(), Tensor::from_slice(&hyper))],
        Default::default(),
    )
    .unwrap();
    WeightFile::write(&exp, &expected, Default::default()).unwrap();
    let out = std::process::Command::new(root().join(".venv/bin/python"))
        .arg(root().join("tests/reference/train_step.py"))
        .args([&w, &batch, &exp])
        .args(["--tol-grad", "1e-3"])
        .output()
        .expect("running the .venv python");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("reference: {stdout}{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the PyTorch step disagrees: {stdout}");
}

/// Preprocessing for training (resize, then normalise a tensor) equals the server's.
#[test]
fn training_inputs_equal_serving_inputs() {
    let p = Preprocess { width: 96, height: 48, ..Default::default() };
    let img = decode(&std::fs::read(data("photos/dog.jpg")).unwrap(), &ImageLimits::default()).unwrap();
    let diff = (to_input(&img, &p) - normalize(&resized_rgb(&img, &p), p.normalization)).abs().max();
    assert!(f64::try_from(diff).unwrap() < 1e-4);
}

#[test]
fn bad_training_input_is_refused_before_any_step() {
    let _turn = turn();
    let dir = tempfile::tempdir().unwrap();
    let err = |f: &dyn Fn(&mut TrainSet) -> anyhow::Result<()>| {
        let mut s = TrainSet::default();
        format!("{:#}", f(&mut s).unwrap_err())
    };
    // An empty folder.
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    assert!(err(&|s| s.add_unlabelled(&empty)).contains("no images"));
    // Ground truth naming frames that do not exist.
    let gt = dir.path().join("gt.csv");
    std::fs::write(&gt, "query,ref\n5,1\n9000,3\n").unwrap();
    let src = TraversalSource {
        sequence: data("slambook2-ch11"),
        query_sequence: None,
        gt: gt.display().to_string(),
        camera: None,
        tolerance: 0,
        range: None,
        filter: None,
    };
    assert!(err(&|s| s.add_traversal(&src)).contains("9000"), "{}", err(&|s| s.add_traversal(&src)));
    // A places CSV whose places have one image each: no positives.
    let csv = dir.path().join("places.csv");
    let a = data("photos/dog.jpg");
    let b = data("photos/eagle.jpg");
    std::fs::write(&csv, format!("image,place\n{},a\n{},b\n", a.display(), b.display())).unwrap();
    assert!(err(&|s| s.add_places_csv(&csv, &["place".into()])).contains("no positives"));
    assert!(err(&|s| s.add_places_csv(&csv, &["floor".into()])).contains("no column 'floor'"));
    // A heads file of another backbone, or not a heads file at all.
    let out = tempfile::tempdir().unwrap();
    let mut spec = tiny_spec(out.path(), 1, 0);
    spec.val.clear();
    spec.recipe.steps_per_epoch = Some(1);
    let heads = train(&spec).unwrap().heads;
    let mut model = Model::new(ModelConfig::default(), Device::Cpu, DType::F32).unwrap();
    let e = format!("{:#}", model.load_heads(&heads).err().unwrap());
    assert!(e.contains("trained on backbone"), "{e}");
    let (mut model, _) = Model::load(&weights(), ModelConfig::default(), Device::Cpu, DType::F32).unwrap();
    let e = format!("{:#}", model.load_heads(&weights()).err().unwrap());
    assert!(e.contains("not a loopd heads file"), "{e}");
    // A heads file with a tensor of the wrong shape leaves the model untouched.
    let mut file = WeightFile::read(&heads).unwrap();
    let i = file.tensors.iter().position(|(n, _)| n == "fusion.conv.weight").unwrap();
    file.tensors[i].1 = Tensor::zeros([3, 3], (Kind::Float, Device::Cpu));
    let bad = out.path().join("bad.safetensors");
    WeightFile::write(&bad, &file.tensors, file.metadata.clone()).unwrap();
    let e = format!("{:#}", model.load_heads(&bad).err().unwrap());
    assert!(e.contains("fusion.conv.weight") && e.contains("shape"), "{e}");
    assert!(model.heads_sha256.is_none());
}

/// The heads shipped in `models/` are what the CLI loads by default: they fit the imported
/// ImageNet weights, name themselves in the descriptor id, and still find the desk loop ahead of
/// every non-loop.
#[test]
fn the_shipped_heads_are_the_default_and_find_the_desk_loop() {
    let _turn = turn();
    let shipped = root().join(loopd::cli::DEFAULT_HEADS);
    let file = WeightFile::read(&shipped).expect("the shipped heads file");
    let backbone = WeightFile::read(&weights()).unwrap().sha256;
    assert_eq!(file.metadata.get("backbone_sha256"), Some(&backbone), "shipped heads were trained on other weights");
    let cache = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_loopd"))
        .current_dir(root())
        .env("LOOPD_DEVICE", "cpu")
        .env_remove("LOOPD_HEADS")
        .args(["eval", "--gt", "tests/gt/desk.csv", "--exclude", "2", "--json", "--sequence"])
        .arg(data("slambook2-ch11"))
        .arg("--cache-dir")
        .arg(cache.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let id = r["descriptor_id"].as_str().unwrap();
    assert!(id.ends_with(&format!("-h{}", &file.sha256[..12])), "default model is not the shipped heads: {id}");
    assert_eq!(r["recall_at_100_precision"], 1.0, "{r}");
    // Its descriptors have the whitening's length.
    let embed = std::process::Command::new(env!("CARGO_BIN_EXE_loopd"))
        .current_dir(root())
        .env("LOOPD_DEVICE", "cpu")
        .env_remove("LOOPD_HEADS")
        .args(["embed", "--json"])
        .arg(data("photos/dog.jpg"))
        .output()
        .unwrap();
    let line: serde_json::Value = serde_json::from_slice(&embed.stdout).unwrap();
    let dim = file.tensors.iter().find(|(n, _)| n == "whiten.proj").map_or(2048, |(_, t)| t.size()[0]);
    assert_eq!(line["descriptor"].as_array().unwrap().len() as i64, dim);
}

/// Sessions made by earlier releases (ids before weight hashes, and with the weight file's byte
/// hash) stay usable by the same weights without heads; with heads they are another space.
#[test]
fn sessions_named_by_earlier_releases_stay_usable_without_heads() {
    let _turn = turn(); // building models draws from torch's generator
    let file = WeightFile::read(&weights()).unwrap();
    let plain = imagenet_model();
    let byte_id = plain.config.descriptor_id(Variant::FULL, &file.file_sha256, None);
    let pre_hash = plain.config.legacy_descriptor_id(Variant::FULL);
    let other = plain.config.descriptor_id(Variant::FULL, &"0".repeat(64), None);
    let cfg = || EngineConfig { warm_up: false, ..Default::default() };
    let engine = Engine::start(plain, cfg(), ImageLimits::default()).unwrap();
    assert!(engine.info().compatible(&byte_id), "{byte_id}");
    assert!(engine.info().compatible(&pre_hash));
    assert!(!engine.info().compatible(&other));
    let mut headed = imagenet_model();
    headed.load_heads(&root().join(loopd::cli::DEFAULT_HEADS)).unwrap();
    let engine = Engine::start(headed, cfg(), ImageLimits::default()).unwrap();
    assert!(!engine.info().compatible(&byte_id) && !engine.info().compatible(&pre_hash));
}

/// An upgrade adds models, it does not replace one (issue #39): `loopd train`'s output folder is a
/// model (`model.json`, kind builtin, its heads), and so is a folder naming the plain backbone.
/// A server whose default is the shipped heads serves both beside it (`serve --models`): a
/// session made by a server without heads (the plain backbone) keeps taking images, answered with
/// the plain backbone's own calibrated confidence, and each model's descriptors are the network's
/// with those heads, computed in process.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
// The training tests' turn is held for the whole test on purpose (servers build models, which
// draw from torch's generator); it is a std mutex only these tests take, never an await's target.
#[allow(clippy::await_holding_lock)]
async fn a_trained_folder_and_the_plain_backbone_are_served_beside_the_shipped_heads() {
    use loopd::api::server::{RunningServer, ServerConfig};
    use loopd::pb::{self, loopd_client::LoopdClient};
    use serde_json::{json, Value};

    let _turn = turn();
    let repo = tempfile::tempdir().unwrap();
    let trained = repo.path().join("nordland-r1");
    let mut spec = tiny_spec(&trained, 1, 3);
    spec.whiten = Some(WhitenSpec { dim: Some(16), frames: 48, shrink: 0.1 });
    let heads = tokio::task::spawn_blocking(move || train(&spec).unwrap().heads).await.unwrap();
    let manifest: Value = serde_json::from_slice(&std::fs::read(trained.join("model.json")).unwrap()).unwrap();
    assert_eq!((manifest["name"].as_str(), manifest["kind"].as_str()), (Some("nordland-r1"), Some("builtin")));
    assert_eq!(manifest["heads"], "heads.safetensors");
    assert!(manifest["source"].as_str().unwrap().contains("nordland-val R@100P"), "{manifest}");
    std::fs::create_dir(repo.path().join("plain")).unwrap();
    std::fs::write(repo.path().join("plain/model.json"), json!({"name": "plain", "kind": "builtin"}).to_string())
        .unwrap();

    // A session of the plain backbone, made by a server without heads.
    let data_dir = tempfile::tempdir().unwrap();
    let config = |models: Option<&Path>| ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        models_dir: models.map(Path::to_path_buf),
        ..ServerConfig::on_loopback(data_dir.path().to_path_buf())
    };
    let old = RunningServer::start(config(None), imagenet_model()).await.unwrap();
    let mut grpc = LoopdClient::connect(format!("http://{}", old.grpc_addr)).await.unwrap();
    grpc.create_session(pb::CreateSessionRequest { id: "old".into(), ..Default::default() }).await.unwrap();
    let first = grpc.add_and_query(desk_frame("old", 1)).await.unwrap().into_inner();
    let old_id = old.service.engine().info().descriptor_id.clone();
    old.shutdown().await.unwrap();

    // The upgraded server: the shipped heads by default, the repository beside them.
    let server = RunningServer::start(config(Some(repo.path())), shipped_model()).await.unwrap();
    let base = format!("http://{}", server.http_addr);
    let http = reqwest::Client::new();
    let listed: Value = http.get(format!("{base}/v1/models")).send().await.unwrap().json().await.unwrap();
    let models = listed["models"].as_array().unwrap();
    let field = |name: &str, f: &str| models.iter().find(|m| m["name"] == name).unwrap()[f].clone();
    let names: Vec<&str> = models.iter().map(|m| m["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["loopd", "nordland-r1", "plain"], "{listed}");
    assert!(models.iter().all(|m| m["kind"] == "builtin"), "{listed}");
    assert_eq!(field("plain", "descriptor_id"), old_id.as_str(), "the plain backbone is the old session's space");
    assert_eq!(field("nordland-r1", "dim"), 16);
    assert!(field("nordland-r1", "source").as_str().unwrap().contains("loopd train on"), "{listed}");
    assert_ne!(field("loopd", "descriptor_id"), field("nordland-r1", "descriptor_id"));

    // Each model's descriptors: the network with its heads, in process (the trained heads on the
    // server's input size, not the training's).
    let image = std::fs::read(data("slambook2-ch11/10.png")).unwrap();
    let input = to_input(&decode(&image, &ImageLimits::default()).unwrap(), &ModelConfig::default().preprocess);
    let mut headed = imagenet_model();
    headed.load_heads(&heads).unwrap();
    for (name, model) in [("plain", imagenet_model()), ("nordland-r1", headed)] {
        let r: Value = http
            .post(format!("{base}/v1/embed?model={name}"))
            .body(image.clone())
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        assert_eq!(r["descriptor_id"], model.descriptor_id(Variant::FULL));
        let got: Vec<f32> = serde_json::from_value(r["descriptor"].clone()).unwrap();
        let want: Vec<f32> =
            model.descriptors(std::slice::from_ref(&input), Variant::FULL).unwrap().squeeze_dim(0).try_into().unwrap();
        assert_eq!(got.len(), want.len(), "{name}");
        let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        eprintln!("{name}: server against the network in process, max abs diff {worst:e}");
        assert!(worst <= 1e-6, "{name}: {worst}");
    }

    // The old session takes images again, embedded by the plain backbone: the revisit 10 -> 1 is
    // its best candidate, verified, with the plain backbone's calibrated confidence (the shipped
    // calibration file covers it).
    let mut grpc = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();
    let revisit = grpc.add_and_query(desk_frame("old", 10)).await.unwrap().into_inner();
    let best = &revisit.matches[0];
    assert_eq!(best.frame_id, first.frame_id, "{:?}", revisit.matches);
    assert!(best.verification.as_ref().is_some_and(|v| v.verified), "{best:?}");
    let c = best.confidence.expect("the plain backbone's calibrated confidence");
    assert!((0.0..=1.0).contains(&c), "{c}");
    // A session of the trained model: its space, its descriptors' length.
    let s = grpc
        .create_session(pb::CreateSessionRequest {
            id: "trained".into(),
            model: "nordland-r1".into(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!((s.model.as_str(), s.dim), ("nordland-r1", 16));
    for i in [1, 10] {
        grpc.add_and_query(desk_frame("trained", i)).await.unwrap();
    }
    let listed: Value = http.get(format!("{base}/v1/sessions/trained")).send().await.unwrap().json().await.unwrap();
    assert_eq!(listed["frames"], 2, "{listed}");
    server.shutdown().await.unwrap();

    // `loopd models check` runs the trained folder on --weights and names the same space.
    let checked = loopd_bin()
        .args(["models", "check"])
        .arg(&trained)
        .arg("--image")
        .arg(data("slambook2-ch11/1.png"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&checked.stdout);
    assert!(checked.status.success(), "{stdout}{}", String::from_utf8_lossy(&checked.stderr));
    assert!(stdout.contains(&format!("descriptor id {}", s.descriptor_id)), "{stdout}");
}
