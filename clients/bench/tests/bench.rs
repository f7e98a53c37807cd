//! prac-bench against a real prac serve it starts itself (target/<profile>/prac, built by the
//! workspace's tests).

use std::process::Command;

fn bench(args: &[&str]) -> serde_json::Value {
    let out = Command::new(env!("CARGO_BIN_EXE_prac-bench"))
        .args(args)
        .args(["--json", "--warmup", "0s"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn closed_loop_counts_exactly_the_steps_asked() {
    for mode in ["stream", "unary"] {
        let r = bench(&["--sessions", "4", "--steps", "200", "--mode", mode]);
        assert_eq!(r["steps"], 200, "{r}");
        assert_eq!(r["errors"], serde_json::json!({}), "{r}");
        let l = &r["latency_us"];
        assert!(l["p50"].as_f64().unwrap() <= l["p99"].as_f64().unwrap());
        assert!(l["p99"].as_f64().unwrap() <= l["max"].as_f64().unwrap());
        assert!(r["throughput"].as_f64().unwrap() > 0.0);
        // Plans grow from 2 by one a step up to the cap (random weights never break them).
        assert!(r["mean_plan_length"].as_f64().unwrap() > 2.0, "{r}");
        assert!(r["mean_forecast"].as_f64().unwrap() >= 1.0, "{r}");
    }
}

#[test]
fn open_loop_holds_its_rate() {
    let r = bench(&[
        "--sessions",
        "4",
        "--duration",
        "2s",
        "--rate",
        "200",
        "--epsilon",
        "0",
        "--max-horizon",
        "1",
    ]);
    // The schedule, not the machine's speed, sets how many steps are sent: 200/s for 2 s.
    let steps = r["steps"].as_u64().unwrap();
    assert!((396..=404).contains(&steps), "{r}");
    assert_eq!(r["open_loop_rate"], 200.0);
    assert_eq!(r["mean_plan_length"], 1.0);
}

#[test]
fn refused_sessions_are_counted_not_fatal() {
    let r = bench(&[
        "--sessions",
        "6",
        "--steps",
        "60",
        "--server-arg=--max-sessions=4",
    ]);
    // One session is the recorder's, closed before the load starts.
    assert_eq!(r["errors"]["OpenSession ResourceExhausted"], 2, "{r}");
    assert_eq!(r["steps"], 60);
}

fn bench_output(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_prac-bench"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn the_sim_workload_drives_simulated_robots_closed_and_open_loop() {
    let dir = tempfile::tempdir().unwrap();
    let saved = dir.path().join("obs.safetensors");
    // The local policy is a Hopper's: its sessions are simulated Hoppers by default.
    let r = bench(&[
        "--sessions",
        "2",
        "--steps",
        "300",
        "--save-observations",
        saved.to_str().unwrap(),
    ]);
    assert_eq!(r["workload"], "sim", "{r}");
    assert_eq!(r["domain"], "hopper", "{r}");
    assert_eq!(r["steps"], 300, "{r}");
    assert_eq!(r["errors"], serde_json::json!({}), "{r}");
    assert!(r["server_cpu_us_per_step"].as_f64().unwrap() > 0.0, "{r}");
    assert!(
        r["old_actions_tested_per_step"].as_f64().unwrap() >= 0.0,
        "{r}"
    );
    assert_eq!(
        r["late_steps"],
        serde_json::Value::Null,
        "closed loop has no late steps"
    );

    // What it sent replays as a file workload.
    let bytes = std::fs::read(&saved).unwrap();
    let tensors = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let obs = tensors.tensor("obs").unwrap();
    assert_eq!(obs.shape()[1], 15);
    assert!(obs.shape()[0] >= 300, "{:?}", obs.shape());
    let replay = bench(&["--steps", "50", "--observations", saved.to_str().unwrap()]);
    assert_eq!(replay["workload"], "file", "{replay}");
    assert_eq!(replay["steps"], 50);

    // Open loop: each robot at 100 Hz for 1 s (a plain number of seconds).
    let r = bench(&[
        "--sessions",
        "2",
        "--duration",
        "1",
        "--rate-per-session",
        "100",
    ]);
    // 2 robots at 100 Hz for 1 s: the schedule's 200 steps.
    let steps = r["steps"].as_u64().unwrap();
    assert!((198..=202).contains(&steps), "{r}");
    assert_eq!(r["open_loop_rate"], 200.0, "{r}");
    let late = r["late_fraction"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&late), "{r}");
}

/// A `prac serve` on a toy policy (domain "toy", not one of prac's) for bench runs against
/// --server; killed when dropped.
struct ToyServer {
    child: std::process::Child,
    addr: String,
    _dir: tempfile::TempDir,
}

impl Drop for ToyServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn toy_server() -> ToyServer {
    use std::io::BufRead;
    let dir = tempfile::tempdir().unwrap();
    let manifest = prac::testing::test_manifest("toy", "toy", 3, 2, &[16], &[8]);
    prac::bundle::save(
        &prac::testing::random_policy(manifest, 1),
        &dir.path().join("toy.safetensors"),
    )
    .unwrap();
    let bin = std::path::Path::new(env!("CARGO_BIN_EXE_prac-bench")).with_file_name("prac");
    let mut child = Command::new(bin)
        .args(["serve", "--listen", "127.0.0.1:0", "--bundles"])
        .arg(dir.path())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let addr = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap()
        .to_string();
    ToyServer {
        child,
        addr,
        _dir: dir,
    }
}

#[test]
fn against_another_server_the_policy_defaults_and_bad_workloads_are_refused() {
    let server = toy_server();
    let url = format!("http://{}", server.addr);
    // The only policy it serves, over an http:// address; its domain is not prac's: model workload.
    let r = bench(&["--server", &url, "--steps", "40"]);
    assert_eq!(r["workload"], "model", "{r}");
    assert_eq!(r["steps"], 40, "{r}");

    let out = bench_output(&["--server", &url, "--workload", "sim", "--steps", "10"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--workload sim needs a policy of one of prac's domains (lander, hopper"),
        "{err}"
    );
    let out = bench_output(&["--server", &url, "--policy", "nope", "--steps", "10"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("it serves: toy"), "{err}");
    let out = bench_output(&[
        "--rate-per-session",
        "50",
        "--mode",
        "unary",
        "--steps",
        "10",
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--mode stream"));
}
