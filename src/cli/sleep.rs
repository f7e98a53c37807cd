//! `prac sleep DURATION`: the Kubernetes preStop pause (deploy/k8s) in an image that carries no
//! shell, so that endpoints stop routing to a pod before its SIGTERM.

use std::time::Duration;

use clap::Args;

#[derive(Args, Debug)]
pub struct SleepArgs {
    /// How long, e.g. "5s".
    #[arg(value_parser = prac::serve::duration)]
    duration: Duration,
}

impl SleepArgs {
    pub fn run(self) -> anyhow::Result<()> {
        std::thread::sleep(self.duration);
        Ok(())
    }
}
