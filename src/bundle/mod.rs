//! Weight bundles: one safetensors file per policy, f32 tensors named as Stable-Baselines3 names
//! them (PyTorch [out, in] layout) plus `model.*`, and a JSON manifest in `__metadata__`.
//! See docs/bundle-format.md.

pub use crate::manifest::*;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use sha2::{Digest, Sha256};

use crate::nn::{Dense, LayerNorm, Mlp};
use crate::policy::{Actor, DynamicsModel, Policy};

/// Key of the manifest JSON in `__metadata__`.
pub(crate) const MANIFEST_KEY: &str = "manifest";
/// Upper bound on a bundle file, to refuse absurd inputs before reading them.
pub(crate) const MAX_BUNDLE_BYTES: u64 = 1 << 30;

/// A bundle that cannot be used: names the file, the field (manifest key or tensor name) and why.
#[derive(Debug, thiserror::Error)]
#[error("{}: {field}: {reason}", file.display())]
pub struct BundleError {
    pub(crate) file: PathBuf,
    pub(crate) field: String,
    pub(crate) reason: String,
}

impl BundleError {
    fn at(file: &Path, field: &str, reason: String) -> BundleError {
        BundleError {
            file: file.to_path_buf(),
            field: field.to_string(),
            reason,
        }
    }
}

/// Names of the tensors of a network that SB3 builds as `nn.Sequential(Linear, act, Linear, ...)`:
/// the i-th linear layer sits at index 2i; with a layer norm after each hidden layer
/// (`Linear, LayerNorm, act, ...`) at 3i, and its norm at 3i + 1.
fn sequential_layer(prefix: &str, i: usize, layer_norm: bool) -> (String, String) {
    let index = if layer_norm { 3 * i } else { 2 * i };
    (
        format!("{prefix}.{index}.weight"),
        format!("{prefix}.{index}.bias"),
    )
}

/// Names of the scale and shift of the layer norm after hidden layer i
/// ([`sequential_layer`]).
fn sequential_norm(prefix: &str, i: usize) -> (String, String) {
    (
        format!("{prefix}.{}.weight", 3 * i + 1),
        format!("{prefix}.{}.bias", 3 * i + 1),
    )
}

pub(crate) fn critic_prefix(k: usize) -> String {
    format!("critic.qf{k}")
}
pub(crate) const ACTOR_TRUNK: &str = "actor.latent_pi";
pub(crate) const ACTOR_MU: &str = "actor.mu";
pub(crate) const ACTOR_LOG_STD: &str = "actor.log_std";
pub(crate) const MODEL_NET: &str = "model.net";

/// "sha256:<hex>" of some bytes.
pub fn content_hash(bytes: &[u8]) -> String {
    format!("sha256:{}", hex::encode(Sha256::digest(bytes)))
}

/// Largest safetensors header read: a manifest and the tensor index take a few KB.
pub(crate) const MAX_HEADER_BYTES: u64 = 16 << 20;

/// Reads, validates and builds a policy from a bundle file. The file must be a regular file; its
/// header (manifest and tensor index) is read and checked against the file's size before the
/// tensors are, so a huge or sparse file costs a few KB of reading, not its size.
pub fn load(path: &Path) -> Result<Policy, BundleError> {
    let err = |field: &str, reason: String| BundleError::at(path, field, reason);
    let meta = std::fs::metadata(path).map_err(|e| err("file", format!("cannot read: {e}")))?;
    if !meta.is_file() {
        return Err(err(
            "file",
            format!(
                "is not a regular file ({}); a bundle must be one",
                file_kind(&meta)
            ),
        ));
    }
    let size = meta.len();
    if size > MAX_BUNDLE_BYTES {
        return Err(err(
            "file",
            format!("is {size} bytes, more than the {MAX_BUNDLE_BYTES} allowed"),
        ));
    }
    let file = std::fs::File::open(path).map_err(|e| err("file", format!("cannot read: {e}")))?;
    from_reader(file, size, path)
}

/// Validates and builds a policy from a reader of `size` bytes: the header first, then, if it
/// holds, the rest. `path` only names the source in errors.
pub(crate) fn from_reader<R: std::io::Read + std::io::Seek>(
    mut reader: R,
    size: u64,
    path: &Path,
) -> Result<Policy, BundleError> {
    let err = |reason: String| BundleError::at(path, "file", reason);
    check_header(&mut reader, size, path)?;
    let mut bytes = Vec::with_capacity(size as usize);
    reader
        .read_to_end(&mut bytes)
        .map_err(|e| err(format!("cannot read: {e}")))?;
    if bytes.len() as u64 != size {
        return Err(err(format!(
            "changed while read: {} bytes, {size} before",
            bytes.len()
        )));
    }
    from_bytes(&bytes, path)
}

