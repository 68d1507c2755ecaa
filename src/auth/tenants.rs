//! Tenants (name, key id, the key's hash, revoked or not), kept in sled, and the check of a
//! request's `Authorization: Bearer <key>`.
use super::caller::Caller;
use super::keys;
use super::quota::{Limits, Quota, Refusal};
use crate::store::{Store, StoreError};
use parking_lot::RwLock;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering::SeqCst};
use std::sync::Arc;

/// Longest Authorization header looked at (a key is 81 characters).
const MAX_HEADER: usize = 1024;

#[derive(Debug, thiserror::Error)]
pub enum AuthError {
    #[error("{0}")]
    Unauthenticated(String),
    #[error("{0}")]
    PermissionDenied(String),
    #[error("{0}")]
    InvalidArgument(String),
    #[error("{0}")]
    NotFound(String),
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// How the server authenticates, from its start-up settings.
#[derive(Clone, Debug, Default)]
pub struct AuthConfig {
    /// The admin key (from a file or the environment, never a flag value).
    pub admin_key: Option<String>,
    /// Requests of one tenant in flight at once unless its limits say otherwise (None: no cap).
    pub tenant_in_flight: Option<u64>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
struct TenantRecord {
    name: String,
    key_id: String,
    key_sha256: String,
    created: f64,
    revoked: bool,
    #[serde(default)]
    limits: Limits,
}

/// A tenant as listed (no secret, no hash).
#[derive(Clone, Debug, Serialize, PartialEq, utoipa::ToSchema)]
#[schema(as = Tenant)]
pub struct TenantInfo {
    pub name: String,
    pub key_id: String,
    pub created: f64,
    pub revoked: bool,
    pub limits: Limits,
}

impl From<&TenantRecord> for TenantInfo {
    fn from(r: &TenantRecord) -> Self {
        Self {
            name: r.name.clone(),
            key_id: r.key_id.clone(),
            created: r.created,
            revoked: r.revoked,
            limits: r.limits,
        }
    }
}

pub struct Auth {
    /// Keys are required (set for good once an admin key or a tenant exists).
    enabled: AtomicBool,
    admin: Option<[u8; 32]>,
    /// By tenant name, with the quota its requests share.
    tenants: RwLock<HashMap<String, (TenantRecord, Arc<Quota>)>>,
    store: Arc<Store>,
    tenant_in_flight: Option<u64>,
}

fn valid_tenant(name: &str) -> bool {
    (1..=32).contains(&name.len())
        && name.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'_')
}

impl Auth {
    /// Keys are required once an admin key is set or any tenant exists; otherwise every request
    /// acts for the default tenant (the server refuses to listen beyond loopback that way unless
    /// told `--insecure`).
    pub fn new(cfg: &AuthConfig, store: Arc<Store>) -> Result<Self, AuthError> {
        let mut tenants = HashMap::new();
        for (name, record) in store.tenants()? {
            let r: TenantRecord = serde_json::from_slice(&record)
                .map_err(|e| AuthError::Store(StoreError::Storage(format!("tenant '{name}': {e}"))))?;
            let quota = Arc::new(Quota::new(r.limits, cfg.tenant_in_flight));
            tenants.insert(name, (r, quota));
        }
        let admin = cfg.admin_key.as_deref().map(str::trim).filter(|k| !k.is_empty()).map(keys::digest);
        let enabled = admin.is_some() || !tenants.is_empty();
        Ok(Self {
            enabled: AtomicBool::new(enabled),
            admin,
            tenants: RwLock::new(tenants),
            store,
            tenant_in_flight: cfg.tenant_in_flight,
        })
    }

    pub fn enabled(&self) -> bool {
        self.enabled.load(SeqCst)
    }

