mod api;
mod depth;
mod inputs;
mod real;
