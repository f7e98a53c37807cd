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
    let throughput = r["throughput"].as_f64().unwrap();
    assert!((150.0..=250.0).contains(&throughput), "{r}");
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
