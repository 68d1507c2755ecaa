mod graph;
mod rows;
mod search_pool;
mod sessions;