fn file_kind(meta: &std::fs::Metadata) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    let t = meta.file_type();
    if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a file"
    }
}

/// One tensor's entry in a safetensors header.
#[derive(serde::Deserialize)]
struct HeaderTensor {
    dtype: String,
    shape: Vec<usize>,
    data_offsets: (u64, u64),
}

/// Reads the header from the start of `file` (leaving the reader at its start) and checks the
/// manifest and the declared tensors against each other and against the file's size.
fn check_header<R: std::io::Read + std::io::Seek>(
    file: &mut R,
    size: u64,
    path: &Path,
) -> Result<(), BundleError> {
    let err = |field: &str, reason: String| BundleError::at(path, field, reason);
    let header_err = |reason: String| err("safetensors header", reason);
    let mut len = [0u8; 8];
    file.read_exact(&mut len)
        .map_err(|_| header_err(format!("the file has {size} bytes, too few for a header")))?;
    let n = u64::from_le_bytes(len);
    if n > MAX_HEADER_BYTES || n > size - 8 {
        return Err(header_err(format!(
            "declares {n} header bytes in a file of {size} bytes (at most {MAX_HEADER_BYTES})"
        )));
    }
    let mut header = vec![0u8; n as usize];
    file.read_exact(&mut header)
        .map_err(|e| err("file", format!("cannot read: {e}")))?;
    let mut entries: HashMap<String, serde_json::Value> = serde_json::from_slice(&header)
        .map_err(|e| header_err(format!("not a valid safetensors header: {e}")))?;
    let metadata = entries.remove("__metadata__");
    let mut tensors = DeclaredTensors::with_capacity(entries.len());
    let mut data_end = 0;
    for (name, entry) in entries {
        let info: HeaderTensor = serde_json::from_value(entry)
            .map_err(|e| err(&name, format!("not a valid tensor entry: {e}")))?;
        data_end = data_end.max(info.data_offsets.1);
        tensors.insert(name, (info.dtype, info.shape));
    }
    // Offsets come from the file: added without overflow.
    match (8 + n).checked_add(data_end) {
        Some(end) if end == size => {}
        Some(end) => {
            return Err(header_err(format!(
                "its tensors end at byte {end} but the file has {size} bytes"
            )));
        }
        None => {
            return Err(header_err(format!(
                "a tensor ends at byte {data_end}, past any file"
            )));
        }
    }
    let manifest_json = metadata
        .as_ref()
        .and_then(|m| m.get(MANIFEST_KEY))
        .and_then(serde_json::Value::as_str)
        .ok_or_else(|| missing_manifest(path))?;
    let manifest = parse_manifest(manifest_json, path)?;
    check_declared_tensors(&manifest, &tensors, path)?;
    file.rewind()
        .map_err(|e| err("file", format!("cannot read: {e}")))?;
    Ok(())
}

fn missing_manifest(path: &Path) -> BundleError {
    BundleError::at(
        path,
        "__metadata__.manifest",
        "missing: a prac bundle keeps its JSON manifest there".into(),
    )
}

fn parse_manifest(json: &str, path: &Path) -> Result<Manifest, BundleError> {
    let err = |field: &str, reason: String| BundleError::at(path, field, reason);
    let manifest: Manifest = serde_json::from_str(json).map_err(|e| {
        err(
            "__metadata__.manifest",
            format!("invalid manifest JSON: {e}"),
        )
    })?;
    manifest
        .validate()
        .map_err(|(field, reason)| err(&format!("manifest.{field}"), reason))?;
    Ok(manifest)
}

/// A safetensors header's tensor index: name to (dtype as safetensors spells it, shape).
type DeclaredTensors = HashMap<String, (String, Vec<usize>)>;

/// Checks one expected tensor by name and shape.
type CheckTensor<'a> = dyn FnMut(String, &[usize]) -> Result<(), BundleError> + 'a;

