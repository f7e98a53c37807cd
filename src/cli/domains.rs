//! `prac domains`: the table of domains.

use clap::Args;

use prac::domains::{DOMAINS, make};

#[derive(Args, Debug)]
pub struct DomainsArgs {}

impl DomainsArgs {
    pub fn run(self) -> anyhow::Result<()> {
        print!("{}", table());
        Ok(())
    }
}

fn table() -> String {
    let mut out = format!(
        "{:<10} {:>7} {:>7} {:>14} {:>8}  {}\n",
        "name", "obs_dim", "act_dim", "episode_steps", "dt", "engine"
    );
    for name in DOMAINS {
        let env = make(name).expect("listed domains exist");
        let s = env.spec();
        out.push_str(&format!(
            "{:<10} {:>7} {:>7} {:>14} {:>8.4}  {}\n",
            s.name, s.obs_dim, s.act_dim, s.episode_len, s.control_period, s.engine
        ));
    }
    out
}
