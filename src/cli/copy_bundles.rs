//! `prac copy-bundles FROM TO`: the init container of deploy/k8s's base (and the writer Job of its
//! shared-volume overlay). It copies the bundles of an image into the server's bundle volume,
//! checked first, so that a bad bundle stops the pod before it starts rather than being skipped
//! by a serving replica.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;

#[derive(Args, Debug)]
pub struct CopyBundlesArgs {
    /// The folder of NAME.safetensors bundles to check and copy.
    from: PathBuf,
    /// Where they go (created if missing).
    to: PathBuf,
}

impl CopyBundlesArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let names = copy(&self.from, &self.to)?;
        println!(
            "copied {} bundles to {}: {}",
            names.len(),
            self.to.display(),
            names.join(", ")
        );
        Ok(())
    }
}

/// Checks every `*.safetensors` file in `from` as the server loads it, then copies them all into
/// `to`, each written under a temporary name and renamed, so that a server reloading `to` never
/// reads half a file. Copies nothing when any is bad or there are none. Returns the names copied.
fn copy(from: &Path, to: &Path) -> anyhow::Result<Vec<String>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(from)
        .with_context(|| format!("cannot read the bundle directory {}", from.display()))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "safetensors"))
        .collect();
    files.sort();
    anyhow::ensure!(
        !files.is_empty(),
        "{} holds no NAME.safetensors bundle",
        from.display()
    );
    let mut bad = Vec::new();
    for file in &files {
        if let Err(e) = prac::serve::servable(file) {
            bad.push(e.to_string());
        }
    }
    anyhow::ensure!(
        bad.is_empty(),
        "copied nothing: {} of {} bundles do not load:\n  {}",
        bad.len(),
        files.len(),
        bad.join("\n  ")
    );
    std::fs::create_dir_all(to).with_context(|| format!("cannot create {}", to.display()))?;
    let mut names = Vec::new();
    for file in &files {
        let name = file
            .file_name()
            .and_then(|n| n.to_str())
            .context("a bundle's file name is not UTF-8")?;
        let partial = to.join(format!(".{name}.partial"));
        std::fs::copy(file, &partial)
            .with_context(|| format!("copying {} to {}", file.display(), partial.display()))?;
        std::fs::rename(&partial, to.join(name))
            .with_context(|| format!("renaming {} into place", partial.display()))?;
        names.push(name.to_string());
    }
    Ok(names)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    fn shipped() -> &'static Path {
        Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/bundles"))
    }

    #[test]
    fn copies_every_shipped_bundle_byte_for_byte() {
        let to = tempfile::tempdir().unwrap();
        let names = super::copy(shipped(), to.path()).unwrap();
        assert!(
            names.contains(&"hopper.safetensors".to_string()),
            "{names:?}"
        );
        for name in &names {
            assert_eq!(
                std::fs::read(shipped().join(name)).unwrap(),
                std::fs::read(to.path().join(name)).unwrap(),
                "{name}"
            );
        }
        let leftovers: Vec<_> = std::fs::read_dir(to.path())
            .unwrap()
            .filter_map(Result::ok)
            .filter(|e| e.file_name().to_string_lossy().starts_with('.'))
            .collect();
        assert!(leftovers.is_empty(), "{leftovers:?}");
    }

    #[test]
    fn one_bad_bundle_copies_nothing_and_names_it() {
        let from = tempfile::tempdir().unwrap();
        std::fs::copy(
            shipped().join("pendulum.safetensors"),
            from.path().join("pendulum.safetensors"),
        )
        .unwrap();
        let hopper = std::fs::read(shipped().join("hopper.safetensors")).unwrap();
        std::fs::write(
            from.path().join("cut.safetensors"),
            &hopper[..hopper.len() / 2],
        )
        .unwrap();
        let to = tempfile::tempdir().unwrap();
        let e = super::copy(from.path(), to.path()).unwrap_err().to_string();
        assert!(
            e.contains("cut.safetensors") && e.contains("copied nothing"),
            "{e}"
        );
        assert_eq!(std::fs::read_dir(to.path()).unwrap().count(), 0);
    }

    #[test]
    fn an_empty_or_missing_source_is_an_error() {
        let from = tempfile::tempdir().unwrap();
        let to = tempfile::tempdir().unwrap();
        let e = super::copy(from.path(), to.path()).unwrap_err().to_string();
        assert!(e.contains("no NAME.safetensors"), "{e}");
        let e = super::copy(&from.path().join("absent"), to.path())
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannot read"), "{e}");
    }
}
