use std::sync::Arc;

use burn::tensor::Tensor;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::model::ModelTrainer;
use super::nets::{matrix, rows};
use super::options::TrainOptions;
use super::run::{CsvLog, Trainer, snapshot};
use super::sac::{Batch, Sac, SacConfig};
use crate::domains;
use crate::plan::Networks;
use crate::policy::Evaluator;

fn small_config() -> SacConfig {
    SacConfig {
        hidden: vec![32, 32],
        ..SacConfig::default()
    }
}

/// Pendulum training options for a quick run into `out`: no evaluations along the way, one
/// episode for the final one and for V_pi and V_rand, no progress bar.
fn quick_options(out: &std::path::Path) -> TrainOptions {
    let mut options = TrainOptions::new("pendulum", out);
    options.eval_every = 1_000_000;
    options.eval_episodes = 1;
    options.value_episodes = 1;
    options.progress = false;
    options
}

fn normals(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.sample(StandardNormal)).collect()
}

fn batch(rng: &mut ChaCha8Rng, n: usize, od: usize, ad: usize) -> Batch {
    Batch {
        len: n,
        obs: normals(rng, n * od),
        actions: normals(rng, n * ad).into_iter().map(f32::tanh).collect(),
        rewards: normals(rng, n),
        next_obs: normals(rng, n * od),
        dones: (0..n).map(|k| if k % 3 == 0 { 1.0 } else { 0.0 }).collect(),
    }
}

fn forward_dense(d: &crate::nn::Dense, x: &[f32]) -> Vec<f32> {
    let mut out = vec![0.0; d.output_dim()];
    d.forward_rows(x, &mut out);
    out
}

#[test]
fn squashed_gaussian_log_prob_matches_the_closed_form() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let (od, ad, n) = (4, 3, 5);
    let sac = Sac::new(small_config(), od, ad, &mut rng);
    let obs = normals(&mut rng, n * od);
    let noise = normals(&mut rng, n * ad);
    let dev = &sac.device;
    let (action, log_prob) = sac
        .actor
        .sample(matrix(&obs, n, od, dev), matrix(&noise, n, ad, dev));
    let (action, log_prob) = (rows(action), rows(log_prob));
    let actor = sac.actor.to_actor(od);
    let mut scratch = actor.trunk.scratch_for(1);
    for k in 0..n {
        let latent = actor
            .trunk
            .forward_rows(&obs[k * od..(k + 1) * od], &mut scratch)
            .to_vec();
        let mu = forward_dense(&actor.mu, &latent);
        let log_std = forward_dense(actor.log_std.as_ref().unwrap(), &latent);
        let mut expected = 0.0f64;
        for i in 0..ad {
            let ls = f64::from(log_std[i].clamp(-20.0, 2.0));
            let z = f64::from(noise[k * ad + i]);
            let u = f64::from(mu[i]) + ls.exp() * z;
            let a = u.tanh();
            assert!((a - f64::from(action[k * ad + i])).abs() < 1e-5);
            let normal = -0.5 * z * z - ls - 0.5 * (2.0 * std::f64::consts::PI).ln();
            expected += normal - (1.0 - a * a + 1e-6).ln();
        }
        let got = f64::from(log_prob[k]);
        assert!(
            (got - expected).abs() < 1e-3 * expected.abs().max(1.0),
            "{got} vs {expected}"
        );
    }
}

