//! Training (Algorithm 1): SAC as Stable-Baselines3 implements it plus the paper's dynamics model,
//! with autodiff by burn on the CPU; optionally acting from the PrAC plan (training-with-PrAC).
//! Writes the bundle format the server loads.
//!
//! - `nets`: burn modules and their conversion to inference networks.
//! - `sac`: the SAC update.
//! - `model`: the dynamics model's update and normalisation.
//! - `buffer`: the replay buffer.
//! - `run`: the training loop, curve and evaluations.
//! - `checkpoint`: checkpoints and resume.
//! - `fit`: `prac fit-model`.
//! - `bench`: `prac bench-train`.

pub mod bench;
pub(crate) mod buffer;
pub(crate) mod checkpoint;
pub mod fit;
pub(crate) mod model;
pub(crate) mod nets;
pub mod options;
pub mod run;
pub mod sac;

#[cfg(test)]
mod tests;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// A bar over `total` steps showing steps/s and the trainer's status line (hidden when `show` is
/// false or stderr is not a terminal).
pub(crate) fn progress_bar(total: u64, position: u64, show: bool) -> ProgressBar {
    let bar = ProgressBar::with_draw_target(
        Some(total),
        if show {
            ProgressDrawTarget::stderr()
        } else {
            ProgressDrawTarget::hidden()
        },
    );
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} {per_sec} eta {eta} | {msg}",
        )
        .expect("a valid template")
        .progress_chars("=> "),
    );
    bar.set_position(position);
    bar
}
