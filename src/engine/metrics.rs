//! Lock-free counters and histograms of the engine, rendered as Prometheus text.
use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

/// A cumulative histogram with fixed upper bounds (Prometheus semantics).
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

    fn render(&self, out: &mut String, name: &str, help: &str) {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cumulative = 0;
        for (c, b) in self.counts.iter().zip(self.bounds) {
            cumulative += c.load(Relaxed);
            let _ = writeln!(out, "{name}_bucket{{le=\"{b}\"}} {cumulative}");
        }
        let _ = writeln!(out, "{name}_bucket{{le=\"+Inf\"}} {}", self.count());
        let _ = writeln!(out, "{name}_sum {}\n{name}_count {}", self.sum(), self.count());
    }
}

const BATCH_BOUNDS: &[f64] = &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0];
const SECONDS_BOUNDS: &[f64] = &[0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0];

pub struct EngineMetrics {
    pub batch_size: Histogram,
    /// Time from admission (before decoding) to the start of the forward pass.
    pub queue_wait: Histogram,
    pub forward_seconds: Histogram,
    pub images: AtomicU64,
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
            rejected_overload: AtomicU64::new(0),
            cancelled: AtomicU64::new(0),
            failed: AtomicU64::new(0),
            queued: AtomicU64::new(0),
            started: std::time::Instant::now(),
        }
    }
}

impl EngineMetrics {
    pub fn render_prometheus(&self) -> String {
        let mut out = String::new();
        let counter = |out: &mut String, name: &str, help: &str, v: u64| {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}");
        };
        counter(&mut out, "loopd_engine_images_total", "Images embedded.", self.images.load(Relaxed));
        counter(
            &mut out,
            "loopd_engine_rejected_total",
            "Requests refused: queue full.",
            self.rejected_overload.load(Relaxed),
        );
        counter(
            &mut out,
            "loopd_engine_cancelled_total",
            "Requests dropped by their caller before the forward pass.",
            self.cancelled.load(Relaxed),
        );
        counter(
            &mut out,
            "loopd_engine_failed_total",
            "Requests whose forward pass failed.",
            self.failed.load(Relaxed),
        );
        let _ = writeln!(
            out,
            "# HELP loopd_engine_queue_depth Requests admitted and not yet answered.\n# TYPE loopd_engine_queue_depth gauge\nloopd_engine_queue_depth {}",
            self.queued.load(Relaxed)
        );
        let rate = self.images.load(Relaxed) as f64 / self.started.elapsed().as_secs_f64().max(1e-9);
        let _ = writeln!(out, "# HELP loopd_engine_images_per_second Images embedded per second since start.\n# TYPE loopd_engine_images_per_second gauge\nloopd_engine_images_per_second {rate}");
        self.batch_size.render(&mut out, "loopd_engine_batch_size", "Images per forward pass.");
        self.queue_wait.render(&mut out, "loopd_engine_queue_wait_seconds", "Admission to forward pass start.");
        self.forward_seconds.render(&mut out, "loopd_engine_forward_seconds", "Forward pass duration.");
        out
    }
}
