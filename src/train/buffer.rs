//! The replay buffer: a ring of transitions in flat arrays, sampled uniformly. Checkpoints save
//! it as a safetensors file, oldest transition first.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context, bail};
use rand::Rng;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use super::sac::Batch;

pub(crate) struct ReplayBuffer {
    obs_dim: usize,
    act_dim: usize,
    capacity: usize,
    len: usize,
    next: usize,
    obs: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    next_obs: Vec<f32>,
    dones: Vec<f32>,
}

impl ReplayBuffer {
    /// Storage grows with use up to `capacity` transitions.
    pub(crate) fn new(obs_dim: usize, act_dim: usize, capacity: usize) -> ReplayBuffer {
        ReplayBuffer {
            obs_dim,
            act_dim,
            capacity: capacity.max(1),
            len: 0,
            next: 0,
            obs: Vec::new(),
            actions: Vec::new(),
            rewards: Vec::new(),
            next_obs: Vec::new(),
            dones: Vec::new(),
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Adds a transition, overwriting the oldest when full. `done` is termination only: a
    /// truncated episode still bootstraps from its last state.
    pub(crate) fn push(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        next_obs: &[f32],
        done: bool,
    ) {
        let (od, ad) = (self.obs_dim, self.act_dim);
        let done = if done { 1.0 } else { 0.0 };
        if self.len < self.capacity {
            self.obs.extend_from_slice(obs);
            self.actions.extend_from_slice(action);
            self.rewards.push(reward);
            self.next_obs.extend_from_slice(next_obs);
            self.dones.push(done);
            self.len += 1;
        } else {
            let i = self.next;
            self.obs[i * od..(i + 1) * od].copy_from_slice(obs);
            self.actions[i * ad..(i + 1) * ad].copy_from_slice(action);
            self.rewards[i] = reward;
            self.next_obs[i * od..(i + 1) * od].copy_from_slice(next_obs);
            self.dones[i] = done;
        }
        self.next = (self.next + 1) % self.capacity;
    }

    /// A uniform sample (with replacement) of `size` transitions into `batch`.
    pub(crate) fn sample<R: Rng>(&self, size: usize, rng: &mut R, batch: &mut Batch) {
        let (od, ad) = (self.obs_dim, self.act_dim);
        batch.len = size;
        for v in [
            &mut batch.obs,
            &mut batch.actions,
            &mut batch.rewards,
            &mut batch.next_obs,
            &mut batch.dones,
        ] {
            v.clear();
        }
        for _ in 0..size {
            let i = rng.random_range(0..self.len);
            batch.obs.extend_from_slice(&self.obs[i * od..(i + 1) * od]);
            batch
                .actions
                .extend_from_slice(&self.actions[i * ad..(i + 1) * ad]);
            batch.rewards.push(self.rewards[i]);
            batch
                .next_obs
                .extend_from_slice(&self.next_obs[i * od..(i + 1) * od]);
            batch.dones.push(self.dones[i]);
        }
    }

    /// Slot indices in insertion order (oldest first).
    fn order(&self) -> impl Iterator<Item = usize> {
        let oldest = if self.len == self.capacity {
            self.next
        } else {
            0
        };
        (oldest..self.len).chain(0..oldest)
    }

    /// The transitions in insertion order (oldest first): obs, actions, next_obs.
    #[cfg(test)]
    pub(crate) fn transitions(&self) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let (od, ad) = (self.obs_dim, self.act_dim);
        let mut out = (Vec::new(), Vec::new(), Vec::new());
        for i in self.order() {
            out.0.extend_from_slice(&self.obs[i * od..(i + 1) * od]);
            out.1.extend_from_slice(&self.actions[i * ad..(i + 1) * ad]);
            out.2
                .extend_from_slice(&self.next_obs[i * od..(i + 1) * od]);
        }
        out
    }

    fn columns(&self) -> [(&'static str, &[f32], usize); 5] {
        let (od, ad) = (self.obs_dim, self.act_dim);
        [
            ("obs", &self.obs, od),
            ("actions", &self.actions, ad),
            ("rewards", &self.rewards, 1),
            ("next_obs", &self.next_obs, od),
            ("dones", &self.dones, 1),
        ]
    }

    /// Writes the transitions, oldest first, as safetensors tensors `obs` [n, obs_dim],
    /// `actions` [n, act_dim], `rewards` [n, 1], `next_obs` [n, obs_dim] and `dones` [n, 1].
    pub(crate) fn save(&self, path: &Path) -> anyhow::Result<()> {
        let data: Vec<(&str, usize, Vec<u8>)> = self
            .columns()
            .into_iter()
            .map(|(name, values, width)| {
                let mut bytes = Vec::with_capacity(values.len() * 4);
                for i in self.order() {
                    for v in &values[i * width..(i + 1) * width] {
                        bytes.extend_from_slice(&v.to_le_bytes());
                    }
                }
                (name, width, bytes)
            })
            .collect();
        let mut views = Vec::with_capacity(data.len());
        for (name, width, bytes) in &data {
            views.push((
                name.to_string(),
                TensorView::new(Dtype::F32, vec![self.len, *width], bytes)?,
            ));
        }
        let metadata = HashMap::from([("format".to_string(), "prac-replay".to_string())]);
        safetensors::serialize_to_file(views, Some(metadata), path)
            .with_context(|| format!("writing {}", path.display()))
    }

    /// Reads a buffer written by `save` into one of `capacity` (the newest transitions are kept
    /// when the file holds more).
    pub(crate) fn load(
        path: &Path,
        obs_dim: usize,
        act_dim: usize,
        capacity: usize,
    ) -> anyhow::Result<ReplayBuffer> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let tensors = SafeTensors::deserialize(&bytes)
            .map_err(|e| anyhow::anyhow!("{}: not a replay buffer: {e}", path.display()))?;
        let mut buffer = ReplayBuffer::new(obs_dim, act_dim, capacity);
        let mut columns: Vec<Vec<f32>> = Vec::with_capacity(5);
        let mut rows = None;
        for (name, _, width) in buffer.columns() {
            let view = tensors
                .tensor(name)
                .map_err(|_| anyhow::anyhow!("{}: {name}: missing tensor", path.display()))?;
            let shape = view.shape();
            if view.dtype() != Dtype::F32 || shape.len() != 2 || shape[1] != width {
                bail!(
                    "{}: {name}: {:?} {shape:?}, expected F32 [n, {width}] for a buffer of \
                     {obs_dim}-dimensional observations and {act_dim}-dimensional actions",
                    path.display(),
                    view.dtype()
                );
            }
            if *rows.get_or_insert(shape[0]) != shape[0] {
                bail!(
                    "{}: {name}: {} transitions, the others {}",
                    path.display(),
                    shape[0],
                    rows.unwrap_or(0)
                );
            }
            columns.push(
                view.data()
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect(),
            );
        }
        let [obs, actions, rewards, next_obs, dones] = &columns[..] else {
            unreachable!("five columns were read")
        };
        let (od, ad) = (obs_dim, act_dim);
        for i in 0..rows.unwrap_or(0) {
            buffer.push(
                &obs[i * od..(i + 1) * od],
                &actions[i * ad..(i + 1) * ad],
                rewards[i],
                &next_obs[i * od..(i + 1) * od],
                dones[i] != 0.0,
            );
        }
        Ok(buffer)
    }
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    use super::*;

    /// A buffer of `capacity` after `pushed` transitions whose values encode their index.
    fn filled(capacity: usize, pushed: usize) -> ReplayBuffer {
        let mut buffer = ReplayBuffer::new(2, 1, capacity);
        for k in 0..pushed {
            let x = k as f32;
            buffer.push(
                &[x, -x],
                &[x / 100.0],
                x * 10.0,
                &[x + 0.5, 0.0],
                k % 3 == 0,
            );
        }
        buffer
    }

    /// Every column, oldest transition first.
    fn all(buffer: &ReplayBuffer) -> Vec<Vec<f32>> {
        buffer
            .columns()
            .into_iter()
            .map(|(_, values, width)| {
                buffer
                    .order()
                    .flat_map(|i| values[i * width..(i + 1) * width].to_vec())
                    .collect()
            })
            .collect()
    }

    #[test]
    fn a_saved_buffer_loads_with_the_same_transitions_in_the_same_order() {
        let dir = tempfile::tempdir().unwrap();
        for (capacity, pushed) in [(5, 0), (5, 3), (5, 5), (5, 8)] {
            let buffer = filled(capacity, pushed);
            let path = dir.path().join(format!("{capacity}-{pushed}.safetensors"));
            buffer.save(&path).unwrap();
            let loaded = ReplayBuffer::load(&path, 2, 1, capacity).unwrap();
            assert_eq!(loaded.len(), pushed.min(capacity));
            assert_eq!(
                all(&loaded),
                all(&buffer),
                "capacity {capacity}, pushed {pushed}"
            );
            // The next push overwrites the same (oldest) transition in both.
            let (mut a, mut b) = (buffer, loaded);
            a.push(&[9.0, 9.0], &[0.9], 90.0, &[9.0, 9.0], false);
            b.push(&[9.0, 9.0], &[0.9], 90.0, &[9.0, 9.0], false);
            assert_eq!(all(&a), all(&b));
        }
        // Into a smaller buffer the newest survive: transitions 5, 6 and 7 of 8.
        let path = dir.path().join("5-8.safetensors");
        let smaller = ReplayBuffer::load(&path, 2, 1, 3).unwrap();
        assert_eq!(
            smaller.transitions().0,
            vec![5.0, -5.0, 6.0, -6.0, 7.0, -7.0]
        );
        let mut batch = Batch::default();
        smaller.sample(16, &mut ChaCha8Rng::seed_from_u64(1), &mut batch);
        assert!(batch.rewards.iter().all(|r| [50.0, 60.0, 70.0].contains(r)));
    }

    #[test]
    fn a_buffer_file_of_other_dimensions_or_cut_short_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("replay.safetensors");
        filled(5, 4).save(&path).unwrap();
        let error = ReplayBuffer::load(&path, 3, 1, 5)
            .err()
            .unwrap()
            .to_string();
        assert!(
            error.contains("obs") && error.contains("expected F32 [n, 3]"),
            "{error}"
        );
        let error = ReplayBuffer::load(&path, 2, 2, 5)
            .err()
            .unwrap()
            .to_string();
        assert!(error.contains("actions"), "{error}");
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 7]).unwrap();
        let error = ReplayBuffer::load(&path, 2, 1, 5)
            .err()
            .unwrap()
            .to_string();
        assert!(error.contains("not a replay buffer"), "{error}");
        let missing = dir.path().join("none.safetensors");
        assert!(ReplayBuffer::load(&missing, 2, 1, 5).is_err());
    }
}
