//! `prac bench-train`: SAC and model updates/s, env steps/s while training, and the replay
//! buffer's checkpoint save and load times.

use std::time::Duration;

use clap::Args;

#[derive(Args, Debug)]
pub struct BenchTrainArgs {
    /// Seconds measured per update kind.
    #[arg(long, default_value_t = 3.0)]
    seconds: f64,
    /// Domain of the short training run.
    #[arg(long, default_value = "hopper")]
    domain: String,
    /// Steps of the short training run.
    #[arg(long, default_value_t = 2000)]
    steps: u64,
    /// Transitions (Humanoid-sized) in the replay buffer whose checkpoint save and load are
    /// timed; 0 skips it.
    #[arg(long, default_value_t = 1_000_000)]
    replay_transitions: usize,
}

impl BenchTrainArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let bench = prac::train::bench::run(
            Duration::from_secs_f64(self.seconds),
            &self.domain,
            self.steps,
            self.replay_transitions,
        )?;
        print!("{}", prac::train::bench::report(&bench));
        Ok(())
    }
}