    /// Takes the tenants as `records` say (a cluster's log, read again every so often): keys
    /// issued through another node start to work here and revoked ones stop. A tenant whose
    /// record is unchanged keeps its quota's counters.
    pub fn sync(&self, records: Vec<(String, Vec<u8>)>) {
        let mut tenants = self.tenants.write();
        for (name, bytes) in records {
            let r: TenantRecord = match serde_json::from_slice(&bytes) {
                Ok(r) => r,
                Err(e) => {
                    tracing::warn!(tenant = %name, error = %e, "unreadable tenant record skipped");
                    continue;
                }
            };
            let same = tenants.get(&name).is_some_and(|(held, _)| {
                (&held.key_id, &held.key_sha256, held.revoked, held.limits)
                    == (&r.key_id, &r.key_sha256, r.revoked, r.limits)
            });
            if !same {
                let quota = Arc::new(Quota::new(r.limits, self.tenant_in_flight));
                tracing::info!(tenant = %name, key_id = %r.key_id, revoked = r.revoked, "tenant record taken from the cluster");
                tenants.insert(name, (r, quota));
                self.enabled.store(true, SeqCst);
            }
        }
    }

    /// The caller a request's Authorization header names. The same answer for an unknown and a
    /// revoked key, and no hint of which part was wrong.
    pub fn authenticate(&self, authorization: Option<&[u8]>) -> Result<Caller, AuthError> {
        if !self.enabled() {
            return Ok(Caller::unauthenticated());
        }
        let unauthenticated = |m: &str| Err(AuthError::Unauthenticated(m.to_string()));
        let Some(header) = authorization else {
            return unauthenticated("missing 'Authorization: Bearer <key>'");
        };
        if header.len() > MAX_HEADER {
            return unauthenticated("Authorization header too long");
        }
        let Some(token) = std::str::from_utf8(header)
            .ok()
            .and_then(|h| h.split_once(' '))
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .map(|(_, t)| t.trim())
        else {
            return unauthenticated("expected 'Authorization: Bearer <key>'");
        };
        if let Some(admin) = &self.admin {
            if subtle::ConstantTimeEq::ct_eq(&keys::digest(token)[..], &admin[..]).into() {
                return Ok(Caller::admin());
            }
        }
        let Some((key_id, secret)) = keys::parse(token) else {
            return unauthenticated("malformed key");
        };
        let tenants = self.tenants.read();
        let found = tenants.values().find(|(r, _)| r.key_id == key_id && !r.revoked);
        match found {
            Some((r, quota)) if keys::unhex(&r.key_sha256).is_some_and(|h| keys::matches(secret, &h)) => {
                Ok(Caller::limited(&r.name, quota.clone()))
            }
            _ => unauthenticated("unknown or revoked key"),
        }
    }

    /// Admin routes: the admin key only (metrics stay open while keys are off). Tenants are
    /// managed only on a server that has an admin key.
    pub fn require_admin(&self, caller: &Caller, tenants: bool) -> Result<(), AuthError> {
        if tenants && self.admin.is_none() {
            return Err(AuthError::PermissionDenied(
                "tenants are managed with the admin key: start the server with LOOPD_ADMIN_KEY_FILE or LOOPD_ADMIN_KEY"
                    .into(),
            ));
        }
        if !self.enabled() || caller.is_admin() {
            return Ok(());
        }
        Err(AuthError::PermissionDenied("this route needs the admin key".into()))
    }

    /// A tenant and its key (returned once, kept only as a hash). An existing tenant gets a new
    /// key and its old one stops working: key rotation, its sessions kept.
    pub async fn create_tenant(&self, name: &str, limits: Limits) -> Result<(TenantInfo, String), AuthError> {
        limits.validate().map_err(AuthError::InvalidArgument)?;
        if !valid_tenant(name) {
            return Err(AuthError::InvalidArgument(format!(
                "tenant name '{}' must be 1-32 characters of a-z, 0-9, '-' or '_'",
                name.chars().take(64).collect::<String>()
            )));
        }
        let (key_id, key, hash) = keys::new_key();
        let created =
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_secs_f64();
        let record = TenantRecord {
            name: name.to_string(),
            key_id,
            key_sha256: keys::hex(&hash),
            created,
            revoked: false,
            limits,
        };
        self.save(&record).await?;
        let info = TenantInfo::from(&record);
        let quota = Arc::new(Quota::new(limits, self.tenant_in_flight));
        self.tenants.write().insert(name.to_string(), (record, quota));
        tracing::info!(tenant = name, key_id = %info.key_id, "tenant key issued");
        Ok((info, key))
    }

