use super::*;
use crate::plan::Networks;
use crate::policy::Evaluator;
use crate::testing::test_manifest;
use std::sync::Arc;

fn small_policy() -> Policy {
    crate::testing::random_policy(test_manifest("small", "toy", 4, 2, &[8, 8], &[6, 6]), 7)
}

fn path() -> PathBuf {
    PathBuf::from("bundles/small.safetensors")
}

/// Rebuilds a bundle from tensors and a manifest, so tests can corrupt either.
fn rebuild(tensors: &[NamedTensor], manifest_json: Option<&str>) -> Vec<u8> {
    let data: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
        .iter()
        .map(|(n, s, v)| {
            (
                n.clone(),
                s.clone(),
                v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            )
        })
        .collect();
    let views: Vec<(String, TensorView)> = data
        .iter()
        .map(|(n, s, d)| {
            (
                n.clone(),
                TensorView::new(Dtype::F32, s.clone(), d).unwrap(),
            )
        })
        .collect();
    let metadata =
        manifest_json.map(|m| HashMap::from([(MANIFEST_KEY.to_string(), m.to_string())]));
    safetensors::serialize(views, metadata).unwrap()
}

fn load_error(bytes: &[u8]) -> BundleError {
    from_bytes(bytes, &path()).expect_err("bundle must be rejected")
}

#[test]
fn round_trip_preserves_every_output() {
    let policy = small_policy();
    let loaded = from_bytes(&to_bytes(&policy).unwrap(), &path()).unwrap();
    assert_eq!(loaded.manifest, policy.manifest);
    assert!(loaded.content_hash.starts_with("sha256:"));
    let (mut a, mut b) = (
        Evaluator::new(Arc::new(policy)),
        Evaluator::new(Arc::new(loaded)),
    );
    let obs = [0.1, -0.3, 0.5, 0.9];
    let (mut act_a, mut act_b) = ([0.0; 2], [0.0; 2]);
    a.act(&obs, &[0.3, -1.0], &mut act_a);
    b.act(&obs, &[0.3, -1.0], &mut act_b);
    assert_eq!(act_a, act_b);
    let (mut qa, mut qb) = ([0.0], [0.0]);
    a.q_pair(&obs, &act_a, &[0.5, 0.5], &mut qa, &mut qb, None);
    let (mut ra, mut rb) = ([0.0], [0.0]);
    b.q_pair(&obs, &act_b, &[0.5, 0.5], &mut ra, &mut rb, None);
    assert_eq!((qa, qb), (ra, rb));
    let (mut na, mut nb) = ([0.0; 4], [0.0; 4]);
    a.predict_next(&obs, &act_a, &mut na);
    b.predict_next(&obs, &act_b, &mut nb);
    assert_eq!(na, nb);
}

#[test]
fn tensor_names_follow_sb3() {
    let names: Vec<String> = tensors(&small_policy()).into_iter().map(|t| t.0).collect();
    for expected in [
        "actor.latent_pi.0.weight",
        "actor.latent_pi.2.bias",
        "actor.mu.weight",
        "actor.log_std.bias",
        "critic.qf0.0.weight",
        "critic.qf1.4.bias",
        "model.net.0.weight",
        "model.net.4.bias",
    ] {
        assert!(
            names.iter().any(|n| n == expected),
            "{expected} missing from {names:?}"
        );
    }
    let shapes: HashMap<String, Vec<usize>> = tensors(&small_policy())
        .into_iter()
        .map(|t| (t.0, t.1))
        .collect();
    // PyTorch layout: [out, in].
    assert_eq!(shapes["actor.latent_pi.0.weight"], vec![8, 4]);
    assert_eq!(shapes["critic.qf0.0.weight"], vec![8, 6]);
    assert_eq!(shapes["critic.qf0.4.weight"], vec![1, 8]);
    assert_eq!(shapes["model.net.4.weight"], vec![4, 6]);
}

/// The small policy with a layer norm after each of its critics' hidden layers.
fn layer_norm_policy() -> Policy {
    let mut policy = small_policy();
    policy.manifest.format_version = crate::manifest::FORMAT_VERSION_CRITIC_NORMS;
    policy.manifest.critic.layer_norm = true;
    policy.critics = policy
        .critics
        .iter()
        .map(|c| {
            let norms = c.layers()[..c.layers().len() - 1]
                .iter()
                .enumerate()
                .map(|(i, d)| {
                    let w = d.output_dim();
                    let scale = (0..w).map(|k| 0.5 + 0.1 * (k + i) as f32).collect();
                    let shift = (0..w).map(|k| 0.05 * k as f32 - 0.2).collect();
                    LayerNorm::new(scale, shift).unwrap()
                })
                .collect();
            c.clone().with_layer_norms(norms).unwrap()
        })
        .collect();
    policy
}