/// Checks that every tensor the manifest implies is declared, as F32 with its shape, and that
/// nothing else is, before anything is allocated from the manifest's sizes: a manifest cannot
/// declare more layers or critics than the file holds.
fn check_declared_tensors(
    manifest: &Manifest,
    declared: &DeclaredTensors,
    path: &Path,
) -> Result<(), BundleError> {
    let err = |field: &str, reason: String| BundleError::at(path, field, reason);
    let mut expected: Vec<String> = Vec::with_capacity(declared.len());
    let mut check = |name: String, shape: &[usize]| -> Result<(), BundleError> {
        let Some((dtype, found)) = declared.get(&name) else {
            return Err(err(
                &name,
                format!("missing tensor, expected shape {shape:?} f32"),
            ));
        };
        if dtype != "F32" {
            return Err(err(&name, format!("dtype {dtype}, expected F32")));
        }
        if found != shape {
            return Err(err(&name, format!("shape {found:?}, expected {shape:?}")));
        }
        expected.push(name);
        Ok(())
    };
    let chain = |check: &mut CheckTensor,
                 prefix: &str,
                 input: usize,
                 hidden: &[usize],
                 output: Option<usize>,
                 layer_norm: bool|
     -> Result<usize, BundleError> {
        let mut width = input;
        for (i, &out) in hidden.iter().chain(output.as_ref()).enumerate() {
            let (w, b) = sequential_layer(prefix, i, layer_norm);
            check(w, &[out, width])?;
            check(b, &[out])?;
            if layer_norm && i < hidden.len() {
                let (scale, shift) = sequential_norm(prefix, i);
                check(scale, &[out])?;
                check(shift, &[out])?;
            }
            width = out;
        }
        Ok(width)
    };
    let (obs, act) = (manifest.obs_dim, manifest.act_dim);
    let latent = chain(
        &mut check,
        ACTOR_TRUNK,
        obs,
        &manifest.actor.hidden,
        None,
        false,
    )?;
    let heads: &[&str] = if manifest.actor.kind.is_gaussian() {
        &[ACTOR_MU, ACTOR_LOG_STD]
    } else {
        &[ACTOR_MU]
    };
    for head in heads {
        check(format!("{head}.weight"), &[act, latent])?;
        check(format!("{head}.bias"), &[act])?;
    }
    // Stops at the first critic the file lacks, so n_critics = 10^9 costs one lookup.
    for k in 0..manifest.critic.n_critics {
        chain(
            &mut check,
            &critic_prefix(k),
            obs + act,
            &manifest.critic.hidden,
            Some(1),
            manifest.critic.layer_norm,
        )?;
    }
    if let Some(spec) = &manifest.model {
        chain(
            &mut check,
            MODEL_NET,
            obs + act,
            &spec.hidden,
            Some(obs),
            false,
        )?;
    }
    if expected.len() < declared.len() {
        let mut extra: Vec<&String> = declared
            .keys()
            .filter(|name| !expected.contains(name))
            .collect();
        extra.sort();
        return Err(err(
            extra[0],
            format!(
                "unexpected tensor ({} in all); a bundle holds only the tensors its manifest \
                 names",
                extra.len()
            ),
        ));
    }
    Ok(())
}

/// Validates and builds a policy from bundle bytes; `path` only names the source in errors.
pub(crate) fn from_bytes(bytes: &[u8], path: &Path) -> Result<Policy, BundleError> {
    let err = |field: &str, reason: String| BundleError::at(path, field, reason);
    let (_, metadata) = SafeTensors::read_metadata(bytes).map_err(|e| {
        err(
            "safetensors header",
            format!("not a valid safetensors file: {e}"),
        )
    })?;
    let manifest_json = metadata
        .metadata()
        .as_ref()
        .and_then(|m| m.get(MANIFEST_KEY))
        .ok_or_else(|| missing_manifest(path))?;
    let manifest = parse_manifest(manifest_json, path)?;
    let declared: DeclaredTensors = metadata
        .tensors()
        .into_iter()
        .map(|(name, info)| (name, (format!("{:?}", info.dtype), info.shape.clone())))
        .collect();
    check_declared_tensors(&manifest, &declared, path)?;
    let tensors = SafeTensors::deserialize(bytes).map_err(|e| {
        err(
            "safetensors data",
            format!("not a valid safetensors file: {e}"),
        )
    })?;
    let reader = TensorReader {
        tensors: &tensors,
        path,
    };
    let (obs, act) = (manifest.obs_dim, manifest.act_dim);

    let trunk_layers = reader.chain(ACTOR_TRUNK, obs, &manifest.actor.hidden, None)?;
    let trunk = Mlp::new(obs, trunk_layers, manifest.actor.activation, true)
        .map_err(|e| err(ACTOR_TRUNK, e.to_string()))?;
    let latent = trunk.output_dim();
    let mu = reader.dense(
        &format!("{ACTOR_MU}.weight"),
        &format!("{ACTOR_MU}.bias"),
        act,
        latent,
    )?;
    let log_std = if manifest.actor.kind.is_gaussian() {
        Some(reader.dense(
            &format!("{ACTOR_LOG_STD}.weight"),
            &format!("{ACTOR_LOG_STD}.bias"),
            act,
            latent,
        )?)
    } else {
        None
    };
    let mean_clip = manifest.actor.mean_clip.unwrap_or(f32::INFINITY);
    let mut critics = Vec::with_capacity(manifest.critic.n_critics);
    for k in 0..manifest.critic.n_critics {
        let prefix = critic_prefix(k);
        let hidden = &manifest.critic.hidden;
        let layer_norm = manifest.critic.layer_norm;
        let layers = reader.chain_of(&prefix, obs + act, hidden, Some(1), layer_norm)?;
        let mut critic = Mlp::new(obs + act, layers, manifest.critic.activation, false)
            .map_err(|e| err(&prefix, e.to_string()))?;
        if layer_norm {
            let norms = reader.norms(&prefix, hidden)?;
            critic = critic
                .with_layer_norms(norms)
                .map_err(|e| err(&prefix, e.to_string()))?;
        }
        critics.push(critic);
    }
    let model = match &manifest.model {
        None => None,
        Some(spec) => {
            let layers = reader.chain(MODEL_NET, obs + act, &spec.hidden, Some(obs))?;
            let net = Mlp::new(obs + act, layers, spec.activation, false)
                .map_err(|e| err(MODEL_NET, e.to_string()))?;
            Some(DynamicsModel {
                net,
                normalization: spec.normalization.clone(),
            })
        }
    };

    Ok(Policy {
        content_hash: content_hash(bytes),
        actor: Actor {
            trunk,
            mu,
            log_std,
            mean_clip,
        },
        critics,
        model,
        manifest,
    })
}

