//! `/metrics`: one prometheus-client registry per server, each layer's counters a `Collector`
//! of its own (the engine's queue and forward passes, the tenants' quotas, the listeners'
//! connections, the loops not kept), encoded as OpenMetrics text on each scrape.
use super::conn::Connections;
use crate::auth::Auth;
use crate::engine::metrics::ModelMetrics;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::registry::Registry;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;

/// A count the service keeps (name, help, value).
#[derive(Debug)]
struct Count(&'static str, &'static str, Arc<AtomicU64>);

impl Collector for Count {
    fn encode(&self, mut encoder: DescriptorEncoder) -> std::fmt::Result {
        let counter = ConstCounter::new(self.2.load(Relaxed));
        counter.encode(encoder.encode_descriptor(self.0, self.1, None, counter.metric_type())?)
    }
}

/// The server's registry.
pub fn registry(
    engines: ModelMetrics,
    auth: Arc<Auth>,
    connections: Arc<Connections>,
    loops_not_kept: Arc<AtomicU64>,
    features_extracted: Arc<AtomicU64>,
) -> Registry {
    let mut r = Registry::default();
    r.register_collector(Box::new(engines));
    r.register_collector(Box::new(auth));
    r.register_collector(Box::new(connections));
    r.register_collector(Box::new(Count(
        "loopd_loops_not_kept",
        "Answers whose loop candidates could not be kept.",
        loops_not_kept,
    )));
    r.register_collector(Box::new(Count(
        "loopd_features_extracted",
        "Images whose local features were extracted (admitted frames and queries, jobs).",
        features_extracted,
    )));
    r
}

/// The OpenMetrics text of a registry, `# EOF` last.
pub fn encode(r: &Registry) -> Result<String, std::fmt::Error> {
    let mut text = String::new();
    prometheus_client::encoding::text::encode(&mut text, r)?;
    Ok(text)
}

/// The content type of [`encode`]'s text.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";