#[test]
fn layer_norm_critics_round_trip_in_pytorchs_sequential_layout() {
    let policy = layer_norm_policy();
    let named = tensors(&policy);
    let shapes: HashMap<&str, &Vec<usize>> = named.iter().map(|t| (t.0.as_str(), &t.1)).collect();
    // Linear, LayerNorm, ReLU, Linear, LayerNorm, ReLU, Linear.
    assert_eq!(shapes["critic.qf0.0.weight"], &vec![8, 6]);
    assert_eq!(shapes["critic.qf0.1.weight"], &vec![8]);
    assert_eq!(shapes["critic.qf1.4.bias"], &vec![8]);
    assert_eq!(shapes["critic.qf1.6.weight"], &vec![1, 8]);
    assert!(!shapes.contains_key("critic.qf0.2.weight"));
    let loaded = from_bytes(&to_bytes(&policy).unwrap(), &path()).unwrap();
    assert_eq!(loaded.manifest, policy.manifest);
    let input = [0.1, -0.3, 0.5, 0.9, 0.2, -0.7];
    for (ours, theirs) in policy.critics.iter().zip(&loaded.critics) {
        assert_eq!(theirs.norms(), ours.norms());
        let a = ours.forward_rows(&input, &mut ours.scratch())[0];
        let b = theirs.forward_rows(&input, &mut theirs.scratch())[0];
        assert_eq!(a, b);
    }
    // The norms change what the critics say (the test compares different networks).
    let plain = small_policy();
    let q = plain.critics[0].forward_rows(&input, &mut plain.critics[0].scratch())[0];
    let normed = policy.critics[0].forward_rows(&input, &mut policy.critics[0].scratch())[0];
    assert_ne!(q, normed);
    // Bundles without norms keep their manifest as it was: no `layer_norm` key.
    let json = serde_json::to_string(&small_policy().manifest).unwrap();
    assert!(!json.contains("layer_norm"), "{json}");

    // A manifest that claims norms needs version 3, and then names the first tensor it lacks.
    let plain = small_policy();
    let mut manifest = plain.manifest.clone();
    manifest.critic.layer_norm = true;
    let json = serde_json::to_string(&manifest).unwrap();
    let e = load_error(&rebuild(&tensors(&plain), Some(&json)));
    assert_eq!(e.field, "manifest.critic.layer_norm");
    assert!(e.reason.contains("needs format_version 3"), "{e}");
    manifest.format_version = crate::manifest::FORMAT_VERSION_CRITIC_NORMS;
    let json = serde_json::to_string(&manifest).unwrap();
    let e = load_error(&rebuild(&tensors(&plain), Some(&json)));
    assert_eq!(e.field, "critic.qf0.1.weight");
    assert!(e.reason.contains("missing"), "{e}");
}

#[test]
fn a_missing_tensor_is_named() {
    let policy = small_policy();
    let json = serde_json::to_string(&policy.manifest).unwrap();
    let tensors: Vec<_> = tensors(&policy)
        .into_iter()
        .filter(|t| t.0 != "critic.qf1.2.weight")
        .collect();
    let e = load_error(&rebuild(&tensors, Some(&json)));
    assert_eq!(e.field, "critic.qf1.2.weight");
    assert!(e.reason.contains("missing"), "{e}");
    assert!(
        e.to_string()
            .starts_with("bundles/small.safetensors: critic.qf1.2.weight")
    );
}

#[test]
fn a_wrong_shape_is_named_with_both_shapes() {
    let policy = small_policy();
    let json = serde_json::to_string(&policy.manifest).unwrap();
    let mut tensors = tensors(&policy);
    let t = tensors
        .iter_mut()
        .find(|t| t.0 == "actor.mu.weight")
        .unwrap();
    t.1 = vec![2, 7];
    t.2.truncate(14);
    let e = load_error(&rebuild(&tensors, Some(&json)));
    assert_eq!(e.field, "actor.mu.weight");
    assert!(
        e.reason.contains("[2, 7]") && e.reason.contains("[2, 8]"),
        "{e}"
    );
}

#[test]
fn a_non_finite_weight_is_named() {
    let policy = small_policy();
    let json = serde_json::to_string(&policy.manifest).unwrap();
    let mut tensors = tensors(&policy);
    tensors
        .iter_mut()
        .find(|t| t.0 == "model.net.2.bias")
        .unwrap()
        .2[3] = f32::NAN;
    let e = load_error(&rebuild(&tensors, Some(&json)));
    assert_eq!(e.field, "model.net.2.bias");
    assert!(e.reason.contains("element 3"), "{e}");
}