#[test]
fn td_targets_mask_terminal_transitions() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let (od, ad, n) = (3, 2, 6);
    let sac = Sac::new(small_config(), od, ad, &mut rng);
    let b = batch(&mut rng, n, od, ad);
    let noise = normals(&mut rng, n * ad);
    let dev = &sac.device;
    let alpha = 0.3;
    let targets = rows(sac.td_targets(
        &matrix(&b.rewards, n, 1, dev),
        &matrix(&b.dones, n, 1, dev),
        &matrix(&b.next_obs, n, od, dev),
        matrix(&noise, n, ad, dev),
        alpha,
    ));
    // The closed form with the inference networks: a' = tanh(mu + std z), its log-prob, and the
    // minimum of the target critics.
    let (next_action, next_log_prob) = sac
        .actor
        .sample(matrix(&b.next_obs, n, od, dev), matrix(&noise, n, ad, dev));
    let (next_action, next_log_prob) = (rows(next_action), rows(next_log_prob));
    let critics = sac.critic_target.to_mlps(od + ad);
    for k in 0..n {
        let mut input = b.next_obs[k * od..(k + 1) * od].to_vec();
        input.extend_from_slice(&next_action[k * ad..(k + 1) * ad]);
        let min_q = critics
            .iter()
            .map(|c| c.forward_rows(&input, &mut c.scratch_for(1))[0])
            .fold(f32::INFINITY, f32::min);
        let expected = if b.dones[k] == 1.0 {
            b.rewards[k]
        } else {
            b.rewards[k] + 0.98 * (min_q - alpha * next_log_prob[k])
        };
        assert!(
            (targets[k] - expected).abs() < 1e-4,
            "row {k}: {} vs {expected}",
            targets[k]
        );
    }
}

#[test]
fn polyak_update_averages_towards_the_online_critic() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut sac = Sac::new(small_config(), 3, 2, &mut rng);
    let b = batch(&mut rng, 16, 3, 2);
    let noise = normals(&mut rng, 2 * 16 * 2);
    let before = sac.critic_target.to_mlps(5);
    sac.update(&b, &noise); // moves the online critics, then the targets by tau
    let online = sac.critic.to_mlps(5);
    let after = sac.critic_target.to_mlps(5);
    let tau = 0.005f32;
    for c in 0..2 {
        for (l, layer) in after[c].layers().iter().enumerate() {
            let (t0, on) = (&before[c].layers()[l], &online[c].layers()[l]);
            for i in 0..layer.weight().len() {
                let expected =
                    (1.0 - tau) * t0.weight().as_slice()[i] + tau * on.weight().as_slice()[i];
                assert!((layer.weight().as_slice()[i] - expected).abs() < 1e-6);
            }
        }
    }
    // The online critics did move, so the test is not comparing equal tensors.
    assert_ne!(
        online[0].layers()[0].weight(),
        before[0].layers()[0].weight()
    );
}

#[test]
fn losses_fall_on_a_fixed_batch() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let (od, ad, n) = (3, 1, 64);
    // gamma 0: the critics regress on the rewards alone, a fixed target.
    let config = SacConfig {
        gamma: 0.0,
        learning_rate: 1e-3,
        ..small_config()
    };
    let mut sac = Sac::new(config, od, ad, &mut rng);
    let mut b = batch(&mut rng, n, od, ad);
    // A reward the critics can represent.
    b.rewards = (0..n)
        .map(|k| 0.5 * b.obs[k * od..(k + 1) * od].iter().sum::<f32>() + b.actions[k])
        .collect();
    let noise = normals(&mut rng, 2 * n * ad);
    let first = sac.update(&b, &noise);
    let mut last = first;
    for _ in 0..200 {
        last = sac.update(&b, &noise);
    }
    assert!(
        last.critic < 0.3 * first.critic,
        "critic loss {} -> {}",
        first.critic,
        last.critic
    );
    assert!(
        last.actor < first.actor,
        "actor loss {} -> {}",
        first.actor,
        last.actor
    );

    let mut model = ModelTrainer::new(od, ad, &[16, 16], 1e-3, &mut rng, &sac.device);
    // A learnable map: next = obs + 0.1 * action (broadcast).
    let next: Vec<f32> = (0..n)
        .flat_map(|k| (0..od).map(move |i| (k, i)))
        .map(|(k, i)| b.obs[k * od + i] + 0.1 * b.actions[k])
        .collect();
    let mut delta = Vec::new();
    for k in 0..n {
        model.stats.push(
            &b.obs[k * od..(k + 1) * od],
            &b.actions[k..k + 1],
            &next[k * od..(k + 1) * od],
            &mut delta,
        );
    }
    let first = model.update(&b.obs, &b.actions, &next);
    let mut last = first;
    for _ in 0..300 {
        last = model.update(&b.obs, &b.actions, &next);
    }
    assert!(last < 0.2 * first, "model loss {first} -> {last}");
}

