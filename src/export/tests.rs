use tract_onnx::prelude::*;

use super::*;

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

/// The parity of every exported network, run by tract, with prac's forward passes on `policy`:
/// the reference file the export writes holds prac's outputs on states its policy visits.
fn check_parity(policy: Policy, label: &str) {
    let dir = tempfile::tempdir().unwrap();
    let bundle = dir.path().join("policy.safetensors");
    crate::bundle::save(&policy, &bundle).unwrap();
    let out = dir.path().join("onnx");
    let contract = export_onnx(&bundle, &out).unwrap();
    let bytes = std::fs::read(out.join(&contract.reference)).unwrap();
    let reference = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let tensor = |name: &str| -> (Vec<f32>, usize) {
        let view = reference.tensor(name).unwrap();
        let values = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        (values, view.shape()[1])
    };
    let (states, od) = tensor("observation");
    let (actions, ad) = tensor("action");
    assert_eq!((od, ad), (policy.obs_dim(), policy.act_dim()));
    assert_eq!(states.len(), REFERENCE_ROWS * od);
    let mut files = vec![&contract.actor];
    files.extend(&contract.critics);
    files.extend(&contract.model);
    for file in files {
        let bytes = std::fs::read(out.join(&file.path)).unwrap();
        let inputs: Vec<(&[f32], usize)> = file
            .inputs
            .iter()
            .map(|name| match name.as_str() {
                "observation" => (states.as_slice(), od),
                _ => (actions.as_slice(), ad),
            })
            .collect();
        let outputs = run_tract(&bytes, &inputs);
        let stem = file.path.trim_end_matches(".onnx");
        for (name, theirs) in file.outputs.iter().zip(outputs) {
            let (ours, _) = tensor(&format!("{stem}.{name}"));
            let difference = largest_difference(&ours, &theirs);
            println!("{label}: {stem}.{name}: largest relative difference {difference:.2e}");
            assert!(difference < 1e-4, "{label} {stem}.{name}: {difference}");
        }
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
    let observation = json["features"]["observation"].as_array().unwrap();
    assert_eq!(observation.len(), 15);
    assert_eq!(observation[8]["name"], "thigh_position");
    assert_eq!(json["features"]["action"][2]["name"], "foot_torque");
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
