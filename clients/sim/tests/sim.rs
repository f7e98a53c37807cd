//! prac-sim against a real `prac serve` it starts itself (target/<profile>/prac, built by the
//! workspace's tests) on the shipped bundles.

use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn shipped_bundles() -> PathBuf {
    root().join("bundles")
}

fn sim(args: &[&str]) -> std::process::Output {
    sim_on(&shipped_bundles(), args)
}

fn sim_on(bundles: &Path, args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_prac-sim"))
        .arg("--bundles")
        .arg(bundles)
        .arg("--quiet")
        .args(args)
        .output()
        .unwrap()
}

/// `prac-sim play ARGS --json` on `bundles`, which must succeed; its episodes.
fn play_json(bundles: &Path, args: &[&str]) -> Vec<serde_json::Value> {
    let out = sim_on(bundles, &[&["play"], args, &["--json"]].concat());
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn play_accounts_the_forecast_as_the_server_reports_it() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("frame.png");
    let episodes = play_json(
        &shipped_bundles(),
        &[
            "--policy",
            "pendulum",
            "--epsilon-coef",
            "0.01",
            "--episodes",
            "3",
            "--seed",
            "5",
            "--render",
            png.to_str().unwrap(),
            "--render-step",
            "10",
        ],
    );
    assert_eq!(episodes.len(), 3);
    for e in &episodes {
        assert_eq!(e["steps"], 200);
        // f_t from each forecast's decided_at equals the server's f_t, and every kept action
        // was executed as committed one step earlier.
        assert_eq!(e["accounting_mismatches"], 0);
        assert_eq!(e["commitment_violations"], 0);
        let forecast = e["forecast"].as_f64().unwrap();
        assert!(forecast > 2.0 && forecast <= 32.0, "{e}");
        assert!(e["ret"].as_f64().unwrap() > -1000.0, "{e}");
    }
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));

    // eps = 0: a fresh decision at every step, forecast 1 except where the policy's plan was
    // kept because pi(s) itself passes the test with equality.
    let e = play_json(
        &shipped_bundles(),
        &["--policy", "pendulum", "--epsilon", "0", "--episodes", "1"],
    );
    assert!(e[0]["forecast"].as_f64().unwrap() < 2.0);

    let out = sim(&["play", "--policy", "nope"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no policy 'nope'"));
}

fn column(text: &str, name: &str) -> Vec<f64> {
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let i = header.iter().position(|h| *h == name).unwrap();
    lines
        .map(|l| l.split(',').nth(i).unwrap().parse().unwrap())
        .collect()
}

/// `prac-sim sweep --policy pendulum ARGS --out DIR`, which must succeed; its sweep.csv.
fn pendulum_sweep(dir: &Path, args: &[&str]) -> String {
    let mut all = vec!["sweep", "--policy", "pendulum"];
    all.extend_from_slice(args);
    all.extend_from_slice(&["--out", dir.to_str().unwrap()]);
    let out = sim(&all);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    std::fs::read_to_string(dir.join("sweep.csv")).unwrap()
}

#[test]
fn sweep_writes_sane_files_and_curves_draw() {
    let dir = tempfile::tempdir().unwrap();
    let csv = pendulum_sweep(dir.path(), &["--coefs", "0,0.003,0.01", "--episodes", "20"]);
    let (np, np_std) = (column(&csv, "np"), column(&csv, "np_std"));
    let forecast = column(&csv, "forecast");
    let bound = column(&csv, "bound");
    // NP at coefficient 0 is 1 within noise: V_pi comes from 20 other episodes, so allow three
    // standard errors of the difference of two 20-episode means.
    let se = np_std[0] * (2.0f64 / 20.0).sqrt();
    assert!(
        (np[0] - 1.0).abs() <= 3.0 * se + 0.02,
        "NP(0) = {} +- {}",
        np[0],
        np_std[0]
    );
    assert!(forecast[0] < forecast[2], "forecast {forecast:?}");
    assert!((forecast[1] + forecast[2]) / 2.0 >= forecast[0]);
    assert_eq!(bound[0], 1.0);
    // The bound is of the eps in force, which the server holds as an f32.
    assert!((bound[2] - 0.5).abs() < 1e-6, "1 - 0.01 / (1 - 0.98)");
    // The Lemma-1 bound holds in expectation here (the paper's claim).
    for k in 0..np.len() {
        assert!(
            np[k] >= bound[k] - 3.0 * np_std[k] / 20f64.sqrt(),
            "row {k}"
        );
    }
    for file in ["sweep.md", "sweep.png"] {
        assert!(
            dir.path().join(file).metadata().unwrap().len() > 100,
            "{file}"
        );
    }

    // Figure 4 from the shipped pendulum training curve.
    let curves = sim(&[
        "curves",
        "--csv",
        root()
            .join("runs/pendulum/pendulum.train.csv")
            .to_str()
            .unwrap(),
        "--normalize=-1237,-137",
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    assert!(
        curves.status.success(),
        "{}",
        String::from_utf8_lossy(&curves.stderr)
    );
    assert!(String::from_utf8_lossy(&curves.stdout).contains("pendulum: 60 episodes"));
    assert!(
        std::fs::read(dir.path().join("curves.png"))
            .unwrap()
            .starts_with(b"\x89PNG")
    );
    assert!(
        !dir.path().join("curves-seeds.png").exists(),
        "one seed has no mean across seeds"
    );

    // A second seed of the same setting (a shifted copy) adds the mean across seeds.
    let shipped = std::fs::read_to_string(root().join("runs/pendulum/pendulum.train.csv")).unwrap();
    let mut lines = shipped.lines();
    let header = lines.next().unwrap();
    let ret = header.split(',').position(|h| h == "return").unwrap();
    let mut shifted = format!("{header}\n");
    for line in lines {
        let mut fields: Vec<String> = line.split(',').map(str::to_string).collect();
        fields[ret] = (fields[ret].parse::<f64>().unwrap() + 100.0).to_string();
        shifted.push_str(&fields.join(","));
        shifted.push('\n');
    }
    let seed1 = dir.path().join("pendulum-seed1.train.csv");
    std::fs::write(&seed1, shifted).unwrap();
    let seeds = sim(&[
        "curves",
        "--csv",
        &format!(
            "{},{}",
            root().join("runs/pendulum/pendulum.train.csv").display(),
            seed1.display()
        ),
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&seeds.stdout);
    assert!(seeds.status.success(), "{stdout}");
    let summary = stdout
        .lines()
        .find(|l| l.starts_with("pendulum: 2 seeds"))
        .unwrap_or_else(|| panic!("no mean across seeds in {stdout}"));
    // The two seeds differ by 100 everywhere: their mean's std across seeds is 50.
    assert!(summary.contains("+- 50.000 across seeds"), "{summary}");
    assert!(
        std::fs::read(dir.path().join("curves-seeds.png"))
            .unwrap()
            .starts_with(b"\x89PNG")
    );
}

#[test]
fn play_drives_a_rapier_domain_with_an_untrained_lander_policy() {
    // Random weights of the SAC architecture for the lander's sizes: the client and server
    // plumbing on a physics domain, whatever the policy's quality.
    let dir = tempfile::tempdir().unwrap();
    let mut manifest = prac::testing::test_manifest(
        "lander-untrained",
        "lander",
        8,
        2,
        &[64, 64],
        &[64, 64, 64, 64],
    );
    manifest.provenance.trainer = "random init (prac-sim test)".into();
    let policy = prac::testing::random_policy(manifest, 11);
    prac::bundle::save(&policy, &dir.path().join("lander-untrained.safetensors")).unwrap();
    let episodes = play_json(
        dir.path(),
        &[
            "--policy",
            "lander-untrained",
            "--epsilon-coef",
            "0.01",
            "--episodes",
            "2",
        ],
    );
    for e in &episodes {
        let steps = e["steps"].as_u64().unwrap();
        assert!((1..=1000).contains(&steps), "{e}");
        assert_eq!(e["terminated"], steps < 1000, "{e}");
        assert!(
            e["distance"].is_null(),
            "the lander has no forward task: {e}"
        );
        assert_eq!(e["accounting_mismatches"], 0);
        assert_eq!(e["commitment_violations"], 0);
    }
}

#[test]
fn play_reports_how_far_the_shipped_cheetah_runs() {
    let episodes = play_json(
        &shipped_bundles(),
        &[
            "--policy",
            "cheetah",
            "--epsilon-coef",
            "0.005",
            "--episodes",
            "1",
        ],
    );
    let e = &episodes[0];
    assert_eq!(e["steps"], 1000);
    assert_eq!(e["terminated"], false);
    assert_eq!(e["commitment_violations"], 0);
    // Random actions go nowhere (-0.4 m); the bundle runs 33.0 m at eps 0 and 30.0 m at this
    // coefficient on the current physics (30.8 m in PyBullet's own HalfCheetah).
    let distance = e["distance"].as_f64().unwrap();
    assert!(distance > 25.0, "{e}");
}

#[test]
fn play_says_what_went_wrong() {
    // A render step the episode never reaches: an error, not a silent success.
    let dir = tempfile::tempdir().unwrap();
    let out = sim(&[
        "play",
        "--policy",
        "pendulum",
        "--episodes",
        "1",
        "--render-step",
        "100000",
        "--render",
        dir.path().join("p.png").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("before --render-step 100000"), "{err}");

    let out = sim(&["play", "--policy", "pendulum", "--episodes", "0"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--episodes must be >= 1"));

    // The local server's own words come through: a folder of bad bundles.
    std::fs::write(dir.path().join("broken.safetensors"), b"not a bundle").unwrap();
    let out = sim_on(
        dir.path(),
        &["play", "--policy", "broken", "--episodes", "1"],
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("the local server logged"), "{err}");
    assert!(err.contains("broken.safetensors"), "{err}");
    // And a missing folder.
    let out = sim_on(&dir.path().join("missing"), &["play", "--policy", "p"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot read bundle directory"), "{err}");
}

#[test]
fn plans_grow_and_stop_where_the_flags_say() {
    let forecasts = |extra: &[&str]| -> Vec<f64> {
        let args = [
            &[
                "--policy",
                "pendulum",
                "--epsilon-coef",
                "0.01",
                "--episodes",
                "2",
            ],
            extra,
        ]
        .concat();
        play_json(&shipped_bundles(), &args)
            .iter()
            .map(|e| e["forecast"].as_f64().unwrap())
            .collect()
    };
    // An action runs at most N - 1 steps after the step that decided it.
    let capped = forecasts(&["--max-horizon", "3"]);
    assert!(
        capped.iter().all(|&f| (1.0..=3.0).contains(&f)),
        "{capped:?}"
    );
    let free = forecasts(&[]);
    assert!(
        free.iter().sum::<f64>() > capped.iter().sum::<f64>(),
        "{free:?} {capped:?}"
    );

    let dir = tempfile::tempdir().unwrap();
    let out = sim(&[
        "sweep",
        "--policy",
        "pendulum",
        "--coefs",
        "0.01",
        "--episodes",
        "2",
        "--fixed",
        "6",
        "--max-horizon",
        "6",
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let md = std::fs::read_to_string(dir.path().join("sweep.md")).unwrap();
    assert!(
        md.contains("2 episodes per coefficient; plans: fixed 6, max horizon 6."),
        "{md}"
    );

    let out = sim(&["play", "--policy", "pendulum", "--grow", "0"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--grow must be >= 1"));
    let out = sim(&[
        "play", "--policy", "pendulum", "--grow", "2", "--fixed", "4",
    ]);
    assert!(
        !out.status.success(),
        "--grow and --fixed exclude each other"
    );
}

/// The pids of the processes whose parent is `parent` (from /proc).
#[cfg(target_os = "linux")]
fn children_of(parent: u32) -> Vec<u32> {
    let mut children = Vec::new();
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<u32>().ok())
        else {
            continue;
        };
        // /proc/PID/stat: "PID (COMM) STATE PPID ..."; COMM may hold spaces, so read after ')'.
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        let ppid = stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().nth(1))
            .and_then(|p| p.parse::<u32>().ok());
        if ppid == Some(parent) {
            children.push(pid);
        }
    }
    children
}

#[cfg(target_os = "linux")]
#[test]
fn a_killed_client_takes_its_local_server_with_it() {
    let out = tempfile::tempdir().unwrap();
    let mut client = Command::new(env!("CARGO_BIN_EXE_prac-sim"))
        .arg("--bundles")
        .arg(shipped_bundles())
        .args([
            "--quiet",
            "sweep",
            "--policy",
            "pendulum",
            "--episodes",
            "100000",
            "--out",
        ])
        .arg(out.path())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let started = std::time::Instant::now();
    // The server once it runs `prac serve` (not the fork before its exec)...
    let server = loop {
        let serving = children_of(client.id()).into_iter().find(|pid| {
            std::fs::read(format!("/proc/{pid}/cmdline"))
                .is_ok_and(|cmdline| cmdline.split(|&b| b == 0).any(|arg| arg == b"serve"))
        });
        if let Some(pid) = serving {
            break pid;
        }
        assert!(
            started.elapsed() < std::time::Duration::from_secs(60),
            "prac-sim started no server"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    // ...and past its ready line, which a server whose stdout reader is gone could not print.
    std::thread::sleep(std::time::Duration::from_secs(2));
    // Killed outright: no destructor runs in prac-sim.
    client.kill().unwrap();
    client.wait().unwrap();
    let killed = std::time::Instant::now();
    while std::path::Path::new(&format!("/proc/{server}")).exists()
        && std::fs::read_to_string(format!("/proc/{server}/stat")).is_ok_and(|stat| {
            !stat
                .rsplit_once(')')
                .is_some_and(|(_, r)| r.trim_start().starts_with('Z'))
        })
    {
        assert!(
            killed.elapsed() < std::time::Duration::from_secs(20),
            "the local server {server} outlived its client"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

#[test]
fn a_sweep_reports_the_eps_a_guard_holds_it_to() {
    let dir = tempfile::tempdir().unwrap();
    let csv = pendulum_sweep(
        dir.path(),
        &[
            "--coefs",
            "0.01",
            "--episodes",
            "5",
            "--max-epsilon-coef",
            "0.002",
        ],
    );
    // Asked: 0.01 x the sweep's V_pi - V_rand, a bound of 0.5. Held to 0.002 x the bundle's, its
    // bound is near 1 - 0.002 / (1 - 0.98) = 0.9 (the two ranges are measured apart).
    let bound = column(&csv, "bound")[0];
    assert!((0.85..0.95).contains(&bound), "bound {bound}");
    let md = std::fs::read_to_string(dir.path().join("sweep.md")).unwrap();
    assert!(md.contains("eps coefficient at most 0.002"), "{md}");
}
