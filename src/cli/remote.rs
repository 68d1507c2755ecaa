//! What the client commands (`export`, `ingest`) share: the server's address, the tenant's key
//! and the CA of an https:// server, and the error a failed call prints.
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct RemoteArgs {
    /// The server's HTTP address.
    #[arg(long, env = "LOOPD_SERVER_HTTP", default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// A file holding the tenant's key (else LOOPD_KEY; none on a server without keys).
    #[arg(long, env = "LOOPD_KEY_FILE")]
    pub key_file: Option<PathBuf>,
    /// The CA (PEM) that signed the server's certificate, for an https:// server.
    #[arg(long, env = "LOOPD_CA")]
    pub ca: Option<PathBuf>,
}

pub struct Remote {
    pub client: reqwest::blocking::Client,
    pub base: String,
    key: Option<String>,
}

impl RemoteArgs {
    pub fn connect(&self) -> Result<Remote> {
        let key = match &self.key_file {
            Some(p) => Some(std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?),
            None => std::env::var("LOOPD_KEY").ok(),
        };
        let mut client = reqwest::blocking::Client::builder().use_rustls_tls().timeout(None);
        if let Some(ca) = &self.ca {
            let pem = std::fs::read(ca).with_context(|| format!("reading {}", ca.display()))?;
            client = client.add_root_certificate(reqwest::Certificate::from_pem(&pem).context("the CA file")?);
        }
        Ok(Remote {
            client: client.build().context("building the HTTP client")?,
            base: self.server.trim_end_matches('/').to_string(),
            key: key.map(|k| k.trim().to_string()).filter(|k| !k.is_empty()),
        })
    }
}

impl Remote {
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