#[test]
fn a_checkpoint_restores_the_exact_learner() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (od, ad, n) = (3, 2, 32);
    let config = small_config();
    let mut sac = Sac::new(config.clone(), od, ad, &mut rng);
    let mut model = ModelTrainer::new(od, ad, &[8], 1e-3, &mut rng, &sac.device);
    let b = batch(&mut rng, n, od, ad);
    let noise = normals(&mut rng, 2 * n * ad);
    let mut delta = Vec::new();
    model.stats.push(
        &b.obs[..od],
        &b.actions[..ad],
        &b.next_obs[..od],
        &mut delta,
    );
    for _ in 0..3 {
        sac.update(&b, &noise);
        model.update(&b.obs, &b.actions, &b.next_obs);
    }
    let options = TrainOptions::new("pendulum", &dir.path().join("p.safetensors"));
    let saved = super::checkpoint::Saved {
        options: options.clone(),
        progress: Trainer::new(options.clone(), false).unwrap().progress,
    };
    let ckpt = dir.path().join("ckpt");
    let mut buffer = super::buffer::ReplayBuffer::new(od, ad, 100);
    for k in 0..n {
        buffer.push(
            &b.obs[k * od..(k + 1) * od],
            &b.actions[k * ad..(k + 1) * ad],
            b.rewards[k],
            &b.next_obs[k * od..(k + 1) * od],
            b.dones[k] != 0.0,
        );
    }
    let without_buffer = dir.path().join("without-buffer");
    super::checkpoint::save(&without_buffer, &saved, &sac, &model, None).unwrap();
    assert!(
        super::checkpoint::load_replay(&without_buffer, od, ad, 100)
            .unwrap()
            .is_none()
    );
    super::checkpoint::save(&ckpt, &saved, &sac, &model, Some(&buffer)).unwrap();
    let restored_buffer = super::checkpoint::load_replay(&ckpt, od, ad, 100)
        .unwrap()
        .unwrap();
    assert_eq!(restored_buffer.transitions(), buffer.transitions());
    // A learner from another seed, restored from the checkpoint, takes the same next step
    // (the Adam moments came back with their parameters).
    let mut other_rng = ChaCha8Rng::seed_from_u64(99);
    let mut restored = Sac::new(config, od, ad, &mut other_rng);
    let mut restored_model =
        ModelTrainer::new(od, ad, &[8], 1e-3, &mut other_rng, &restored.device);
    super::checkpoint::load(&ckpt, &mut restored, &mut restored_model).unwrap();
    let a = sac.update(&b, &noise);
    let r = restored.update(&b, &noise);
    assert_eq!(a, r);
    let weights = |s: &Sac| s.actor.to_actor(od).mu.weight().clone();
    assert_eq!(weights(&sac), weights(&restored));
    assert_eq!(
        model.update(&b.obs, &b.actions, &b.next_obs),
        restored_model.update(&b.obs, &b.actions, &b.next_obs)
    );
}

#[test]
fn a_run_takes_one_trainer_at_a_time() {
    let dir = tempfile::tempdir().unwrap();
    let mut options = quick_options(&dir.path().join("p.safetensors"));
    options.steps = 300;
    let mut first = Trainer::new(options.clone(), false).unwrap();
    first.run().unwrap();
    first.checkpoint().unwrap();
    let csv = std::fs::read(&options.csv).unwrap();
    let state = std::fs::read(options.checkpoint_dir.join("state.json")).unwrap();
    // Neither a resume nor a fresh start (which would delete the CSVs) takes the held run.
    for resume in [true, false] {
        let Err(e) = Trainer::new(options.clone(), resume) else {
            panic!("a second trainer took the run (resume: {resume})");
        };
        assert!(
            e.to_string()
                .contains("another trainer is running this run"),
            "{e}"
        );
    }
    assert_eq!(std::fs::read(&options.csv).unwrap(), csv);
    assert_eq!(
        std::fs::read(options.checkpoint_dir.join("state.json")).unwrap(),
        state
    );
    // A run with another name is another run.
    let other = quick_options(&dir.path().join("q.safetensors"));
    drop(Trainer::new(other, false).unwrap());
    // Once the first trainer is gone the run resumes.
    drop(first);
    options.steps = 400;
    let mut resumed = Trainer::new(options, true).unwrap();
    assert_eq!(resumed.progress.step, 300);
    resumed.run().unwrap();
    assert_eq!(resumed.progress.step, 400);
}

