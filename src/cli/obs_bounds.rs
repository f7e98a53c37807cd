//! `prac obs-bounds FILE...`: writes each bundle's domain observation space into it.

use std::path::PathBuf;

use clap::Args;

use prac::bundle;

#[derive(Args, Debug)]
pub struct ObsBoundsArgs {
    /// Bundles of prac's domains; each is rewritten in place (atomically).
    #[arg(required = true)]
    files: Vec<PathBuf>,
}

impl ObsBoundsArgs {
    pub fn run(self) -> anyhow::Result<()> {
        for file in &self.files {
            let mut policy = bundle::load(file)?;
            if !bundle::add_domain_obs_bounds(&mut policy) {
                anyhow::bail!(
                    "{}: its domain {:?} is not one of prac's with {} observations",
                    file.display(),
                    policy.manifest.domain,
                    policy.manifest.obs_dim
                );
            }
            bundle::save(&policy, file)?;
            println!(
                "{}: obs_bounds of {} (format {})",
                file.display(),
                policy.manifest.domain,
                policy.manifest.format_version
            );
        }
        Ok(())
    }
}
