use std::sync::Arc;

use tract_onnx::prelude::*;

use super::*;
use crate::plan::Networks;
use crate::policy::{Evaluator, ObsScale};

/// States the bundle's own policy visits on its domain (deterministic, seed 0): what a robot
/// would feed the exported files. Falls back to random states for a domain prac lacks.
fn visited_states(policy: &Arc<Policy>, count: usize) -> Vec<f32> {
    let od = policy.obs_dim();
    let Some(mut env) = crate::domains::make(&policy.manifest.domain) else {
        return (0..count * od)
            .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
            .collect();
    };
    let mut evaluator = Evaluator::new(policy.clone());
    let (mut obs, mut squashed, mut action) = (
        vec![0.0; od],
        vec![0.0; policy.act_dim()],
        vec![0.0; policy.act_dim()],
    );
    env.reset(0, &mut obs).unwrap();
    let mut states = Vec::with_capacity(count * od);
    let noise = vec![0.0; policy.act_dim()];
    for episode in 1.. {
        while states.len() < count * od {
            states.extend_from_slice(&obs);
            evaluator.act(&obs, &noise, &mut squashed);
            policy.unscale_action(&squashed, &mut action);
            let t = env.step(&action, &mut obs).unwrap();
            if t.terminated || t.truncated {
                env.reset(episode, &mut obs).unwrap();
                break;
            }
        }
        if states.len() >= count * od {
            break;
        }
    }
    states
}

/// Runs an exported file on `inputs` ([rows, width] each) with tract; its outputs in order.
fn run_tract(bytes: &[u8], inputs: &[(&[f32], usize)]) -> Vec<Vec<f32>> {
    let mut model = tract_onnx::onnx()
        .model_for_read(&mut std::io::Cursor::new(bytes))
        .unwrap();
    let rows = inputs[0].0.len() / inputs[0].1;
    for (k, (_, width)) in inputs.iter().enumerate() {
        model
            .set_input_fact(k, f32::fact([rows, *width]).into())
            .unwrap();
    }
    let runnable = model.into_optimized().unwrap().into_runnable().unwrap();
    let tensors: TVec<TValue> = inputs
        .iter()
        .map(|(data, width)| {
            Tensor::from_shape(&[rows, *width], data)
                .unwrap()
                .into_tvalue()
        })
        .collect();
    runnable
        .run(tensors)
        .unwrap()
        .iter()
        .map(|t| {
            t.to_plain_array_view::<f32>()
                .unwrap()
                .iter()
                .copied()
                .collect()
        })
        .collect()
}

/// The largest difference between `ours` and `theirs`, relative to the values' size.
fn largest_difference(ours: &[f32], theirs: &[f32]) -> f32 {
    assert_eq!(ours.len(), theirs.len());
    ours.iter()
        .zip(theirs)
        .map(|(a, b)| (a - b).abs() / (1.0 + a.abs()))
        .fold(0.0, f32::max)
}