#[test]
fn a_resume_counts_the_restored_transitions_toward_the_warm_up() {
    let dir = tempfile::tempdir().unwrap();
    let options = quick_options(&dir.path().join("p.safetensors"));
    let warmup = options
        .sac
        .learning_starts
        .max(options.sac.batch_size as u64);
    let resumed_after = |steps: u64| {
        let mut options = options.clone();
        options.steps = steps;
        let mut trainer = Trainer::new(options.clone(), false).unwrap();
        trainer.run().unwrap();
        trainer.checkpoint().unwrap();
        drop(trainer);
        options.steps = steps + 100;
        let resumed = Trainer::new(options, true).unwrap();
        (resumed.restored_transitions, resumed.progress.fresh_steps)
    };
    // A checkpoint from inside the warm-up finishes it rather than learning from a few samples.
    assert_eq!(
        resumed_after(warmup / 4),
        (Some(warmup as usize / 4), warmup / 4)
    );
    // One past it learns on at once.
    assert_eq!(
        resumed_after(warmup + 10),
        (Some(warmup as usize + 10), warmup)
    );
}

#[test]
fn exported_networks_compute_what_the_learner_computes() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let spec = domains::make("pendulum").unwrap().spec().clone();
    let sac = Sac::new(small_config(), spec.obs_dim, spec.act_dim, &mut rng);
    let model = ModelTrainer::new(3, 1, &[8, 8], 1e-4, &mut rng, &sac.device);
    let policy = Arc::new(snapshot(&sac, &model, &spec, 0, 0));
    // The bundle round trip keeps them.
    let bytes = crate::bundle::to_bytes(&policy).unwrap();
    let loaded = Arc::new(crate::bundle::from_bytes(&bytes, std::path::Path::new("t")).unwrap());
    let obs = [0.3f32, -0.2, 0.7];
    let mean: Tensor<2> = sac.actor.mean_action(matrix(&obs, 1, 3, &sac.device));
    let mut action = [0.0f32];
    Evaluator::new(loaded).act(&obs, &[0.0], &mut action);
    assert!((rows(mean)[0] - action[0]).abs() < 1e-5);
}

#[test]
fn pendulum_training_beats_the_random_policy() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("pendulum.safetensors");
    let mut options = TrainOptions::new("pendulum", &out);
    options.steps = 4000;
    options.eval_every = 2000;
    options.value_episodes = 10;
    options.progress = false;
    let report = Trainer::new(options, false).unwrap().run().unwrap();
    assert_eq!(report.steps, 4000);
    assert!(
        report.eval_return_mean > report.random_return_mean + 400.0
            && report.eval_return_mean > -700.0,
        "policy {:.0} vs random {:.0}",
        report.eval_return_mean,
        report.random_return_mean
    );
    let policy = crate::bundle::load(&out).unwrap();
    let scale = policy.manifest.value_scale.unwrap();
    assert!(scale.v_pi > scale.v_rand);
    assert_eq!(policy.manifest.provenance.steps, 4000);
    assert!(report.model_errors[0].nrmse.is_finite());
}

#[test]
fn the_trainer_refuses_what_the_command_line_refuses() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("p.safetensors");
    let refused = |change: &dyn Fn(&mut TrainOptions)| {
        let mut options = TrainOptions::new("pendulum", &out);
        change(&mut options);
        let Err(e) = Trainer::new(options, false) else {
            panic!("accepted");
        };
        e.to_string()
    };
    assert!(refused(&|o| o.epsilon_coef = -1.0).contains("--epsilon-coef"));
    assert!(refused(&|o| o.max_horizon = 0).contains("--max-horizon"));
    assert!(refused(&|o| o.eval_episodes = 0).contains("--eval-episodes"));
    assert!(refused(&|o| o.value_scale = Some((0.0, 1.0))).contains("V_PI > V_RAND"));
    assert!(refused(&|o| o.sac.gamma = 1.0).contains("--gamma"));
    assert!(refused(&|o| o.sac.hidden.clear()).contains("--hidden"));
}

