//! TLS on both servers (issue #13), with certificates made here at run time (no private key is
//! committed): mutual TLS with a client CA, clients without a certificate or with one from
//! another CA refused, plain text refused, and a SIGHUP reload of the certificate that new
//! connections see while an open stream goes on.
use crate::common::certs::{write, Ca};
use crate::common::*;
use loopd::api::server::{RunningServer, ServerConfig};
use loopd::api::tls::TlsFiles;
use loopd::auth::AuthConfig;
use loopd::engine::EngineConfig;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use std::sync::Arc;
use std::time::Duration;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity};

const ADMIN: &str = "admin-key-for-the-tls-tests-0123456789";

fn der(pem: &str) -> Vec<u8> {
    use rustls::pki_types::pem::PemObject;
    rustls::pki_types::CertificateDer::from_pem_slice(pem.as_bytes()).unwrap().to_vec()
}

async fn grpc(
    addr: std::net::SocketAddr,
    ca: &str,
    client: Option<&(String, String)>,
) -> Result<tonic::transport::Channel, tonic::transport::Error> {
    let mut tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(ca)).domain_name("localhost");
    if let Some((cert, key)) = client {
        tls = tls.identity(Identity::from_pem(cert, key));
    }
    Endpoint::from_shared(format!("https://{addr}")).unwrap().tls_config(tls).unwrap().connect().await
}