    pub fn list(&self) -> Vec<TenantInfo> {
        let mut v: Vec<TenantInfo> = self.tenants.read().values().map(|(r, _)| TenantInfo::from(r)).collect();
        v.sort_by(|a, b| a.name.cmp(&b.name));
        v
    }

    /// Revokes a tenant's key, by tenant name or key id; its sessions stay.
    pub async fn revoke(&self, name_or_key_id: &str) -> Result<TenantInfo, AuthError> {
        let found =
            self.tenants.read().values().find(|(r, _)| r.name == name_or_key_id || r.key_id == name_or_key_id).cloned();
        let Some((mut record, quota)) = found else {
            return Err(AuthError::NotFound("no tenant or key with that name".into()));
        };
        record.revoked = true;
        self.save(&record).await?;
        let info = TenantInfo::from(&record);
        self.tenants.write().insert(record.name.clone(), (record, quota));
        tracing::info!(tenant = %info.name, key_id = %info.key_id, "tenant key revoked");
        Ok(info)
    }

    async fn save(&self, r: &TenantRecord) -> Result<(), AuthError> {
        let bytes = serde_json::to_vec(r).map_err(|e| AuthError::Store(StoreError::Storage(e.to_string())))?;
        self.store.put_tenant_durable(&r.name, &bytes).await?;
        Ok(())
    }
}

impl std::fmt::Debug for Auth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Auth").field("tenants", &self.tenants.read().len()).finish_non_exhaustive()
    }
}

/// Per-tenant requests, frames added, requests in flight and refusals by limit (`/metrics`).
impl prometheus_client::collector::Collector for Auth {
    fn encode(&self, mut encoder: prometheus_client::encoding::DescriptorEncoder) -> std::fmt::Result {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::{counter::ConstCounter, gauge::ConstGauge, MetricType};
        let tenants = self.tenants.read();
        let mut quotas: Vec<(&String, &Arc<Quota>)> = tenants.iter().map(|(n, (_, q))| (n, q)).collect();
        quotas.sort_by_key(|(n, _)| *n);
        type Sample = fn(&Quota) -> u64;
        let counters: [(&str, &str, Sample); 2] = [
            ("loopd_tenant_requests", "Writes and queries a tenant's key made (checked against its limits).", |q| {
                q.counters.requests.load(std::sync::atomic::Ordering::Relaxed)
            }),
            ("loopd_tenant_frames_added", "Frames a tenant stored.", |q| {
                q.counters.frames_added.load(std::sync::atomic::Ordering::Relaxed)
            }),
        ];
        for (name, help, sample) in counters {
            let mut family = encoder.encode_descriptor(name, help, None, MetricType::Counter)?;
            for (tenant, q) in &quotas {
                ConstCounter::new(sample(q)).encode(family.encode_family(&[("tenant", tenant.as_str())])?)?;
            }
        }
        let mut family = encoder.encode_descriptor(
            "loopd_tenant_in_flight",
            "A tenant's requests being embedded or searched now.",
            None,
            MetricType::Gauge,
        )?;
        for (tenant, q) in &quotas {
            ConstGauge::new(q.in_flight() as i64).encode(family.encode_family(&[("tenant", tenant.as_str())])?)?;
        }
        let mut family = encoder.encode_descriptor(
            "loopd_tenant_refused",
            "Requests refused by a tenant limit.",
            None,
            MetricType::Counter,
        )?;
        for (tenant, q) in &quotas {
            for r in Refusal::ALL {
                let labels = [("tenant", tenant.as_str()), ("limit", r.label())];
                ConstCounter::new(q.refused_by(r)).encode(family.encode_family(&labels)?)?;
            }
        }
        Ok(())
    }
}