/// The parity of every exported network with prac's forward passes on `policy`'s states.
fn check_parity(policy: Policy, label: &str) {
    let policy = Arc::new(policy);
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("policy.safetensors");
    crate::bundle::save(&policy, &bundle).unwrap();
    let out = dir.path().join("onnx");
    let contract = export_onnx(&bundle, &out).unwrap();
    let (od, ad) = (policy.obs_dim(), policy.act_dim());
    let rows = 64;
    let states = visited_states(&policy, rows);
    let read = |file: &ExportedFile| std::fs::read(out.join(&file.path)).unwrap();

    // Actor: the deterministic action in the bounds.
    let mut evaluator = Evaluator::with_capacity(policy.clone(), rows);
    let mut squashed = vec![0.0; rows * ad];
    evaluator.act(&states, &vec![0.0; rows * ad], &mut squashed);
    let mut ours = vec![0.0; rows * ad];
    for (s, a) in squashed.chunks(ad).zip(ours.chunks_mut(ad)) {
        policy.unscale_action(s, a);
    }
    let theirs = run_tract(&read(&contract.actor), &[(&states, od)]);
    let mut report = vec![("actor".to_string(), largest_difference(&ours, &theirs[0]))];

    // Critics, on the policy's actions and on others nearby, as Replan asks them. The server's
    // critics see actions in [-1, 1]; the files take them in the bounds and map them back.
    let mut actions = ours.clone();
    for (i, a) in actions.iter_mut().enumerate() {
        let k = i % ad;
        let (lo, hi) = (
            policy.manifest.action_low[k],
            policy.manifest.action_high[k],
        );
        *a = (*a + 0.1 * (hi - lo) * ((i % 7) as f32 / 7.0 - 0.5)).clamp(lo, hi);
    }
    let mut back = vec![0.0; rows * ad];
    for (a, s) in actions.chunks(ad).zip(back.chunks_mut(ad)) {
        policy.scale_action(a, s);
    }
    let mut critic_input = Vec::new();
    let normalized = match &policy.manifest.obs_normalization {
        Some(n) => {
            let mut out = Vec::new();
            ObsScale::new(n).extend_normalized(&states, &mut out);
            out
        }
        None => states.clone(),
    };
    for k in 0..rows {
        critic_input.extend_from_slice(&normalized[k * od..(k + 1) * od]);
        critic_input.extend_from_slice(&back[k * ad..(k + 1) * ad]);
    }
    for (c, file) in contract.critics.iter().enumerate() {
        let critic = &policy.critics[c];
        let ours = critic
            .forward_rows(&critic_input, &mut critic.scratch())
            .to_vec();
        let theirs = run_tract(&read(file), &[(&states, od), (&actions, ad)]);
        report.push((format!("critic_{c}"), largest_difference(&ours, &theirs[0])));
    }

    // Model: the next observation, inside the bounds.
    if let Some(file) = &contract.model {
        let mut ours = vec![0.0; rows * od];
        evaluator.predict_next(&states, &back, &mut ours);
        let theirs = run_tract(&read(file), &[(&states, od), (&actions, ad)]);
        report.push(("model".into(), largest_difference(&ours, &theirs[0])));
    }
    for (network, difference) in &report {
        println!("{label}: {network}: largest relative difference {difference:.2e}");
        assert!(*difference < 1e-4, "{label} {network}: {difference}");
    }
}

#[test]
fn exported_networks_match_prac_on_the_toy_policy() {
    check_parity(crate::testing::toy_policy("toy", 1), "toy");
}

#[test]
fn exported_networks_match_prac_on_every_shipped_bundle() {
    let shipped = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("bundles");
    let mut bundles: Vec<_> = std::fs::read_dir(&shipped)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "safetensors"))
        .collect();
    bundles.sort();
    assert!(bundles.len() >= 7, "{bundles:?}");
    for path in bundles {
        let policy = crate::bundle::load(&path).unwrap();
        let label = path.file_stem().unwrap().to_string_lossy().to_string();
        check_parity(policy, &label);
    }
}

#[test]
fn a_truncated_bundle_or_an_existing_folder_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("toy.safetensors");
    crate::bundle::save(&crate::testing::toy_policy("toy", 1), &bundle).unwrap();
    let bytes = std::fs::read(&bundle).unwrap();
    let truncated = dir.path().join("truncated.safetensors");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let out = dir.path().join("out");
    let err = export_onnx(&truncated, &out).unwrap_err();
    assert!(format!("{err:#}").contains("cannot export"), "{err:#}");
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    assert_eq!(left.len(), 2, "nothing written: {left:?}");

    std::fs::create_dir(&out).unwrap();
    let err = export_onnx(&bundle, &out).unwrap_err();
    assert!(format!("{err:#}").contains("already exists"), "{err:#}");
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 0);
}

#[test]
fn the_contract_names_the_files_and_what_replan_needs() {
    let dir = tempfile::tempdir().unwrap();
    let bundle =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("bundles/hopper.safetensors");
    let policy = crate::bundle::load(&bundle).unwrap();
    let out = dir.path().join("hopper");
    export_onnx(&bundle, &out).unwrap();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("prac.json")).unwrap()).unwrap();
    assert_eq!(json["content_hash"], policy.content_hash.as_str());
    assert_eq!(json["opset"], OPSET);
    assert_eq!(json["observation"]["size"], 15);
    assert_eq!(json["action"]["low"].as_array().unwrap().len(), 3);
    assert!(json["control_period"].as_f64().unwrap() > 0.0);
    assert_eq!(
        json["critics"].as_array().unwrap().len(),
        policy.critics.len()
    );
    for file in [&json["actor"], &json["model"], &json["critics"][0]] {
        let path = out.join(file["path"].as_str().unwrap());
        let digest = format!(
            "sha256:{}",
            hex::encode(Sha256::digest(std::fs::read(path).unwrap()))
        );
        assert_eq!(file["sha256"], digest.as_str());
    }
}
