//! Which cluster nodes hold a session's index warm. Each node heartbeats in the log
//! (`pg_members.rs`); a session's owners are the `owners` live members ranked highest by
//! rendezvous hashing of (session, node), so every node computes the same owners from the same
//! member list, and a node leaving moves only its own sessions, each to the next in rank. Owners
//! load their sessions and follow their tails without waiting for a request, so a second owner
//! is already warm when the first is gone. Any node still answers any session (it loads it on
//! demand: the fallback); it drops a session it does not own once no request used it for
//! `evict_idle`, which bounds a node's memory to what it owns and what it serves.
use super::{Store, StoreError};
use serde::Serialize;
use sha2::{Digest, Sha256};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Duration;

/// This node's place in the cluster.
#[derive(Clone, Debug)]
pub struct Membership {
    /// Unique among the nodes (a host name and port by default).
    pub node: String,
    /// Nodes that hold each session warm.
    pub owners: usize,
    /// A member not seen for this long is gone.
    pub ttl: Duration,
    /// A session this node does not own is dropped once unused for this long (None: never).
    pub evict_idle: Option<Duration>,
}

/// What `GET /v1/cluster` shows: the members this node sees and the sessions it holds.
#[derive(Clone, Debug, Default, Serialize, utoipa::ToSchema)]
pub struct ClusterView {
    pub node: String,
    pub owners: usize,
    pub members: Vec<String>,
    pub held: Vec<HeldSession>,
}

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct HeldSession {
    pub session: String,
    pub frames: usize,
    /// Whether this node is one of its owners (else it holds it for requests it served).
    pub owner: bool,
}

/// The node's membership and the live members it saw last.
#[derive(Default)]
pub(super) struct Members {
    me: parking_lot::RwLock<Option<Membership>>,
    live: parking_lot::RwLock<Vec<String>>,
}

impl Members {
    pub(super) fn join(&self, me: Membership) {
        *self.me.write() = Some(me);
    }

    /// This node's membership (None before it joined).
    pub(super) fn me(&self) -> Option<Membership> {
        self.me.read().clone()
    }

    pub(super) fn set_live(&self, live: Vec<String>) {
        *self.live.write() = live;
    }

    /// The live members seen at the last round (empty before the first).
    pub(super) fn live(&self) -> Vec<String> {
        self.live.read().clone()
    }
}

pub(super) fn now_ms() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

/// The `r` owners of `session` among `members`: highest rendezvous weight first.
pub fn owners<'a>(session: &str, members: &'a [String], r: usize) -> Vec<&'a str> {
    let weight = |node: &str| {
        let digest = Sha256::new().chain_update(session).chain_update([0]).chain_update(node).finalize();
        let mut first = [0u8; 8];
        first.copy_from_slice(&digest[..8]);
        u64::from_be_bytes(first)
    };
    let mut ranked: Vec<(u64, &str)> = members.iter().map(|m| (weight(m), m.as_str())).collect();
    ranked.sort_unstable_by(|a, b| b.cmp(a));
    ranked.into_iter().take(r).map(|(_, m)| m).collect()
}

impl Store {
    /// Drops a session from memory and this node's cache if no request holds it and none used
    /// it within `idle` (the log keeps it; the next request loads it again).
    pub(super) fn evict_if_idle(&self, id: &str, idle: Duration) -> Result<(), StoreError> {
        let _admin = self.admin.lock();
        let evicted = {
            let mut held = self.sessions.write();
            // Only the map holds it (no request or job uses it), and nothing used it lately.
            let unused = held.get(id).is_some_and(|s| {
                Arc::strong_count(s) == 1 && now_ms().saturating_sub(s.used.load(Relaxed)) >= idle.as_millis() as u64
            });
            if unused {
                held.remove(id)
            } else {
                None
            }
        };
        let Some(s) = evicted else { return Ok(()) };
        tracing::debug!(session = id, "evicted: not owned here and unused");
        self.drop_trees(id, &s)
    }

    /// Notes that a request uses the session now (it is then kept at least `evict_idle`).
    pub(super) fn touch(s: &super::Session) {
        s.used.store(now_ms(), Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::owners;

    fn nodes(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("node-{i}:50051")).collect()
    }

    #[test]
    fn every_node_computes_the_same_two_distinct_owners() {
        let (a, mut b) = (nodes(5), nodes(5));
        b.reverse();
        for s in 0..100 {
            let id = format!("session-{s}");
            let o = owners(&id, &a, 2);
            assert_eq!(o, owners(&id, &b, 2), "the member list's order changed the owners of {id}");
            assert_eq!(o.len(), 2);
            assert_ne!(o[0], o[1]);
        }
        assert_eq!(owners("s", &a[..1], 2), vec![a[0].as_str()], "one member owns everything");
    }

    #[test]
    fn a_node_leaving_moves_only_its_own_sessions_and_spreads_them() {
        let all = nodes(4);
        let gone = all[1].clone();
        let left: Vec<String> = all.iter().filter(|n| **n != gone).cloned().collect();
        let mut per_node = std::collections::HashMap::<&str, usize>::new();
        for s in 0..400 {
            let id = format!("s{s}");
            let before = owners(&id, &all, 2);
            let after = owners(&id, &left, 2);
            // Owners that are still there stay owners; only the one that left is replaced.
            for o in before.iter().filter(|o| **o != gone) {
                assert!(after.contains(o), "{id}: {o} lost ownership when {gone} left");
            }
            for o in before {
                *per_node.entry(o).or_default() += 1;
            }
        }
        // 800 ownerships over 4 nodes: each near 200 (rendezvous hashing spreads them).
        for (node, n) in per_node {
            assert!((140..=260).contains(&n), "{node} owns {n} of 800");
        }
    }
}
