//! Checkpoints: the networks, target critics, temperature and model with their Adam states
//! (burnpack files), the options, counters and model statistics (state.json), and the replay
//! buffer (replay.safetensors) unless the run leaves it out. A run resumed without a saved buffer
//! refills it with its current policy before learning again (see docs/training.md).
//!
//! A checkpoint is written to `DIR.tmp` and renamed into place, so a run killed while saving
//! still has its previous checkpoint. One trainer at a time holds `DIR.lock`: two on one run would
//! share `DIR.tmp` and append each other's rows to its CSVs.

use std::path::{Path, PathBuf};

use anyhow::Context;
use burn::module::Module;
use serde::{Deserialize, Serialize};

use super::buffer::ReplayBuffer;
use super::model::{ModelStats, ModelTrainer};
use super::options::{Progress, TrainOptions};
use super::sac::Sac;

pub(crate) const STATE_FILE: &str = "state.json";
pub(crate) const REPLAY_FILE: &str = "replay.safetensors";

#[derive(Clone, Debug, Serialize, Deserialize)]
pub(crate) struct Saved {
    pub(crate) options: TrainOptions,
    pub(crate) progress: Progress,
}

#[derive(Serialize, Deserialize)]
struct StateFile {
    options: TrainOptions,
    progress: Progress,
    /// Observation and action sizes (absent in checkpoints written before they were recorded).
    #[serde(default)]
    dims: Option<(usize, usize)>,
    model_stats: ModelStats,
}

fn sibling(dir: &Path, suffix: &str) -> PathBuf {
    PathBuf::from(format!("{}{suffix}", dir.display()))
}

/// Holds the run at `dir` for this trainer, or says that another one holds it. The lock is the
/// operating system's, so a trainer that dies, however it ends, lets go of it.
pub(crate) fn lock(dir: &Path) -> anyhow::Result<std::fs::File> {
    let path = sibling(dir, ".lock");
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .with_context(|| format!("opening {}", path.display()))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => anyhow::bail!(
            "another trainer is running this run (it holds {}); one run takes one trainer, \
             or their rows and checkpoints would mix",
            path.display()
        ),
        Err(std::fs::TryLockError::Error(e)) => {
            Err(e).with_context(|| format!("locking {}", path.display()))
        }
    }
}

/// Writes one saved part to a path.
type PartWriter<'a> = Box<dyn FnOnce(&Path) -> Result<(), String> + 'a>;

/// The directory holding the newest complete checkpoint, if any.
fn complete(dir: &Path) -> Option<PathBuf> {
    [dir.to_path_buf(), sibling(dir, ".old")]
        .into_iter()
        .find(|d| d.join(STATE_FILE).is_file())
}

pub(crate) fn exists(dir: &Path) -> bool {
    complete(dir).is_some()
}

fn record_error(path: &Path, e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("{}: {e}", path.display())
}

pub(crate) fn save(
    dir: &Path,
    saved: &Saved,
    sac: &Sac,
    model: &ModelTrainer,
    replay: Option<&ReplayBuffer>,
) -> anyhow::Result<()> {
    let tmp = sibling(dir, ".tmp");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp)?;
    }
    std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    let file = |name: &str| tmp.join(name);
    let modules: [(&str, PartWriter); 5] = [
        (
            "actor.bpk",
            Box::new(|p| sac.actor.clone().save_file(p).map_err(|e| e.to_string())),
        ),
        (
            "critic.bpk",
            Box::new(|p| sac.critic.clone().save_file(p).map_err(|e| e.to_string())),
        ),
        (
            "critic_target.bpk",
            Box::new(|p| {
                sac.critic_target
                    .clone()
                    .save_file(p)
                    .map_err(|e| e.to_string())
            }),
        ),
        (
            "ent_coef.bpk",
            Box::new(|p| sac.ent_coef.clone().save_file(p).map_err(|e| e.to_string())),
        ),
        (
            "model.bpk",
            Box::new(|p| model.net.clone().save_file(p).map_err(|e| e.to_string())),
        ),
    ];
    for (name, write) in modules {
        let path = file(name);
        write(&path).map_err(|e| record_error(&path, e))?;
    }
    for (name, optim) in [
        ("actor_optim.bpk", &sac.actor_optim),
        ("critic_optim.bpk", &sac.critic_optim),
        ("ent_coef_optim.bpk", &sac.ent_coef_optim),
        ("model_optim.bpk", &model.optim),
    ] {
        let path = file(name);
        optim.save(&path).map_err(|e| record_error(&path, e))?;
    }
    let state = StateFile {
        options: saved.options.clone(),
        progress: saved.progress.clone(),
        dims: Some((sac.obs_dim, sac.act_dim)),
        model_stats: model.stats.clone(),
    };
    if let Some(buffer) = replay {
        buffer.save(&file(REPLAY_FILE))?;
    }
    std::fs::write(file(STATE_FILE), serde_json::to_vec_pretty(&state)?)?;
    // Swap in: the old checkpoint stays complete until the new one has its final name.
    let old = sibling(dir, ".old");
    if old.exists() {
        std::fs::remove_dir_all(&old)?;
    }
    if dir.exists() {
        std::fs::rename(dir, &old)?;
    }
    std::fs::rename(&tmp, dir)?;
    if old.exists() {
        std::fs::remove_dir_all(&old)?;
    }
    Ok(())
}

