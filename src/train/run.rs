//! Algorithm 1: SAC with a dynamics model, acting either from the policy (plain SAC) or from the
//! PrAC plan (training-with-PrAC, the same `plan::replan` the server runs), with a training
//! curve, periodic deterministic evaluations, checkpoints and resume.

use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Instant, SystemTime};

use anyhow::{Context, bail};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::Serialize;

use super::buffer::ReplayBuffer;
use super::checkpoint;
use super::model::ModelTrainer;
use super::options::{Progress, TrainOptions};
use super::sac::{Batch, Sac, SacConfig, SacLosses};
use crate::bundle::{
    ActorKind, ActorSpec, CriticSpec, FORMAT_VERSION_ACTOR_KINDS, FORMAT_VERSION_CRITIC_NORMS,
    FORMAT_VERSION_OBS_BOUNDS, Manifest, ModelSpec, ObsBounds, Provenance, QAggregation,
    ValueScale,
};
use crate::domains::{self, Env, EnvSpec, EpisodeTotals};
use crate::eval::{self, ModelError, Trajectory};
use crate::nn::Activation;
use crate::plan::{Growth, Networks, Planner, ReplanConfig};
use crate::policy::{Evaluator, ObsScale, Policy};

/// What a finished run reports.
#[derive(Clone, Debug, Serialize)]
pub struct TrainReport {
    pub(crate) steps: u64,
    pub(crate) episodes: u64,
    pub(crate) seconds: f64,
    pub(crate) value_scale: ValueScale,
    pub(crate) eval_return_mean: f64,
    pub(crate) eval_return_std: f64,
    /// Of the deterministic evaluation's episodes, how many the task ended early (a fall).
    pub(crate) eval_terminated: usize,
    /// Their mean forward distance in metres (walkers).
    pub(crate) eval_distance_mean: Option<f64>,
    pub(crate) random_return_mean: f64,
    pub(crate) model_errors: Vec<ModelError>,
    pub(crate) out: PathBuf,
}

pub(crate) const CSV_HEADER: &str = "step,episode,return,discounted_return,length,forecast,epsilon,critic_loss,actor_loss,model_loss,ent_coef";
/// Per evaluation: its returns, how many of its episodes the task ended early (falls), their
/// mean forward distance (walkers; empty elsewhere) and the run's training seconds so far.
pub(crate) const EVAL_CSV_HEADER: &str = "step,eval_return_mean,eval_return_std,eval_discounted_mean,eval_terminated,eval_distance_mean,seconds";

/// Builds the manifest of a trained bundle.
pub(crate) fn manifest(
    spec: &EnvSpec,
    config: &SacConfig,
    normalization: crate::bundle::Normalization,
    steps: u64,
    seed: u64,
) -> Manifest {
    Manifest {
        // The domain's observation space bounds the model's forecasts (format 4).
        format_version: FORMAT_VERSION_OBS_BOUNDS,
        name: spec.name.to_string(),
        domain: spec.name.to_string(),
        obs_dim: spec.obs_dim,
        act_dim: spec.act_dim,
        action_low: spec.action_low.clone(),
        action_high: spec.action_high.clone(),
        gamma: config.gamma,
        actor: ActorSpec {
            hidden: config.hidden.clone(),
            activation: Activation::Relu,
            kind: ActorKind::Gaussian,
            mean_clip: None,
        },
        critic: CriticSpec {
            n_critics: config.n_critics,
            hidden: config.hidden.clone(),
            activation: Activation::Relu,
            layer_norm: config.critic_layer_norm,
        },
        model: Some(ModelSpec {
            hidden: config.model_hidden.clone(),
            activation: Activation::Relu,
            normalization,
        }),
        q_aggregation: QAggregation::Min,
        value_scale: None,
        obs_normalization: None,
        obs_bounds: Some(ObsBounds::from_limits(&spec.obs_low, &spec.obs_high)),
        default_guard: None,
        features: crate::domains::features(spec.name),
        provenance: Provenance {
            trainer: "prac train (SAC + dynamics model, burn 0.22.1)".to_string(),
            steps,
            seed,
            date: humantime::format_rfc3339_seconds(SystemTime::now()).to_string(),
        },
    }
}

