//! The policies a server serves: every `NAME.safetensors` of the bundle directory, served as NAME.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use crate::bundle::{self, BundleError};
use crate::policy::Policy;

#[derive(Default, Clone)]
pub(super) struct Registry {
    policies: BTreeMap<String, Arc<Policy>>,
    /// Bundles of the directory that are not served, by the name they would have, with why
    /// (field and reason, not the server's path): a client asking for one is told.
    skipped: BTreeMap<String, String>,
}

/// The bundles of a directory that loaded, and the errors of those that did not.
pub(super) struct Loaded {
    pub(crate) registry: Registry,
    pub(crate) errors: Vec<BundleError>,
}

/// Loads a bundle the way the server serves it: fully validated, with a dynamics model.
pub fn servable(file: &Path) -> Result<Policy, BundleError> {
    let policy = bundle::load(file)?;
    if policy.model.is_none() {
        return Err(BundleError {
            file: file.to_path_buf(),
            field: "manifest.model".into(),
            reason: "absent: PrAC needs a dynamics model to imagine plans; add one with prac \
                     fit-model"
                .into(),
        });
    }
    Ok(policy)
}

impl Registry {
    pub(super) fn get(&self, name: &str) -> Option<&Arc<Policy>> {
        self.policies.get(name)
    }
    pub(super) fn iter(&self) -> impl Iterator<Item = (&String, &Arc<Policy>)> {
        self.policies.iter()
    }
    pub(super) fn len(&self) -> usize {
        self.policies.len()
    }
    pub(super) fn is_empty(&self) -> bool {
        self.policies.is_empty()
    }
    /// The largest valid requests any served policy allows with plans of at most `max_horizon`.
    pub(super) fn largest_requests(&self, max_horizon: usize) -> super::intake::RequestSizes {
        use super::intake::{largest_request_bytes, largest_step_bytes};
        let mut sizes = super::intake::RequestSizes::default();
        for p in self.policies.values() {
            let open = largest_request_bytes(max_horizon, p.obs_dim(), p.act_dim());
            sizes.open_session = sizes.open_session.max(open);
            sizes.other = sizes.other.max(largest_step_bytes(p.obs_dim()));
        }
        sizes
    }

    pub(super) fn names(&self) -> Vec<&str> {
        self.policies.keys().map(String::as_str).collect()
    }

    /// What a client asking for an unserved `name` is told: why its bundle was skipped, or the
    /// policies served and the bundles skipped (at most `LISTED` of each, names cut to 64 chars).
    pub(super) fn not_served(&self, name: &str) -> String {
        const LISTED: usize = 16;
        let shown = |name: &str| name.chars().take(64).collect::<String>();
        if let Some(reason) = self.skipped.get(name) {
            return format!(
                "policy '{}' is not served: its bundle was skipped ({reason}); the server's log \
                 names the file",
                shown(name)
            );
        }
        let list = |names: Vec<&str>| {
            let more = names.len().saturating_sub(LISTED);
            let mut text = names
                .into_iter()
                .take(LISTED)
                .map(shown)
                .collect::<Vec<_>>()
                .join(", ");
            if more > 0 {
                text.push_str(&format!(" and {more} more"));
            }
            text
        };
        let mut message = format!(
            "unknown policy '{}'; this server has: {}",
            shown(name),
            if self.policies.is_empty() {
                "no policies".to_string()
            } else {
                list(self.names())
            }
        );
        if !self.skipped.is_empty() {
            message.push_str(&format!(
                "; bundles skipped (the server's log says why): {}",
                list(self.skipped.keys().map(String::as_str).collect())
            ));
        }
        message
    }

    fn skip(&mut self, error: &BundleError) {
        if let Some(name) = error.file.file_stem().and_then(|s| s.to_str()) {
            self.skipped.insert(
                name.to_string(),
                format!("{}: {}", error.field, error.reason),
            );
        }
    }

    /// Loads every `*.safetensors` entry of `dir` (not recursive). A bad bundle is reported in
    /// `errors` and skipped, and so is an entry that is not a regular file (a directory, FIFO,
    /// device or dangling link); an unreadable directory is an error.
    pub(super) fn load_dir(dir: &Path) -> std::io::Result<Loaded> {
        let mut files: Vec<_> = std::fs::read_dir(dir)?
            .filter_map(Result::ok)
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|e| e == "safetensors"))
            .collect();
        files.sort();
        let mut registry = Registry::default();
        let mut errors = Vec::new();
        for file in files {
            let Some(name) = file.file_stem().and_then(|s| s.to_str()) else {
                errors.push(BundleError {
                    file: file.clone(),
                    field: "file".into(),
                    reason: "its name is not UTF-8, so it cannot name a policy".into(),
                });
                continue;
            };
            match servable(&file) {
                Ok(policy) => {
                    if policy.manifest.name != name {
                        tracing::warn!(
                            file = %file.display(),
                            manifest_name = %policy.manifest.name,
                            "serving the bundle under its file name"
                        );
                    }
                    tracing::info!(
                        policy = name,
                        domain = %policy.manifest.domain,
                        obs_dim = policy.obs_dim(),
                        act_dim = policy.act_dim(),
                        hash = %policy.content_hash,
                        "loaded bundle"
                    );
                    registry.policies.insert(name.to_string(), Arc::new(policy));
                }
                Err(e) => errors.push(e),
            }
        }
        for error in &errors {
            registry.skip(error);
        }
        Ok(Loaded { registry, errors })
    }

    /// The registry after re-reading `dir` (hot reload): a file whose bytes are unchanged keeps
    /// its loaded policy (same `Arc`), a changed or new file that loads replaces or adds its
    /// policy, a file that no longer loads keeps the old version, and a removed file leaves the
    /// registry. Open sessions hold their own `Arc` and are not affected.
    pub(super) fn reload(&self, dir: &Path) -> std::io::Result<(Registry, ReloadReport)> {
        let Loaded {
            registry: fresh,
            errors,
        } = Registry::load_dir(dir)?;
        let mut next = Registry::default();
        let mut report = ReloadReport::default();
        for (name, policy) in fresh.policies {
            match self.policies.get(&name) {
                Some(old) if old.content_hash == policy.content_hash => {
                    report.unchanged.push(name.clone());
                    next.policies.insert(name, old.clone());
                }
                Some(_) => {
                    report.replaced.push(name.clone());
                    next.policies.insert(name, policy);
                }
                None => {
                    report.added.push(name.clone());
                    next.policies.insert(name, policy);
                }
            }
        }
        for error in errors {
            let name = error
                .file
                .file_stem()
                .and_then(|s| s.to_str())
                .unwrap_or_default()
                .to_string();
            if let Some(old) = self.policies.get(&name) {
                report.kept_old.push(name.clone());
                next.policies.insert(name, old.clone());
            } else {
                next.skip(&error);
            }
            report.errors.push(error);
        }
        for name in self.policies.keys() {
            if !next.policies.contains_key(name) {
                report.removed.push(name.clone());
            }
        }
        Ok((next, report))
    }
}

