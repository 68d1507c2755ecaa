mod bad_images;
mod engine;
mod network;
mod script;
