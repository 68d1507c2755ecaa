mod search_pool;
mod sessions;
