//! `prac bench-train`: SAC updates per second ([256, 256], batch 256, Hopper's sizes), model
//! updates per second, env steps per second of a real training run, and how long a checkpoint
//! takes to save and load a full replay buffer.

use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::buffer::ReplayBuffer;
use super::model::ModelTrainer;
use super::options::TrainOptions;
use super::run::Trainer;
use super::sac::{Batch, Sac, SacConfig};

pub struct BenchTrain {
    pub(crate) sac_update_ms: f64,
    pub(crate) model_update_ms: f64,
    pub(crate) train_domain: String,
    pub(crate) train_steps: u64,
    pub(crate) train_steps_per_s: f64,
    pub(crate) replay: Option<ReplayTiming>,
}

/// Saving and loading a replay buffer as checkpoints do.
pub(crate) struct ReplayTiming {
    pub(crate) transitions: usize,
    pub(crate) bytes: u64,
    pub(crate) save_ms: f64,
    pub(crate) load_ms: f64,
}

/// Humanoid's observation and action sizes: the largest buffer of our domains.
const REPLAY_DIMS: (usize, usize) = (44, 17);

fn time_replay(dir: &std::path::Path, transitions: usize) -> anyhow::Result<ReplayTiming> {
    let (od, ad) = REPLAY_DIMS;
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let mut buffer = ReplayBuffer::new(od, ad, transitions);
    let (mut obs, mut action, mut next_obs) = (vec![0.0; od], vec![0.0; ad], vec![0.0; od]);
    for _ in 0..transitions {
        for v in obs.iter_mut().chain(&mut action).chain(&mut next_obs) {
            *v = rng.random_range(-1.0..1.0);
        }
        buffer.push(&obs, &action, rng.random_range(-1.0..1.0), &next_obs, false);
    }
    let path = dir.join(super::checkpoint::REPLAY_FILE);
    let start = Instant::now();
    buffer.save(&path)?;
    let save_ms = start.elapsed().as_secs_f64() * 1e3;
    drop(buffer);
    let start = Instant::now();
    let loaded = ReplayBuffer::load(&path, od, ad, transitions)?;
    let load_ms = start.elapsed().as_secs_f64() * 1e3;
    anyhow::ensure!(loaded.len() == transitions, "the buffer came back short");
    Ok(ReplayTiming {
        transitions,
        bytes: std::fs::metadata(&path)?.len(),
        save_ms,
        load_ms,
    })
}

fn random_batch(rng: &mut ChaCha8Rng, n: usize, od: usize, ad: usize) -> Batch {
    let mut normal =
        |k: usize| -> Vec<f32> { (0..k).map(|_| rng.sample(StandardNormal)).collect() };
    Batch {
        len: n,
        obs: normal(n * od),
        actions: normal(n * ad).into_iter().map(f32::tanh).collect(),
        rewards: normal(n),
        next_obs: normal(n * od),
        dones: vec![0.0; n],
    }
}

/// Times updates for `per_case` each, then trains `domain` for `train_steps` steps (learning
/// after `learning_starts` = 1000 steps) and reports its overall env steps/s.
/// Then saves and loads a replay buffer of `replay_transitions` (0: skipped).
pub fn run(
    per_case: Duration,
    domain: &str,
    train_steps: u64,
    replay_transitions: usize,
) -> anyhow::Result<BenchTrain> {
    let (od, ad, n) = (15, 3, 256);
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut sac = Sac::new(SacConfig::default(), od, ad, &mut rng);
    let batch = random_batch(&mut rng, n, od, ad);
    let noise: Vec<f32> = (0..2 * n * ad)
        .map(|_| rng.sample(StandardNormal))
        .collect();
    let time = |f: &mut dyn FnMut()| {
        f(); // warm-up
        let start = Instant::now();
        let mut count = 0u32;
        while start.elapsed() < per_case || count < 3 {
            f();
            count += 1;
        }
        start.elapsed().as_secs_f64() * 1e3 / f64::from(count)
    };
    let sac_update_ms = time(&mut || {
        sac.update(&batch, &noise);
    });
    let mut model = ModelTrainer::new(od, ad, &[64, 64, 64, 64], 1e-4, &mut rng, &sac.device);
    let mut delta = Vec::new();
    for k in 0..n {
        model.stats.push(
            &batch.obs[k * od..(k + 1) * od],
            &batch.actions[k * ad..(k + 1) * ad],
            &batch.next_obs[k * od..(k + 1) * od],
            &mut delta,
        );
    }
    let model_update_ms = time(&mut || {
        model.update(&batch.obs, &batch.actions, &batch.next_obs);
    });

    let dir = tempfile_dir()?;
    let mut options = TrainOptions::new(domain, &dir.join("bench.safetensors"));
    options.steps = train_steps;
    options.sac.learning_starts = 1000;
    options.eval_every = u64::MAX;
    options.value_episodes = 1;
    options.progress = false;
    options.checkpoint_every = Duration::from_secs(3600);
    let start = Instant::now();
    let mut trainer = Trainer::new(options, false)?;
    trainer.run()?;
    let seconds = start.elapsed().as_secs_f64();
    drop(trainer);
    let replay = (replay_transitions > 0)
        .then(|| time_replay(&dir, replay_transitions))
        .transpose();
    let _ = std::fs::remove_dir_all(&dir);
    let replay = replay?;
    Ok(BenchTrain {
        sac_update_ms,
        model_update_ms,
        train_domain: domain.to_string(),
        train_steps,
        train_steps_per_s: train_steps as f64 / seconds,
        replay,
    })
}

fn tempfile_dir() -> anyhow::Result<std::path::PathBuf> {
    let dir = std::env::temp_dir().join(format!("prac-bench-train-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    Ok(dir)
}

pub fn report(b: &BenchTrain) -> String {
    let mut text = format!(
        "SAC update ([256, 256] actor and twin critics, batch 256, Hopper sizes 15/3): {:.2} ms ({:.0} updates/s)\n\
         dynamics model update (4 x 64, batch 256): {:.2} ms ({:.0} updates/s)\n\
         training {} for {} steps (1000 random, then an update and a model step per env step): {:.0} env steps/s\n",
        b.sac_update_ms,
        1e3 / b.sac_update_ms,
        b.model_update_ms,
        1e3 / b.model_update_ms,
        b.train_domain,
        b.train_steps,
        b.train_steps_per_s,
    );
    if let Some(r) = &b.replay {
        let (od, ad) = REPLAY_DIMS;
        text.push_str(&format!(
            "replay buffer in a checkpoint ({} transitions, obs {od} / action {ad}): {:.0} MB, save {:.0} ms, load {:.0} ms\n",
            r.transitions,
            r.bytes as f64 / 1e6,
            r.save_ms,
            r.load_ms,
        ));
    }
    text
}
