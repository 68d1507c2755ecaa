mod crash;
mod disk_full;
mod overload;
mod server;