#[test]
fn constant_features_are_normalised_by_one() {
    use super::model::RunningStats;
    let mut stats = RunningStats::new(3);
    for k in 0..100 {
        let x = k as f32 / 100.0;
        // A varying feature, an exactly constant one, and one that only rounds.
        stats.push(&[x, 0.7, 1.0 + 1e-7 * (k % 2) as f32]);
    }
    let std = stats.std_f32();
    assert!((std[0] - 0.2887).abs() < 1e-3, "{std:?}");
    assert_eq!(std[1], 1.0);
    assert_eq!(std[2], 1.0);
    assert_eq!(RunningStats::new(2).std_f32(), vec![1.0, 1.0]);
}

/// `--norm-obs`: the snapshot that acts (and the bundle) normalises raw observations with the
/// running statistics exactly as the learner's inputs were normalised, so the served actor
/// computes what the burn actor computes on the normalised observation.
#[test]
fn norm_obs_policies_normalise_as_the_learner_did() {
    use crate::policy::ObsScale;
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let spec = domains::make("pendulum").unwrap().spec().clone();
    let config = SacConfig {
        norm_obs: true,
        ..small_config()
    };
    let sac = Sac::new(config, spec.obs_dim, spec.act_dim, &mut rng);
    let mut model = ModelTrainer::new(3, 1, &[8, 8], 1e-4, &mut rng, &sac.device);
    let mut delta = Vec::new();
    for k in 0..50 {
        let x = k as f32 / 10.0;
        model.stats.push(
            &[x.cos(), 3.0 * x.sin(), 8.0 + x],
            &[0.1],
            &[0.0; 3],
            &mut delta,
        );
    }
    let policy = snapshot(&sac, &model, &spec, 50, 0);
    let norm = policy.manifest.obs_normalization.clone().unwrap();
    assert_eq!(norm.mean, model.stats.obs.mean_f32());
    assert!((norm.var[2] - 2.0825).abs() < 1e-3, "{:?}", norm.var);
    // Through the bundle format and back.
    let bytes = crate::bundle::to_bytes(&policy).unwrap();
    let loaded = Arc::new(crate::bundle::from_bytes(&bytes, std::path::Path::new("t")).unwrap());
    let raw = [0.3f32, -2.0, 9.5];
    let mut normalised = Vec::new();
    ObsScale::new(&norm).extend_normalized(&raw, &mut normalised);
    assert!(normalised[2].abs() < 3.0 && (normalised[2] - raw[2]).abs() > 5.0);
    let mean: Tensor<2> = sac
        .actor
        .mean_action(matrix(&normalised, 1, 3, &sac.device));
    let mut action = [0.0f32];
    Evaluator::new(loaded).act(&raw, &[0.0], &mut action);
    assert!((rows(mean)[0] - action[0]).abs() < 1e-5);
    // Without the flag the bundle carries no normalisation.
    let plain = Sac::new(small_config(), 3, 1, &mut rng);
    assert!(
        snapshot(&plain, &model, &spec, 50, 0)
            .manifest
            .obs_normalization
            .is_none()
    );
}