type WithKey = fn(tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status>;

fn with_admin_key(mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
    req.metadata_mut().insert("authorization", format!("Bearer {ADMIN}").parse().unwrap());
    Ok(req)
}

/// A client whose calls carry the admin key.
fn authed(
    channel: tonic::transport::Channel,
) -> LoopdClient<tonic::service::interceptor::InterceptedService<tonic::transport::Channel, WithKey>> {
    LoopdClient::with_interceptor(channel, with_admin_key as WithKey)
}

/// The certificate a new TLS connection is shown (the client presents `client`).
async fn served_certificate(addr: std::net::SocketAddr, ca: &str, client: &(String, String)) -> Vec<u8> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
    let mut roots = rustls::RootCertStore::empty();
    roots.add(CertificateDer::from_pem_slice(ca.as_bytes()).unwrap()).unwrap();
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let cfg = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_client_auth_cert(
            vec![CertificateDer::from_pem_slice(client.0.as_bytes()).unwrap()],
            PrivateKeyDer::from_pem_slice(client.1.as_bytes()).unwrap(),
        )
        .unwrap();
    let tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let tls = tokio_rustls::TlsConnector::from(Arc::new(cfg))
        .connect(ServerName::try_from("localhost").unwrap(), tcp)
        .await
        .unwrap();
    tls.get_ref().1.peer_certificates().unwrap()[0].to_vec()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_on_both_apis_and_a_reload_on_sighup() {
    let dir = tempfile::tempdir().unwrap();
    let ca = Ca::new("loopd test CA");
    let ca_pem = ca.cert.pem();
    let server_cert = ca.issue(&["localhost", "127.0.0.1"]);
    let robot = ca.issue(&["robot-7"]);
    let rogue = Ca::new("someone else").issue(&["robot-7"]);
    let files = TlsFiles {
        cert: write(dir.path(), "server.pem", &server_cert.0),
        key: write(dir.path(), "server.key", &server_cert.1),
        client_ca: Some(write(dir.path(), "ca.pem", &ca_pem)),
    };
    let cfg = ServerConfig {
        engine: EngineConfig { max_batch: 2, warm_up: false, ..Default::default() },
        auth: AuthConfig { admin_key: Some(ADMIN.into()), ..Default::default() },
        tls: Some(files.clone()),
        ..ServerConfig::on_loopback(dir.path().join("data"))
    };
    let server = RunningServer::start(cfg, imagenet_model()).await.unwrap();
    let dim = server.service.engine().info().dim;

    // gRPC with the robot's certificate and a key.
    let mut c = authed(grpc(server.grpc_addr, &ca_pem, Some(&robot)).await.unwrap());
    c.create_session(pb::CreateSessionRequest { id: "s".into(), ..Default::default() }).await.unwrap();
    let frame = |i: usize| pb::AddFrameRequest {
        session_id: "s".into(),
        robot_id: "robot-7".into(),
        timestamp: Some(i as f64),
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
            values: (0..dim).map(|k| ((k + i * 5) % 17) as f32 - 8.0).collect(),
            ..Default::default()
        })),
        ..Default::default()
    };
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let mut stream = c.stream_frames(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
    tx.send(frame(0)).await.unwrap();
    assert_eq!(stream.message().await.unwrap().unwrap().error, "");

    // Refused: no client certificate, one from another CA, plain text.
    for (what, client) in [("no client certificate", None), ("another CA's certificate", Some(&rogue))] {
        let refused = match grpc(server.grpc_addr, &ca_pem, client).await {
            Err(_) => true,
            Ok(ch) => authed(ch).list_sessions(pb::ListSessionsRequest {}).await.is_err(),
        };
        assert!(refused, "gRPC with {what} must fail");
    }
    let plain = LoopdClient::connect(format!("http://{}", server.grpc_addr)).await;
    assert!(plain.is_err() || plain.unwrap().list_sessions(pb::ListSessionsRequest {}).await.is_err());

    // HTTP over TLS with the robot's certificate; without one, or in plain text, refused.
    let https = |identity: Option<&(String, String)>| {
        let mut b = reqwest::Client::builder()
            .use_rustls_tls()
            .tls_built_in_root_certs(false)
            .add_root_certificate(reqwest::Certificate::from_pem(ca_pem.as_bytes()).unwrap())
            .resolve("localhost", server.http_addr);
        if let Some((cert, key)) = identity {
            b = b.identity(reqwest::Identity::from_pem(format!("{cert}{key}").as_bytes()).unwrap());
        }
        b.build().unwrap()
    };
    let url = |p: &str| format!("https://localhost:{}{p}", server.http_addr.port());
    let r = https(Some(&robot)).get(url("/v1/sessions")).bearer_auth(ADMIN).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert!(https(None).get(url("/healthz")).send().await.is_err(), "no client certificate");
    assert!(https(Some(&rogue)).get(url("/healthz")).send().await.is_err(), "another CA's certificate");
    let plain = reqwest::get(format!("http://{}/healthz", server.http_addr)).await;
    assert!(plain.is_err() || plain.unwrap().status() != 200, "plain HTTP on the TLS port");

    // `loopd tenant` on the mTLS server: with the robot's certificate it lists, without it fails.
    let robot_cert = write(dir.path(), "robot.pem", &robot.0);
    let robot_key = write(dir.path(), "robot.key", &robot.1);
    let (server_url, ca_file) = (format!("https://127.0.0.1:{}", server.http_addr.port()), files.client_ca.clone());
    let listed = tokio::task::spawn_blocking(move || {
        let run = |with_cert: bool| {
            let mut c = loopd_bin();
            c.args(["tenant", "list", "--server", &server_url]).arg("--ca").arg(ca_file.as_ref().unwrap());
            if with_cert {
                c.arg("--client-cert").arg(&robot_cert).arg("--client-key").arg(&robot_key);
            }
            c.env("LOOPD_ADMIN_KEY", ADMIN).output().unwrap()
        };
        (run(true), run(false))
    })
    .await
    .unwrap();
    assert!(listed.0.status.success(), "{}", String::from_utf8_lossy(&listed.0.stderr));
    assert!(!listed.1.status.success(), "loopd tenant without a client certificate on an mTLS server");

    // `loopd eval --server` over gRPC on the same server: the one client's key, CA and certificate.
    let gt = write(dir.path(), "gt.csv", "0,0\n");
    let (grpc_url, ca_file) = (format!("https://127.0.0.1:{}", server.grpc_addr.port()), files.client_ca.clone());
    let (robot_cert, robot_key) = (dir.path().join("robot.pem"), dir.path().join("robot.key"));
    let evaluated = tokio::task::spawn_blocking(move || {
        let run = |with_cert: bool, key: &str| {
            let mut c = loopd_bin();
            c.args(["eval", "--server", &grpc_url, "--session", "s", "--json", "--gt"]).arg(&gt);
            c.arg("--ca").arg(ca_file.as_ref().unwrap());
            if with_cert {
                c.arg("--client-cert").arg(&robot_cert).arg("--client-key").arg(&robot_key);
            }
            c.env_remove("LOOPD_KEY_FILE").env("LOOPD_KEY", key).output().unwrap()
        };
        (run(true, ADMIN), run(false, ADMIN), run(true, "not-a-key"))
    })
    .await
    .unwrap();
    assert!(evaluated.0.status.success(), "{}", String::from_utf8_lossy(&evaluated.0.stderr));
    let report: serde_json::Value = serde_json::from_slice(&evaluated.0.stdout).unwrap();
    assert_eq!(report["frames"], 1, "{report}");
    assert!(!evaluated.1.status.success(), "loopd eval without a client certificate on an mTLS server");
    let refused = String::from_utf8_lossy(&evaluated.2.stderr);
    assert!(
        !evaluated.2.status.success() && refused.contains("valid authentication credentials"),
        "a wrong key: {refused}"
    );

    // A new certificate, then SIGHUP: new connections get it, the open stream goes on.
    let before = served_certificate(server.http_addr, &ca_pem, &robot).await;
    assert_eq!(before, der(&server_cert.0));
    let renewed = ca.issue(&["localhost", "127.0.0.1"]);
    std::fs::write(&files.cert, &renewed.0).unwrap();
    std::fs::write(&files.key, &renewed.1).unwrap();
    let hup = |pid: u32| std::process::Command::new("kill").args(["-HUP", &pid.to_string()]).status().unwrap();
    assert!(hup(std::process::id()).success());
    let mut served = Vec::new();
    for _ in 0..50 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        served = served_certificate(server.grpc_addr, &ca_pem, &robot).await;
        if served != before {
            break;
        }
    }
    assert_eq!(served, der(&renewed.0), "new connections see the reloaded certificate");
    tx.send(frame(1)).await.unwrap();
    assert_eq!(stream.message().await.unwrap().unwrap().error, "", "the open stream survived the reload");

    // A broken file on reload: the certificate in use stays.
    std::fs::write(&files.cert, "not a certificate").unwrap();
    assert!(hup(std::process::id()).success());
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(served_certificate(server.http_addr, &ca_pem, &robot).await, der(&renewed.0));
    drop(tx);
    server.shutdown().await.unwrap();
}