struct TensorReader<'a> {
    tensors: &'a SafeTensors<'a>,
    path: &'a Path,
}

impl TensorReader<'_> {
    fn error(&self, field: &str, reason: String) -> BundleError {
        BundleError::at(self.path, field, reason)
    }

    fn tensor(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, BundleError> {
        let view: TensorView = self.tensors.tensor(name).map_err(|_| {
            self.error(
                name,
                format!("missing tensor, expected shape {shape:?} f32"),
            )
        })?;
        if view.dtype() != Dtype::F32 {
            return Err(self.error(name, format!("dtype {:?}, expected F32", view.dtype())));
        }
        if view.shape() != shape {
            return Err(self.error(
                name,
                format!("shape {:?}, expected {shape:?}", view.shape()),
            ));
        }
        let values: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(self.error(name, format!("element {i} is {}, not finite", values[i])));
        }
        Ok(values)
    }

    fn dense(
        &self,
        weight: &str,
        bias: &str,
        out: usize,
        inp: usize,
    ) -> Result<Dense, BundleError> {
        let w = self.tensor(weight, &[out, inp])?;
        let b = self.tensor(bias, &[out])?;
        Ok(Dense::from_row_major(out, inp, &w, &b))
    }

    /// The layers of `prefix.{0,2,4,..}` with the given hidden widths and optional output width.
    fn chain(
        &self,
        prefix: &str,
        input: usize,
        hidden: &[usize],
        output: Option<usize>,
    ) -> Result<Vec<Dense>, BundleError> {
        self.chain_of(prefix, input, hidden, output, false)
    }

    /// The layers of `prefix.{0,3,6,..}` when `layer_norm`, else as [`TensorReader::chain`].
    fn chain_of(
        &self,
        prefix: &str,
        input: usize,
        hidden: &[usize],
        output: Option<usize>,
        layer_norm: bool,
    ) -> Result<Vec<Dense>, BundleError> {
        let mut layers = Vec::new();
        let mut width = input;
        for (i, &out) in hidden.iter().chain(output.as_ref()).enumerate() {
            let (w, b) = sequential_layer(prefix, i, layer_norm);
            layers.push(self.dense(&w, &b, out, width)?);
            width = out;
        }
        Ok(layers)
    }

    /// The layer norms of `prefix.{1,4,7,..}`, one per hidden layer.
    fn norms(&self, prefix: &str, hidden: &[usize]) -> Result<Vec<LayerNorm>, BundleError> {
        let mut norms = Vec::with_capacity(hidden.len());
        for (i, &width) in hidden.iter().enumerate() {
            let (scale, shift) = sequential_norm(prefix, i);
            let scale = self.tensor(&scale, &[width])?;
            let shift = self.tensor(&shift, &[width])?;
            norms.push(LayerNorm::new(scale, shift).expect("both read at the layer's width"));
        }
        Ok(norms)
    }
}

/// A named tensor in bundle layout: name, shape, row-major values.
pub(crate) type NamedTensor = (String, Vec<usize>, Vec<f32>);

