//! The tenant a request acts for, and how its session ids map to the store's.
use super::quota::Quota;
use crate::store::SessionInfo;
use std::sync::Arc;

/// The tenant that owns sessions made before tenants existed (and everything while auth is off).
pub const DEFAULT_TENANT: &str = "default";

/// A request's identity, set by the API layer after the key was checked.
#[derive(Clone, Debug)]
pub struct Caller {
    tenant: String,
    admin: bool,
    /// The tenant's limits (None: unlimited: the admin, and everything while keys are off).
    quota: Option<Arc<Quota>>,
}

impl Caller {
    /// A tenant's key.
    pub fn tenant(name: &str) -> Self {
        Self { tenant: name.to_string(), admin: false, quota: None }
    }

    /// A tenant's key, with its limits.
    pub fn limited(name: &str, quota: Arc<Quota>) -> Self {
        Self { quota: Some(quota), ..Self::tenant(name) }
    }

    pub fn quota(&self) -> Option<&Quota> {
        self.quota.as_deref()
    }

    pub fn quota_arc(&self) -> Option<&Arc<Quota>> {
        self.quota.as_ref()
    }

    /// The admin key: manages tenants and acts on the default tenant's sessions.
    pub fn admin() -> Self {
        Self { tenant: DEFAULT_TENANT.to_string(), admin: true, quota: None }
    }

    /// Auth off (loopback only): everything is the default tenant's.
    pub fn unauthenticated() -> Self {
        Self::tenant(DEFAULT_TENANT)
    }

    pub fn is_admin(&self) -> bool {
        self.admin
    }

    pub fn tenant_name(&self) -> &str {
        &self.tenant
    }

    /// The store's id of this tenant's session `id`: the default tenant's are stored as they are
    /// (data directories from before tenants keep working), another's as `tenant/id`. Client ids
    /// never hold '/', so no tenant can name another's.
    pub fn store_id(&self, id: &str) -> String {
        if self.tenant == DEFAULT_TENANT {
            id.to_string()
        } else {
            format!("{}/{id}", self.tenant)
        }
    }

    /// The client's id of a store session if this tenant owns it.
    pub fn own<'a>(&self, store_id: &'a str) -> Option<&'a str> {
        match store_id.split_once('/') {
            None => (self.tenant == DEFAULT_TENANT).then_some(store_id),
            Some((tenant, id)) => (tenant == self.tenant).then_some(id),
        }
    }

    /// A session's listing as this tenant sees it (its own id).
    pub fn view(&self, mut info: SessionInfo) -> SessionInfo {
        if let Some(id) = self.own(&info.meta.id) {
            info.meta.id = id.to_string();
        }
        info
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tenants_cannot_name_each_others_sessions() {
        let (a, b, d) = (Caller::tenant("acme"), Caller::tenant("blue"), Caller::unauthenticated());
        assert_eq!(a.store_id("warehouse"), "acme/warehouse");
        assert_eq!(d.store_id("warehouse"), "warehouse");
        assert_eq!(a.own("acme/warehouse"), Some("warehouse"));
        assert_eq!(b.own("acme/warehouse"), None);
        assert_eq!(a.own("warehouse"), None);
        assert_eq!(d.own("warehouse"), Some("warehouse"));
        assert_eq!(d.own("acme/warehouse"), None);
        assert_eq!(Caller::admin().own("warehouse"), Some("warehouse"));
    }
}
