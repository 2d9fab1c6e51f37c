//! The DDPG replay buffer: fixed capacity, oldest overwritten, uniform
//! sampling. Stored as flat f32 arrays so a checkpoint can save it as
//! tensors.

use rand::Rng;
use tch::Tensor;

/// A sampled minibatch as tensors on the CPU.
pub struct Batch {
    pub obs: Tensor,
    pub action: Tensor,
    pub reward: Tensor,
    pub next_obs: Tensor,
    /// 1.0 where the episode terminated (no bootstrapping); truncation is 0.
    pub done: Tensor,
}

impl Batch {
    pub fn to_device(self, device: tch::Device) -> Batch {
        Batch {
            obs: self.obs.to_device(device),
            action: self.action.to_device(device),
            reward: self.reward.to_device(device),
            next_obs: self.next_obs.to_device(device),
            done: self.done.to_device(device),
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct ReplayBuffer {
    capacity: usize,
    obs_dim: usize,
    action_dim: usize,
    obs: Vec<f32>,
    action: Vec<f32>,
    reward: Vec<f32>,
    next_obs: Vec<f32>,
    done: Vec<f32>,
    /// Where the next transition goes once the buffer is full.
    cursor: usize,
}

impl ReplayBuffer {
    pub fn new(capacity: usize, obs_dim: usize, action_dim: usize) -> Self {
        ReplayBuffer {
            capacity,
            obs_dim,
            action_dim,
            obs: Vec::new(),
            action: Vec::new(),
            reward: Vec::new(),
            next_obs: Vec::new(),
            done: Vec::new(),
            cursor: 0,
        }
    }

    pub fn len(&self) -> usize {
        self.reward.len()
    }

    pub fn is_empty(&self) -> bool {
        self.reward.is_empty()
    }

    pub fn push(&mut self, obs: &[f32], action: &[f32], reward: f32, next_obs: &[f32], done: bool) {
        let done = f32::from(u8::from(done));
        if self.len() < self.capacity {
            self.obs.extend_from_slice(obs);
            self.action.extend_from_slice(action);
            self.reward.push(reward);
            self.next_obs.extend_from_slice(next_obs);
            self.done.push(done);
            return;
        }
        let k = self.cursor;
        self.obs[k * self.obs_dim..(k + 1) * self.obs_dim].copy_from_slice(obs);
        self.action[k * self.action_dim..(k + 1) * self.action_dim].copy_from_slice(action);
        self.reward[k] = reward;
        self.next_obs[k * self.obs_dim..(k + 1) * self.obs_dim].copy_from_slice(next_obs);
        self.done[k] = done;
        self.cursor = (self.cursor + 1) % self.capacity;
    }

    /// `size` transitions drawn uniformly with replacement.
    pub fn sample(&self, size: usize, rng: &mut impl Rng) -> Batch {
        let picks: Vec<usize> = (0..size).map(|_| rng.random_range(0..self.len())).collect();
        let gather = |data: &[f32], width: usize| -> Tensor {
            let mut out = Vec::with_capacity(size * width);
            for &k in &picks {
                out.extend_from_slice(&data[k * width..(k + 1) * width]);
            }
            Tensor::from_slice(&out).view([size as i64, width as i64])
        };
        Batch {
            obs: gather(&self.obs, self.obs_dim),
            action: gather(&self.action, self.action_dim),
            reward: gather(&self.reward, 1),
            next_obs: gather(&self.next_obs, self.obs_dim),
            done: gather(&self.done, 1),
        }
    }

    /// The contents as named tensors (for checkpoints).
    pub fn to_tensors(&self) -> Vec<(String, Tensor)> {
        let n = self.len() as i64;
        vec![
            ("obs".into(), Tensor::from_slice(&self.obs).view([n, self.obs_dim as i64])),
            ("action".into(), Tensor::from_slice(&self.action).view([n, self.action_dim as i64])),
            ("reward".into(), Tensor::from_slice(&self.reward)),
            ("next_obs".into(), Tensor::from_slice(&self.next_obs).view([n, self.obs_dim as i64])),
            ("done".into(), Tensor::from_slice(&self.done)),
            ("cursor".into(), Tensor::from(self.cursor as i64)),
        ]
    }

    /// Rebuilds a buffer from [`ReplayBuffer::to_tensors`].
    pub fn from_tensors(capacity: usize, obs_dim: usize, action_dim: usize, named: &[(String, Tensor)]) -> Result<Self, String> {
        let get = |key: &str| -> Result<Vec<f32>, String> {
            let t = named.iter().find(|(n, _)| n == key).map(|(_, t)| t).ok_or_else(|| format!("replay buffer lacks {key}"))?;
            Vec::<f32>::try_from(t.flatten(0, -1)).map_err(|e| e.to_string())
        };
        let cursor = named.iter().find(|(n, _)| n == "cursor").map(|(_, t)| i64::try_from(t)).ok_or("replay buffer lacks cursor")?;
        let buffer = ReplayBuffer {
            capacity,
            obs_dim,
            action_dim,
            obs: get("obs")?,
            action: get("action")?,
            reward: get("reward")?,
            next_obs: get("next_obs")?,
            done: get("done")?,
            cursor: cursor.map_err(|e| e.to_string())? as usize,
        };
        if buffer.obs.len() != buffer.len() * obs_dim || buffer.action.len() != buffer.len() * action_dim {
            return Err("replay buffer shapes do not match the environment".into());
        }
        Ok(buffer)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn overwrites_oldest_and_round_trips() {
        let mut buffer = ReplayBuffer::new(3, 2, 1);
        for k in 0..5 {
            let v = k as f32;
            buffer.push(&[v, v], &[v], v, &[v + 1.0, v + 1.0], k == 4);
        }
        assert_eq!(buffer.len(), 3);
        // Transitions 0 and 1 were overwritten by 3 and 4.
        assert_eq!(buffer.reward, vec![3.0, 4.0, 2.0]);
        let restored = ReplayBuffer::from_tensors(3, 2, 1, &buffer.to_tensors()).unwrap();
        assert_eq!(restored, buffer);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let batch = buffer.sample(8, &mut rng);
        assert_eq!(batch.obs.size(), vec![8, 2]);
        let rewards: Vec<f32> = Vec::try_from(batch.reward.flatten(0, -1)).unwrap();
        assert!(rewards.iter().all(|r| [2.0, 3.0, 4.0].contains(r)));
    }
}
