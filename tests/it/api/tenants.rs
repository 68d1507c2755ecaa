//! Tenants and API keys (issue #13) against the real server on loopback, over real gRPC and HTTP
//! clients with TLS on: two tenants with the same session id, every session route tried by the
//! other tenant (NOT_FOUND / 404, never a hint), bad keys of every kind, admin-only routes, open
//! health, keys kept across a restart, and the refusal to serve beyond loopback without keys.
use crate::common::certs::{write, Ca};
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::api::tls::TlsFiles;
use loopd::auth::AuthConfig;
use loopd::engine::EngineConfig;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use serde_json::json;
use std::time::Duration;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

const ADMIN: &str = "admin-key-for-the-tenant-tests-0123456789";

async fn start(dir: &std::path::Path) -> RunningServer {
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        auth: AuthConfig { admin_key: Some(ADMIN.into()), ..Default::default() },
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    RunningServer::start(cfg, imagenet_model()).await.unwrap()
}

/// The CA of each server started with TLS here, by gRPC and HTTP address: its clients use TLS.
static TLS_CA: std::sync::Mutex<Vec<(std::net::SocketAddr, String)>> = std::sync::Mutex::new(Vec::new());

fn ca_of(addr: std::net::SocketAddr) -> Option<String> {
    TLS_CA.lock().unwrap().iter().find(|(a, _)| *a == addr).map(|(_, ca)| ca.clone())
}

/// A server with TLS on both APIs (a certificate for 127.0.0.1 from a CA made here).
async fn start_tls(dir: &std::path::Path) -> RunningServer {
    let ca = Ca::new("tenants test CA");
    let (cert, key) = ca.issue(&["localhost", "127.0.0.1"]);
    let tls = TlsFiles { cert: write(dir, "server.pem", &cert), key: write(dir, "server.key", &key), client_ca: None };
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        auth: AuthConfig { admin_key: Some(ADMIN.into()), ..Default::default() },
        tls: Some(tls),
        ..ServerConfig::on_loopback(dir.to_path_buf())
    };
    let server = RunningServer::start(cfg, imagenet_model()).await.unwrap();
    let pem = ca.cert.pem();
    write(dir, "ca.pem", &pem);
    TLS_CA.lock().unwrap().extend([(server.grpc_addr, pem.clone()), (server.http_addr, pem)]);
    server
}

/// A gRPC channel to a server of this file (TLS where it was started with TLS).
async fn channel(addr: std::net::SocketAddr) -> Channel {
    let Some(ca) = ca_of(addr) else {
        return tonic::transport::Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap();
    };
    let tls = tonic::transport::ClientTlsConfig::new()
        .ca_certificate(tonic::transport::Certificate::from_pem(ca))
        .domain_name("localhost");
    tonic::transport::Endpoint::from_shared(format!("https://{addr}"))
        .unwrap()
        .tls_config(tls)
        .unwrap()
        .connect()
        .await
        .unwrap()
}

/// What adds a caller's key to each gRPC call.
type AddKey = Box<dyn FnMut(tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> + Send>;
type Authed = LoopdClient<InterceptedService<Channel, AddKey>>;

async fn grpc(addr: std::net::SocketAddr, key: Option<&str>) -> Authed {
    let channel = channel(addr).await;
    let header = key.map(|k| format!("Bearer {k}").parse::<tonic::metadata::MetadataValue<_>>().unwrap());
    let add: AddKey = Box::new(move |mut req: tonic::Request<()>| {
        if let Some(h) = &header {
            req.metadata_mut().insert("authorization", h.clone());
        }
        Ok(req)
    });
    LoopdClient::with_interceptor(channel, add)
}

fn descriptor_frame(session: &str, dim: usize, i: usize) -> pb::AddFrameRequest {
    pb::AddFrameRequest {
        session_id: session.into(),
        robot_id: "r".into(),
        timestamp: Some(i as f64),
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
            values: (0..dim).map(|k| ((k * 13 + i * 7) % 89) as f32 - 44.0).collect(),
            ..Default::default()
        })),
        ..Default::default()
    }
}

struct Http {
    c: reqwest::Client,
    base: String,
}

impl Http {
    fn new(server: &RunningServer) -> Self {
        let addr = server.http_addr;
        match ca_of(addr) {
            None => Http { c: reqwest::Client::new(), base: format!("http://{addr}") },
            Some(ca) => Http {
                c: reqwest::Client::builder()
                    .add_root_certificate(reqwest::Certificate::from_pem(ca.as_bytes()).unwrap())
                    .build()
                    .unwrap(),
                base: format!("https://{addr}"),
            },
        }
    }