/// The learner's current networks as an inference policy.
pub(crate) fn snapshot(
    sac: &Sac,
    model: &ModelTrainer,
    spec: &EnvSpec,
    steps: u64,
    seed: u64,
) -> Policy {
    let input = spec.obs_dim + spec.act_dim;
    let mut manifest = manifest(spec, &sac.config, model.stats.normalization(), steps, seed);
    if let Some(m) = &mut manifest.model {
        m.hidden = model.hidden();
    }
    if sac.config.norm_obs {
        manifest.format_version = manifest.format_version.max(FORMAT_VERSION_ACTOR_KINDS);
        manifest.obs_normalization = Some(model.stats.obs.obs_normalization());
    }
    if sac.config.critic_layer_norm {
        manifest.format_version = manifest.format_version.max(FORMAT_VERSION_CRITIC_NORMS);
    }
    Policy {
        manifest,
        content_hash: String::new(),
        actor: sac.actor.to_actor(spec.obs_dim),
        critics: sac.critic.to_mlps(input),
        model: Some(model.to_model()),
    }
}

pub struct Trainer {
    pub(crate) options: TrainOptions,
    spec: EnvSpec,
    env: Box<dyn Env>,
    /// Evaluations play here, so the training episode goes on undisturbed.
    eval_env: Box<dyn Env>,
    pub(crate) sac: Sac,
    pub(crate) model: ModelTrainer,
    buffer: ReplayBuffer,
    rng: ChaCha8Rng,
    pub progress: Progress,
    policy: Arc<Policy>,
    /// Training-with-PrAC: the agent acts from its committed plan.
    agent: Option<Planner<ChaCha8Rng>>,
    /// Transitions restored from the checkpoint's replay buffer on resume.
    pub restored_transitions: Option<usize>,
    /// Held while the trainer lives: no second trainer takes this run.
    _run_lock: File,
}

/// A CSV a run appends rows to. Each row opens the file afresh: a run holding it open would,
/// once the file is replaced under it (a `git checkout` or `git stash` of runs/, an editor's
/// save), write every later row into the unlinked old file, where nobody can read them.
pub(crate) struct CsvLog {
    path: PathBuf,
}

impl CsvLog {
    /// Opens `path` for appending, writing `header` first into a new or empty file.
    pub(crate) fn open(path: &Path, header: &str) -> anyhow::Result<CsvLog> {
        widen_csv(path, header)?;
        let log = CsvLog {
            path: path.to_path_buf(),
        };
        if !path.exists() || std::fs::metadata(path)?.len() == 0 {
            log.row(format_args!("{header}"))?;
        }
        Ok(log)
    }

    /// Appends one row, in one write.
    pub(crate) fn row(&self, row: std::fmt::Arguments<'_>) -> anyhow::Result<()> {
        let mut file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.path)
            .with_context(|| format!("opening {}", self.path.display()))?;
        file.write_all(format!("{row}\n").as_bytes())
            .with_context(|| format!("writing {}", self.path.display()))
    }
}

/// A CSV written with fewer of `header`'s columns (an earlier version's) takes the new header,
/// its rows left empty in the new columns, so a resumed run appends full rows to a valid file.
fn widen_csv(path: &Path, header: &str) -> anyhow::Result<()> {
    if !path.exists() {
        return Ok(());
    }
    let text = std::fs::read_to_string(path)?;
    let Some(old) = text.lines().next() else {
        return Ok(());
    };
    if old == header {
        return Ok(());
    }
    let Some(added) = header
        .strip_prefix(old)
        .and_then(|rest| rest.strip_prefix(','))
    else {
        bail!(
            "{} has columns '{old}', not a start of '{header}'",
            path.display()
        );
    };
    let padding = ",".repeat(added.split(',').count());
    let mut widened = format!("{header}\n");
    for line in text.lines().skip(1) {
        widened.push_str(line);
        widened.push_str(&padding);
        widened.push('\n');
    }
    std::fs::write(path, widened)?;
    Ok(())
}

