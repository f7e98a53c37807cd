//! `prac default-guard FILE... [--every-critic] [--support-limit Z] [--max-epsilon-coef C] |
//! --none`: sets the plan guard a bundle's sessions get when they ask for none.

use std::path::PathBuf;

use clap::Args;

use prac::bundle;
use prac::manifest::{FORMAT_VERSION_DEFAULT_GUARD, FORMAT_VERSION_EPSILON_LIMIT, Guard};

#[derive(Args, Debug)]
pub struct DefaultGuardArgs {
    /// Bundles; each is rewritten in place (atomically).
    #[arg(required = true)]
    files: Vec<PathBuf>,
    /// Any one critic rating a kept action more than eps below pi(s) breaks the plan.
    #[arg(long, conflicts_with = "none")]
    every_critic: bool,
    /// An action further than Z of the policy's standard deviations from its mean breaks the plan.
    #[arg(long, value_name = "Z", conflicts_with = "none")]
    support_limit: Option<f32>,
    /// Hold every session's eps to at most C x (V_pi - V_rand), whatever it asks for.
    #[arg(long, value_name = "C", conflicts_with = "none")]
    max_epsilon_coef: Option<f64>,
    /// Remove the default: sessions that set no guard get the paper's test.
    #[arg(long)]
    none: bool,
}

impl DefaultGuardArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let guard = Guard {
            every_critic: self.every_critic,
            support_limit: self.support_limit.unwrap_or(0.0),
            max_epsilon_coef: self.max_epsilon_coef.unwrap_or(0.0),
        };
        if !self.none
            && !self.every_critic
            && self.support_limit.is_none()
            && self.max_epsilon_coef.is_none()
        {
            anyhow::bail!(
                "give --every-critic, --support-limit Z > 0 and/or --max-epsilon-coef C > 0, or \
                 --none to remove the default"
            );
        }
        for file in &self.files {
            let mut policy = bundle::load(file)?;
            let manifest = &mut policy.manifest;
            if self.none {
                manifest.default_guard = None;
            } else {
                manifest.default_guard = Some(guard);
                let needed = if guard.max_epsilon_coef > 0.0 {
                    FORMAT_VERSION_EPSILON_LIMIT
                } else {
                    FORMAT_VERSION_DEFAULT_GUARD
                };
                manifest.format_version = manifest.format_version.max(needed);
            }
            // Checked as a server loading it checks it, before the file is replaced.
            if let Err((field, why)) = policy.manifest.validate() {
                anyhow::bail!("{}: manifest.{field} {why}", file.display());
            }
            bundle::save(&policy, file)?;
            println!(
                "{}: default guard {} (format {})",
                file.display(),
                policy.manifest.default_guard.unwrap_or_default(),
                policy.manifest.format_version
            );
        }
        Ok(())
    }
}
