//! Lock-free counters and histograms of the engine, encoded for `/metrics` by prometheus-client
//! (the engine's metrics are one `Collector`).
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric, MetricEncoder, NoLabelSet};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::MetricType;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

/// A cumulative histogram with fixed upper bounds (Prometheus semantics).
#[derive(Debug)]
pub struct Histogram {
    bounds: &'static [f64],
    counts: Vec<AtomicU64>,
    sum_bits: AtomicU64,
    count: AtomicU64,
}

impl Histogram {
    pub fn new(bounds: &'static [f64]) -> Self {
        Self {
            bounds,
            counts: (0..bounds.len()).map(|_| AtomicU64::new(0)).collect(),
            sum_bits: AtomicU64::new(0f64.to_bits()),
            count: AtomicU64::new(0),
        }
    }

    pub fn observe(&self, v: f64) {
        if let Some(i) = self.bounds.iter().position(|&b| v <= b) {
            self.counts[i].fetch_add(1, Relaxed);
        }
        self.count.fetch_add(1, Relaxed);
        let _ = self.sum_bits.fetch_update(Relaxed, Relaxed, |bits| Some((f64::from_bits(bits) + v).to_bits()));
    }

    pub fn count(&self) -> u64 {
        self.count.load(Relaxed)
    }

    pub fn sum(&self) -> f64 {
        f64::from_bits(self.sum_bits.load(Relaxed))
    }

    /// Largest bucket bound that received an observation (0 when empty).
    pub fn max_bucket(&self) -> f64 {
        self.counts.iter().zip(self.bounds).filter(|(c, _)| c.load(Relaxed) > 0).map(|(_, &b)| b).fold(0.0, f64::max)
    }

    fn encode(&self, encoder: &mut DescriptorEncoder, name: &str, help: &str) -> std::fmt::Result {
        self.encode_into(encoder.encode_descriptor(name, help, None, MetricType::Histogram)?)
    }

    fn encode_into(&self, mut metric: MetricEncoder) -> std::fmt::Result {
        // prometheus-client takes each bucket's own count (it sums them) and f64::MAX as +Inf.
        let mut buckets: Vec<(f64, u64)> =
            self.counts.iter().zip(self.bounds).map(|(c, &b)| (b, c.load(Relaxed))).collect();
        let counted: u64 = buckets.iter().map(|(_, n)| n).sum();
        buckets.push((f64::MAX, self.count().saturating_sub(counted)));
        metric.encode_histogram::<NoLabelSet>(self.sum(), self.count(), &buckets, None)
    }
}

const BATCH_BOUNDS: &[f64] = &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0];
const SECONDS_BOUNDS: &[f64] = &[0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0];

#[derive(Debug)]
pub struct EngineMetrics {
    pub batch_size: Histogram,
    /// Time from admission (before decoding) to the start of the forward pass.
    pub queue_wait: Histogram,
    pub forward_seconds: Histogram,
    pub images: AtomicU64,
    /// Zero inputs added to fill batches up to their bucket (`EngineConfig::batch_buckets`).
    pub padded: AtomicU64,
    /// Batches cut to the shared batch time because several lanes had work (`shared_batch_time`).
    pub shared_batches: AtomicU64,
    pub rejected_overload: AtomicU64,
    pub cancelled: AtomicU64,
    pub failed: AtomicU64,
    pub queued: AtomicU64,
    started: std::time::Instant,
}

impl Default for EngineMetrics {
    fn default() -> Self {
        Self {
            batch_size: Histogram::new(BATCH_BOUNDS),
            queue_wait: Histogram::new(SECONDS_BOUNDS),
            forward_seconds: Histogram::new(SECONDS_BOUNDS),
            images: AtomicU64::new(0),
            padded: AtomicU64::new(0),
            shared_batches: AtomicU64::new(0),
            rejected_overload: AtomicU64::new(0),
            cancelled: AtomicU64::new(0),
            failed: AtomicU64::new(0),
            queued: AtomicU64::new(0),
            started: std::time::Instant::now(),
        }
    }
}