/// Drops CSV rows past `step` (written after the checkpoint a resumed run starts from).
fn truncate_csv(path: &Path, step: u64) -> anyhow::Result<()> {
    if !path.exists() {
        return Ok(());
    }
    let reader = BufReader::new(File::open(path)?);
    let mut kept = String::new();
    for (i, line) in reader.lines().enumerate() {
        let line = line?;
        let row_step = line.split(',').next().and_then(|s| s.parse::<u64>().ok());
        if i == 0 || row_step.is_some_and(|s| s <= step) {
            kept.push_str(&line);
            kept.push('\n');
        }
    }
    std::fs::write(path, kept)?;
    Ok(())
}

impl Trainer {
    /// A fresh run, or the run in `checkpoint_dir` when `resume` is set and a checkpoint exists.
    pub fn new(options: TrainOptions, resume: bool) -> anyhow::Result<Trainer> {
        let (Some(env), Some(eval_env)) = (
            domains::make(&options.domain),
            domains::make(&options.domain),
        ) else {
            bail!(
                "unknown domain '{}'; known: {}",
                options.domain,
                domains::DOMAINS.join(", ")
            );
        };
        Trainer::with_envs(options, resume, env, eval_env)
    }

    /// As [`Trainer::new`] on given environments (e.g. served over dm_env_rpc): `env` for
    /// training, `eval_env` (the same task) for evaluations. `options.domain` names the task in
    /// the bundle and the checkpoint.
    pub fn with_envs(
        options: TrainOptions,
        resume: bool,
        env: Box<dyn Env>,
        eval_env: Box<dyn Env>,
    ) -> anyhow::Result<Trainer> {
        options.validate()?;
        if eval_env.spec() != env.spec() {
            bail!("the evaluation environment differs from the training one");
        }
        // Before anything of the run is read or removed.
        let run_lock = checkpoint::lock(&options.checkpoint_dir)?;
        let spec = env.spec().clone();
        let (od, ad) = (spec.obs_dim, spec.act_dim);
        let mut init_rng = ChaCha8Rng::seed_from_u64(options.seed);
        let mut sac = Sac::new(options.sac.clone(), od, ad, &mut init_rng);
        let mut model = ModelTrainer::new(
            od,
            ad,
            &options.sac.model_hidden,
            options.sac.model_learning_rate,
            &mut init_rng,
            &sac.device,
        );
        let mut progress = Progress {
            step: 0,
            episode: 0,
            gradient_steps: 0,
            fresh_steps: 0,
            v_rand: None,
            recent_returns: Vec::new(),
            recent_forecasts: Vec::new(),
            last_losses: SacLosses::default(),
            last_model_loss: 0.0,
            seconds: 0.0,
        };
        let resumed = resume && checkpoint::exists(&options.checkpoint_dir);
        let mut buffer = None;
        if resumed {
            let saved = checkpoint::load(&options.checkpoint_dir, &mut sac, &mut model)?;
            if saved.options.domain != options.domain {
                bail!(
                    "checkpoint {} is for domain '{}', not '{}'",
                    options.checkpoint_dir.display(),
                    saved.options.domain,
                    options.domain
                );
            }
            progress = saved.progress;
            buffer =
                checkpoint::load_replay(&options.checkpoint_dir, od, ad, options.sac.buffer_size)?;
            // The restored transitions count toward the warm-up: a full buffer learns on at
            // once, a checkpoint taken during warm-up (or after a refill began) finishes it.
            let restored = buffer.as_ref().map_or(0, |b| b.len() as u64);
            progress.fresh_steps = restored.min(warmup_steps(&options.sac));
            truncate_csv(&options.csv, progress.step)?;
            truncate_csv(&options.eval_csv, progress.step)?;
        } else {
            for path in [&options.csv, &options.eval_csv] {
                if path.exists() {
                    std::fs::remove_file(path)?;
                }
            }
        }
        // A resumed run draws from a stream of its own, fixed by the seed and the step.
        let rng = ChaCha8Rng::seed_from_u64(
            options.seed ^ progress.step.wrapping_mul(0x9e37_79b9_7f4a_7c15),
        );
        let policy = Arc::new(snapshot(&sac, &model, &spec, progress.step, options.seed));
        // eps is set from the value scale once learning starts.
        let agent = (options.epsilon_coef > 0.0).then(|| {
            let config = ReplanConfig {
                epsilon: 0.0,
                growth: Growth::default(),
                max_horizon: options.max_horizon,
                sampled: true,
                ..ReplanConfig::default()
            };
            let rng = ChaCha8Rng::seed_from_u64(options.seed.wrapping_add(progress.step) ^ 0x91a7);
            Planner::new(config, od, ad, rng)
        });
        let restored_transitions = buffer.as_ref().map(ReplayBuffer::len);
        Ok(Trainer {
            buffer: buffer.unwrap_or_else(|| ReplayBuffer::new(od, ad, options.sac.buffer_size)),
            restored_transitions,
            eval_env,
            env,
            spec,
            sac,
            model,
            rng,
            progress,
            policy,
            agent,
            options,
            _run_lock: run_lock,
        })
    }

