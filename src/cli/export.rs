//! `loopd export`: a session's loop graph (frames.csv, loops.csv, graph.g2o, TUM trajectories)
//! as a tar, from a running server's export route (the server holds the store).
use crate::client::ServerArgs;
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
    #[command(flatten)]
    remote: ServerArgs,
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
    /// Only loops a client accepted become edges (not verified metric loops without a verdict).
    #[arg(long)]
    accepted_only: bool,
}

pub fn run(a: ExportArgs) -> Result<ExitCode> {
    let remote = a.remote.connect()?;
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
    if a.accepted_only {
        query.push(("accepted_only", "true".into()));
    }
    let r =
        remote.send(remote.client.get(format!("{}/v1/sessions/{}/export", remote.base, a.session)).query(&query))?;
    if let Some(summary) = r.headers().get("x-loopd-loops-left-out").and_then(|v| v.to_str().ok()) {
        eprintln!("graph.g2o: {summary}");
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
