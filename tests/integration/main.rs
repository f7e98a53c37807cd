//! The integration tests, one binary (one link instead of one per file): each module drives the
//! real `prac` binary, as a server over gRPC or as a command. `cargo test --release --test
//! integration MODULE::` runs one module's tests, e.g. `connections::`.

mod common;

mod auth;
mod bundles;
mod cli;
mod connections;
mod deadlines;
mod fallback;
mod memory;
mod metrics;
mod reload;
mod render;
mod replicas;
mod requests;
mod resume;
mod rotation;
mod server;
mod train;
