//! The bridge's counters per robot, and `/metrics` (OpenMetrics text by prometheus-client) on
//! `--metrics-addr`.
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use std::sync::Arc;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RobotLabel {
    pub robot: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RejectLabel {
    pub robot: String,
    /// image (a message that is not an image loopd reads), camera_info, server (refused).
    pub what: String,
}

#[derive(Default)]
pub struct Metrics {
    pub received: Family<RobotLabel, Counter>,
    pub keyframes: Family<RobotLabel, Counter>,
    pub sent: Family<RobotLabel, Counter>,
    pub dropped: Family<RobotLabel, Counter>,
    pub rejected: Family<RejectLabel, Counter>,
    pub loops: Family<RobotLabel, Counter>,
    pub queued: Family<RobotLabel, Gauge>,
    pub retries: Family<RobotLabel, Counter>,
}

impl Metrics {
    pub fn registry(self: &Arc<Self>) -> Registry {
        let mut r = Registry::with_prefix("loopd_ros2");
        r.register("messages_received", "Camera messages received", self.received.clone());
        r.register("keyframes", "Camera messages kept as keyframes", self.keyframes.clone());
        r.register("frames_sent", "Keyframes the server acknowledged (stored)", self.sent.clone());
        r.register("frames_dropped", "Keyframes dropped unsent: the robot's queue was full", self.dropped.clone());
        r.register("rejected", "Messages refused (logged): what was wrong", self.rejected.clone());
        r.register("loops_published", "LoopClosure messages published", self.loops.clone());
        r.register("queued_frames", "Keyframes waiting for the server", self.queued.clone());
        r.register("send_retries", "Sends retried (server unreachable or busy)", self.retries.clone());
        r
    }

    pub fn robot(robot: &str) -> RobotLabel {
        RobotLabel { robot: robot.to_string() }
    }

    pub fn reject(&self, robot: &str, what: &str) {
        self.rejected.get_or_create(&RejectLabel { robot: robot.to_string(), what: what.to_string() }).inc();
    }
}

/// Serves `/metrics` until the process ends.
pub async fn serve(addr: std::net::SocketAddr, metrics: Arc<Metrics>) -> anyhow::Result<()> {
    use axum::routing::get;
    let registry = Arc::new(metrics.registry());
    let app = axum::Router::new().route(
        "/metrics",
        get(move || {
            let registry = registry.clone();
            async move {
                let mut body = String::new();
                match prometheus_client::encoding::text::encode(&mut body, &registry) {
                    Ok(()) => (
                        axum::http::StatusCode::OK,
                        [(
                            axum::http::header::CONTENT_TYPE,
                            "application/openmetrics-text; version=1.0.0; charset=utf-8",
                        )],
                        body,
                    ),
                    Err(e) => (
                        axum::http::StatusCode::INTERNAL_SERVER_ERROR,
                        [(axum::http::header::CONTENT_TYPE, "text/plain")],
                        e.to_string(),
                    ),
                }
            }
        }),
    );
    let listener = tokio::net::TcpListener::bind(addr).await?;
    tracing::info!(addr = %listener.local_addr()?, "metrics on /metrics");
    axum::serve(listener, app).await?;
    Ok(())
}
