mod api;
mod inputs;
mod real;