    async fn call(
        &self,
        method: &str,
        path: &str,
        key: Option<&str>,
        body: Option<serde_json::Value>,
    ) -> (u16, serde_json::Value) {
        let mut r = self.c.request(method.parse().unwrap(), format!("{}{path}", self.base));
        if let Some(k) = key {
            r = r.bearer_auth(k);
        }
        if let Some(b) = body {
            r = r.json(&b);
        }
        let r = r.send().await.unwrap();
        let status = r.status().as_u16();
        (status, r.json().await.unwrap_or(serde_json::Value::Null))
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tenants_see_only_their_own_sessions_on_every_route() {
    let dir = tempfile::tempdir().unwrap();
    let server = start_tls(dir.path()).await;
    let http = Http::new(&server);
    assert!(http.base.starts_with("https://"));
    let plain = reqwest::Client::new().get(format!("http://{}/healthz", server.http_addr)).send().await;
    assert!(plain.is_err() || plain.unwrap().status() != 200, "TLS on: plain HTTP gets no answer");
    let dim = server.service.engine().info().dim;

    // A session of the default tenant, from before tenants: the admin key acts for it.
    assert_eq!(http.call("POST", "/v1/sessions", Some(ADMIN), Some(json!({ "id": "legacy" }))).await.0, 201);

    // Tenants: admin only; the key is shown once.
    let (st, acme) = http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": "acme" }))).await;
    assert_eq!(st, 201, "{acme}");
    let acme_key = acme["key"].as_str().unwrap().to_string();
    let (_, blue) = http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": "blue" }))).await;
    let blue_key = blue["key"].as_str().unwrap().to_string();
    assert_eq!(http.call("POST", "/v1/tenants", Some(&acme_key), Some(json!({ "name": "x" }))).await.0, 403);
    assert_eq!(http.call("GET", "/v1/tenants", Some(&blue_key), None).await.0, 403);
    let (_, list) = http.call("GET", "/v1/tenants", Some(ADMIN), None).await;
    assert!(!list.to_string().contains(&acme_key[20..]), "listings never hold a key");
    assert_eq!(http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": "Bad/Name" }))).await.0, 400);

    // The same session id in two tenants: one over gRPC, one over HTTP.
    let mut acme_g = grpc(server.grpc_addr, Some(&acme_key)).await;
    let mut blue_g = grpc(server.grpc_addr, Some(&blue_key)).await;
    let made = acme_g.create_session(pb::CreateSessionRequest { id: "warehouse".into(), ..Default::default() }).await;
    assert_eq!(made.unwrap().into_inner().id, "warehouse");
    assert_eq!(http.call("POST", "/v1/sessions", Some(&blue_key), Some(json!({ "id": "warehouse" }))).await.0, 201);
    acme_g.create_session(pb::CreateSessionRequest { id: "secret".into(), ..Default::default() }).await.unwrap();
    for i in 0..5 {
        acme_g.add_frame(descriptor_frame("secret", dim, i)).await.unwrap();
        acme_g.add_frame(descriptor_frame("warehouse", dim, i)).await.unwrap();
    }
    blue_g.add_frame(descriptor_frame("warehouse", dim, 100)).await.unwrap();
    let job_form = reqwest::multipart::Form::new().part(
        "image",
        reqwest::multipart::Part::bytes(std::fs::read(data("slambook2-ch11/1.png")).unwrap()).file_name("1.png"),
    );
    let r =
        http.c.post(format!("{}/v1/sessions/secret/sequences", http.base)).bearer_auth(&acme_key).multipart(job_form);
    let job: serde_json::Value = r.send().await.unwrap().json().await.unwrap();
    let job_id = job["job_id"].as_str().unwrap().to_string();

    // Blue tries acme's session and job on every HTTP route: 404, as for a session that does not exist.
    let d = vec![0.5f32; dim];
    let attacks: Vec<(&str, String, Option<serde_json::Value>)> = vec![
        ("GET", "/v1/sessions/secret".into(), None),
        ("DELETE", "/v1/sessions/secret".into(), None),
        ("GET", "/v1/sessions/secret/frames/0".into(), None),
        (
            "POST",
            "/v1/sessions/secret/frames".into(),
            Some(json!({ "robot_id": "b", "timestamp": 1, "descriptor": d })),
        ),
        ("POST", "/v1/sessions/secret/query".into(), Some(json!({ "robot_id": "b", "descriptor": d }))),
        (
            "POST",
            "/v1/sessions/secret/add_and_query".into(),
            Some(json!({ "robot_id": "b", "timestamp": 1, "descriptor": d })),
        ),
        ("POST", "/v1/sessions/secret/sequences".into(), None),
        ("GET", "/v1/sessions/secret/loops".into(), None),
        ("GET", "/v1/sessions/secret/export".into(), None),
        ("GET", "/v1/sessions/secret/frames".into(), None),
        ("GET", "/v1/sessions/secret/frames/0/thumbnail".into(), None),
        ("GET", "/v1/sessions/secret/similarity".into(), None),
        ("POST", "/v1/sessions/secret/loops/0/1/verdict".into(), Some(json!({ "accepted": false }))),
        ("GET", format!("/v1/jobs/{job_id}"), None),
        ("GET", "/v1/sessions/acme%2Fsecret".into(), None),
        ("GET", "/v1/sessions/legacy".into(), None),
    ];
    for (method, path, body) in &attacks {
        let (st, v) = http.call(method, path, Some(&blue_key), body.clone()).await;
        assert_eq!(st, 404, "blue {method} {path}: {v}");
        let (st, _) = http.call(method, &path.replace("secret", "nosuch"), Some(&blue_key), body.clone()).await;
        assert_eq!(st, 404, "the same answer as for a session that does not exist");
    }
    // ... and over gRPC.
    let nf = tonic::Code::NotFound;
    assert_eq!(blue_g.get_session(pb::GetSessionRequest { id: "secret".into() }).await.unwrap_err().code(), nf);
    assert_eq!(blue_g.add_frame(descriptor_frame("secret", dim, 9)).await.unwrap_err().code(), nf);
    assert_eq!(blue_g.add_and_query(descriptor_frame("secret", dim, 9)).await.unwrap_err().code(), nf);
    let q = pb::QueryRequest {
        session_id: "secret".into(),
        content: Some(pb::query_request::Content::FrameId(0)),
        ..Default::default()
    };
    assert_eq!(blue_g.query(q).await.unwrap_err().code(), nf);
    assert_eq!(blue_g.delete_session(pb::DeleteSessionRequest { id: "secret".into() }).await.unwrap_err().code(), nf);
    let loops = pb::ListLoopsRequest { session_id: "secret".into(), ..Default::default() };
    assert_eq!(blue_g.list_loops(loops).await.unwrap_err().code(), nf);
    let verdict =
        pb::SetLoopVerdictRequest { session_id: "secret".into(), query_frame: 1, match_frame: 0, ..Default::default() };
    assert_eq!(blue_g.set_loop_verdict(verdict).await.unwrap_err().code(), nf);
    let thumbnail = pb::GetThumbnailRequest { session_id: "secret".into(), frame_id: 0 };
    assert_eq!(blue_g.get_thumbnail(thumbnail).await.unwrap_err().code(), nf);
    let mut answers =
        blue_g.stream_frames(tokio_stream::iter(vec![descriptor_frame("secret", dim, 9)])).await.unwrap().into_inner();
    assert_eq!(answers.message().await.unwrap().unwrap().error_code, nf as i32);
    let listed = blue_g.list_sessions(pb::ListSessionsRequest {}).await.unwrap().into_inner().sessions;
    assert_eq!(listed.iter().map(|s| s.id.as_str()).collect::<Vec<_>>(), ["warehouse"]);
    assert_eq!(listed[0].frames, 1, "blue's own warehouse, not acme's");

    // Nothing of acme's changed.
    let secret = acme_g.get_session(pb::GetSessionRequest { id: "secret".into() }).await.unwrap().into_inner();
    assert!(secret.frames >= 5, "{secret:?}");
    let mut listed: Vec<String> = acme_g
        .list_sessions(pb::ListSessionsRequest {})
        .await
        .unwrap()
        .into_inner()
        .sessions
        .into_iter()
        .map(|s| s.id)
        .collect();
    listed.sort();
    assert_eq!(listed, ["secret", "warehouse"]);
    let (st, j) = http.call("GET", &format!("/v1/jobs/{job_id}"), Some(&acme_key), None).await;
    assert_eq!((st, j["session_id"].as_str()), (200, Some("secret")), "{j}");
    // A job id names nothing that can be counted to: its number and 64 random bits. The number
    // alone, or with other bits, is not the job, even for its owner (issue #35).
    let parts: Vec<&str> = job_id.split('-').collect();
    assert!(
        parts.len() == 3 && parts[1].parse::<u64>().is_ok() && parts[2].len() == 16,
        "job id {job_id}: job-N-<16 hex digits>"
    );
    assert!(u64::from_str_radix(parts[2], 16).is_ok(), "{job_id}");
    for guess in [format!("job-{}", parts[1]), format!("job-{}-{:016x}", parts[1], 0u64)] {
        let (st, _) = http.call("GET", &format!("/v1/jobs/{guess}"), Some(&acme_key), None).await;
        assert_eq!(st, 404, "a guessed id {guess} found job {job_id}");
    }
    let (_, legacy) = http.call("GET", "/v1/sessions", Some(ADMIN), None).await;
    assert_eq!(legacy["sessions"].as_array().unwrap().len(), 1, "the admin sees the default tenant's: {legacy}");

    // Bad keys, every kind: 401 / UNAUTHENTICATED.
    let revoked = http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": "gone" }))).await.1["key"]
        .as_str()
        .unwrap()
        .to_string();
    assert_eq!(http.call("DELETE", "/v1/tenants/gone", Some(ADMIN), None).await.0, 200);
    let mut wrong = acme_key.clone();
    wrong.pop();
    wrong.push(if acme_key.ends_with('0') { '1' } else { '0' });
    let long = "x".repeat(8000);
    for (what, key) in
        [("revoked", revoked.as_str()), ("wrong secret", &wrong), ("malformed", "lpd_nope"), ("huge", &long)]
    {
        let (st, v) = http.call("GET", "/v1/sessions", Some(key), None).await;
        assert_eq!(st, 401, "{what}: {v}");
        let mut g = grpc(server.grpc_addr, Some(key)).await;
        let code = g.list_sessions(pb::ListSessionsRequest {}).await.unwrap_err().code();
        assert_eq!(code, tonic::Code::Unauthenticated, "{what}");
    }
    let r = http.c.get(format!("{}/v1/sessions", http.base)).send().await.unwrap();
    assert_eq!((r.status().as_u16(), r.headers()["www-authenticate"].to_str().unwrap()), (401, "Bearer"));
    let r = http.c.get(format!("{}/v1/sessions", http.base)).header("authorization", format!("Basic {acme_key}"));
    assert_eq!(r.send().await.unwrap().status(), 401, "only Bearer");
    let r = http.c.get(format!("{}/v1/sessions?api_key={acme_key}", http.base)).bearer_auth(&acme_key);
    assert_eq!(r.send().await.unwrap().status(), 401, "a key in the URL is refused");
    let mut anonymous = grpc(server.grpc_addr, None).await;
    let code = anonymous.get_session(pb::GetSessionRequest { id: "secret".into() }).await.unwrap_err().code();
    assert_eq!(code, tonic::Code::Unauthenticated);
    // A small body: the server answers 401 before reading a body, and a large one may still be
    // being written when it closes the connection (the client then sees a broken pipe).
    let r = http.c.post(format!("{}/v1/embed", http.base)).body(b"\x89PNG not read".to_vec());
    assert_eq!(r.send().await.unwrap().status(), 401, "inference needs a key");

    // The inspector page and its files need no key: they hold no data (the page asks for one).
    for (path, kind) in [
        ("/v1/sessions/secret/inspect", "text/html"),
        ("/v1/inspector/app.js", "text/javascript"),
        ("/v1/inspector/app.css", "text/css"),
    ] {
        let r = http.c.get(format!("{}{path}", http.base)).send().await.unwrap();
        assert_eq!(r.status(), 200, "{path}");
        assert!(r.headers()["content-type"].to_str().unwrap().starts_with(kind), "{path}");
        assert!(r.headers()["content-security-policy"].to_str().unwrap().contains("frame-ancestors 'none'"));
        assert!(!r.text().await.unwrap().contains("secret"), "{path} holds nothing of the session");
    }
    for path in ["/v1/sessions/secret/frames", "/v1/sessions/secret/inspect/x", "/v1/sessions/a/b/inspect"] {
        let r = http.c.get(format!("{}{path}", http.base)).send().await.unwrap();
        assert_eq!(r.status(), 401, "{path}: only the page itself is open");
    }

    // Health stays open; metrics are the admin's.
    for path in ["/healthz", "/readyz"] {
        assert_eq!(http.c.get(format!("{}{path}", http.base)).send().await.unwrap().status(), 200, "{path}");
    }
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel(server.grpc_addr).await);
    health
        .check(tonic_health::pb::HealthCheckRequest { service: String::new() })
        .await
        .expect("gRPC health needs no key");
    assert_eq!(http.call("GET", "/metrics", Some(&acme_key), None).await.0, 403);
    let r = http.c.get(format!("{}/metrics", http.base)).bearer_auth(ADMIN).send().await.unwrap();
    assert_eq!(r.status(), 200);

    // Quotas: sessions, frames and rate, each refused with 429 naming the limit; the other
    // tenants are not touched.
    let limits = json!({ "max_sessions": 1, "max_frames": 3 });
    let (st, small) =
        http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": "small", "limits": limits }))).await;
    assert_eq!(st, 201, "{small}");
    let small_key = small["key"].as_str().unwrap().to_string();
    assert_eq!(http.call("POST", "/v1/sessions", Some(&small_key), Some(json!({ "id": "a" }))).await.0, 201);
    let (st, v) = http.call("POST", "/v1/sessions", Some(&small_key), Some(json!({ "id": "b" }))).await;
    assert_eq!(st, 429, "{v}");
    assert!(v["error"].as_str().unwrap().contains("limit is 1"), "{v}");
    let frame = |t: usize| json!({ "robot_id": "r", "timestamp": t, "descriptor": vec![t as f32 + 1.0; dim] });
    for t in 0..3 {
        assert_eq!(http.call("POST", "/v1/sessions/a/frames", Some(&small_key), Some(frame(t))).await.0, 201);
    }
    let (st, v) = http.call("POST", "/v1/sessions/a/frames", Some(&small_key), Some(frame(3))).await;
    assert_eq!(st, 429, "{v}");
    assert!(v["error"].as_str().unwrap().contains("its limit is 3"), "{v}");
    let (_, fast) =
        http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": "fast", "limits": { "rate": 2.0 } }))).await;
    let fast_key = fast["key"].as_str().unwrap().to_string();
    assert_eq!(http.call("POST", "/v1/sessions", Some(&fast_key), Some(json!({ "id": "f" }))).await.0, 201);
    // Twelve clients at once, over gRPC: a bucket of two, the rest RESOURCE_EXHAUSTED.
    let flood: Vec<_> = (0..12)
        .map(|i| {
            let (addr, key) = (server.grpc_addr, fast_key.clone());
            tokio::spawn(async move {
                let mut g = grpc(addr, Some(&key)).await;
                g.add_frame(descriptor_frame("f", dim, i)).await.map(drop).map_err(|s| s.code())
            })
        })
        .collect();
    let mut codes = Vec::new();
    for f in flood {
        codes.push(f.await.unwrap());
    }
    let ok = codes.iter().filter(|c| c.is_ok()).count();
    assert!((1..=3).contains(&ok), "{codes:?}");
    assert!(codes.iter().all(|c| c.is_ok() || *c == Err(tonic::Code::ResourceExhausted)), "{codes:?}");
    let r = http.c.post(format!("{}/v1/sessions/f/frames", http.base)).bearer_auth(&fast_key).json(&frame(9));
    let r = r.send().await.unwrap();
    assert_eq!((r.status().as_u16(), r.headers()["retry-after"].to_str().unwrap()), (429, "1"));
    blue_g.add_frame(descriptor_frame("warehouse", dim, 101)).await.expect("other tenants are not limited");
    let (_, listed) = http.call("GET", "/v1/tenants", Some(ADMIN), None).await;
    assert!(listed.to_string().contains("\"max_frames\":3"), "{listed}");

    // The command line: `loopd tenant create|list|revoke` through the admin routes.
    let server_url = http.base.clone();
    let ca_file = dir.path().join("ca.pem");
    let cli = move |args: &[&str]| {
        let out = loopd_bin()
            .arg("tenant")
            .args(args)
            .args(["--server", &server_url])
            .arg("--ca")
            .arg(&ca_file)
            .env("LOOPD_ADMIN_KEY", ADMIN)
            .output()
            .unwrap();
        assert!(out.status.success(), "loopd tenant {args:?}: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8(out.stdout).unwrap()
    };
    let (c1, c2, c3) = (cli.clone(), cli.clone(), cli);
    let made = tokio::task::spawn_blocking(move || c1(&["create", "cli-made", "--rate", "100"])).await.unwrap();
    let cli_key = made.lines().nth(1).unwrap().trim().to_string();
    assert_eq!(http.call("GET", "/v1/sessions", Some(&cli_key), None).await.0, 200);
    let listed = tokio::task::spawn_blocking(move || c2(&["list"])).await.unwrap();
    assert!(listed.contains("cli-made") && !listed.contains(&cli_key), "{listed}");
    tokio::task::spawn_blocking(move || c3(&["revoke", "cli-made"])).await.unwrap();
    assert_eq!(http.call("GET", "/v1/sessions", Some(&cli_key), None).await.0, 401);

    // Keys and ownership survive a restart.
    tokio::time::sleep(Duration::from_millis(500)).await; // the job on acme's session finishes
    server.shutdown().await.unwrap();
    let server = start_tls(dir.path()).await;
    let mut acme_g = grpc(server.grpc_addr, Some(&acme_key)).await;
    let secret = acme_g.get_session(pb::GetSessionRequest { id: "secret".into() }).await.unwrap().into_inner();
    assert!(secret.frames >= 5);
    let mut gone = grpc(server.grpc_addr, Some(&revoked)).await;
    assert_eq!(gone.list_sessions(pb::ListSessionsRequest {}).await.unwrap_err().code(), tonic::Code::Unauthenticated);
    server.shutdown().await.unwrap();
}

/// Without keys the server listens on loopback only, unless told --insecure.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_keys_beyond_loopback_without_insecure() {
    let dir = tempfile::tempdir().unwrap();
    let wide = |insecure| ServerConfig {
        engine: EngineConfig { max_batch: 1, warm_up: false, ..Default::default() },
        grpc_addr: "0.0.0.0:0".parse().unwrap(),
        insecure,
        ..ServerConfig::on_loopback(dir.path().to_path_buf())
    };
    let refused = RunningServer::start(wide(false), imagenet_model()).await.err().expect("refused");
    assert!(refused.to_string().contains("refusing to listen"), "{refused}");
    let server = RunningServer::start(wide(true), imagenet_model()).await.expect("--insecure serves");
    server.shutdown().await.unwrap();
}

/// One tenant flooding the inference queue with real images gets RESOURCE_EXHAUSTED naming its
/// share, while another tenant's frames are all served; /metrics counts both per tenant.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flooding_tenant_cannot_starve_another() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 2, queue_capacity: 8, warm_up: false, ..Default::default() },
        auth: AuthConfig { admin_key: Some(ADMIN.into()), tenant_in_flight: Some(4) },
        ..ServerConfig::on_loopback(dir.path().to_path_buf())
    };
    let server = RunningServer::start(cfg, imagenet_model()).await.unwrap();
    let http = Http::new(&server);
    let mut keys = Vec::new();
    for name in ["flood", "calm"] {
        let (_, t) = http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": name }))).await;
        let key = t["key"].as_str().unwrap().to_string();
        grpc(server.grpc_addr, Some(&key))
            .await
            .create_session(pb::CreateSessionRequest { id: "map".into(), ..Default::default() })
            .await
            .unwrap();
        keys.push(key);
    }
    let flood: Vec<_> = (0..32)
        .map(|i| {
            let key = keys[0].clone();
            let addr = server.grpc_addr;
            tokio::spawn(async move { grpc(addr, Some(&key)).await.add_and_query(corridor_frame("map", "f", i)).await })
        })
        .collect();
    let mut calm = grpc(server.grpc_addr, Some(&keys[1])).await;
    for i in 0..6 {
        calm.add_and_query(corridor_frame("map", "c", i)).await.expect("the calm tenant is served during the flood");
    }
    let (mut stored, mut refused) = (0, 0);
    for f in flood {
        match f.await.unwrap() {
            Ok(_) => stored += 1,
            Err(s) => {
                assert_eq!(s.code(), tonic::Code::ResourceExhausted, "{s:?}");
                assert!(s.message().contains("share is 4"), "{}", s.message());
                refused += 1;
            }
        }
    }
    assert!(refused > 0 && stored > 0, "{stored} stored, {refused} refused");
    let metrics = http.c.get(format!("{}/metrics", http.base)).bearer_auth(ADMIN).send().await.unwrap();
    let metrics = metrics.text().await.unwrap();
    let sample = |name: &str| {
        metrics.lines().find(|l| l.starts_with(name)).and_then(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
    };
    assert_eq!(sample("loopd_tenant_refused_total{tenant=\"flood\",limit=\"queue\"}"), Some(refused));
    assert_eq!(sample("loopd_tenant_frames_added_total{tenant=\"flood\"}"), Some(stored));
    assert_eq!(sample("loopd_tenant_frames_added_total{tenant=\"calm\"}"), Some(6));
    assert_eq!(sample("loopd_tenant_refused_total{tenant=\"calm\",limit=\"queue\"}"), Some(0));
    assert_eq!(sample("loopd_tenant_in_flight{tenant=\"flood\"}"), Some(0));
    server.shutdown().await.unwrap();
}

/// Tenants managed over gRPC (the Admin service): the admin key only, the key shown once and
/// usable at once, revocation by key id.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tenants_are_managed_over_grpc_with_the_admin_key() {
    use loopd::pb::admin_client::AdminClient;
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path()).await;
    let admin_client = |key: Option<&str>| {
        let header = key.map(|k| format!("Bearer {k}").parse::<tonic::metadata::MetadataValue<_>>().unwrap());
        let addr = server.grpc_addr;
        async move {
            let channel =
                tonic::transport::Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap();
            AdminClient::with_interceptor(channel, move |mut req: tonic::Request<()>| {
                if let Some(h) = &header {
                    req.metadata_mut().insert("authorization", h.clone());
                }
                Ok(req)
            })
        }
    };
    let mut admin = admin_client(Some(ADMIN)).await;
    let limits = pb::TenantLimits { rate: Some(50.0), max_in_flight: Some(2), ..Default::default() };
    let made = admin
        .create_tenant(pb::CreateTenantRequest { name: "grpc-made".into(), limits: Some(limits) })
        .await
        .unwrap()
        .into_inner();
    let tenant = made.tenant.unwrap();
    assert_eq!((tenant.name.as_str(), tenant.limits.unwrap().max_in_flight), ("grpc-made", Some(2)));
    let bad = admin.create_tenant(pb::CreateTenantRequest { name: "Bad/Name".into(), limits: None }).await;
    assert_eq!(bad.unwrap_err().code(), tonic::Code::InvalidArgument);

    let mut robot = grpc(server.grpc_addr, Some(&made.key)).await;
    robot.create_session(pb::CreateSessionRequest { id: "m".into(), ..Default::default() }).await.unwrap();
    let denied = admin_client(Some(&made.key)).await.list_tenants(pb::ListTenantsRequest {}).await;
    assert_eq!(denied.unwrap_err().code(), tonic::Code::PermissionDenied);
    let anonymous = admin_client(None).await.list_tenants(pb::ListTenantsRequest {}).await;
    assert_eq!(anonymous.unwrap_err().code(), tonic::Code::Unauthenticated);

    let listed = admin.list_tenants(pb::ListTenantsRequest {}).await.unwrap().into_inner().tenants;
    assert!(listed.iter().any(|t| t.name == "grpc-made" && !t.revoked));
    let revoked = admin
        .revoke_tenant(pb::RevokeTenantRequest { name_or_key_id: tenant.key_id.clone() })
        .await
        .unwrap()
        .into_inner();
    assert!(revoked.revoked);
    let gone = robot.list_sessions(pb::ListSessionsRequest {}).await.unwrap_err();
    assert_eq!(gone.code(), tonic::Code::Unauthenticated);
    let missing = admin.revoke_tenant(pb::RevokeTenantRequest { name_or_key_id: "nobody".into() }).await;
    assert_eq!(missing.unwrap_err().code(), tonic::Code::NotFound);
    server.shutdown().await.unwrap();
}