    fn learning(&self) -> bool {
        self.progress.fresh_steps >= warmup_steps(&self.options.sac)
            && self.buffer.len() >= self.options.sac.batch_size
    }

    /// Runs to `options.steps`, then writes the bundle; returns the report.
    pub fn run(&mut self) -> anyhow::Result<TrainReport> {
        let (od, ad) = (self.spec.obs_dim, self.spec.act_dim);
        let gamma = self.options.sac.gamma;
        if self.progress.v_rand.is_none() {
            let episodes = eval::random_episodes(self.env.as_mut(), gamma, 20, self.options.seed)?;
            self.progress.v_rand = Some(eval::Summary::of_episodes(&episodes).discounted_mean);
        }
        let csv = CsvLog::open(&self.options.csv, CSV_HEADER)?;
        let eval_csv = CsvLog::open(&self.options.eval_csv, EVAL_CSV_HEADER)?;
        let bar = super::progress_bar(
            self.options.steps,
            self.progress.step,
            self.options.progress,
        );

        let mut obs = vec![0.0; od];
        let mut next_obs = vec![0.0; od];
        let mut action = vec![0.0; ad];
        let mut scaled = vec![0.0; ad];
        let mut noise = vec![0.0; ad];
        let mut delta = Vec::with_capacity(od);
        let mut batch = Batch::default();
        let mut normalized = Vec::new();
        let mut update_noise = Vec::new();
        let mut evaluator = Evaluator::new(self.policy.clone());

        let started = Instant::now();
        let seconds_before = self.progress.seconds;
        let mut last_checkpoint = Instant::now();
        let mut episode_seed = self.options.seed.wrapping_mul(1_000_003) + self.progress.episode;
        self.env.reset(episode_seed, &mut obs)?;
        let mut totals = EpisodeTotals::new(gamma);
        self.start_episode(&obs, &mut evaluator);

        while self.progress.step < self.options.steps {
            // Act: random before learning starts, then the policy or the PrAC plan.
            let mut f_t = 1u64;
            if self.progress.step < self.options.sac.learning_starts {
                action
                    .iter_mut()
                    .for_each(|a| *a = self.rng.random_range(-1.0..=1.0));
            } else if let Some(agent) = &mut self.agent {
                if let Err(e) = agent.replan(&mut evaluator, &obs, totals.steps) {
                    bail!("replan failed at step {}: {e}", self.progress.step);
                }
                action.copy_from_slice(agent.plan().action(0));
                f_t = agent.forecast(totals.steps);
            } else {
                noise
                    .iter_mut()
                    .for_each(|z| *z = self.rng.sample(StandardNormal));
                evaluator.act(&obs, &noise, &mut action);
            }
            self.policy.unscale_action(&action, &mut scaled);
            let transition = self.env.step(&scaled, &mut next_obs)?;
            self.buffer.push(
                &obs,
                &action,
                transition.reward as f32,
                &next_obs,
                transition.terminated,
            );
            self.model.stats.push(&obs, &action, &next_obs, &mut delta);
            self.progress.step += 1;
            self.progress.fresh_steps += 1;
            std::mem::swap(&mut obs, &mut next_obs);

            // Learn.
            if self.learning()
                && self
                    .progress
                    .step
                    .is_multiple_of(self.options.sac.train_freq)
            {
                // The actor and critics learn on observations normalised as the policy that
                // acts next (refreshed below) will normalise them; the model learns on raw ones.
                let obs_scale = self
                    .sac
                    .config
                    .norm_obs
                    .then(|| ObsScale::new(&self.model.stats.obs.obs_normalization()));
                for _ in 0..self.options.sac.gradient_steps {
                    let n = self.options.sac.batch_size;
                    self.buffer.sample(n, &mut self.rng, &mut batch);
                    if let Some(scale) = &obs_scale {
                        for rows in [&mut batch.obs, &mut batch.next_obs] {
                            normalized.clear();
                            scale.extend_normalized(rows, &mut normalized);
                            std::mem::swap(rows, &mut normalized);
                        }
                    }
                    update_noise.clear();
                    update_noise.extend((0..2 * n * ad).map(|_| {
                        let z: f32 = self.rng.sample(StandardNormal);
                        z
                    }));
                    self.progress.last_losses = self.sac.update(&batch, &update_noise);
                    // Algorithm 1 line 14: a model step per gradient step, on its own sample.
                    self.buffer.sample(n, &mut self.rng, &mut batch);
                    self.progress.last_model_loss =
                        self.model
                            .update(&batch.obs, &batch.actions, &batch.next_obs);
                    self.progress.gradient_steps += 1;
                }
                self.refresh_policy(&mut evaluator);
            }

            if totals.record(&transition, f_t) {
                let forecast = totals.forecast();
                let (ret, disc, t) = (totals.ret, totals.discounted, totals.steps);
                let l = &self.progress.last_losses;
                let epsilon = self.agent.as_ref().map_or(0.0, |a| a.config.epsilon);
                csv.row(format_args!(
                    "{},{},{ret},{disc},{t},{forecast},{epsilon},{},{},{},{}",
                    self.progress.step,
                    self.progress.episode,
                    l.critic,
                    l.actor,
                    self.progress.last_model_loss,
                    l.ent_coef
                ))?;
                push_recent(&mut self.progress.recent_returns, ret);
                push_recent(&mut self.progress.recent_forecasts, forecast);
                self.progress.episode += 1;
                episode_seed = self.options.seed.wrapping_mul(1_000_003) + self.progress.episode;
                self.env.reset(episode_seed, &mut obs)?;
                totals = EpisodeTotals::new(gamma);
                self.start_episode(&obs, &mut evaluator);
                // Checkpoints fall between episodes, so a resumed run starts a fresh one.
                if last_checkpoint.elapsed() >= self.options.checkpoint_every {
                    self.progress.seconds = seconds_before + started.elapsed().as_secs_f64();
                    self.checkpoint()?;
                    last_checkpoint = Instant::now();
                }
            }

            if self.progress.step.is_multiple_of(self.options.eval_every) {
                let episodes = eval::policy_episodes(
                    &self.policy,
                    self.eval_env.as_mut(),
                    self.options.eval_episodes,
                    1 << 40,
                )?;
                let summary = eval::Summary::of_episodes(&episodes);
                let (mean, std) = (summary.return_mean, summary.return_std);
                let (dmean, falls) = (summary.discounted_mean, summary.terminated);
                let distance = summary
                    .distance_mean
                    .map_or_else(String::new, |d| d.to_string());
                let seconds = seconds_before + started.elapsed().as_secs_f64();
                eval_csv.row(format_args!(
                    "{},{mean},{std},{dmean},{falls},{distance},{seconds:.1}",
                    self.progress.step
                ))?;
                bar.println(format!(
                    "step {}: deterministic evaluation return {mean:.1} +- {std:.1}, {falls} of {} ended early",
                    self.progress.step,
                    episodes.len()
                ));
            }

            if self.progress.step.is_multiple_of(100) {
                bar.set_position(self.progress.step);
                bar.set_message(self.status_line());
            }
        }
        bar.finish_and_clear();
        self.progress.seconds = seconds_before + started.elapsed().as_secs_f64();
        self.checkpoint()?;
        self.finish()
    }

