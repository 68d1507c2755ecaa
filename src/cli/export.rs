//! `loopd export`: a session's loop graph (frames.csv, loops.csv, graph.g2o, TUM trajectories)
//! as a tar, from a running server's export route (the server holds the store).
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct ExportArgs {
    /// The session to export.
    session: String,
    /// Where the tar goes ("-": standard output).
    #[arg(long, short, default_value = "-")]
    out: PathBuf,
    /// The server's HTTP address.
    #[arg(long, env = "LOOPD_SERVER_HTTP", default_value = "http://127.0.0.1:8080")]
    server: String,
    /// A file holding the tenant's key (else LOOPD_KEY; none on a server without keys).
    #[arg(long, env = "LOOPD_KEY_FILE")]
    key_file: Option<PathBuf>,
    /// The CA (PEM) that signed the server's certificate, for an https:// server.
    #[arg(long, env = "LOOPD_CA")]
    ca: Option<PathBuf>,
    /// Odometry standard deviations in the graph (metres, radians).
    #[arg(long)]
    odometry_sigma_m: Option<f64>,
    #[arg(long)]
    odometry_sigma_rad: Option<f64>,
    /// Standard deviations of accepted loops given without a covariance.
    #[arg(long)]
    loop_sigma_m: Option<f64>,
    #[arg(long)]
    loop_sigma_rad: Option<f64>,
}

pub fn run(a: ExportArgs) -> Result<ExitCode> {
    let key = match &a.key_file {
        Some(p) => Some(std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?),
        None => std::env::var("LOOPD_KEY").ok(),
    };
    let mut client = reqwest::blocking::Client::builder().use_rustls_tls().timeout(None);
    if let Some(ca) = &a.ca {
        let pem = std::fs::read(ca).with_context(|| format!("reading {}", ca.display()))?;
        client = client.add_root_certificate(reqwest::Certificate::from_pem(&pem).context("the CA file")?);
    }
    let client = client.build().context("building the HTTP client")?;
    let base = a.server.trim_end_matches('/');
    let mut query = Vec::new();
    for (name, v) in [
        ("odometry_sigma_m", a.odometry_sigma_m),
        ("odometry_sigma_rad", a.odometry_sigma_rad),
        ("loop_sigma_m", a.loop_sigma_m),
        ("loop_sigma_rad", a.loop_sigma_rad),
    ] {
        if let Some(v) = v {
            query.push((name, v.to_string()));
        }
    }
    let mut request = client.get(format!("{base}/v1/sessions/{}/export", a.session)).query(&query);
    if let Some(k) = key.as_deref().map(str::trim).filter(|k| !k.is_empty()) {
        request = request.bearer_auth(k);
    }
    let r = request.send().with_context(|| format!("reaching {base}"))?;
    let status = r.status();
    if !status.is_success() {
        let body: serde_json::Value = r.json().unwrap_or_default();
        anyhow::bail!("{status}: {}", body["error"].as_str().unwrap_or("(no message)"));
    }
    let bytes = r.bytes().context("reading the export")?;
    if a.out.as_os_str() == "-" {
        use std::io::Write;
        std::io::stdout().write_all(&bytes)?;
    } else {
        std::fs::write(&a.out, &bytes).with_context(|| format!("writing {}", a.out.display()))?;
        eprintln!("{}: {} bytes", a.out.display(), bytes.len());
    }
    Ok(ExitCode::SUCCESS)
}
