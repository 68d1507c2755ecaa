mod confidence;
mod inspect;
mod jobs;
mod loops;
mod openapi;
mod server;
mod tenants;
mod tls;
