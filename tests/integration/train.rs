//! `prac train` as a process: a run killed with SIGKILL resumes from its checkpoint (networks,
//! optimisers and replay buffer) and continues its step count and curve; training-with-PrAC
//! commits to plans; `prac fit-model` fits a model from recorded transitions.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn prac() -> Command {
    Command::new(env!("CARGO_BIN_EXE_prac"))
}

fn checkpoint_step(dir: &Path) -> Option<u64> {
    let text = std::fs::read_to_string(dir.join("state.json")).ok()?;
    let state: serde_json::Value = serde_json::from_str(&text).ok()?;
    state["progress"]["step"].as_u64()
}

/// (step, episode, forecast) of each CSV row.
fn curve(path: &Path) -> Vec<(u64, u64, f64)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (s, e, f) = (col("step"), col("episode"), col("forecast"));
    lines
        .map(|l| {
            let v: Vec<&str> = l.split(',').collect();
            (
                v[s].parse().unwrap(),
                v[e].parse().unwrap(),
                v[f].parse().unwrap(),
            )
        })
        .collect()
}

#[test]
fn a_killed_run_resumes_from_its_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("pendulum.safetensors");
    let ckpt = dir.path().join("pendulum.ckpt");
    let args = [
        "train",
        "--domain",
        "pendulum",
        "--steps",
        "1600",
        "--learning-starts",
        "200",
        "--batch-size",
        "64",
        "--hidden",
        "64,64",
        "--checkpoint-every",
        "1s",
        "--eval-every",
        "400",
        "--value-episodes",
        "2",
        "--quiet",
        "--out",
        out.to_str().unwrap(),
    ];
    let mut child = prac().args(args).stdout(Stdio::null()).spawn().unwrap();
    let deadline = Instant::now() + Duration::from_secs(240);
    let killed_after = loop {
        if let Some(step) = checkpoint_step(&ckpt).filter(|&s| s >= 400) {
            break step;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "training ended before a checkpoint"
        );
        assert!(Instant::now() < deadline, "no checkpoint past step 400");
        std::thread::sleep(Duration::from_millis(100));
    };
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    assert!(!out.exists(), "a killed run wrote no bundle");
    let at_kill = checkpoint_step(&ckpt).unwrap();
    assert!(at_kill >= killed_after && at_kill < 1600);

    let resumed = prac().args(args).arg("--resume").output().unwrap();
    assert!(
        resumed.status.success(),
        "{}",
        String::from_utf8_lossy(&resumed.stderr)
    );
    let stderr = String::from_utf8_lossy(&resumed.stderr);
    assert!(
        stderr.contains(&format!("resuming at step {at_kill}")),
        "{stderr}"
    );
    // The buffer came back whole: one transition per step before the kill.
    assert!(
        stderr.contains(&format!(
            "restored {at_kill} transitions from the checkpoint's replay buffer"
        )),
        "{stderr}"
    );
    let report: serde_json::Value = serde_json::from_slice(&resumed.stdout).unwrap();
    assert_eq!(report["steps"], 1600);

    // The curve goes on: steps and episode numbers strictly increase across the kill, no row is
    // repeated, and the last episode ends at the last step.
    let rows = curve(&dir.path().join("pendulum.train.csv"));
    assert_eq!(rows.len(), 8, "{rows:?}"); // pendulum episodes are 200 steps
    for (i, w) in rows.windows(2).enumerate() {
        assert!(w[1].0 > w[0].0 && w[1].1 == w[0].1 + 1, "row {i}: {w:?}");
    }
    assert_eq!(rows.last().unwrap().0, 1600);
    let policy = prac::bundle::load(&out).unwrap();
    assert_eq!(policy.manifest.provenance.steps, 1600);
    assert!(checkpoint_step(&ckpt) == Some(1600));
}

