//! The policies a server serves: every `NAME.safetensors` of the bundle directory, served as NAME.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use crate::bundle::{self, BundleError};
use crate::policy::Policy;

#[derive(Default)]
pub struct Registry {
    policies: BTreeMap<String, Arc<Policy>>,
}

/// The bundles of a directory that loaded, and the errors of those that did not.
pub struct Loaded {
    pub registry: Registry,
    pub errors: Vec<BundleError>,
}

impl Registry {
    pub fn get(&self, name: &str) -> Option<&Arc<Policy>> {
        self.policies.get(name)
    }
    pub fn iter(&self) -> impl Iterator<Item = (&String, &Arc<Policy>)> {
        self.policies.iter()
    }
    pub fn len(&self) -> usize {
        self.policies.len()
    }
    pub fn is_empty(&self) -> bool {
        self.policies.is_empty()
    }
    pub fn names(&self) -> Vec<&str> {
        self.policies.keys().map(String::as_str).collect()
    }

    /// Loads every `*.safetensors` file of `dir` (not recursive). A bad bundle is reported in
    /// `errors` and skipped; an unreadable directory is an error.
    pub fn load_dir(dir: &Path) -> std::io::Result<Loaded> {
        let mut files: Vec<_> = std::fs::read_dir(dir)?
            .filter_map(Result::ok)
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|e| e == "safetensors") && p.is_file())
            .collect();
        files.sort();
        let mut registry = Registry::default();
        let mut errors = Vec::new();
        for file in files {
            let Some(name) = file.file_stem().and_then(|s| s.to_str()) else {
                continue;
            };
            match bundle::load(&file) {
                Ok(policy) if policy.model.is_none() => errors.push(BundleError {
                    file: file.clone(),
                    field: "manifest.model".into(),
                    reason: "absent: PrAC needs a dynamics model to imagine plans; add one with \
                             prac fit-model"
                        .into(),
                }),
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
        Ok(Loaded { registry, errors })
    }
}