/// One sequence job of `n` corridor frames for `key`'s session `map` (HTTP, multipart); the
/// status and the answer.
async fn corridor_job(http: &Http, key: &str, n: usize) -> (u16, serde_json::Value) {
    let mut form = reqwest::multipart::Form::new().text("order", "name");
    for i in 0..n {
        let image = std::fs::read(data(&format!("corridor/ref/{:07}.jpg", i * 7))).unwrap();
        form = form.part("image", reqwest::multipart::Part::bytes(image).file_name(format!("{i:03}.jpg")));
    }
    let r = http.c.post(format!("{}/v1/sessions/map/sequences", http.base)).bearer_auth(key).multipart(form);
    let r = r.send().await.unwrap();
    (r.status().as_u16(), r.json().await.unwrap_or_default())
}

/// Issue #35, items 1 and 2, through the real server: a sequence job's frames wait for their
/// tenant's rate (a rate-2/s tenant's job never has more than rate x time + burst frames added)
/// and count as its frames in /metrics; a tenant that runs a job cannot take the last free job
/// slot, and another tenant gets it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_wait_for_their_tenants_rate_and_leave_a_slot_for_another_tenant() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 4, warm_up: false, ..Default::default() },
        auth: AuthConfig { admin_key: Some(ADMIN.into()), ..Default::default() },
        max_jobs: 2,
        ..ServerConfig::on_loopback(dir.path().to_path_buf())
    };
    let server = RunningServer::start(cfg, imagenet_model()).await.unwrap();
    let http = Http::new(&server);
    let mut keys = Vec::new();
    for (name, limits) in [("bulk", json!({ "rate": 2.0 })), ("other", json!({}))] {
        let (_, t) =
            http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": name, "limits": limits }))).await;
        let key = t["key"].as_str().unwrap().to_string();
        let (st, _) = http.call("POST", "/v1/sessions", Some(&key), Some(json!({ "id": "map" }))).await;
        assert_eq!(st, 201);
        keys.push(key);
    }
    // Bulk starts with two tokens (one second of burst); the job's submission takes one.
    let (rate, burst, n) = (2.0, 2.0, 14);
    let (st, job) = corridor_job(&http, &keys[0], n).await;
    assert_eq!(st, 202, "{job}");
    let started = std::time::Instant::now();
    let url = job["status_url"].as_str().unwrap().to_string();

    // Bulk's second job would take the last free slot: refused, naming the rule. Other's is not.
    let (st, refused) = corridor_job(&http, &keys[0], 2).await;
    assert_eq!(st, 429, "{refused}");
    assert!(refused["error"].as_str().unwrap().contains("kept for a tenant that runs none"), "{refused}");
    let (st, other_job) = corridor_job(&http, &keys[1], 2).await;
    assert_eq!(st, 202, "the other tenant's job takes the free slot: {other_job}");

    let mut polls = Vec::new();
    let done = loop {
        let (st, status) = http.call("GET", &url, Some(&keys[0]), None).await;
        assert_eq!(st, 200, "{status}");
        let done = status["done"].as_u64().unwrap() as f64;
        let t = started.elapsed().as_secs_f64();
        polls.push((t, done));
        assert!(done <= rate * t + burst, "{done} frames added {t:.2} s after the job started, at 2/s: {polls:?}");
        if status["state"] != "running" {
            assert_eq!(status["state"], "done", "{status}");
            break done;
        }
        assert!(t < 60.0, "the job did not end in 60 s: {status}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert_eq!(done as usize, n);
    let took = started.elapsed().as_secs_f64();
    assert!(took >= (n as f64 - burst) / rate - 0.5, "{n} frames at 2/s took {took:.1} s");
    let metrics = http.c.get(format!("{}/metrics", http.base)).bearer_auth(ADMIN).send().await.unwrap();
    let metrics = metrics.text().await.unwrap();
    let sample = |name: &str| {
        metrics.lines().find(|l| l.starts_with(name)).and_then(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
    };
    assert_eq!(sample("loopd_tenant_frames_added_total{tenant=\"bulk\"}"), Some(n as u64));

    // A stream is paced the same way: 16 frames sent at once on one gRPC stream, each takes a
    // token; those beyond the rate are refused in the stream (RESOURCE_EXHAUSTED), never stored.
    let dim = server.service.engine().info().dim;
    let mut g = grpc(server.grpc_addr, Some(&keys[0])).await;
    tokio::time::sleep(Duration::from_secs(1)).await; // the bucket full again: 2 tokens
    let sent = std::time::Instant::now();
    let frames: Vec<pb::AddFrameRequest> = (0..16).map(|i| descriptor_frame("map", dim, 1000 + i)).collect();
    let mut answers = g.stream_frames(tokio_stream::iter(frames)).await.unwrap().into_inner();
    let (mut acked, mut refused) = (0usize, 0usize);
    while let Some(a) = answers.message().await.unwrap() {
        match a.error_code {
            0 => acked += 1,
            c => {
                assert_eq!(c, tonic::Code::ResourceExhausted as i32, "{a:?}");
                refused += 1;
            }
        }
    }
    let t = sent.elapsed().as_secs_f64();
    assert_eq!(acked + refused, 16);
    assert!(acked as f64 <= rate * t + burst, "{acked} stream frames stored in {t:.2} s at 2/s");
    assert!(refused > 0, "16 frames at once at 2/s: none refused");
    let (_, map) = http.call("GET", "/v1/sessions/map", Some(&keys[0]), None).await;
    assert_eq!(map["frames"].as_u64(), Some((n + acked) as u64), "{map}");
    server.shutdown().await.unwrap();
}

/// The model is shared between tenants by batches, not by arrival: a tenant's backlog of images
/// delays another tenant's image by about one batch (real server, real images over HTTP).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_tenants_backlog_delays_another_tenants_image_by_about_one_batch() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(dir.path()).await; // max_batch 4
    let http = Http::new(&server);
    let mut keys = Vec::new();
    for name in ["bulk", "light"] {
        let (st, t) = http.call("POST", "/v1/tenants", Some(ADMIN), Some(json!({ "name": name }))).await;
        assert_eq!(st, 201, "{t}");
        keys.push(t["key"].as_str().unwrap().to_string());
    }
    let image = std::fs::read(data("corridor/query/0000000.jpg")).unwrap();
    let done = std::sync::Arc::new(parking_lot::Mutex::new(Vec::new()));
    let send = |key: &str, tag: &'static str| {
        let (c, url, key, body, done) =
            (http.c.clone(), format!("{}/v1/embed", http.base), key.to_string(), image.clone(), done.clone());
        tokio::spawn(async move {
            let r = c.post(url).bearer_auth(key).body(body).send().await.unwrap();
            assert_eq!(r.status(), 200, "{tag}: {}", r.text().await.unwrap());
            done.lock().push(tag);
        })
    };
    let mut tasks: Vec<_> = (0..24).map(|_| send(&keys[0], "bulk")).collect();
    // Light's image goes in once bulk's are in the engine.
    let start = std::time::Instant::now();
    loop {
        let m = http.c.get(format!("{}/metrics", http.base)).bearer_auth(ADMIN).send().await.unwrap();
        let text = m.text().await.unwrap();
        let depth = text
            .lines()
            .find_map(|l| l.strip_prefix("loopd_engine_queue_depth{model=\"loopd\"} "))
            .and_then(|v| v.trim().parse::<u64>().ok())
            .unwrap_or(0);
        if depth >= 20 {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(20), "bulk's images did not reach the engine: depth {depth}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    tasks.push(send(&keys[1], "light"));
    for t in tasks {
        t.await.unwrap();
    }
    let order = done.lock().clone();
    let before = order.iter().position(|t| *t == "light").unwrap();
    // One queue for all would answer it after about 20 of bulk's.
    assert!(before <= 8, "{before} of bulk's images were answered before light's: {order:?}");
    server.shutdown().await.unwrap();
}