#[test]
fn manifest_problems_are_named() {
    let policy = small_policy();
    let tensors = tensors(&policy);
    let e = load_error(&rebuild(&tensors, None));
    assert_eq!(e.field, "__metadata__.manifest");
    let e = load_error(&rebuild(&tensors, Some("{not json")));
    assert!(e.reason.contains("invalid manifest JSON"), "{e}");

    type Corruption = (fn(&mut Manifest), &'static str);
    let cases: Vec<Corruption> = vec![
        (|m| m.format_version = 9, "manifest.format_version"),
        (|m| m.obs_dim = 0, "manifest.obs_dim"),
        (|m| m.action_high = vec![1.0], "manifest.action_high"),
        (|m| m.action_low[1] = 2.0, "manifest.action_low[1]"),
        (|m| m.gamma = 1.5, "manifest.gamma"),
        (|m| m.critic.n_critics = 0, "manifest.critic.n_critics"),
        (
            |m| {
                m.action_low = vec![-3e38; 2];
                m.action_high = vec![3e38; 2];
            },
            "manifest.action_high[0]",
        ),
        (
            |m| {
                m.value_scale = Some(ValueScale {
                    v_pi: 1.7e308,
                    v_rand: -1.7e308,
                })
            },
            "manifest.value_scale",
        ),
        (
            |m| m.model.as_mut().unwrap().normalization.delta_std[2] = 0.0,
            "manifest.model.normalization.delta_std[2]",
        ),
        (
            |m| m.model.as_mut().unwrap().normalization.obs_mean.push(0.0),
            "manifest.model.normalization.obs_mean",
        ),
    ];
    for (corrupt, field) in cases {
        let mut manifest = policy.manifest.clone();
        corrupt(&mut manifest);
        let json = serde_json::to_string(&manifest).unwrap();
        let e = load_error(&rebuild(&tensors, Some(&json)));
        assert_eq!(e.field, field, "{e}");
    }
    // A manifest whose dimensions disagree with the tensors: the tensor is named.
    let mut manifest = policy.manifest.clone();
    manifest.actor.hidden = vec![8, 9];
    let e = load_error(&rebuild(
        &tensors,
        Some(&serde_json::to_string(&manifest).unwrap()),
    ));
    assert_eq!(e.field, "actor.latent_pi.2.weight");
}

#[test]
fn truncated_and_garbage_files_are_rejected() {
    let bytes = to_bytes(&small_policy()).unwrap();
    for cut in [0, 7, 8, 100, bytes.len() / 2, bytes.len() - 1] {
        let e = load_error(&bytes[..cut]);
        assert!(e.field.starts_with("safetensors"), "cut {cut}: {e}");
    }
    let e = load_error(b"\xff\xff\xff\xff\xff\xff\xff\x7fgarbage");
    assert!(e.field.starts_with("safetensors"), "{e}");
}

#[test]
fn a_wrong_dtype_is_named() {
    let policy = small_policy();
    let json = serde_json::to_string(&policy.manifest).unwrap();
    let tensors = tensors(&policy);
    let data: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
        .iter()
        .map(|(n, s, v)| {
            let bytes = if n == "actor.mu.bias" {
                v.iter().flat_map(|x| (*x as f64).to_le_bytes()).collect()
            } else {
                v.iter().flat_map(|x| x.to_le_bytes()).collect()
            };
            (n.clone(), s.clone(), bytes)
        })
        .collect();
    let views: Vec<(String, TensorView)> = data
        .iter()
        .map(|(n, s, d)| {
            let dtype = if n == "actor.mu.bias" {
                Dtype::F64
            } else {
                Dtype::F32
            };
            (n.clone(), TensorView::new(dtype, s.clone(), d).unwrap())
        })
        .collect();
    let bytes = safetensors::serialize(
        views,
        Some(HashMap::from([(MANIFEST_KEY.to_string(), json)])),
    )
    .unwrap();
    let e = load_error(&bytes);
    assert_eq!(e.field, "actor.mu.bias");
    assert!(e.reason.contains("F64"), "{e}");
}

#[test]
fn save_and_load_a_file() {
    let dir = std::env::temp_dir().join(format!("prac-bundle-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("small.safetensors");
    save(&small_policy(), &file).unwrap();
    let loaded = load(&file).unwrap();
    assert_eq!(loaded.manifest.name, "small");
    let e = load(&dir.join("absent.safetensors")).unwrap_err();
    assert_eq!(e.field, "file");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_bundle_without_a_model_loads_and_cannot_imagine() {
    let mut policy = small_policy();
    policy.manifest.model = None;
    policy.model = None;
    let bytes = to_bytes(&policy).unwrap();
    let loaded = from_bytes(&bytes, &path()).unwrap();
    assert!(loaded.model.is_none());
    assert!(!tensors(&loaded).iter().any(|t| t.0.starts_with("model.")));
    let mut eval = Evaluator::new(Arc::new(loaded));
    let mut next = [0.0; 4];
    eval.predict_next(&[0.0; 4], &[0.0; 2], &mut next);
    assert!(next.iter().all(|v| v.is_nan()));
}

#[test]
fn sizes_a_manifest_declares_are_bounded_by_the_tensors_present() {
    let policy = small_policy();
    let tensors = tensors(&policy);
    // These aborted the process (a 40 GB allocation) or panicked (capacity overflow).
    for n_critics in [3, 1_000_000_000, 1 << 62, usize::MAX] {
        let mut manifest = policy.manifest.clone();
        manifest.critic.n_critics = n_critics;
        let json = serde_json::to_string(&manifest).unwrap();
        let e = load_error(&rebuild(&tensors, Some(&json)));
        assert_eq!(e.field, "critic.qf2.0.weight", "{n_critics}: {e}");
        assert!(e.reason.contains("missing tensor"), "{e}");
    }
    // Wider layers than the tensors hold: refused by shape, before any allocation.
    let mut manifest = policy.manifest.clone();
    manifest.critic.hidden = vec![1 << 40, 1 << 40];
    let e = load_error(&rebuild(
        &tensors,
        Some(&serde_json::to_string(&manifest).unwrap()),
    ));
    assert_eq!(e.field, "critic.qf0.0.weight", "{e}");
}

#[test]
fn tensors_the_manifest_does_not_name_are_refused() {
    let policy = small_policy();
    let mut tensors = tensors(&policy);
    tensors.push(("padding".into(), vec![4], vec![0.0; 4]));
    let json = serde_json::to_string(&policy.manifest).unwrap();
    let e = load_error(&rebuild(&tensors, Some(&json)));
    assert_eq!(e.field, "padding");
    assert!(e.reason.contains("unexpected tensor"), "{e}");
}

/// Resident memory of this process, in bytes.
fn resident_bytes() -> u64 {
    let statm = std::fs::read_to_string("/proc/self/statm").unwrap();
    let pages: u64 = statm.split_whitespace().nth(1).unwrap().parse().unwrap();
    pages * 4096
}

#[test]
fn a_file_is_checked_by_its_header_before_it_is_read() {
    let dir = tempfile::tempdir().unwrap();
    // A 1 GiB sparse file (the size limit): all zeros, so its header length is 0.
    let sparse = dir.path().join("sparse.safetensors");
    std::fs::File::create(&sparse)
        .unwrap()
        .set_len(MAX_BUNDLE_BYTES)
        .unwrap();
    let before = resident_bytes();
    let e = load(&sparse).unwrap_err();
    assert_eq!(e.field, "safetensors header", "{e}");
    let grown = resident_bytes().saturating_sub(before);
    assert!(
        grown < 64 << 20,
        "loading grew the process by {grown} bytes"
    );

    // A real bundle followed by junk: the header says where the tensors end.
    let padded = dir.path().join("padded.safetensors");
    let mut bytes = to_bytes(&small_policy()).unwrap();
    let real = bytes.len();
    bytes.resize(real + 4096, 0);
    std::fs::write(&padded, &bytes).unwrap();
    let e = load(&padded).unwrap_err();
    assert_eq!(e.field, "safetensors header", "{e}");
    assert!(
        e.reason.contains(&format!(
            "end at byte {real} but the file has {}",
            real + 4096
        )),
        "{e}"
    );

    // A tensor whose offsets would overflow the file position.
    let huge = dir.path().join("huge-offsets.safetensors");
    let header = br#"{"t":{"dtype":"F32","shape":[1],"data_offsets":[0,18446744073709551615]}}"#;
    let mut bytes_huge = (header.len() as u64).to_le_bytes().to_vec();
    bytes_huge.extend_from_slice(header);
    std::fs::write(&huge, &bytes_huge).unwrap();
    let e = load(&huge).unwrap_err();
    assert!(e.reason.contains("past any file"), "{e}");

    // A header longer than the file.
    let long = dir.path().join("long.safetensors");
    std::fs::write(&long, 1_000_000u64.to_le_bytes()).unwrap();
    assert_eq!(load(&long).unwrap_err().field, "safetensors header");

    // The same checks pass a good file.
    let good = dir.path().join("good.safetensors");
    std::fs::write(&good, &bytes[..real]).unwrap();
    assert_eq!(load(&good).unwrap().manifest.name, "small");
}

/// The small policy as an actor without a Gaussian head (format 2).
fn without_log_std(kind: crate::manifest::ActorKind, mean_clip: Option<f32>) -> Policy {
    let mut policy = small_policy();
    policy.manifest.format_version = crate::manifest::FORMAT_VERSION_ACTOR_KINDS;
    policy.manifest.actor.kind = kind;
    policy.manifest.actor.mean_clip = mean_clip;
    policy.actor.log_std = None;
    policy.actor.mean_clip = mean_clip.unwrap_or(f32::INFINITY);
    policy
}

#[test]
fn actors_without_a_gaussian_head_act_tanh_of_the_clipped_mean_whatever_the_noise() {
    use crate::manifest::ActorKind;
    let obs = [0.4, -2.0, 1.5, 0.9];
    for (kind, clip) in [
        (ActorKind::Deterministic, None),
        (ActorKind::GaussianSde, Some(0.05)),
        (ActorKind::GaussianSde, None),
    ] {
        let policy = without_log_std(kind, clip);
        let bytes = to_bytes(&policy).unwrap();
        let loaded = from_bytes(&bytes, &path()).unwrap();
        assert_eq!(loaded.manifest, policy.manifest);
        assert!(loaded.actor.log_std.is_none() && !loaded.actor.samples());
        let names = SafeTensors::deserialize(&bytes).unwrap().names().len();
        assert_eq!(
            names,
            tensors(&small_policy()).len() - 2,
            "no log_std tensors"
        );
        let mut latent_scratch = loaded.actor.trunk.scratch_for(1);
        let latent = loaded
            .actor
            .trunk
            .forward_rows(&obs, &mut latent_scratch)
            .to_vec();
        let mut mu = [0.0; 2];
        loaded.actor.mu.forward_rows(&latent, &mut mu);
        let limit = clip.unwrap_or(f32::INFINITY);
        let expected = mu.map(|m| m.clamp(-limit, limit).tanh());
        let mut evaluator = Evaluator::new(Arc::new(loaded));
        for noise in [[0.0, 0.0], [2.5, -1.0]] {
            let mut action = [0.0; 2];
            evaluator.act(&obs, &noise, &mut action);
            assert_eq!(action, expected, "{kind:?}");
        }
        if clip.is_some() {
            assert!(expected.iter().all(|a| a.abs() < 0.05), "{expected:?}");
        }
    }
}

#[test]
fn actor_kinds_need_format_2_and_a_clip_only_where_it_means_something() {
    use crate::manifest::ActorKind;
    let reason = load_reason;
    let mut old = without_log_std(ActorKind::Deterministic, None);
    old.manifest.format_version = 1;
    assert_eq!(
        reason(old),
        "manifest.actor.kind: needs format_version 2, the bundle says 1"
    );
    assert!(
        reason(without_log_std(ActorKind::GaussianSde, Some(-1.0)))
            .starts_with("manifest.actor.mean_clip: is -1")
    );
    assert!(
        reason(without_log_std(ActorKind::Deterministic, Some(2.0)))
            .contains("only for gaussian_sde actors")
    );
    let mut newer = small_policy();
    newer.manifest.format_version = 7;
    assert!(reason(newer).contains("this prac reads versions 1 to 6"));
    // A Gaussian actor's manifest says nothing of kinds: version-1 bytes stay as they were.
    let json = serde_json::to_string(&small_policy().manifest).unwrap();
    assert!(
        !json.contains("kind") && !json.contains("mean_clip"),
        "{json}"
    );
}

fn normalized(policy: &Policy, n: crate::manifest::ObsNormalization) -> Policy {
    let mut policy = policy.clone();
    policy.manifest.format_version = crate::manifest::FORMAT_VERSION_ACTOR_KINDS;
    policy.manifest.obs_normalization = Some(n);
    policy
}

fn vec_normalize() -> crate::manifest::ObsNormalization {
    crate::manifest::ObsNormalization {
        mean: vec![0.5, -1.0, 0.0, 2.0],
        var: vec![4.0, 0.25, 0.0, 1.0],
        clip_obs: 3.0,
        epsilon: 1e-8,
    }
}

#[test]
fn a_normalising_bundle_feeds_its_actor_and_critics_normalised_observations_and_its_model_raw_ones()
{
    let plain = small_policy();
    let policy = normalized(&plain, vec_normalize());
    let loaded = from_bytes(&to_bytes(&policy).unwrap(), &path()).unwrap();
    assert_eq!(loaded.manifest, policy.manifest);
    let raw = [2.5, -1.25, 0.001, 2.0];
    // (s - mean) / sqrt(var + 1e-8), clipped to +-3: the third feature (var 0) hits the clip.
    let seen = [1.0, -0.5, 3.0, 0.0];
    let (mut served, mut reference) = (
        Evaluator::new(Arc::new(loaded)),
        Evaluator::new(Arc::new(plain)),
    );
    let noise = [0.4, -0.8];
    let (mut a, mut b) = ([0.0; 2], [0.0; 2]);
    served.act(&raw, &noise, &mut a);
    reference.act(&seen, &noise, &mut b);
    assert_eq!(a, b);
    let other = [0.2, -0.6];
    let (mut qa, mut qb, mut ra, mut rb) = ([0.0], [0.0], [0.0], [0.0]);
    served.q_pair(&raw, &a, &other, &mut qa, &mut qb, None);
    reference.q_pair(&seen, &a, &other, &mut ra, &mut rb, None);
    assert_eq!((qa, qb), (ra, rb));
    let (mut next_a, mut next_b) = ([0.0; 4], [0.0; 4]);
    served.predict_next(&raw, &a, &mut next_a);
    reference.predict_next(&raw, &a, &mut next_b);
    assert_eq!(next_a, next_b, "the model speaks raw observations");
    // Batched rows normalise row by row.
    let rows: Vec<f32> = raw.iter().chain(&seen).copied().collect();
    let mut both = [0.0; 4];
    served.act(&rows, &[noise, noise].concat(), &mut both);
    assert_eq!(both[..2], a);
    let mut c = [0.0; 2];
    served.act(&seen, &noise, &mut c);
    assert_eq!(both[2..], c);
}

#[test]
fn a_bad_obs_normalization_is_named() {
    let reason = load_reason;
    let plain = small_policy();
    let mut old = normalized(&plain, vec_normalize());
    old.manifest.format_version = 1;
    assert_eq!(
        reason(old),
        "manifest.obs_normalization: needs format_version 2, the bundle says 1"
    );
    let mut short = vec_normalize();
    short.mean.pop();
    assert!(reason(normalized(&plain, short)).starts_with("manifest.obs_normalization.mean: "));
    let mut negative = vec_normalize();
    negative.var[1] = -1.0;
    assert_eq!(
        reason(normalized(&plain, negative)),
        "manifest.obs_normalization.var[1]: is -1, a variance must be >= 0"
    );
    // JSON has no infinities: 1e39 is one once read as f32.
    let mut huge = normalized(&plain, vec_normalize());
    huge.manifest.obs_normalization.as_mut().unwrap().mean[0] = 12345.0;
    let json = serde_json::to_string(&huge.manifest)
        .unwrap()
        .replace("12345.0", "1e39");
    let e = load_error(&rebuild(&tensors(&huge), Some(&json)));
    assert_eq!(
        (e.field.as_str(), e.reason.as_str()),
        ("manifest.obs_normalization.mean[0]", "is not finite")
    );
    for (clip_obs, epsilon, field) in [(0.0, 1e-8, "clip_obs"), (10.0, 0.0, "epsilon")] {
        let n = crate::manifest::ObsNormalization {
            clip_obs,
            epsilon,
            ..vec_normalize()
        };
        assert!(
            reason(normalized(&plain, n))
                .starts_with(&format!("manifest.obs_normalization.{field}: is 0")),
        );
    }
    // Bundles without it say nothing of it.
    let json = serde_json::to_string(&plain.manifest).unwrap();
    assert!(!json.contains("obs_normalization"), "{json}");
}

fn bounded(policy: &Policy, bounds: crate::manifest::ObsBounds) -> Policy {
    let mut policy = policy.clone();
    policy.manifest.format_version = crate::manifest::FORMAT_VERSION_OBS_BOUNDS;
    policy.manifest.obs_bounds = Some(bounds);
    policy
}

#[test]
fn observation_bounds_round_trip_and_keep_every_prediction_inside() {
    use crate::manifest::ObsBounds;
    let inf = f32::INFINITY;
    // Feature 3 is unbounded above, feature 2 below: null in JSON.
    let bounds = ObsBounds::from_limits(&[-0.1, -0.2, -inf, -0.1], &[0.1, 0.2, 0.1, inf]);
    assert_eq!(bounds.low[2], None);
    assert_eq!(bounds.high[3], None);
    let policy = bounded(&small_policy(), bounds.clone());
    let loaded = from_bytes(&to_bytes(&policy).unwrap(), &path()).unwrap();
    assert_eq!(loaded.manifest.obs_bounds, Some(bounds));
    let (loaded, plain) = (Arc::new(loaded), Arc::new(small_policy()));
    let (mut served, mut unbounded) = (Evaluator::new(loaded), Evaluator::new(plain));
    let obs: Vec<f32> = (0..4 * 16)
        .map(|i| ((i as f32) * 0.7).sin() * 3.0)
        .collect();
    let actions: Vec<f32> = (0..2 * 16).map(|i| ((i as f32) * 0.3).cos()).collect();
    let (mut got, mut raw) = (vec![0.0; 4 * 16], vec![0.0; 4 * 16]);
    served.predict_next(&obs, &actions, &mut got);
    unbounded.predict_next(&obs, &actions, &mut raw);
    let (low, high) = ([-0.1, -0.2, -inf, -0.1], [0.1, 0.2, 0.1, inf]);
    let mut clamped = 0;
    for (k, (g, r)) in got.iter().zip(&raw).enumerate() {
        let (lo, hi) = (low[k % 4], high[k % 4]);
        assert!((lo..=hi).contains(g), "feature {}: {g}", k % 4);
        // Inside the bounds a prediction is the model's own; outside, the nearest bound.
        assert_eq!(*g, r.clamp(lo, hi));
        clamped += usize::from(g != r);
    }
    assert!(
        clamped > 0,
        "no prediction left the bounds: the test shows nothing"
    );
    // A non-finite prediction stays non-finite, for Replan to refuse.
    let mut nan_obs = obs.clone();
    nan_obs[0] = f32::NAN;
    served.predict_next(&nan_obs, &actions, &mut got);
    assert!(got[..4].iter().any(|v| v.is_nan()));
}

#[test]
fn bad_observation_bounds_are_named() {
    use crate::manifest::ObsBounds;
    let reason = load_reason;
    let plain = small_policy();
    let good = ObsBounds::from_limits(&[-1.0; 4], &[1.0; 4]);
    let mut old = bounded(&plain, good.clone());
    old.manifest.format_version = crate::manifest::FORMAT_VERSION_CRITIC_NORMS;
    assert_eq!(
        reason(old),
        "manifest.obs_bounds: needs format_version 4, the bundle says 3"
    );
    let mut short = good.clone();
    short.high.pop();
    assert_eq!(
        reason(bounded(&plain, short)),
        "manifest.obs_bounds.high: has 3 entries, obs_dim is 4"
    );
    let mut crossed = good;
    crossed.low[1] = Some(2.0);
    assert_eq!(
        reason(bounded(&plain, crossed)),
        "manifest.obs_bounds.low[1]: 2 is above obs_bounds.high[1] = 1"
    );
    // A bundle without bounds writes none: its bytes stay readable by older servers.
    let json = serde_json::to_string(&plain.manifest).unwrap();
    assert!(!json.contains("obs_bounds"), "{json}");
}

#[test]
fn features_round_trip_take_precedence_and_bad_ones_are_named() {
    use crate::manifest::{Feature, Features};
    let entry = |name: &str| Feature {
        name: name.into(),
        unit: "1".into(),
    };
    let features = Features {
        observation: ["a", "b", "c", "d"].map(entry).to_vec(),
        action: ["x", "y"].map(entry).to_vec(),
    };
    let mut policy = small_policy();
    assert_eq!(policy.features(), None, "a domain prac does not know");
    policy.manifest.features = Some(features.clone());
    let loaded = from_bytes(&to_bytes(&policy).unwrap(), &path()).unwrap();
    assert_eq!(loaded.features(), Some(features.clone()));
    let mut short = policy.clone();
    short.manifest.features.as_mut().unwrap().action.pop();
    assert_eq!(
        load_reason(short),
        "manifest.features.action: has 1 entries, the policy has 2"
    );
    let mut unnamed = policy;
    unnamed.manifest.features.as_mut().unwrap().observation[2].name = String::new();
    assert_eq!(
        load_reason(unnamed),
        "manifest.features.observation[2].name: is empty"
    );
    // A bundle without features writes none: its bytes stay as they were.
    let json = serde_json::to_string(&small_policy().manifest).unwrap();
    assert!(!json.contains("features"), "{json}");
}

fn guarded(policy: &Policy, guard: crate::plan::Guard) -> Policy {
    let mut policy = policy.clone();
    policy.manifest.format_version = crate::manifest::FORMAT_VERSION_DEFAULT_GUARD;
    policy.manifest.default_guard = Some(guard);
    policy
}

#[test]
fn a_default_guard_round_trips_and_bad_ones_are_named() {
    use crate::plan::Guard;
    let reason = load_reason;
    let plain = small_policy();
    let guard = Guard {
        every_critic: true,
        support_limit: 3.5,
        ..Default::default()
    };
    let loaded = from_bytes(&to_bytes(&guarded(&plain, guard)).unwrap(), &path()).unwrap();
    assert_eq!(loaded.manifest.default_guard, Some(guard));
    // An older server must refuse it rather than serve without the guard: format 5.
    let mut old = guarded(&plain, guard);
    old.manifest.format_version = crate::manifest::FORMAT_VERSION_OBS_BOUNDS;
    assert_eq!(
        reason(old),
        "manifest.default_guard: needs format_version 5, the bundle says 4"
    );
    let negative = Guard {
        every_critic: false,
        support_limit: -1.0,
        ..Default::default()
    };
    assert_eq!(
        reason(guarded(&plain, negative)),
        "manifest.default_guard.support_limit: is -1; expected a finite value >= 0 (0: no limit)"
    );
    let mut deterministic = guarded(&plain, guard);
    deterministic.manifest.format_version = crate::manifest::FORMAT_VERSION_DEFAULT_GUARD;
    deterministic.manifest.actor.kind = crate::manifest::ActorKind::Deterministic;
    deterministic.actor.log_std = None;
    let why = reason(deterministic.clone());
    assert!(
        why.starts_with("manifest.default_guard.support_limit: measures actions against"),
        "{why}"
    );
    // every_critic alone needs no Gaussian.
    deterministic.manifest.default_guard = Some(Guard {
        every_critic: true,
        support_limit: 0.0,
        ..Default::default()
    });
    let json = serde_json::to_string(&deterministic.manifest).unwrap();
    assert!(deterministic.manifest.validate().is_ok(), "{json}");
    // A bundle without one writes none.
    let json = serde_json::to_string(&plain.manifest).unwrap();
    assert!(!json.contains("default_guard"), "{json}");
}

/// The "field: reason" a loader gives for a bundle of this policy's tensors and manifest.
fn load_reason(policy: Policy) -> String {
    let json = serde_json::to_string(&policy.manifest).unwrap();
    let e = load_error(&rebuild(&tensors(&policy), Some(&json)));
    format!("{}: {}", e.field, e.reason)
}

#[test]
fn a_default_epsilon_limit_needs_format_6_and_a_value_scale() {
    use crate::plan::Guard;
    let reason = load_reason;
    let plain = small_policy();
    let capped = Guard {
        support_limit: 3.0,
        max_epsilon_coef: 0.005,
        ..Default::default()
    };
    // A version-5 server would ignore the limit and serve the larger eps: format 6.
    assert_eq!(
        reason(guarded(&plain, capped)),
        "manifest.default_guard.max_epsilon_coef: needs format_version 6, the bundle says 5"
    );
    let mut six = guarded(&plain, capped);
    six.manifest.format_version = crate::manifest::FORMAT_VERSION_EPSILON_LIMIT;
    let loaded = from_bytes(&to_bytes(&six).unwrap(), &path()).unwrap();
    assert_eq!(loaded.manifest.default_guard, Some(capped));
    // JSON holds no NaN or infinity; the manifest's own check refuses them all the same.
    for bad in [-0.01, f64::NAN, f64::INFINITY] {
        let mut policy = six.clone();
        policy.manifest.default_guard = Some(Guard {
            max_epsilon_coef: bad,
            ..capped
        });
        let (field, why) = policy.manifest.validate().unwrap_err();
        assert_eq!(field, "default_guard.max_epsilon_coef", "{bad}");
        assert!(why.starts_with("is "), "{bad}: {why}");
        if bad.is_finite() {
            assert!(reason(policy).starts_with("manifest.default_guard.max_epsilon_coef: is "));
        }
    }
    let mut unscaled = six.clone();
    unscaled.manifest.value_scale = None;
    assert_eq!(
        reason(unscaled),
        "manifest.default_guard.max_epsilon_coef: needs value_scale with V_pi > V_rand"
    );
    // A guard without a limit writes none: its bundle stays format 5 and hashes as before.
    let json = serde_json::to_string(
        &guarded(
            &plain,
            Guard {
                max_epsilon_coef: 0.0,
                ..capped
            },
        )
        .manifest,
    )
    .unwrap();
    assert!(!json.contains("max_epsilon_coef"), "{json}");
}
