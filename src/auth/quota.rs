//! Per-tenant limits: sessions, stored frames, and a request rate (token bucket). Over one, a
//! request gets RESOURCE_EXHAUSTED / 429 with a message naming the limit.
use parking_lot::Mutex;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// A tenant's limits; None: unlimited.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    pub max_sessions: Option<u64>,
    pub max_frames: Option<u64>,
    /// Frames added and queries made per second (bursts of up to one second's worth).
    pub rate: Option<f64>,
}

impl Limits {
    pub fn validate(&self) -> Result<(), String> {
        match self.rate {
            Some(r) if !(r.is_finite() && r > 0.0 && r <= 1e6) => {
                Err(format!("rate {r} must be in (0, 1e6] per second"))
            }
            _ => Ok(()),
        }
    }
}

/// A tenant's limits and the state of its rate bucket, shared by all its requests.
#[derive(Debug)]
pub struct Quota {
    pub limits: Limits,
    bucket: Mutex<(f64, Instant)>,
}

impl Quota {
    pub fn new(limits: Limits) -> Self {
        Self { limits, bucket: Mutex::new((limits.rate.unwrap_or(0.0).max(1.0), Instant::now())) }
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bucket_allows_a_second_of_burst_then_the_rate() {
        let q = Quota::new(Limits { rate: Some(5.0), ..Default::default() });
        let allowed = (0..20).filter(|_| q.take().is_ok()).count();
        assert_eq!(allowed, 5);
        std::thread::sleep(std::time::Duration::from_millis(450));
        assert!(q.take().is_ok(), "refilled at 5 per second");
        assert!(Quota::new(Limits::default()).take().is_ok());
        assert!(Limits { rate: Some(f64::NAN), ..Default::default() }.validate().is_err());
    }
}