    /// Episode start: refresh eps from the value scale (training-with-PrAC).
    fn start_episode(&mut self, obs: &[f32], evaluator: &mut Evaluator) {
        let coef = self.options.epsilon_coef;
        let v_rand_measured = self.progress.v_rand;
        let fixed = self.options.value_scale;
        let Some(agent) = &mut self.agent else {
            return;
        };
        let range = match fixed {
            Some((v_pi, v_rand)) => v_pi - v_rand,
            None => {
                let mut pi = vec![0.0; self.spec.act_dim];
                let zeros = vec![0.0; self.spec.act_dim];
                evaluator.act(obs, &zeros, &mut pi);
                let (mut q, mut q2) = ([0.0], [0.0]);
                evaluator.q_pair(obs, &pi, &pi, &mut q, &mut q2, None);
                f64::from(q[0]) - v_rand_measured.unwrap_or(0.0)
            }
        };
        agent.config.epsilon = (coef * range.max(0.0)) as f32;
        agent.clear();
    }

    fn refresh_policy(&mut self, evaluator: &mut Evaluator) {
        self.policy = Arc::new(snapshot(
            &self.sac,
            &self.model,
            &self.spec,
            self.progress.step,
            self.options.seed,
        ));
        *evaluator = Evaluator::new(self.policy.clone());
    }