/// A run trained with `--norm-obs` writes a bundle that carries its statistics, and resumes only
/// the way it started: its networks learned on normalised inputs.
#[test]
fn norm_obs_runs_ship_their_statistics_and_resume_only_with_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("p.safetensors");
    let mut options = quick_options(&out);
    options.steps = 600;
    options.value_episodes = 2;
    options.sac.norm_obs = true;
    let mut trainer = Trainer::new(options.clone(), false).unwrap();
    trainer.run().unwrap();
    trainer.checkpoint().unwrap();
    let bundle = crate::bundle::load(&out).unwrap();
    let norm = bundle.manifest.obs_normalization.unwrap();
    // The pendulum's cos and sin of the angle, and its speed: 600 steps of them.
    assert!(
        norm.var.iter().all(|&v| v > 0.0 && v.is_finite()),
        "{norm:?}"
    );
    assert!(
        norm.mean[0].abs() <= 1.0 && norm.var[2] > norm.var[0],
        "{norm:?}"
    );
    // Trained bundles carry their domain's observation space, which needs format 4.
    assert_eq!(
        bundle.manifest.format_version,
        crate::manifest::FORMAT_VERSION_OBS_BOUNDS
    );
    assert!(bundle.manifest.obs_bounds.is_some());

    let state = std::fs::read(options.checkpoint_dir.join("state.json")).unwrap();
    drop(trainer);
    let mut plain = options.clone();
    plain.sac.norm_obs = false;
    plain.steps = 700;
    let Err(e) = Trainer::new(plain, true) else {
        panic!("resumed without --norm-obs");
    };
    assert!(e.to_string().contains("with --norm-obs"), "{e}");
    assert_eq!(
        std::fs::read(options.checkpoint_dir.join("state.json")).unwrap(),
        state
    );
    options.steps = 700;
    let mut resumed = Trainer::new(options, true).unwrap();
    assert_eq!(resumed.progress.step, 600);
    resumed.run().unwrap();
    assert_eq!(resumed.progress.step, 700);
}

#[test]
fn evaluations_record_falls_distance_and_time_and_widen_an_older_csv() {
    let dir = tempfile::tempdir().unwrap();
    let mut options = TrainOptions::new("pendulum", &dir.path().join("p.safetensors"));
    options.steps = 300;
    options.eval_every = 100;
    options.eval_episodes = 1;
    options.value_episodes = 1;
    options.progress = false;
    Trainer::new(options.clone(), false).unwrap().run().unwrap();
    let rows = |path: &std::path::Path| -> Vec<Vec<String>> {
        std::fs::read_to_string(path)
            .unwrap()
            .lines()
            .map(|l| l.split(',').map(str::to_string).collect())
            .collect()
    };
    let written = rows(&options.eval_csv);
    assert_eq!(written[0].join(","), super::run::EVAL_CSV_HEADER);
    assert_eq!(written.len(), 4, "{written:?}");
    let mut last_seconds = 0.0;
    for row in &written[1..] {
        assert_eq!(row.len(), 7, "{row:?}");
        // The pendulum never ends early and has no forward distance.
        assert_eq!((row[4].as_str(), row[5].as_str()), ("0", ""), "{row:?}");
        let seconds: f64 = row[6].parse().unwrap();
        assert!(seconds >= last_seconds, "{row:?}");
        last_seconds = seconds;
    }

    // A run written before these columns: resuming widens its file instead of appending rows
    // longer than its header.
    let old: Vec<String> = written.iter().map(|row| row[..4].join(",")).collect();
    std::fs::write(&options.eval_csv, old.join("\n") + "\n").unwrap();
    options.steps = 400;
    Trainer::new(options.clone(), true).unwrap().run().unwrap();
    let widened = rows(&options.eval_csv);
    assert_eq!(widened[0].join(","), super::run::EVAL_CSV_HEADER);
    assert_eq!(widened.len(), 5, "{widened:?}");
    assert!(widened.iter().all(|row| row.len() == 7), "{widened:?}");
    assert_eq!(widened[1][4..], ["", "", ""]);
    assert_eq!(widened[4][0], "400");
    assert_eq!(widened[4][4], "0");

    // A file whose columns are not these is refused, not mixed into.
    std::fs::write(&options.eval_csv, "step,something_else\n100,1\n").unwrap();
    options.steps = 500;
    let Err(e) = Trainer::new(options.clone(), true).unwrap().run() else {
        panic!("appended to a foreign CSV");
    };
    assert!(e.to_string().contains("not a start of"), "{e}");
}

