//! Per-tenant limits: sessions, stored frames, a request rate (token bucket) and a share of the
//! inference queue. Over one, a request gets RESOURCE_EXHAUSTED / 429 with a message naming the
//! limit. Each tenant's requests and refusals are counted for /metrics.
use parking_lot::Mutex;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// A tenant's limits; None: unlimited.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
#[schema(as = TenantLimits)]
pub struct Limits {
    pub max_sessions: Option<u64>,
    pub max_frames: Option<u64>,
    /// Frames added and queries made per second (bursts of up to one second's worth).
    pub rate: Option<f64>,
    /// Frames and queries of this tenant being embedded or searched at once (default: the
    /// server's --tenant-queue-share of its queue), so one flooding tenant cannot starve others.
    pub max_in_flight: Option<u64>,
    /// The tenant's share of the model's forward passes against other tenants with work
    /// queued (default 1: equal shares; 1 to 1000): each batch is filled from the tenants'
    /// queues by deficit round robin in proportion to their weights.
    pub weight: Option<u32>,
}

/// Most weight a tenant may have (its share against a weight-1 tenant).
pub const MAX_WEIGHT: u32 = 1000;

impl Limits {
    pub fn validate(&self) -> Result<(), String> {
        if self.max_in_flight == Some(0) {
            return Err("max_in_flight must be at least 1".into());
        }
        if let Some(w) = self.weight.filter(|w| !(1..=MAX_WEIGHT).contains(w)) {
            return Err(format!("weight {w} must be in 1..={MAX_WEIGHT}"));
        }
        match self.rate {
            Some(r) if !(r.is_finite() && r > 0.0 && r <= 1e6) => {
                Err(format!("rate {r} must be in (0, 1e6] per second"))
            }
            _ => Ok(()),
        }
    }
}

/// Which limit refused a request (the `limit` label of loopd_tenant_refused_total).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Refusal {
    Rate,
    Frames,
    Sessions,
    Queue,
}

impl Refusal {
    pub const ALL: [Refusal; 4] = [Refusal::Rate, Refusal::Frames, Refusal::Sessions, Refusal::Queue];

    pub fn label(self) -> &'static str {
        match self {
            Refusal::Rate => "rate",
            Refusal::Frames => "frames",
            Refusal::Sessions => "sessions",
            Refusal::Queue => "queue",
        }
    }
}

/// A tenant's counters since the server started.
#[derive(Debug, Default)]
pub struct Counters {
    pub requests: AtomicU64,
    pub frames_added: AtomicU64,
    refused: [AtomicU64; 4],
}

/// A tenant's limits, the state of its rate bucket and its requests in flight, shared by all its
/// requests.
#[derive(Debug)]
pub struct Quota {
    pub limits: Limits,
    bucket: Mutex<(f64, Instant)>,
    /// The in-flight limit in force (the tenant's own, else the server's default share).
    max_in_flight: Option<u64>,
    in_flight: AtomicU64,
    pub counters: Counters,
}

/// One request of a tenant in flight; the slot is freed when this drops.
pub struct InFlight(Arc<Quota>);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.in_flight.fetch_sub(1, Ordering::AcqRel);
    }
}

impl Quota {
    pub fn new(limits: Limits, default_in_flight: Option<u64>) -> Self {
        Self {
            limits,
            bucket: Mutex::new((limits.rate.unwrap_or(0.0).max(1.0), Instant::now())),
            max_in_flight: limits.max_in_flight.or(default_in_flight),
            in_flight: AtomicU64::new(0),
            counters: Counters::default(),
        }
    }

    /// A slot among the tenant's requests in flight, or why not.
    pub fn enter(self: &Arc<Self>) -> Result<InFlight, String> {
        let before = self.in_flight.fetch_add(1, Ordering::AcqRel);
        let slot = InFlight(self.clone());
        match self.max_in_flight {
            Some(max) if before >= max => Err(format!(
                "the tenant has {before} requests in the inference queue; its share is {max} (retry later)"
            )),
            _ => Ok(slot),
        }
    }

    pub fn refused(&self, why: Refusal) {
        self.counters.refused[why as usize].fetch_add(1, Ordering::Relaxed);
    }

    /// Requests in flight now.
    pub fn in_flight(&self) -> u64 {
        self.in_flight.load(Ordering::Relaxed)
    }

    /// Requests refused by `r` since the start.
    pub fn refused_by(&self, r: Refusal) -> u64 {
        self.counters.refused[r as usize].load(Ordering::Relaxed)
    }

    /// One request's token, or why not.
    pub fn take(&self) -> Result<(), String> {
        let Some(rate) = self.limits.rate else { return Ok(()) };
        let burst = rate.max(1.0);
        let mut b = self.bucket.lock();
        let now = Instant::now();
        b.0 = (b.0 + now.duration_since(b.1).as_secs_f64() * rate).min(burst);
        b.1 = now;
        if b.0 >= 1.0 {
            b.0 -= 1.0;
            return Ok(());
        }
        Err(format!("request rate over the tenant's limit of {rate} per second"))
    }

    /// One frame's token for work that waits instead of being refused (a sequence job's frames,
    /// issue #35): returns once the tenant's bucket holds a token, and takes it. A tenant's jobs
    /// and its live requests draw on the same bucket, so together they stay within its rate.
    pub async fn pace(&self) {
        let Some(rate) = self.limits.rate else { return };
        loop {
            let wait = {
                let mut b = self.bucket.lock();
                let now = Instant::now();
                b.0 = (b.0 + now.duration_since(b.1).as_secs_f64() * rate).min(rate.max(1.0));
                b.1 = now;
                if b.0 >= 1.0 {
                    b.0 -= 1.0;
                    return;
                }
                (1.0 - b.0) / rate
            };
            tokio::time::sleep(std::time::Duration::from_secs_f64(wait.clamp(0.001, 60.0))).await;
        }
    }

    /// Counts frames the tenant stored.
    pub fn added(&self, frames: usize) {
        self.counters.frames_added.fetch_add(frames as u64, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bucket_allows_a_second_of_burst_then_the_rate() {
        let q = Quota::new(Limits { rate: Some(5.0), ..Default::default() }, None);
        let allowed = (0..20).filter(|_| q.take().is_ok()).count();
        assert_eq!(allowed, 5);
        std::thread::sleep(std::time::Duration::from_millis(450));
        assert!(q.take().is_ok(), "refilled at 5 per second");
        assert!(Quota::new(Limits::default(), None).take().is_ok());
        assert!(Limits { rate: Some(f64::NAN), ..Default::default() }.validate().is_err());
        for (weight, ok) in [(0, false), (1, true), (MAX_WEIGHT, true), (MAX_WEIGHT + 1, false)] {
            assert_eq!(Limits { weight: Some(weight), ..Default::default() }.validate().is_ok(), ok, "weight {weight}");
        }
    }

    #[test]
    fn in_flight_slots_are_shared_and_freed() {
        let q = Arc::new(Quota::new(Limits::default(), Some(2)));
        let (a, b) = (q.enter().unwrap(), q.enter().unwrap());
        assert!(q.enter().is_err(), "a third request over a share of 2");
        drop(a);
        let _c = q.enter().expect("a slot freed by the first");
        drop(b);
        let own = Arc::new(Quota::new(Limits { max_in_flight: Some(1), ..Default::default() }, Some(8)));
        let _d = own.enter().unwrap();
        assert!(own.enter().is_err(), "the tenant's own limit wins over the default");
    }
}
