mod confidence;
mod inspect;
mod loops;
mod server;
mod tenants;
mod tls;
