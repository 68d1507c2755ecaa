mod confidence;
mod inspect;
mod jobs;
mod loops;
mod server;
mod tenants;
mod tls;
