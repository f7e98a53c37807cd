//! `prac inspect` on bundles written by test code, `prac evaluate` on a shipped one,
//! `prac bench-replan --bundle` and `prac play-from-states` on PyBullet's states, and the README's
//! command table against the binary's own help.

use crate::common;

use std::process::Command;

use common::toy_policy;
use prac::bundle::Manifest;

fn prac(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_prac"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn inspect_prints_the_manifest_and_a_forward_pass() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("toy.safetensors");
    let policy = toy_policy("toy", 4);
    prac::bundle::save(&policy, &file).unwrap();
    let file = file.to_str().unwrap();

    let out = prac(&["inspect", file]);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    for expected in [
        "name         toy",
        "obs_dim      3",
        "critics      2 x hidden [32, 32] Relu, Q = min of critics",
        "V_pi(s0) = 10, V_rand(s0) = -10",
        "guard        the paper's test (sessions that set none)",
        "Q(s,pi(s))",
        "P(s,pi(s))",
        "sha256:",
    ] {
        assert!(text.contains(expected), "{expected:?} not in\n{text}");
    }

    let out = prac(&["inspect", file, "--json"]);
    assert!(out.status.success());
    let manifest: Manifest = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(manifest, policy.manifest);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_default_guards_epsilon_limit_holds_served_sessions_to_it() {
    use prac::proto::session_options::Tolerance;
    use prac::proto::{OpenSessionRequest, PlanGuard, SessionOptions};
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("toy.safetensors");
    let policy = toy_policy("toy", 4);
    let scale = policy
        .manifest
        .value_scale
        .expect("the toy has a value scale");
    let range = scale.v_pi - scale.v_rand;
    prac::bundle::save(&policy, &file).unwrap();
    let file = file.to_str().unwrap();
    let out = prac(&["default-guard", file, "--max-epsilon-coef", "0.005"]);
    assert!(out.status.success(), "{out:?}");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("default guard the paper's test, eps coefficient at most 0.005 (format 6)"),
        "{stdout}"
    );
    let before = std::fs::read(file).unwrap();
    let out = prac(&["default-guard", file, "--max-epsilon-coef=-1"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("manifest.default_guard.max_epsilon_coef is -1"),
        "{stderr}"
    );
    assert_eq!(std::fs::read(file).unwrap(), before);

    let server = common::Server::start(dir.path(), &[]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let open = |coef: f64, guard: Option<PlanGuard>| OpenSessionRequest {
        local_steps: 0,
        policy: "toy".into(),
        options: Some(SessionOptions {
            tolerance: Some(Tolerance::EpsilonCoef(coef)),
            guard,
            ..Default::default()
        }),
        resume: None,
    };
    let epsilon = |response: tonic::Response<prac::proto::OpenSessionResponse>| {
        response.into_inner().options.unwrap().epsilon
    };
    let held = (0.005 * range) as f32 as f64;
    assert_eq!(
        epsilon(client.open_session(open(0.01, None)).await.unwrap()),
        held
    );
    assert_eq!(
        epsilon(client.open_session(open(0.002, None)).await.unwrap()),
        (0.002 * range) as f32 as f64
    );
    // The paper's test is not held.
    assert_eq!(
        epsilon(
            client
                .open_session(open(0.01, Some(PlanGuard::default())))
                .await
                .unwrap()
        ),
        (0.01 * range) as f32 as f64
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn default_guard_sets_what_sessions_without_a_guard_get() {
    use prac::proto::{OpenSessionRequest, PlanGuard, SessionOptions};
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("toy.safetensors");
    prac::bundle::save(&toy_policy("toy", 4), &file).unwrap();
    let file = file.to_str().unwrap();
    let out = prac(&[
        "default-guard",
        file,
        "--every-critic",
        "--support-limit",
        "3",
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{out:?}");
    assert!(
        stdout.contains("default guard every critic, support limit 3 (format 5)"),
        "{stdout}"
    );
    // Bad requests change nothing.
    let before = std::fs::read(file).unwrap();
    let out = prac(&["default-guard", file]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--none to remove"));
    let out = prac(&["default-guard", file, "--support-limit=-1"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("manifest.default_guard.support_limit is -1"),
        "{stderr}"
    );
    assert_eq!(std::fs::read(file).unwrap(), before);

    let server = common::Server::start(dir.path(), &[]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let listed = client
        .list_policies(prac::proto::ListPoliciesRequest {})
        .await
        .unwrap()
        .into_inner();
    let guard = PlanGuard {
        every_critic: true,
        support_limit: 3.0,
        ..Default::default()
    };
    assert_eq!(listed.policies[0].default_guard, Some(guard));
    let open = |guard: Option<PlanGuard>| OpenSessionRequest {
        local_steps: 0,
        policy: "toy".into(),
        options: Some(SessionOptions {
            guard,
            ..Default::default()
        }),
        resume: None,
    };
    let resolved = |response: tonic::Response<prac::proto::OpenSessionResponse>| {
        response.into_inner().options.unwrap().guard.unwrap()
    };
    assert_eq!(
        resolved(client.open_session(open(None)).await.unwrap()),
        guard
    );
    // An empty guard still asks for the paper's test.
    let paper = Some(PlanGuard::default());
    assert_eq!(
        resolved(client.open_session(open(paper)).await.unwrap()),
        PlanGuard::default()
    );
    drop(server);

    let out = prac(&["inspect", file]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("guard        every critic, support limit 3 (sessions that set none)"),
        "{text}"
    );
    let out = prac(&["default-guard", file, "--none"]);
    assert!(out.status.success(), "{out:?}");
    let policy = prac::bundle::load(std::path::Path::new(file)).unwrap();
    assert_eq!(policy.manifest.default_guard, None);
}

#[test]
fn a_manifest_declaring_a_billion_critics_is_an_error_not_an_abort() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("huge.safetensors");
    let policy = toy_policy("huge", 4);
    let mut manifest = policy.manifest.clone();
    manifest.critic.n_critics = 1_000_000_000;
    let text = serde_json::to_string(&manifest).unwrap();
    std::fs::write(
        &file,
        prac::bundle::to_bytes_with_manifest(&policy, &text).unwrap(),
    )
    .unwrap();
    let out = prac(&["inspect", file.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("huge.safetensors: critic.qf2.0.weight: missing tensor"),
        "{err}"
    );
    // The server skips it and serves the rest; --strict refuses to start.
    prac::bundle::save(&toy_policy("toy", 5), &dir.path().join("toy.safetensors")).unwrap();
    let strict = Command::new(env!("CARGO_BIN_EXE_prac"))
        .args(["serve", "--listen", "127.0.0.1:0", "--strict", "--bundles"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert_eq!(strict.status.code(), Some(1), "{strict:?}");
    assert!(String::from_utf8_lossy(&strict.stderr).contains("critic.qf2.0.weight"));
}

#[test]
fn serve_strict_on_a_missing_bundle_directory_fails_before_its_ready_line() {
    let out = prac(&[
        "serve",
        "--listen",
        "127.0.0.1:0",
        "--strict",
        "--bundles",
        "/nonexistent/prac-bundles",
    ]);
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    assert!(
        out.stdout.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("cannot read bundle directory /nonexistent/prac-bundles"),
        "{err}"
    );
}

/// A volume not mounted or not yet filled: the server stays up, NOT_SERVING (a readiness probe
/// fails, a liveness probe passes: no crash loop), with the reason in its log.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_on_a_missing_bundle_directory_stays_up_not_serving() {
    use tonic_health::pb::health_check_response::ServingStatus;
    let server = common::Server::start(std::path::Path::new("/nonexistent/prac-bundles"), &[]);
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    assert_eq!(
        server.health("prac.v1.Prac").await,
        ServingStatus::NotServing
    );
    assert_eq!(server.health("").await, ServingStatus::NotServing);
    assert_eq!(server.health("liveness").await, ServingStatus::Serving);
    let log = server.stderr();
    assert!(
        log.contains("cannot read bundle directory") && log.contains("/nonexistent/prac-bundles"),
        "{log}"
    );
}

#[test]
fn inspect_names_the_file_and_field_of_a_bad_bundle() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.safetensors");
    let mut policy = toy_policy("bad", 4);
    policy.manifest.gamma = 1.0;
    prac::bundle::save(&policy, &file).unwrap();
    let out = prac(&["inspect", file.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("bad.safetensors: manifest.gamma: is 1"),
        "{err}"
    );
}

#[test]
fn evaluate_plays_a_bundle_against_random_actions() {
    let bundle = concat!(env!("CARGO_MANIFEST_DIR"), "/bundles/pendulum.safetensors");
    let dir = tempfile::tempdir().unwrap();
    let json_out = dir.path().join("evaluation.json");
    let out = prac(&[
        "evaluate",
        bundle,
        "--episodes",
        "3",
        "--seed",
        "5",
        "--json-out",
        json_out.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.contains("(pendulum), 3 episodes from seed 5"),
        "{text}"
    );
    let e: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json_out).unwrap()).unwrap();
    // The trained swing-up beats random torques by far.
    let (policy, random) = (&e["policy"], &e["random"]);
    assert!(
        policy["return_mean"].as_f64().unwrap() > random["return_mean"].as_f64().unwrap() + 300.0,
        "{e}"
    );
    assert_eq!(policy["terminated"], 0);
    assert!(policy["distance_mean"].is_null());

    let bad = prac(&["evaluate", bundle, "--episodes", "0"]);
    assert!(!bad.status.success());
    assert!(
        String::from_utf8(bad.stderr)
            .unwrap()
            .contains("--episodes")
    );
}

#[test]
fn bench_train_times_updates_a_short_run_and_the_replay_checkpoint() {
    let out = prac(&[
        "bench-train",
        "--seconds",
        "0.01",
        "--domain",
        "pendulum",
        "--steps",
        "1050",
        "--replay-transitions",
        "2000",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    for line in [
        "SAC update",
        "dynamics model update",
        "training pendulum for 1050 steps",
        "replay buffer in a checkpoint (2000 transitions, obs 44 / action 17)",
    ] {
        assert!(text.contains(line), "no '{line}' in:\n{text}");
    }
}

#[test]
fn bench_replan_measures_the_kernel_it_is_told_to() {
    let out = prac(&[
        "bench-replan",
        "--seconds",
        "0.02",
        "--lengths",
        "1",
        "--batches",
        "1",
        "--kernel",
        "scalar",
    ]);
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.starts_with("dense-layer kernel: Scalar\n"), "{text}");
    assert!(text.contains("MLP kernel: one critic"), "{text}");
}

#[test]
fn bench_replan_on_a_bundle_plays_its_domain_and_refuses_a_foreign_one() {
    let bundle = concat!(env!("CARGO_MANIFEST_DIR"), "/bundles/pendulum.safetensors");
    let out = prac(&["bench-replan", "--seconds", "0.05", "--bundle", bundle]);
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8(out.stdout).unwrap();
    let row = text
        .lines()
        .find(|l| l.starts_with("pendulum "))
        .unwrap_or_else(|| panic!("no pendulum row in\n{text}"));
    let values: Vec<f64> = row
        .split_whitespace()
        .skip(1)
        .map(|v| v.trim_end_matches('%').parse().unwrap())
        .collect();
    // steps, us/step, tested, plan, calls, MFLOP/step: a real run's figures, all positive.
    assert!(values[..6].iter().all(|&v| v > 0.0), "{row}");
    // Each step keeps at most the old actions it tested and adds at least one: the mean plan is
    // longer than the mean count of tested actions, and every step calls the networks.
    let (tested, plan, calls) = (values[2], values[3], values[4]);
    assert!(plan >= 1.0 && tested < plan, "{row}");
    assert!(calls >= 1.0, "{row}");

    // A bundle whose domain this build does not have.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("toy.safetensors");
    prac::bundle::save(&toy_policy("toy", 4), &file).unwrap();
    let out = prac(&[
        "bench-replan",
        "--seconds",
        "0.05",
        "--bundle",
        file.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("domain"), "{err}");
}

#[test]
fn play_from_states_plays_pybullets_states_and_refuses_bad_ones() {
    let fixture: serde_json::Value = serde_json::from_str(include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/pybullet-states.json"
    )))
    .unwrap();
    let case = &fixture["walker"][0];
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("cases.json");
    let output = dir.path().join("ours.json");
    let play = |domain: &str, state: &serde_json::Value| {
        let cases = serde_json::json!({
            "domain": domain,
            "cases": [{"state": state, "actions": vec![case["action"].clone(); 3]}],
        });
        std::fs::write(&input, cases.to_string()).unwrap();
        prac(&[
            "play-from-states",
            input.to_str().unwrap(),
            "--out",
            output.to_str().unwrap(),
        ])
    };
    // A successful run's output file.
    let played = |out: std::process::Output| -> serde_json::Value {
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_str(&std::fs::read_to_string(&output).unwrap()).unwrap()
    };
    let played_from_state = played(play("walker", &case["state"]));
    let start = played_from_state[0]["start"].as_array().unwrap();
    // The torso's height, speeds and pitch as PyBullet observes them in that state.
    for i in [0, 3, 5, 7] {
        let (ours, theirs) = (start[i].as_f64().unwrap(), case["obs"][i].as_f64().unwrap());
        assert!(
            (ours - theirs).abs() < 2e-3,
            "obs[{i}] {ours} against {theirs}"
        );
    }
    let steps = played_from_state[0]["steps"].as_array().unwrap();
    assert!(!steps.is_empty() && steps.len() <= 3);
    for step in steps {
        let terms = step["reward_terms"].as_object().unwrap();
        let names: Vec<&str> = terms.keys().map(String::as_str).collect();
        assert_eq!(
            names,
            ["alive", "electricity", "joints_at_limit", "progress"]
        );
        let sum: f64 = terms.values().map(|v| v.as_f64().unwrap()).sum();
        assert!(
            (sum - step["reward"].as_f64().unwrap()).abs() < 1e-6,
            "{step}"
        );
    }

    // The walker bundle's policy from the same state, closed loop.
    let closed_loop = |bundle: &str| {
        prac(&[
            "play-from-states",
            input.to_str().unwrap(),
            "--out",
            output.to_str().unwrap(),
            "--policy",
            &format!(
                "{}/bundles/{bundle}.safetensors",
                env!("CARGO_MANIFEST_DIR")
            ),
            "--steps",
            "5",
        ])
    };
    let closed = played(closed_loop("walker"));
    let steps = closed[0]["steps"].as_array().unwrap();
    assert!(steps.len() == 5 || steps.last().unwrap()["terminated"] == true);
    let actions: Vec<&serde_json::Value> = steps.iter().map(|s| &s["action"]).collect();
    assert!(actions.iter().all(|a| *a != &case["action"]), "{actions:?}");
    assert!(actions.windows(2).any(|w| w[0] != w[1]), "{actions:?}");
    let wrong_domain = closed_loop("hopper");
    assert!(!wrong_domain.status.success());
    let stderr = String::from_utf8(wrong_domain.stderr).unwrap();
    assert!(
        stderr.contains("the bundle is for hopper, the cases for walker"),
        "{stderr}"
    );

    let not_planar = play("ant", &case["state"]);
    assert!(!not_planar.status.success());
    let stderr = String::from_utf8(not_planar.stderr).unwrap();
    assert!(stderr.contains("ant is not a planar walker"), "{stderr}");

    let mut short = case["state"].clone();
    short["joints"].as_array_mut().unwrap().pop();
    let refused = play("walker", &short);
    assert!(!refused.status.success());
    let stderr = String::from_utf8(refused.stderr).unwrap();
    assert!(stderr.contains("joint angles"), "{stderr}");
}

/// The README's command table names every subcommand clap knows and, in its row, every flag of
/// it, so the documented interface cannot drift from the binary's.
#[test]
fn the_readme_lists_every_subcommand_and_every_flag() {
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).unwrap();
    // A row's first cell, up to its first unescaped `|`.
    let first_cell = |row: &str| -> String {
        let mut cell = String::new();
        let mut escaped = false;
        for c in row.trim_start_matches('|').chars() {
            if c == '|' && !escaped {
                break;
            }
            escaped = c == '\\';
            cell.push(c);
        }
        cell
    };
    let help = |args: &[&str]| String::from_utf8(prac(args).stdout).unwrap();
    let top = help(&["--help"]);
    let commands: Vec<&str> = top
        .split("Commands:")
        .nth(1)
        .and_then(|rest| rest.split("Options:").next())
        .unwrap()
        .lines()
        .filter_map(|l| l.strip_prefix("  ")?.split_whitespace().next())
        .filter(|c| *c != "help")
        .collect();
    assert!(commands.len() >= 14, "{commands:?}");
    let mut missing = Vec::new();
    for command in &commands {
        let prefix = format!("| `prac {command}");
        let Some(row) = readme.lines().find(|l| {
            l.strip_prefix(&prefix)
                .is_some_and(|rest| rest.starts_with(' ') || rest.starts_with('`'))
        }) else {
            missing.push(format!("no row for `prac {command}`"));
            continue;
        };
        let cell = first_cell(row);
        for line in help(&[command, "--help"]).lines() {
            let flag = line.trim_start().trim_start_matches("-h, ");
            let Some(flag) = flag
                .strip_prefix("--")
                .map(|f| f.split([' ', '=', '<']).next().unwrap_or(""))
            else {
                continue;
            };
            if !flag.is_empty() && flag != "help" && !cell.contains(&format!("--{flag}")) {
                missing.push(format!("`prac {command}` row lacks --{flag}"));
            }
        }
    }
    assert!(missing.is_empty(), "{}", missing.join("\n"));
}
