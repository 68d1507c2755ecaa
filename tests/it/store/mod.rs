mod graph;
mod search_pool;
mod sessions;
