//! `POST /v1/sessions/{id}/frames` bodies: JSON, multipart forms and raw images with fields in
//! the query string, read, converted and validated as the server does before embedding.
#![no_main]
use axum::body::Body;
use axum::http::Request;
use libfuzzer_sys::fuzz_target;
use loopd::api::http::parse_frame_request;
use std::sync::OnceLock;

const BOUNDARY: &str = "loopdfuzzboundary";

fn runtime() -> &'static tokio::runtime::Runtime {
    static RT: OnceLock<tokio::runtime::Runtime> = OnceLock::new();
    RT.get_or_init(|| tokio::runtime::Builder::new_current_thread().build().expect("a runtime"))
}

fuzz_target!(|data: &[u8]| {
    let Some((&pick, rest)) = data.split_first() else { return };
    // The first byte picks the content type; a raw body takes its fields from a query string
    // carried before the first NUL.
    let (content_type, uri, body) = match pick % 3 {
        0 => ("application/json".to_string(), "/".to_string(), rest),
        1 => (format!("multipart/form-data; boundary={BOUNDARY}"), "/".to_string(), rest),
        _ => {
            let split = rest.iter().position(|&b| b == 0).unwrap_or(rest.len());
            let query = String::from_utf8_lossy(&rest[..split]).replace(['#', ' '], "");
            ("image/jpeg".to_string(), format!("/?{query}"), rest.get(split + 1..).unwrap_or_default())
        }
    };
    let Ok(req) =
        Request::builder().method("POST").uri(uri).header("content-type", content_type).body(Body::from(body.to_vec()))
    else {
        return;
    };
    let _ = runtime().block_on(parse_frame_request(req));
});
