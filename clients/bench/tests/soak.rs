//! A short prac-soak against a real prac serve it starts itself: session churn with bad requests
//! mixed in and stalled clients; every answer must be the expected one, and memory is sampled.

use std::process::Command;

#[test]
fn a_short_soak_gets_only_expected_answers() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("soak.json");
    let out = Command::new(env!("CARGO_BIN_EXE_prac-soak"))
        .args(["--duration", "6s", "--sample-every", "1s", "--clients", "4"])
        .args(["--bad-fraction", "0.2", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(r["unexpected"], serde_json::json!({}), "{r}");
    assert!(r["good_requests"].as_u64().unwrap() > 0, "{r}");
    assert!(r["sessions_opened"].as_u64().unwrap() > 4, "{r}");
    // Every kind of bad request came up and got its status.
    let refused = r["refused"].as_object().unwrap();
    for kind in [
        "wrong obs length: InvalidArgument",
        "NaN observation: InvalidArgument",
        "unknown session: NotFound",
        "open with bad options: InvalidArgument",
        "open unknown policy: NotFound",
    ] {
        assert!(
            refused.get(kind).is_some_and(|n| n.as_u64().unwrap() > 0),
            "{kind}: {r}"
        );
    }
    let memory = r["memory"].as_array().unwrap();
    assert!(memory.len() >= 5, "{r}");
    assert!(memory.iter().all(|s| s["rss_kib"].as_u64().unwrap() > 0));
}
