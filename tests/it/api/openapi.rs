//! The OpenAPI document: `openapi.yaml` is what this build generates from its handlers
//! (`loopd openapi`), and every operation it names is served by the real server on loopback (a
//! route the router lacks answers an empty 404 or a 405, which this tells apart from the
//! handlers' own JSON 404s).
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::engine::EngineConfig;

#[test]
fn the_checked_in_document_is_the_generated_one() {
    let generated = loopd::api::http::doc::yaml().unwrap();
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/openapi.yaml");
    let checked_in = std::fs::read_to_string(path).unwrap();
    assert!(
        generated == checked_in,
        "openapi.yaml differs from the document the routes generate: run `loopd openapi > openapi.yaml`"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_documented_operation_is_served() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 1, warm_up: false, ..Default::default() },
        ..ServerConfig::on_loopback(dir.path().to_path_buf())
    };
    let server = RunningServer::start(cfg, imagenet_model()).await.unwrap();
    let http = reqwest::Client::new();
    // The checked-in document, as a client reads it.
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/openapi.yaml")).unwrap();
    let doc: serde_yaml::Value = serde_yaml::from_str(&text).unwrap();
    let mut operations = 0;
    let served = |status: u16, body: &str| !(status == 405 || (status == 404 && body.is_empty()));
    // The check itself: a path no handler has is told apart.
    let r = http.get(format!("http://{}/v1/no-such-route", server.http_addr)).send().await.unwrap();
    let status = r.status().as_u16();
    assert!(!served(status, &r.text().await.unwrap()), "an unrouted path answered {status}");
    let paths = doc["paths"].as_mapping().expect("openapi.yaml has paths");
    for (path, item) in paths {
        let path = path.as_str().unwrap();
        let url = format!(
            "http://{}{}",
            server.http_addr,
            path.replace("{id}", "missing")
                .replace("{name}", "nobody")
                .replace("{job_id}", "7")
                .replace("{frame_id}", "0")
                .replace("{query_frame}", "0")
                .replace("{match_frame}", "1")
        );
        for (name, method) in [
            ("get", reqwest::Method::GET),
            ("post", reqwest::Method::POST),
            ("delete", reqwest::Method::DELETE),
            ("put", reqwest::Method::PUT),
            ("patch", reqwest::Method::PATCH),
        ] {
            if item.get(name).is_none() {
                continue;
            }
            // A body of no known shape: a handler answers 400/404/413/..., never the router's 404/405.
            let r = http.request(method.clone(), &url).body("{").send().await.unwrap();
            let status = r.status().as_u16();
            let body = r.text().await.unwrap();
            assert!(served(status, &body), "{method} {path} is documented but not served: {status} {body:?}");
            operations += 1;
        }
    }
    assert!(operations >= 28, "the document names {operations} operations");
    server.shutdown().await.unwrap();
}
