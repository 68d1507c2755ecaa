//! The PostgreSQL primary and synchronous standby that `scripts/pg-replicated` starts on loopback
//! for the cluster tests, and the settings it exports (LOOPD_PG_*).
use std::process::Command;

pub fn env(name: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| panic!("{name} is unset: run these through scripts/pg-replicated"))
}

/// `pg_ctl -D dir -w ARGS` as the postgres user, as the script started the servers.
pub fn pg_ctl(dir: &str, args: &[&str]) {
    let status = Command::new("runuser")
        .args(["-u", "postgres", "--"])
        .arg(format!("{}/pg_ctl", env("LOOPD_PG_BIN")))
        .args(["-D", dir, "-w"])
        .args(args)
        .status()
        .unwrap();
    assert!(status.success(), "pg_ctl {args:?} on {dir}");
}

/// Stops (fast) or starts the server whose folder `var` names (LOOPD_PG_PRIMARY, LOOPD_PG_STANDBY).
pub fn server(var: &str, action: &str) {
    let dir = env(var);
    match action {
        "stop" => pg_ctl(&dir, &["stop", "-m", "fast"]),
        _ => pg_ctl(&dir, &["start", "-l", &format!("{dir}.log")]),
    }
}

/// One statement on the primary; its output, trimmed.
pub fn psql(sql: &str) -> String {
    let out = Command::new("psql").args([&env("LOOPD_PG_URL"), "-tAc", sql]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}
