//! `prac export-onnx BUNDLE --out DIR`: the bundle's actor, critics and dynamics model as ONNX
//! files, with `prac.json`, the contract that says what they take and give.

use std::path::PathBuf;

use clap::Args;

#[derive(Args, Debug)]
pub struct ExportOnnxArgs {
    /// The bundle (NAME.safetensors) to export; checked as the server loads it.
    bundle: PathBuf,
    /// The folder to create (it must not exist); nothing is left there unless every file is
    /// written.
    #[arg(long)]
    out: PathBuf,
}

impl ExportOnnxArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let contract = prac::export::export_onnx(&self.bundle, &self.out)?;
        let mut files = vec![contract.actor.path.clone()];
        files.extend(contract.critics.iter().map(|c| c.path.clone()));
        files.extend(contract.model.iter().map(|m| m.path.clone()));
        files.push("prac.json".into());
        println!(
            "exported {} ({}, {}) to {} (ONNX opset {}): {}",
            contract.name,
            contract.domain,
            contract.content_hash,
            self.out.display(),
            contract.opset,
            files.join(", ")
        );
        Ok(())
    }
}
