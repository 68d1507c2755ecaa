mod failover;
mod nodes;
mod pg;
