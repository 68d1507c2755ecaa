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

/// `serve --models`: one server serves the built-in network and two TorchScript models at once
/// (each its own engine: queue, batches, metrics). Sessions bound to each answer over both APIs;
/// `/v1/embed?model=` gives the descriptors `models check` saved, which PyTorch reproduces on the
/// same pixels within 1e-5; a name not served, a variant a TorchScript model lacks and a broken
/// model in the repository are refused with the reason.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_server_serves_the_builtin_model_and_two_torchscript_models_over_both_apis() {
    use loopd::api::server::{RunningServer, ServerConfig};
    use loopd::engine::EngineConfig;
    use loopd::pb;
    use loopd::pb::loopd_client::LoopdClient;
    use serde_json::{json, Value};

    let dir = tempfile::tempdir().unwrap();
    export(dir.path());
    let repo = dir.path().join("repo");
    std::fs::create_dir(&repo).unwrap();
    for m in ["small-resnet", "small-bgr"] {
        std::fs::rename(dir.path().join(m), repo.join(m)).unwrap();
        // loopd's descriptors of the real images, checked against PyTorch on the same inputs.
        let saved = dir.path().join(format!("{m}.out"));
        assert!(check(&repo.join(m), Some(&saved)).status.success(), "models check {m}");
        let cmp = python(&["compare".as_ref(), repo.join(m).as_os_str(), saved.as_os_str()]);
        eprintln!("{m} against PyTorch: {}", String::from_utf8_lossy(&cmp.stdout));
        assert!(cmp.status.success(), "{m}: loopd and PyTorch differ by more than 1e-5");
    }
    let data_dir = tempfile::tempdir().unwrap();
    let config = |models: &Path| ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        models_dir: Some(models.to_path_buf()),
        ..ServerConfig::on_loopback(data_dir.path().to_path_buf())
    };
    let server = RunningServer::start(config(&repo), imagenet_model()).await.unwrap();
    let base = format!("http://{}", server.http_addr);
    let http = reqwest::Client::new();
    let mut grpc = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await.unwrap();

    // Listed over both APIs, the default first, then the repository's by folder name.
    let listed: Value = http.get(format!("{base}/v1/models")).send().await.unwrap().json().await.unwrap();
    let models = listed["models"].as_array().unwrap();
    let names: Vec<&str> = models.iter().map(|m| m["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["loopd", "small-bgr", "small-resnet"], "{listed}");
    let defaults: Vec<bool> = models.iter().map(|m| m["default"].as_bool().unwrap()).collect();
    assert_eq!(defaults, [true, false, false]);
    let dims: Vec<u64> = models.iter().map(|m| m["dim"].as_u64().unwrap()).collect();
    assert_eq!(&dims[1..], [256, 512]);
    assert_eq!(models[2]["kind"], "torchscript");
    assert!(models[2]["license"].as_str().unwrap().contains("seeded random weights"));
    let id = |name: &str| models.iter().find(|m| m["name"] == name).unwrap()["descriptor_id"].as_str().unwrap();
    let over_grpc = grpc.list_models(pb::ListModelsRequest {}).await.unwrap().into_inner().models;
    assert_eq!(
        over_grpc.iter().map(|m| (m.name.as_str(), m.descriptor_id.as_str(), m.dim as u64)).collect::<Vec<_>>(),
        models
            .iter()
            .map(|m| (m["name"].as_str().unwrap(), m["descriptor_id"].as_str().unwrap(), m["dim"].as_u64().unwrap()))
            .collect::<Vec<_>>()
    );

    // Each model's descriptors through the server: what `models check` saved, bit for bit
    // within 1e-6 (so PyTorch's within 1e-5, above).
    for m in ["small-resnet", "small-bgr"] {
        let mut worst = 0f32;
        for img in IMAGES {
            let r = http
                .post(format!("{base}/v1/embed?model={m}"))
                .body(std::fs::read(data(img)).unwrap())
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200);
            let r: Value = r.json().await.unwrap();
            assert_eq!(r["descriptor_id"], id(m));
            let got: Vec<f32> = serde_json::from_value(r["descriptor"].clone()).unwrap();
            let stem = Path::new(img).file_stem().unwrap().to_string_lossy().into_owned();
            let saved = tch::Tensor::read_safetensors(dir.path().join(format!("{m}.out/{stem}.safetensors"))).unwrap();
            let want: Vec<f32> =
                saved.iter().find(|(k, _)| k == "descriptor").unwrap().1.shallow_clone().try_into().unwrap();
            assert_eq!(got.len(), want.len());
            worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(worst, f32::max);
        }
        eprintln!("{m}: server against models check, max abs diff {worst:e}");
        assert!(worst <= 1e-6, "{m}: {worst}");
    }
    let refused = http
        .post(format!("{base}/v1/embed?model=small-bgr&attention=false"))
        .body(std::fs::read(data(IMAGES[2])).unwrap())
        .send()
        .await
        .unwrap();
    assert_eq!(refused.status(), 400);
    assert!(refused.text().await.unwrap().contains("whole output only"));

    // Sessions bound to each model: HTTP, gRPC, and the default.
    let create = |body: Value| http.post(format!("{base}/v1/sessions")).json(&body).send();
    let unknown = create(json!({"id": "x", "model": "netvlad"})).await.unwrap();
    assert_eq!(unknown.status(), 400);
    let why = unknown.text().await.unwrap();
    assert!(why.contains("'netvlad' is not served here") && why.contains("small-resnet"), "{why}");
    let r = create(json!({"id": "resnet", "model": "small-resnet"})).await.unwrap();
    assert_eq!(r.status(), 201);
    let s: Value = r.json().await.unwrap();
    assert_eq!(
        (s["model"].as_str(), s["dim"].as_u64(), s["descriptor_id"].as_str()),
        (Some("small-resnet"), Some(512), Some(id("small-resnet")))
    );
    let bgr = grpc
        .create_session(pb::CreateSessionRequest { id: "bgr".into(), model: "small-bgr".into(), ..Default::default() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!((bgr.model.as_str(), bgr.dim, bgr.descriptor_id.as_str()), ("small-bgr", 256, id("small-bgr")));
    let r = create(json!({"id": "builtin"})).await.unwrap();
    let s: Value = r.json().await.unwrap();
    assert_eq!((s["model"].as_str(), s["descriptor_id"].as_str()), (Some("loopd"), Some(id("loopd"))));

    // Frames in by image on each session; a query by image finds its own frame first.
    let frames = ["slambook2-ch11/1.png", "photos/dog.jpg", "photos/scream.jpg"];
    for session in ["resnet", "builtin"] {
        for (i, f) in frames.iter().enumerate() {
            let form = reqwest::multipart::Form::new()
                .text("robot_id", "r1")
                .text("timestamp", i.to_string())
                .part("image", reqwest::multipart::Part::bytes(std::fs::read(data(f)).unwrap()).file_name("f"));
            let r = http.post(format!("{base}/v1/sessions/{session}/frames")).multipart(form).send().await.unwrap();
            assert_eq!(r.status(), 201, "{session}: {}", r.text().await.unwrap());
        }
    }
    for (i, f) in frames.iter().enumerate() {
        grpc.add_frame(pb::AddFrameRequest {
            session_id: "bgr".into(),
            robot_id: "r1".into(),
            timestamp: Some(i as f64),
            content: Some(pb::add_frame_request::Content::Image(std::fs::read(data(f)).unwrap().into())),
            ..Default::default()
        })
        .await
        .unwrap();
    }
    for session in ["resnet", "bgr", "builtin"] {
        let q = grpc
            .query(pb::QueryRequest {
                session_id: session.into(),
                robot_id: "r2".into(),
                content: Some(pb::query_request::Content::Image(std::fs::read(data(frames[1])).unwrap().into())),
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner();
        let best = &q.matches[0];
        assert_eq!(best.timestamp, 1.0, "{session}: {q:?}");
        assert!(best.score > 0.999, "{session}: {}", best.score);
        let info: Value = http.get(format!("{base}/v1/sessions/{session}")).send().await.unwrap().json().await.unwrap();
        assert_eq!(info["frames"], 3);
    }
    // A descriptor of the wrong model's length is refused.
    let d512 = vec![0.044f32; 512];
    let r = http
        .post(format!("{base}/v1/sessions/bgr/frames"))
        .json(&json!({"robot_id": "r1", "descriptor": d512}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 400);
    // A descriptor that says it is another model's is refused naming both; its own is taken.
    let frame = |id: &str| json!({"robot_id": "r1", "timestamp": 9.0, "descriptor": d512, "descriptor_id": id});
    let r = http.post(format!("{base}/v1/sessions/resnet/frames")).json(&frame(id("small-bgr"))).send().await.unwrap();
    assert_eq!(r.status(), 409);
    let why = r.text().await.unwrap();
    assert!(why.contains("(model small-resnet)") && why.contains("(model small-bgr)"), "{why}");
    let r =
        http.post(format!("{base}/v1/sessions/resnet/frames")).json(&frame(id("small-resnet"))).send().await.unwrap();
    assert_eq!(r.status(), 201);
    let refused = grpc
        .query(pb::QueryRequest {
            session_id: "bgr".into(),
            robot_id: "r2".into(),
            content: Some(pb::query_request::Content::Descriptor(pb::Descriptor {
                values: vec![0.0625; 256],
                descriptor_id: id("loopd").into(),
            })),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(refused.code(), tonic::Code::FailedPrecondition);
    assert!(
        refused.message().contains("(model loopd)") && refused.message().contains("(model small-bgr)"),
        "{refused:?}"
    );
    // Each model's engine counts its own images.
    let metrics = http.get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    let images = |m: &str| {
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(&format!("loopd_engine_images_total{{model=\"{m}\"}} ")))
            .and_then(|v| v.trim().parse::<u64>().ok())
            .unwrap_or_else(|| panic!("no images count for {m}: {metrics}"))
    };
    assert_eq!(images("small-resnet"), IMAGES.len() as u64 + 3 + 1);
    assert_eq!(images("small-bgr"), IMAGES.len() as u64 + 3 + 1);
    assert_eq!(images("loopd"), 3 + 1);

    // `loopd eval --model` runs a TorchScript model through the engine the server runs it on: on
    // the desk frames its report is eval --server's on a session of that model holding them (f32,
    // as eval's index), point by point of the precision-recall curve (the same scores). This
    // random-weight model scores every pair about 0.9997: f16 rows would reorder them.
    let r = create(json!({"id": "desk", "model": "small-resnet", "storage": "f32"})).await.unwrap();
    assert_eq!(r.status(), 201);
    for i in 1..=10 {
        let form = reqwest::multipart::Form::new().text("robot_id", "r1").text("timestamp", i.to_string()).part(
            "image",
            reqwest::multipart::Part::bytes(std::fs::read(data(&format!("slambook2-ch11/{i}.png"))).unwrap())
                .file_name("f"),
        );
        let r = http.post(format!("{base}/v1/sessions/desk/frames")).multipart(form).send().await.unwrap();
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    }
    let (grpc_addr, model, cache) = (server.grpc_addr.to_string(), repo.join("small-resnet"), dir.path().join("cache"));
    let eval = move |local: bool| {
        let mut c = loopd_bin();
        c.arg("eval");
        if local {
            c.arg("--model").arg(&model).arg("--sequence").arg(data("slambook2-ch11")).arg("--cache-dir").arg(&cache);
            // What the server does with a query's candidates by default.
            c.args(["--verify", "geometric"]);
        } else {
            c.args(["--server", &grpc_addr, "--session", "desk"]);
        }
        let out = c.arg("--gt").arg(root().join("tests/gt/desk.csv")).args(["--exclude", "2", "--json"]).output();
        let out = out.expect("running loopd eval");
        assert!(out.status.success(), "eval (local {local}): {}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice::<Value>(&out.stdout).unwrap()
    };
    let (local, remote) = tokio::task::spawn_blocking(move || (eval(true), eval(false))).await.unwrap();
    eprintln!("eval --model: {local}\neval --server: {remote}");
    assert_eq!(local["descriptor_id"], id("small-resnet"));
    for k in ["queries", "positives", "recall_at_1", "average_precision", "recall_at_100_precision"] {
        assert_eq!(local[k], remote[k], "{k}");
    }
    // Every point of the precision-recall curve: each at a query's best score.
    let curve = |v: &Value| -> Vec<f64> {
        v["pr_curve"]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|p| p.as_object().unwrap().values())
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let (a, b) = (curve(&local), curve(&remote));
    assert!(!a.is_empty() && a.len() == b.len(), "{a:?} against {b:?}");
    assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-5), "{a:?} against {b:?}");
    server.shutdown().await.unwrap();

    // A repository holding a broken model: the server does not start, and says which.
    std::fs::rename(dir.path().join("nan"), repo.join("nan")).unwrap();
    let bad = |name: &str| repo.join(name).join("model.json");
    std::fs::write(bad("nan"), "{\"name\": \"nan\"}").unwrap();
    let e = RunningServer::start(config(&repo), imagenet_model()).await.err().expect("a broken model refused");
    let e = format!("{e:#}");
    assert!(e.contains("nan") && e.contains("not a model manifest"), "{e}");
}

/// The paper's network as a user would bring it: `tests/reference/reference.py` (an independent
/// PyTorch implementation of loopd's network) with seeded random heads, traced to TorchScript and
/// served beside the built-in network holding the same weights. Both give the same descriptors
/// of real images (max abs diff printed; the two implementations differ only in rounding), and a
/// bare descriptor of one is refused by a session of the other (two descriptor spaces).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_reference_network_as_torchscript_gives_the_builtin_descriptors() {
    use loopd::api::server::{RunningServer, ServerConfig};
    use loopd::engine::EngineConfig;
    use loopd::model::weights::{named_tensors, WeightFile};
    use serde_json::{json, Value};

    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("random-heads.safetensors");
    let model = imagenet_model();
    model.randomize(11, true);
    let meta = [("stride_layout".to_string(), "v1".to_string())].into_iter().collect();
    WeightFile::write(&weights, &named_tensors(model.var_store()), meta).unwrap();
    let repo = dir.path().join("repo");
    let out = python(&["reference".as_ref(), weights.as_os_str(), repo.as_os_str()]);
    assert!(out.status.success(), "exporting the reference: {}", String::from_utf8_lossy(&out.stderr));
    let (model, _) = loopd::model::Model::load(
        &weights,
        loopd::model::config::ModelConfig::default(),
        tch::Device::Cpu,
        loopd::model::device::DType::F32,
    )
    .unwrap();
    let data_dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        models_dir: Some(repo.clone()),
        ..ServerConfig::on_loopback(data_dir.path().to_path_buf())
    };
    let server = RunningServer::start(cfg, model).await.unwrap();
    let (base, http) = (format!("http://{}", server.http_addr), reqwest::Client::new());
    let embed = |model: &'static str, img: &'static str| {
        let (http, base) = (http.clone(), base.clone());
        async move {
            let r = http.post(format!("{base}/v1/embed?model={model}")).body(std::fs::read(data(img)).unwrap());
            let r: Value = r.send().await.unwrap().json().await.unwrap();
            let d: Vec<f32> = serde_json::from_value(r["descriptor"].clone()).unwrap();
            (r["descriptor_id"].as_str().unwrap().to_string(), d)
        }
    };
    let mut worst = 0f32;
    for img in ["slambook2-ch11/1.png", "slambook2-ch11/10.png", "photos/dog.jpg"] {
        let ((builtin_id, a), (reference_id, b)) = (embed("loopd", img).await, embed("reference", img).await);
        assert_ne!(builtin_id, reference_id);
        assert_eq!((a.len(), b.len()), (2048, 2048));
        worst = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(worst, f32::max);
    }
    eprintln!("the reference network as TorchScript against the built-in network: max abs diff {worst:e}");
    assert!(worst <= 1e-5, "{worst}");
    // Two spaces all the same: a reference descriptor sent to a built-in session is refused.
    let (reference_id, d) = embed("reference", "photos/dog.jpg").await;
    let r = http.post(format!("{base}/v1/sessions")).json(&json!({"id": "b"})).send().await.unwrap();
    assert_eq!(r.status(), 201);
    let body = json!({"robot_id": "r", "timestamp": 0.0, "descriptor": d, "descriptor_id": reference_id});
    let r = http.post(format!("{base}/v1/sessions/b/frames")).json(&body).send().await.unwrap();
    assert_eq!(r.status(), 409);
    assert!(r.text().await.unwrap().contains("reference"));
    server.shutdown().await.unwrap();
}
