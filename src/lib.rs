//! prac: predictable actor-critic control (PrAC) served over gRPC.
//!
//! What an embedder uses:
//! - [`manifest`]: what a policy is (sizes, bounds, architecture, normalisation), as a bundle
//!   stores it.
//! - [`bundle`]: the safetensors weight-bundle format.
//! - [`policy`]: a loaded policy's networks and the per-session evaluator.
//! - [`plan`]: Replan (Algorithm 2), shared by serving and training.
//! - [`domains`]: the environments (task interface) for training and the simulator client.
//! - [`eval`]: rollouts: returns, the value scale and the dynamics model's error.
//! - [`client`]: connecting, waiting for a server's policies, a local server, resuming sessions.
//! - [`proto`]: the gRPC API's messages and stubs.
//!
//! What the `prac` binary runs, each through a few entry points:
//! - [`serve`]: the gRPC daemon.
//! - [`env_rpc`]: environments over DeepMind's dm_env_rpc protocol (training on any served env).
//! - [`train`]: SAC + dynamics model training (Algorithm 1) with burn (feature `train`).
//! - [`render`]: pictures of domains and plans, and charts with plotters (feature `render`).
//!
//! Everything else is private to the crate (the f32 MLPs of `nn`, the server's sessions, batch
//! workers and transport); tests and benchmarks reach what they need of it through `testing`,
//! which is not part of the API. The fuzz targets are built with the feature `fuzz`.
//!
//! The features `train` and `render` (both default) carry the heavy dependencies, burn and
//! plotters; a client that only talks to the server or plays the domains (prac-bench) goes
//! without them.

// Items no caller outside the crate can reach are marked so: visibility is the boundary.
#![warn(unreachable_pub)]

pub mod bundle;
pub mod client;
pub mod domains;
pub mod env_rpc;
pub mod eval;
#[cfg(feature = "onnx")]
pub mod export;
pub mod manifest;
pub(crate) mod nn;
pub mod plan;
pub mod policy;
#[cfg(feature = "render")]
pub mod render;
pub mod serve;
#[doc(hidden)]
pub mod testing;
#[cfg(feature = "train")]
pub mod train;

pub use nn::{Kernel, kernel, use_kernel};

pub mod proto {
    //! Generated from proto/prac/v1/prac.proto.
    tonic::include_proto!("prac.v1");
    pub mod codec;
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("prac_descriptor");
}
