mod graph;
mod kept;
mod rows;
mod search_pool;
mod sessions;
