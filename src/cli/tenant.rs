//! `loopd tenant create|list|revoke`: tenant keys, through a running server's admin routes (the
//! server holds the store; the admin key comes from LOOPD_ADMIN_KEY or --admin-key-file).
use crate::client::{Http, TlsArgs};
use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct TenantArgs {
    #[command(subcommand)]
    command: TenantCommand,
    /// The server's HTTP address.
    #[arg(long, env = "LOOPD_SERVER_HTTP", default_value = "http://127.0.0.1:8080", global = true)]
    server: String,
    /// A file holding the admin key (else LOOPD_ADMIN_KEY).
    #[arg(long, env = "LOOPD_ADMIN_KEY_FILE", global = true)]
    admin_key_file: Option<PathBuf>,
    #[command(flatten)]
    tls: TlsArgs,
}

#[derive(Subcommand)]
enum TenantCommand {
    /// A new tenant and its key, printed once (an existing tenant gets a new key; the old one
    /// stops working).
    Create {
        name: String,
        /// Most sessions the tenant may hold.
        #[arg(long)]
        max_sessions: Option<u64>,
        /// Most frames over all its sessions.
        #[arg(long)]
        max_frames: Option<u64>,
        /// Frames added and queries made per second (token bucket, one second of burst).
        #[arg(long)]
        rate: Option<f64>,
        /// Its frames and queries being embedded or searched at once (default: the server's
        /// --tenant-queue-share of its queue).
        #[arg(long)]
        max_in_flight: Option<u64>,
        /// Its share of the model's forward passes against other tenants with work queued
        /// (1-1000; default 1, equal shares).
        #[arg(long)]
        weight: Option<u32>,
    },
    /// Every tenant: name, key id, created, revoked.
    List,
    /// Revokes a tenant's key, by tenant name or key id (its sessions stay).
    Revoke { name_or_key_id: String },
}

fn admin_key(file: &Option<PathBuf>) -> Result<String> {
    crate::auth::keys::read_admin_key(file.as_deref())?.context("no admin key: set LOOPD_ADMIN_KEY or --admin-key-file")
}

pub fn run(a: TenantArgs) -> Result<ExitCode> {
    let key = admin_key(&a.admin_key_file)?;
    let http = Http::new(&a.server, Some(key), &a.tls)?;
    let (client, base) = (&http.client, &http.base);
    let request = match &a.command {
        TenantCommand::Create { name, max_sessions, max_frames, rate, max_in_flight, weight } => {
            let limits = serde_json::json!({
                "max_sessions": max_sessions, "max_frames": max_frames, "rate": rate, "max_in_flight": max_in_flight,
                "weight": weight
            });
            client.post(format!("{base}/v1/tenants")).json(&serde_json::json!({ "name": name, "limits": limits }))
        }
        TenantCommand::List => client.get(format!("{base}/v1/tenants")),
        TenantCommand::Revoke { name_or_key_id } => client.delete(format!("{base}/v1/tenants/{name_or_key_id}")),
    };
    let body: serde_json::Value = http.send(request)?.json().context("reading the server's answer")?;
    match &a.command {
        TenantCommand::Create { .. } => {
            println!("tenant {} key id {}", body["name"].as_str().unwrap_or(""), body["key_id"].as_str().unwrap_or(""));
            println!("{}", body["key"].as_str().unwrap_or(""));
            eprintln!("the key is shown once: give it to the tenant now (clients send 'Authorization: Bearer <key>')");
        }
        TenantCommand::List => {
            println!("{:<32} {:<12} {:>14} revoked", "tenant", "key id", "created");
            for t in body["tenants"].as_array().into_iter().flatten() {
                println!(
                    "{:<32} {:<12} {:>14.0} {}",
                    t["name"].as_str().unwrap_or(""),
                    t["key_id"].as_str().unwrap_or(""),
                    t["created"].as_f64().unwrap_or(0.0),
                    t["revoked"].as_bool().unwrap_or(false)
                );
            }
        }
        TenantCommand::Revoke { .. } => println!("revoked: tenant {} key id {}", body["name"], body["key_id"]),
    }
    Ok(ExitCode::SUCCESS)
}