#[test]
fn layer_norm_critics_ship_in_pytorchs_layout_and_resume_only_with_the_flag() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let spec = domains::make("pendulum").unwrap().spec().clone();
    let (od, ad) = (spec.obs_dim, spec.act_dim);
    let config = SacConfig {
        critic_layer_norm: true,
        learning_rate: 1e-2,
        ..small_config()
    };
    let mut sac = Sac::new(config, od, ad, &mut rng);
    let b = batch(&mut rng, 32, od, ad);
    let noise = normals(&mut rng, 2 * 32 * ad);
    for _ in 0..5 {
        sac.update(&b, &noise);
    }
    // The updates moved the norms' scales, and the target's by tau of the way.
    let online = sac.critic.to_mlps(od + ad);
    let target = sac.critic_target.to_mlps(od + ad);
    let scale = online[0].norms()[0].scale()[0];
    assert!((scale - 1.0).abs() > 1e-3, "scale {scale}");
    let target_scale = target[0].norms()[0].scale()[0];
    assert!(target_scale != 1.0 && (target_scale - 1.0).abs() < (scale - 1.0).abs());

    let model = ModelTrainer::new(od, ad, &[8, 8], 1e-4, &mut rng, &sac.device);
    let policy = snapshot(&sac, &model, &spec, 0, 0);
    assert!(policy.manifest.critic.layer_norm);
    assert_eq!(
        policy.manifest.format_version,
        crate::manifest::FORMAT_VERSION_OBS_BOUNDS
    );
    let names: Vec<String> = crate::bundle::tensors(&policy)
        .into_iter()
        .map(|(name, ..)| name)
        .collect();
    for name in [
        "critic.qf1.1.weight",
        "critic.qf1.4.bias",
        "critic.qf1.6.weight",
    ] {
        assert!(names.iter().any(|n| n == name), "{name} not in {names:?}");
    }
    let bytes = crate::bundle::to_bytes(&policy).unwrap();
    let loaded = crate::bundle::from_bytes(&bytes, std::path::Path::new("t")).unwrap();
    let (obs, action) = ([0.3f32, -0.2, 0.7], [0.4f32]);
    let theirs = sac.critic.forward(
        matrix(&obs, 1, od, &sac.device),
        matrix(&action, 1, ad, &sac.device),
    );
    let input = [obs.as_slice(), action.as_slice()].concat();
    for (critic, q) in loaded.critics.iter().zip(theirs) {
        let ours = critic.forward_rows(&input, &mut critic.scratch())[0];
        assert!((ours - rows(q)[0]).abs() < 1e-4, "{ours}");
    }

    // A run resumes only the way it started.
    let dir = tempfile::tempdir().unwrap();
    let mut options = quick_options(&dir.path().join("p.safetensors"));
    options.steps = 300;
    options.sac.critic_layer_norm = true;
    let mut trainer = Trainer::new(options.clone(), false).unwrap();
    trainer.run().unwrap();
    trainer.checkpoint().unwrap();
    drop(trainer);
    let mut plain = options.clone();
    plain.sac.critic_layer_norm = false;
    plain.steps = 400;
    let Err(e) = Trainer::new(plain, true) else {
        panic!("resumed without --critic-layer-norm");
    };
    assert!(e.to_string().contains("with --critic-layer-norm"), "{e}");
    options.steps = 400;
    let mut resumed = Trainer::new(options, true).unwrap();
    resumed.run().unwrap();
    assert_eq!(resumed.progress.step, 400);
}

#[test]
fn a_csv_replaced_while_a_run_writes_it_gets_the_rows_that_follow() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.train.csv");
    let log = CsvLog::open(&path, "step,return").unwrap();
    log.row(format_args!("1,10")).unwrap();
    // What `git checkout` does: a new file renamed over the one the run is writing.
    let replacement = dir.path().join("checked-out.csv");
    std::fs::write(&replacement, "step,return\n1,10\n").unwrap();
    std::fs::rename(&replacement, &path).unwrap();
    log.row(format_args!("2,20")).unwrap();
    assert_eq!(
        std::fs::read_to_string(&path).unwrap(),
        "step,return\n1,10\n2,20\n"
    );
    // A file that exists with rows keeps them and takes no second header.
    let again = CsvLog::open(&path, "step,return").unwrap();
    again.row(format_args!("3,30")).unwrap();
    assert_eq!(
        std::fs::read_to_string(&path).unwrap(),
        "step,return\n1,10\n2,20\n3,30\n"
    );
}
