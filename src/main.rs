use clap::Parser;

fn main() -> std::process::ExitCode {
    // Logs on stderr; LOOPD_LOG_FORMAT=json gives one JSON object per line for log collectors.
    // The DDS stack of `loopd ros2` logs every discovery step at info: its warnings only.
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| "info,rustdds=warn,ros2_client=warn".into());
    let logs = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    if std::env::var("LOOPD_LOG_FORMAT").is_ok_and(|f| f == "json") {
        logs.json().init();
    } else {
        logs.init();
    }
    let cli = loopd::cli::Cli::parse();
    match loopd::cli::run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::from(2)
        }
    }
}
