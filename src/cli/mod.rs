//! The `prac` binary's subcommands, one file each: its arguments (`Args`, with their help and
//! defaults) and what it does (`run`). The library holds the work; these read arguments, call
//! it and print.

pub mod bench_domains;
pub mod bench_replan;
#[cfg(feature = "train")]
pub mod bench_train;
pub mod copy_bundles;
pub mod default_guard;
pub mod domains;
pub mod env_serve;
pub mod evaluate;
#[cfg(feature = "onnx")]
pub mod export_onnx;
#[cfg(feature = "train")]
pub mod fit_model;
pub mod inspect;
pub mod model_error;
pub mod obs_bounds;
pub mod play_from_states;
#[cfg(feature = "render")]
pub mod render;
pub mod serve;
pub mod sleep;
#[cfg(feature = "train")]
pub mod train;