/// Restores the learner and model in place; returns the saved options and counters.
pub(crate) fn load(dir: &Path, sac: &mut Sac, model: &mut ModelTrainer) -> anyhow::Result<Saved> {
    let dir = complete(dir).with_context(|| format!("no checkpoint in {}", dir.display()))?;
    let state_path = dir.join(STATE_FILE);
    let state: StateFile = serde_json::from_slice(&std::fs::read(&state_path)?)
        .with_context(|| format!("reading {}", state_path.display()))?;
    if let Some((obs, act)) = state.dims
        && (obs, act) != (sac.obs_dim, sac.act_dim)
    {
        let (want_obs, want_act) = (sac.obs_dim, sac.act_dim);
        anyhow::bail!(
            "checkpoint {} was trained on {obs} observation and {act} action values; this \
             environment has {want_obs} and {want_act}",
            dir.display()
        );
    }
    // Flags that shape the networks or what they see: a run resumes the way it started.
    let (saved, now) = (&state.options.sac, &sac.config);
    for (flag, was_on, is_on) in [
        ("--norm-obs", saved.norm_obs, now.norm_obs),
        (
            "--critic-layer-norm",
            saved.critic_layer_norm,
            now.critic_layer_norm,
        ),
    ] {
        if was_on != is_on {
            let was = if was_on { "with" } else { "without" };
            anyhow::bail!(
                "checkpoint {} was trained {was} {flag}; resume it the same way",
                dir.display()
            );
        }
    }
    let file = |name: &str| dir.join(name);
    let p = file("actor.bpk");
    sac.actor = sac
        .actor
        .clone()
        .try_load_file(&p)
        .map_err(|e| record_error(&p, e))?;
    let p = file("critic.bpk");
    sac.critic = sac
        .critic
        .clone()
        .try_load_file(&p)
        .map_err(|e| record_error(&p, e))?;
    let p = file("critic_target.bpk");
    sac.critic_target = sac
        .critic_target
        .clone()
        .try_load_file(&p)
        .map_err(|e| record_error(&p, e))?;
    let p = file("ent_coef.bpk");
    sac.ent_coef = sac
        .ent_coef
        .clone()
        .try_load_file(&p)
        .map_err(|e| record_error(&p, e))?;
    let p = file("model.bpk");
    model.net = model
        .net
        .clone()
        .try_load_file(&p)
        .map_err(|e| record_error(&p, e))?;
    for (name, optim) in [
        ("actor_optim.bpk", &mut sac.actor_optim),
        ("critic_optim.bpk", &mut sac.critic_optim),
        ("ent_coef_optim.bpk", &mut sac.ent_coef_optim),
        ("model_optim.bpk", &mut model.optim),
    ] {
        let p = file(name);
        *optim = optim.clone().load(&p).map_err(|e| record_error(&p, e))?;
    }
    model.stats = state.model_stats;
    Ok(Saved {
        options: state.options,
        progress: state.progress,
    })
}

/// The replay buffer saved with the newest complete checkpoint, if it has one.
pub(crate) fn load_replay(
    dir: &Path,
    obs_dim: usize,
    act_dim: usize,
    capacity: usize,
) -> anyhow::Result<Option<ReplayBuffer>> {
    let Some(path) = complete(dir).map(|d| d.join(REPLAY_FILE)) else {
        return Ok(None);
    };
    if !path.is_file() {
        return Ok(None);
    }
    ReplayBuffer::load(&path, obs_dim, act_dim, capacity).map(Some)
}