/// What a reload changed, by policy name.
#[derive(Debug, Default)]
pub(super) struct ReloadReport {
    pub(crate) added: Vec<String>,
    pub(crate) replaced: Vec<String>,
    pub(crate) unchanged: Vec<String>,
    pub(crate) removed: Vec<String>,
    /// Policies whose new file is broken: the old version stays.
    pub(crate) kept_old: Vec<String>,
    pub(crate) errors: Vec<BundleError>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_that_are_not_regular_files_are_errors_not_silent_skips() {
        use std::os::unix::fs::symlink;
        let dir = tempfile::tempdir().unwrap();
        symlink("/dev/zero", dir.path().join("zero.safetensors")).unwrap();
        symlink(
            dir.path().join("absent"),
            dir.path().join("dangling.safetensors"),
        )
        .unwrap();
        std::fs::create_dir(dir.path().join("folder.safetensors")).unwrap();
        let fifo = dir.path().join("fifo.safetensors");
        let made = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(made.success());
        std::fs::write(dir.path().join("notes.txt"), "not a bundle").unwrap();

        let loaded = Registry::load_dir(dir.path()).unwrap();
        assert!(loaded.registry.is_empty());
        let mut named: Vec<String> = loaded
            .errors
            .iter()
            .map(|e| {
                let name = e.file.file_name().unwrap().to_string_lossy().into_owned();
                format!("{name}: {}", e.reason)
            })
            .collect();
        named.sort();
        assert_eq!(named.len(), 4, "{named:?}");
        assert!(
            named[0].starts_with("dangling.safetensors: cannot read"),
            "{named:?}"
        );
        assert!(
            named[1].contains("not a regular file (a FIFO)"),
            "{named:?}"
        );
        assert!(
            named[2].contains("not a regular file (a directory)"),
            "{named:?}"
        );
        assert!(
            named[3].contains("not a regular file (a character device)"),
            "{named:?}"
        );
    }

    #[test]
    fn a_client_asking_for_a_skipped_bundle_is_told_why() {
        use crate::testing::toy_policy;
        let dir = tempfile::tempdir().unwrap();
        let save = |policy: &Policy, name: &str| {
            let bytes = bundle::to_bytes(policy).unwrap();
            std::fs::write(dir.path().join(format!("{name}.safetensors")), bytes).unwrap();
        };
        let mut no_model = toy_policy("sb3pend", 1);
        no_model.manifest.model = None;
        no_model.model = None;
        save(&no_model, "sb3pend");

        let only_skipped = Registry::load_dir(dir.path()).unwrap().registry;
        assert!(only_skipped.is_empty());
        let told = only_skipped.not_served("sb3pend");
        assert!(told.contains("'sb3pend' is not served"), "{told}");
        assert!(told.contains("manifest.model: absent"), "{told}");
        assert!(told.contains("prac fit-model"), "{told}");
        assert!(!told.contains(dir.path().to_str().unwrap()), "{told}");
        let told = only_skipped.not_served("other");
        assert!(
            told.contains("this server has: no policies; bundles skipped"),
            "{told}"
        );
        assert!(told.ends_with(": sb3pend"), "{told}");

        // Served once fixed; skipped again when a reload finds it broken and it was never served.
        save(&toy_policy("sb3pend", 1), "sb3pend");
        let (fixed, _) = only_skipped.reload(dir.path()).unwrap();
        assert!(fixed.get("sb3pend").is_some());
        assert!(!fixed.not_served("other").contains("skipped"));
        std::fs::write(dir.path().join("late.safetensors"), b"truncated").unwrap();
        let (with_late, report) = fixed.reload(dir.path()).unwrap();
        assert_eq!(report.errors.len(), 1);
        let told = with_late.not_served("late");
        assert!(told.contains("'late' is not served"), "{told}");
        assert!(with_late.not_served("nope").contains(
            "this server has: sb3pend; bundles skipped (the server's log says why): late"
        ));
    }
}