impl EngineMetrics {
    /// The counters: name, help, value.
    fn counters(&self) -> [(&'static str, &'static str, &AtomicU64); 6] {
        [
            ("loopd_engine_images", "Images embedded.", &self.images),
            ("loopd_engine_padded", "Zero inputs that filled batches up to their bucket size.", &self.padded),
            (
                "loopd_engine_shared_batches",
                "Batches cut to --shared-batch-ms because several tenants had work.",
                &self.shared_batches,
            ),
            ("loopd_engine_rejected", "Requests refused: queue full.", &self.rejected_overload),
            ("loopd_engine_cancelled", "Requests dropped by their caller before the forward pass.", &self.cancelled),
            ("loopd_engine_failed", "Requests whose forward pass failed.", &self.failed),
        ]
    }

    fn rate(&self) -> f64 {
        self.images.load(Relaxed) as f64 / self.started.elapsed().as_secs_f64().max(1e-9)
    }

    /// The histograms: name, help, histogram.
    fn histograms(&self) -> [(&'static str, &'static str, &Histogram); 3] {
        [
            ("loopd_engine_batch_size", "Images per forward pass.", &self.batch_size),
            ("loopd_engine_queue_wait_seconds", "Admission to forward pass start.", &self.queue_wait),
            ("loopd_engine_forward_seconds", "Forward pass duration.", &self.forward_seconds),
        ]
    }
}

const QUEUE_DEPTH: (&str, &str) = ("loopd_engine_queue_depth", "Requests admitted and not yet answered.");
const RATE: (&str, &str) = ("loopd_engine_images_per_second", "Images embedded per second since start.");

/// The engines of several served models (`serve --models`): each family once, a series per
/// model labelled `model="<name>"`.
#[derive(Debug)]
pub struct ModelMetrics(pub Vec<(String, std::sync::Arc<EngineMetrics>)>);

impl Collector for ModelMetrics {
    fn encode(&self, mut encoder: DescriptorEncoder) -> std::fmt::Result {
        let Some((_, first)) = self.0.first() else { return Ok(()) };
        let label = |model: &str| [("model".to_string(), model.to_string())];
        for (i, (name, help, _)) in first.counters().into_iter().enumerate() {
            let mut family = encoder.encode_descriptor(name, help, None, MetricType::Counter)?;
            for (model, m) in &self.0 {
                ConstCounter::new(m.counters()[i].2.load(Relaxed)).encode(family.encode_family(&label(model))?)?;
            }
        }
        let mut family = encoder.encode_descriptor(QUEUE_DEPTH.0, QUEUE_DEPTH.1, None, MetricType::Gauge)?;
        for (model, m) in &self.0 {
            ConstGauge::new(m.queued.load(Relaxed) as i64).encode(family.encode_family(&label(model))?)?;
        }
        let mut family = encoder.encode_descriptor(RATE.0, RATE.1, None, MetricType::Gauge)?;
        for (model, m) in &self.0 {
            ConstGauge::new(m.rate()).encode(family.encode_family(&label(model))?)?;
        }
        for (i, (name, help, _)) in first.histograms().into_iter().enumerate() {
            let mut family = encoder.encode_descriptor(name, help, None, MetricType::Histogram)?;
            for (model, m) in &self.0 {
                m.histograms()[i].2.encode_into(family.encode_family(&label(model))?)?;
            }
        }
        Ok(())
    }
}

impl Collector for EngineMetrics {
    fn encode(&self, mut encoder: DescriptorEncoder) -> std::fmt::Result {
        for (name, help, v) in self.counters() {
            let counter = ConstCounter::new(v.load(Relaxed));
            counter.encode(encoder.encode_descriptor(name, help, None, counter.metric_type())?)?;
        }
        let queued = ConstGauge::new(self.queued.load(Relaxed) as i64);
        queued.encode(encoder.encode_descriptor(QUEUE_DEPTH.0, QUEUE_DEPTH.1, None, queued.metric_type())?)?;
        let rate = ConstGauge::new(self.rate());
        rate.encode(encoder.encode_descriptor(RATE.0, RATE.1, None, rate.metric_type())?)?;
        for (name, help, h) in self.histograms() {
            h.encode(&mut encoder, name, help)?;
        }
        Ok(())
    }
}
