//! A short prac-flood against a prac serve it starts itself under a small memory budget: the
//! flood is shed with clean statuses, the probe is answered throughout, the server stays up.

use std::process::Command;

#[test]
fn a_short_flood_is_shed_cleanly_and_the_probe_answered() {
    let dir = tempfile::tempdir().unwrap();
    let policy = prac::testing::random_policy(prac::testing::hopper_sized_manifest(), 7);
    prac::bundle::save(&policy, &dir.path().join("hopper-bench.safetensors")).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_prac-flood"))
        .args(["--policy", "hopper-bench", "--bundles"])
        .arg(dir.path())
        .args(["--connections", "24", "--calls", "250", "--duration", "4s"])
        .args(["--watchers", "2000", "--settle", "3s"])
        .arg("--server-arg=--max-memory=48Mi")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let clean = [
        "ResourceExhausted",
        "refused by GOAWAY",
        "connection closed",
    ];
    for ended in ["calls_ended", "watchers_ended"] {
        let codes = r[ended]["by_code"].as_object().unwrap();
        assert!(codes.keys().all(|c| clean.contains(&c.as_str())), "{r}");
    }
    assert!(
        r["calls_ended"]["by_code"]["ResourceExhausted"]
            .as_u64()
            .unwrap()
            > 0,
        "{r}"
    );
    assert_eq!(r["probes_failed"], 0, "{r}");
    assert!(r["probes"].as_u64().unwrap() > 0, "{r}");
    assert_eq!(r["server_alive_after"], true, "{r}");
    // Under the budget throughout, and back near where it started.
    let (before, max, after) = (
        r["server_rss_before_kib"].as_u64().unwrap(),
        r["server_rss_max_kib"].as_u64().unwrap(),
        r["server_rss_after_kib"].as_u64().unwrap(),
    );
    assert!(max < 48 * 1024, "{r}");
    assert!(after < before + 8 * 1024, "{r}");
}
