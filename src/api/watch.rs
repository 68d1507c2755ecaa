//! What a running server keeps doing beside its calls: a cluster node follows the log (tenants,
//! the probe behind readiness) and its membership every round; every node reports its store's
//! health in gRPC health and reopens a store whose writes failed.
use super::grpc::{GrpcApi, LoopdServer};
use crate::auth::Auth;
use crate::store::Store;
use anyhow::Result;
use std::sync::Arc;
use std::time::Duration;
use tonic_health::ServingStatus;

/// Waits for the next of `tick`; false once the server shuts down.
async fn next_round(tick: &mut tokio::time::Interval, shutdown: &mut tokio::sync::watch::Receiver<bool>) -> bool {
    tokio::select! {
        _ = tick.tick() => true,
        _ = shutdown.changed() => false,
    }
}

fn rounds(every: Duration) -> tokio::time::Interval {
    let mut tick = tokio::time::interval(every.max(Duration::from_millis(10)));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tick
}

/// A cluster node following the log every `every` until shutdown: its tenants read again, and
/// whether the log takes writes (readiness: /readyz and gRPC health).
pub(super) async fn follow_cluster(
    auth: Arc<Auth>,
    store: Arc<Store>,
    every: Duration,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) {
    let mut tick = rounds(every);
    while next_round(&mut tick, &mut shutdown).await {
        match store.tenants_fresh().await {
            Ok(records) => auth.sync(records),
            Err(e) => tracing::debug!(error = %e, "tenants not read again from the cluster log"),
        }
        store.probe_log(every.max(Duration::from_secs(2))).await;
    }
}

/// A cluster node's membership, every `every` until shutdown (a task of its own: loading an
/// owned session can take seconds, which must not delay readiness). It leaves the members as it
/// stops, so the others own its sessions at once.
pub(super) async fn follow_members(
    store: Arc<Store>,
    every: Duration,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) {
    let mut tick = rounds(every);
    while next_round(&mut tick, &mut shutdown).await {
        if let Err(e) = store.follow_members().await {
            tracing::debug!(error = %e, "cluster membership not followed this round");
        }
    }
    let _ = tokio::time::timeout(Duration::from_secs(2), store.leave_members()).await;
}

/// While the store refuses writes (a full disk, say), tries to reopen it every `every` and
/// reports the state in gRPC health (NOT_SERVING until writes succeed again; `/readyz` reads the
/// store itself).
pub(super) async fn watch_storage(
    store: Arc<Store>,
    health: tonic_health::server::HealthReporter,
    every: std::time::Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) -> Result<()> {
    let serving = std::sync::atomic::AtomicBool::new(true);
    // Health follows the store (and in a cluster the log's last probe) within a tick, before and
    // after each reopen (which can take seconds); reopens are tried every `every`.
    let report = || async {
        let ok = store.readiness().is_none();
        if serving.swap(ok, std::sync::atomic::Ordering::Relaxed) != ok {
            let status = if ok { ServingStatus::Serving } else { ServingStatus::NotServing };
            health.set_service_status("", status).await;
            match ok {
                true => health.set_serving::<LoopdServer<GrpcApi>>().await,
                false => health.set_not_serving::<LoopdServer<GrpcApi>>().await,
            }
        }
    };
    let tick = every.min(Duration::from_millis(100));
    let mut next_try = tokio::time::Instant::now();
    loop {
        tokio::select! {
            _ = stop.wait_for(|s| *s) => return Ok(()),
            _ = tokio::time::sleep(tick) => {}
        }
        report().await;
        if store.failure().is_some() && tokio::time::Instant::now() >= next_try {
            let s = store.clone();
            match tokio::task::spawn_blocking(move || s.reopen()).await {
                Ok(Err(e)) => tracing::warn!(error = %e, "store not reopened yet"),
                Err(e) => tracing::error!(error = %e, "store reopen panicked"),
                Ok(Ok(())) => {}
            }
            next_try = tokio::time::Instant::now() + every;
            report().await;
        }
    }
}
