//! `prac inspect` on bundles written by test code.

mod common;

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