/// The named tensors of a policy, in bundle layout.
pub(crate) fn tensors(policy: &Policy) -> Vec<NamedTensor> {
    fn push_dense(out: &mut Vec<NamedTensor>, prefix: &str, d: &Dense) {
        push_layer(out, format!("{prefix}.weight"), format!("{prefix}.bias"), d);
    }
    fn push_layer(out: &mut Vec<NamedTensor>, weight: String, bias: String, d: &Dense) {
        out.push((
            weight,
            vec![d.output_dim(), d.input_dim()],
            d.weight_row_major(),
        ));
        out.push((bias, vec![d.output_dim()], d.bias().as_slice().to_vec()));
    }
    fn push_chain(out: &mut Vec<NamedTensor>, prefix: &str, mlp: &Mlp) {
        let layer_norm = !mlp.norms().is_empty();
        for (i, d) in mlp.layers().iter().enumerate() {
            let (w, b) = sequential_layer(prefix, i, layer_norm);
            push_layer(out, w, b, d);
            if let Some(norm) = mlp.norms().get(i) {
                let (scale, shift) = sequential_norm(prefix, i);
                out.push((scale, vec![norm.dim()], norm.scale().to_vec()));
                out.push((shift, vec![norm.dim()], norm.shift().to_vec()));
            }
        }
    }
    let mut out = Vec::new();
    push_chain(&mut out, ACTOR_TRUNK, &policy.actor.trunk);
    push_dense(&mut out, ACTOR_MU, &policy.actor.mu);
    if let Some(log_std) = &policy.actor.log_std {
        push_dense(&mut out, ACTOR_LOG_STD, log_std);
    }
    for (k, critic) in policy.critics.iter().enumerate() {
        push_chain(&mut out, &critic_prefix(k), critic);
    }
    if let Some(model) = &policy.model {
        push_chain(&mut out, MODEL_NET, &model.net);
    }
    out
}

/// Serialises a policy (its manifest and networks) as bundle bytes.
pub fn to_bytes(policy: &Policy) -> Result<Vec<u8>, safetensors::SafeTensorError> {
    let manifest = serde_json::to_string(&policy.manifest).expect("manifest serialises");
    to_bytes_with_manifest(policy, &manifest)
}

/// A policy's networks with any manifest text (for fuzzing the loader's manifest checks).
pub fn to_bytes_with_manifest(
    policy: &Policy,
    manifest: &str,
) -> Result<Vec<u8>, safetensors::SafeTensorError> {
    let metadata = HashMap::from([
        ("format".to_string(), "prac-bundle".to_string()),
        (MANIFEST_KEY.to_string(), manifest.to_string()),
    ]);
    serialize_f32(tensors(policy), metadata)
}

/// f32 tensors (name, shape, row-major values) as safetensors bytes, with `metadata`.
pub(crate) fn serialize_f32(
    tensors: Vec<(String, Vec<usize>, Vec<f32>)>,
    metadata: HashMap<String, String>,
) -> Result<Vec<u8>, safetensors::SafeTensorError> {
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
        .into_iter()
        .map(|(name, shape, values)| {
            let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            (name, shape, data)
        })
        .collect();
    let views: Vec<(String, TensorView)> = bytes
        .iter()
        .map(|(name, shape, data)| {
            (
                name.clone(),
                TensorView::new(Dtype::F32, shape.clone(), data).expect("shape matches data"),
            )
        })
        .collect();
    safetensors::serialize(views, Some(metadata))
}

/// Gives a bundle of one of prac's domains that domain's observation space as its `obs_bounds`
/// (format 4), for bundles made before bundles carried them. False, and nothing changed, when
/// the domain is not prac's or its observations are not the bundle's size.
pub fn add_domain_obs_bounds(policy: &mut Policy) -> bool {
    let Some(env) = crate::domains::make(&policy.manifest.domain) else {
        return false;
    };
    let spec = env.spec();
    if spec.obs_dim != policy.manifest.obs_dim {
        return false;
    }
    let manifest = &mut policy.manifest;
    manifest.obs_bounds = Some(crate::manifest::ObsBounds::from_limits(
        &spec.obs_low,
        &spec.obs_high,
    ));
    manifest.format_version = manifest
        .format_version
        .max(crate::manifest::FORMAT_VERSION_OBS_BOUNDS);
    true
}

/// Writes a policy as a bundle file (atomically: a temporary file renamed into place, so a server
/// never reads half a bundle).
pub fn save(policy: &Policy, path: &Path) -> std::io::Result<()> {
    let bytes = to_bytes(policy).map_err(std::io::Error::other)?;
    let tmp = path.with_extension("safetensors.tmp");
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}

#[cfg(test)]
mod tests;