/// Also with layer-norm critics taking two gradient steps per environment step: the plans are
/// judged by those critics, and the bundle carries them through fit-model.
#[test]
fn training_with_prac_commits_to_plans_and_fit_model_fits_a_model() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("p.safetensors");
    let run = prac()
        .args([
            "train",
            "--domain",
            "pendulum",
            "--steps",
            "800",
            "--learning-starts",
            "200",
            "--batch-size",
            "64",
            "--hidden",
            "64,64",
            "--epsilon-coef",
            "0.05",
            "--value-scale=-100,-300",
            "--value-episodes",
            "2",
            "--critic-layer-norm",
            "--gradient-steps",
            "2",
            "--quiet",
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let trained = prac::bundle::load(&out).unwrap();
    assert!(trained.manifest.critic.layer_norm);
    let norms = prac::testing::critic_norms(&trained);
    assert!(norms.iter().all(|critic| critic.len() == 2));
    let rows = curve(&dir.path().join("p.train.csv"));
    // Before learning starts actions are random (forecast 1); after, eps = 10 keeps plans.
    assert_eq!(rows[0].2, 1.0);
    assert!(rows[1..].iter().any(|r| r.2 > 2.0), "{rows:?}");

    // Transitions recorded from the domain with random actions.
    let mut env = prac::domains::make("pendulum").unwrap();
    let (mut obs, mut next) = (vec![0.0f32; 3], vec![0.0f32; 3]);
    let mut data = prac::train::fit::Transitions {
        len: 0,
        obs: vec![],
        action: vec![],
        next_obs: vec![],
        exploratory: Some(vec![]),
    };
    for episode in 0..10 {
        env.reset(episode, &mut obs).unwrap();
        for t in 0..200u32 {
            // A fifth of the rows explore: another action, flagged as record --random-fraction does.
            let explore = t % 10 < 2;
            let action = if explore {
                [2.0 * ((t as f32 * 1.3 + episode as f32).cos())]
            } else {
                [2.0 * ((t as f32 * 0.37 + episode as f32).sin())]
            };
            data.exploratory.as_mut().unwrap().push(explore);
            let step = env.step(&action, &mut next).unwrap();
            data.obs.extend_from_slice(&obs);
            data.action.extend_from_slice(&action);
            data.next_obs.extend_from_slice(&next);
            data.len += 1;
            obs.copy_from_slice(&next);
            if step.terminated || step.truncated {
                break;
            }
        }
    }
    let file = dir.path().join("transitions.safetensors");
    data.save(&file).unwrap();
    // Into a folder that does not exist yet: fit-model makes it.
    let fitted = dir.path().join("fitted").join("fitted.safetensors");
    let fit = prac()
        .args([
            "fit-model",
            "--bundle",
            out.to_str().unwrap(),
            "--transitions",
            file.to_str().unwrap(),
            "--steps",
            "1500",
            "--learning-rate",
            "1e-3",
            "--out",
            fitted.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(
        fit.status.success(),
        "{}",
        String::from_utf8_lossy(&fit.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&fit.stdout).unwrap();
    let after = report["after"].as_array().unwrap();
    let one_step = after[0]["nrmse"].as_f64().unwrap();
    let ten_step = after[2]["nrmse"].as_f64().unwrap();
    // Held out: 200 rows, one episode. One step ahead the model is within a tenth of a standard
    // deviation per feature; errors grow with the horizon.
    assert_eq!(report["heldout_transitions"], 200);
    assert!(one_step < 0.1, "{report}");
    assert!(ten_step > one_step, "{report}");
    let refitted = prac::bundle::load(&fitted).unwrap();
    assert!(refitted.model.is_some());
    assert_eq!(prac::testing::critic_norms(&refitted)[1], norms[1]);
    // Split by action: 160 held-out rows acted as the policy, 40 explored; every window is in
    // exactly one group.
    let split = &report["after_by_action"];
    let samples = |group: &str, i: usize| split[group][i]["samples"].as_u64().unwrap();
    assert_eq!(
        (samples("on_policy", 0), samples("exploratory", 0)),
        (160, 40)
    );
    for (i, row) in after.iter().enumerate() {
        let all = row["samples"].as_u64().unwrap();
        assert_eq!(samples("on_policy", i) + samples("exploratory", i), all);
    }
    // Every 10-step window holds a randomised row (two in each ten): none is on-policy, and an
    // error over no windows is absent, not zero.
    assert_eq!(samples("on_policy", 2), 0);
    assert!(split["on_policy"][2]["nrmse"].is_null(), "{split}");

    // Bad transitions are refused with the field named.
    std::fs::write(&file, b"not safetensors").unwrap();
    let bad = prac()
        .args([
            "fit-model",
            "--bundle",
            out.to_str().unwrap(),
            "--transitions",
            file.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("not a safetensors file"));
}
