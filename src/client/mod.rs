//! One client for every remote subcommand (`export`, `ingest`, `tenant`, `eval --server`): the
//! server's address, a key (a tenant's, or the admin key), the CA of a TLS server and a client
//! certificate for a server that asks for one (`serve --tls-client-ca`), read from the same
//! arguments and made into an HTTP client (blocking reqwest) or a gRPC client (tonic). What
//! goes over the wire comes from `api::wire` and `pb`, never from the server's internals.
use crate::pb::loopd_client::LoopdClient;
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Identity};

/// The TLS side of a connection: whom to trust, and who we are when the server asks.
#[derive(Args, Clone, Debug, Default)]
pub struct TlsArgs {
    /// The CA (PEM) that signed the server's certificate, for an https:// server.
    #[arg(long, env = "LOOPD_CA", global = true)]
    pub ca: Option<PathBuf>,
    /// A client certificate chain (PEM), for a server that requires one (--tls-client-ca).
    #[arg(long, env = "LOOPD_CLIENT_CERT", global = true, requires = "client_key")]
    pub client_cert: Option<PathBuf>,
    /// The client certificate's private key (PEM).
    #[arg(long, env = "LOOPD_CLIENT_KEY", global = true, requires = "client_cert")]
    pub client_key: Option<PathBuf>,
}

/// A tenant's HTTP client: the server, the tenant's key and TLS (`export`, `ingest`).
#[derive(Args)]
pub struct ServerArgs {
    /// The server's HTTP address.
    #[arg(long, env = "LOOPD_SERVER_HTTP", default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// A file holding the tenant's key (else LOOPD_KEY; none on a server without keys).
    #[arg(long, env = "LOOPD_KEY_FILE")]
    pub key_file: Option<PathBuf>,
    #[command(flatten)]
    pub tls: TlsArgs,
}

impl ServerArgs {
    pub fn connect(&self) -> Result<Http> {
        Http::new(&self.server, tenant_key(self.key_file.as_deref())?, &self.tls)
    }
}

/// The tenant's key: the file's contents, else LOOPD_KEY; None when neither holds one.
pub fn tenant_key(file: Option<&Path>) -> Result<Option<String>> {
    let key = match file {
        Some(p) => Some(std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?),
        None => std::env::var("LOOPD_KEY").ok(),
    };
    Ok(key.map(|k| k.trim().to_string()).filter(|k| !k.is_empty()))
}

fn read(path: &Path, what: &str) -> Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("reading {what} {}", path.display()))
}

/// The client certificate chain and its key, when both are given.
fn identity(tls: &TlsArgs) -> Result<Option<(Vec<u8>, Vec<u8>)>> {
    match (&tls.client_cert, &tls.client_key) {
        (Some(cert), Some(key)) => Ok(Some((read(cert, "the client certificate")?, read(key, "the client key")?))),
        _ => Ok(None),
    }
}

/// An HTTP client bound to one server and key.
pub struct Http {
    pub client: reqwest::blocking::Client,
    pub base: String,
    key: Option<String>,
}

impl Http {
    pub fn new(server: &str, key: Option<String>, tls: &TlsArgs) -> Result<Self> {
        let mut client = reqwest::blocking::Client::builder().use_rustls_tls().timeout(None);
        if let Some(ca) = &tls.ca {
            let pem = read(ca, "the CA")?;
            client = client.add_root_certificate(reqwest::Certificate::from_pem(&pem).context("the CA file")?);
        }
        if let Some((mut pem, key)) = identity(tls)? {
            pem.push(b'\n');
            pem.extend(key);
            client = client.identity(reqwest::Identity::from_pem(&pem).context("the client certificate and key")?);
        }
        Ok(Self {
            client: client.build().context("building the HTTP client")?,
            base: server.trim_end_matches('/').to_string(),
            key,
        })
    }

    /// Sends with the key, if any; the answer whatever its status.
    pub fn call(&self, request: reqwest::blocking::RequestBuilder) -> Result<reqwest::blocking::Response> {
        let request = match &self.key {
            Some(k) => request.bearer_auth(k),
            None => request,
        };
        request.send().with_context(|| format!("reaching {}", self.base))
    }

    /// As `call`; a non-2xx answer becomes an error carrying the server's message.
    pub fn send(&self, request: reqwest::blocking::RequestBuilder) -> Result<reqwest::blocking::Response> {
        let r = self.call(request)?;
        if !r.status().is_success() {
            return Err(failed(r));
        }
        Ok(r)
    }
}

/// A non-2xx answer as an error: its status and the server's message.
pub fn failed(r: reqwest::blocking::Response) -> anyhow::Error {
    let status = r.status();
    let body: serde_json::Value = r.json().unwrap_or_default();
    anyhow::anyhow!("{status}: {}", body["error"].as_str().unwrap_or("(no message)"))
}

/// Puts the key in every gRPC call's `authorization` metadata (`Bearer <key>`).
#[derive(Clone)]
pub struct Bearer(Option<MetadataValue<Ascii>>);

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

pub type Grpc = LoopdClient<InterceptedService<Channel, Bearer>>;

/// A gRPC client for `addr` (`host:port`, `http://…` or `https://…`; https needs the CA).
pub async fn grpc(addr: &str, key: Option<String>, tls: &TlsArgs) -> Result<Grpc> {
    let url = if addr.contains("://") { addr.to_string() } else { format!("http://{addr}") };
    let bearer = match key {
        Some(k) => Some(format!("Bearer {k}").parse().context("the key is not valid in a gRPC header")?),
        None => None,
    };
    let mut endpoint = Channel::from_shared(url.clone()).with_context(|| format!("'{url}' is not a gRPC address"))?;
    if url.starts_with("https://") {
        let Some(ca) = &tls.ca else { bail!("{url} is a TLS server: give the CA that signed its certificate (--ca)") };
        let mut config = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(read(ca, "the CA")?));
        if let Some((cert, key)) = identity(tls)? {
            config = config.identity(Identity::from_pem(cert, key));
        }
        endpoint = endpoint.tls_config(config).context("the TLS settings")?;
    } else if tls.client_cert.is_some() {
        bail!("a client certificate needs an https:// server address, got {url}");
    }
    let channel = endpoint.connect().await.with_context(|| format!("connecting to {url}"))?;
    Ok(LoopdClient::with_interceptor(channel, Bearer(bearer)))
}
