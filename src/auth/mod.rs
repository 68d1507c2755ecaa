//! Who is calling: API keys, tenants, and the admin key. Every session belongs to a
//! tenant; a key sees only its tenant's sessions and jobs.
pub mod caller;
pub mod keys;
pub mod quota;
pub mod tenants;

pub use caller::Caller;
pub use quota::Limits;
pub use tenants::{Auth, AuthConfig, TenantInfo};