    fn status_line(&self) -> String {
        let recent = |v: &[f64]| eval::mean_std(v).0;
        format!(
            "return {:.1} | forecast {:.2} | alpha {:.3} | critic {:.3} | model {:.4}",
            recent(&self.progress.recent_returns),
            recent(&self.progress.recent_forecasts),
            self.progress.last_losses.ent_coef,
            self.progress.last_losses.critic,
            self.progress.last_model_loss,
        )
    }

    pub(crate) fn checkpoint(&self) -> anyhow::Result<()> {
        checkpoint::save(
            &self.options.checkpoint_dir,
            &checkpoint::Saved {
                options: self.options.clone(),
                progress: self.progress.clone(),
            },
            &self.sac,
            &self.model,
            self.options.checkpoint_replay.then_some(&self.buffer),
        )
    }

    /// Measures the value scale and the model's error, and writes the bundle.
    fn finish(&mut self) -> anyhow::Result<TrainReport> {
        let mut policy = snapshot(
            &self.sac,
            &self.model,
            &self.spec,
            self.progress.step,
            self.options.seed,
        );
        let arc = Arc::new(policy.clone());
        let eval_seed = 1 << 41;
        let episodes = eval::policy_episodes(
            &arc,
            self.env.as_mut(),
            self.options.value_episodes,
            eval_seed,
        )?;
        let randoms = eval::random_episodes(
            self.env.as_mut(),
            self.options.sac.gamma,
            self.options.value_episodes,
            eval_seed,
        )?;
        let played = eval::Summary::of_episodes(&episodes);
        let random = eval::Summary::of_episodes(&randoms);
        let value_scale = ValueScale {
            v_pi: played.discounted_mean,
            v_rand: random.discounted_mean,
        };
        let trajectories: Vec<Trajectory> = episodes
            .iter()
            .map(|e| Trajectory {
                observations: &e.observations,
                actions: &e.actions,
                exploratory: &[],
            })
            .collect();
        let model_errors = eval::model_errors(&arc, &trajectories, &[1, 5, 10]);
        policy.manifest.value_scale = Some(value_scale);
        if let Some(dir) = self.options.out.parent() {
            std::fs::create_dir_all(dir)?;
        }
        crate::bundle::save(&policy, &self.options.out)
            .with_context(|| format!("writing {}", self.options.out.display()))?;
        Ok(TrainReport {
            steps: self.progress.step,
            episodes: self.progress.episode,
            seconds: self.progress.seconds,
            value_scale,
            eval_return_mean: played.return_mean,
            eval_return_std: played.return_std,
            eval_terminated: played.terminated,
            eval_distance_mean: played.distance_mean,
            random_return_mean: random.return_mean,
            model_errors,
            out: self.options.out.clone(),
        })
    }
}

/// Steps a run (or a resumed run without its buffer) collects before it learns.
fn warmup_steps(config: &SacConfig) -> u64 {
    config.learning_starts.max(config.batch_size as u64)
}

fn push_recent(values: &mut Vec<f64>, value: f64) {
    const WINDOW: usize = 20;
    values.push(value);
    if values.len() > WINDOW {
        values.remove(0);
    }
}
