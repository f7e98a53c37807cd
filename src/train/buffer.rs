//! The replay buffer: a ring of transitions in flat arrays, sampled uniformly.

use rand::Rng;

use super::sac::Batch;

pub struct ReplayBuffer {
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
    pub fn new(obs_dim: usize, act_dim: usize, capacity: usize) -> ReplayBuffer {
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

    pub fn len(&self) -> usize {
        self.len
    }
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Adds a transition, overwriting the oldest when full. `done` is termination only: a
    /// truncated episode still bootstraps from its last state.
    pub fn push(&mut self, obs: &[f32], action: &[f32], reward: f32, next_obs: &[f32], done: bool) {
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
    pub fn sample<R: Rng>(&self, size: usize, rng: &mut R, batch: &mut Batch) {
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

    /// The transitions in insertion order (oldest first): obs, actions, next_obs.
    pub fn transitions(&self) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let (od, ad) = (self.obs_dim, self.act_dim);
        let order: Vec<usize> = if self.len < self.capacity {
            (0..self.len).collect()
        } else {
            (self.next..self.capacity).chain(0..self.next).collect()
        };
        let mut out = (Vec::new(), Vec::new(), Vec::new());
        for i in order {
            out.0.extend_from_slice(&self.obs[i * od..(i + 1) * od]);
            out.1.extend_from_slice(&self.actions[i * ad..(i + 1) * ad]);
            out.2
                .extend_from_slice(&self.next_obs[i * od..(i + 1) * od]);
        }
        out
    }
}
