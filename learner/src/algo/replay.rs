//! The DDPG replay buffer: fixed capacity, oldest overwritten, uniform
//! sampling. Stored as flat f32 arrays so a checkpoint can save it as
//! tensors. On a GPU learner a [`DeviceMirror`] keeps a copy on the device
//! and gathers minibatches there.

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
    /// Transitions pushed, counted so that push k went to slot
    /// k mod capacity (a restored buffer continues the count).
    pushed: u64,
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
            pushed: 0,
        }
    }

    pub fn len(&self) -> usize {
        self.reward.len()
    }

    pub fn is_empty(&self) -> bool {
        self.reward.is_empty()
    }

    /// Stores one transition, overwriting the oldest once full. Every field
    /// is checked against the buffer's widths first: a transition with a
    /// short or long `obs`, `action` or `next_obs` is refused with an error
    /// and the buffer is left as it was (stored, it would shift every later
    /// row or panic on overwrite).
    pub fn push(&mut self, obs: &[f32], action: &[f32], reward: f32, next_obs: &[f32], done: bool) -> Result<(), String> {
        for (field, len, width) in [("obs", obs.len(), self.obs_dim), ("action", action.len(), self.action_dim), ("next_obs", next_obs.len(), self.obs_dim)] {
            if len != width {
                return Err(format!("transition refused: {field} holds {len} values, the replay buffer stores {width}"));
            }
        }
        if self.capacity == 0 {
            return Err("transition refused: the replay buffer has no capacity".into());
        }
        let done = f32::from(u8::from(done));
        self.pushed += 1;
        if self.len() < self.capacity {
            self.obs.extend_from_slice(obs);
            self.action.extend_from_slice(action);
            self.reward.push(reward);
            self.next_obs.extend_from_slice(next_obs);
            self.done.push(done);
            return Ok(());
        }
        let k = self.cursor;
        self.obs[k * self.obs_dim..(k + 1) * self.obs_dim].copy_from_slice(obs);
        self.action[k * self.action_dim..(k + 1) * self.action_dim].copy_from_slice(action);
        self.reward[k] = reward;
        self.next_obs[k * self.obs_dim..(k + 1) * self.obs_dim].copy_from_slice(next_obs);
        self.done[k] = done;
        self.cursor = (self.cursor + 1) % self.capacity;
        Ok(())
    }

    /// `size` slots drawn uniformly with replacement.
    fn picks(&self, size: usize, rng: &mut impl Rng) -> Vec<usize> {
        (0..size).map(|_| rng.random_range(0..self.len())).collect()
    }

    /// `size` transitions drawn uniformly with replacement.
    pub fn sample(&self, size: usize, rng: &mut impl Rng) -> Batch {
        let picks = self.picks(size, rng);
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
        let cursor = usize::try_from(cursor.map_err(|e| e.to_string())?).map_err(|_| "replay buffer's cursor is negative".to_string())?;
        let mut buffer = ReplayBuffer {
            capacity,
            obs_dim,
            action_dim,
            obs: get("obs")?,
            action: get("action")?,
            reward: get("reward")?,
            next_obs: get("next_obs")?,
            done: get("done")?,
            cursor,
            pushed: 0,
        };
        if buffer.cursor >= capacity.max(1) || buffer.len() > capacity {
            return Err("replay buffer holds more than its capacity".into());
        }
        // The next push goes to the cursor once full, else to the end.
        buffer.pushed = if buffer.len() == capacity { (capacity + buffer.cursor) as u64 } else { buffer.len() as u64 };
        // Field by field: a short `next_obs` or `done` would panic at the
        // first minibatch that draws a row past its end.
        let rows = buffer.len();
        for (field, len, width) in [
            ("obs", buffer.obs.len(), obs_dim),
            ("action", buffer.action.len(), action_dim),
            ("next_obs", buffer.next_obs.len(), obs_dim),
            ("done", buffer.done.len(), 1),
        ] {
            if Some(len) != rows.checked_mul(width) {
                return Err(format!("replay buffer shapes do not match the environment: {field} holds {len} values, {rows} transitions need {}", rows * width));
            }
        }
        Ok(buffer)
    }
}

/// The replay buffer's copy on a GPU: one row per slot, [obs | action |
/// reward | next_obs | done]. Before each minibatch the rows pushed since
/// the last one travel in one copy (two where they wrap), without waiting
/// (`device::to_device_async`); the minibatch is gathered on the device
/// from the same slots the host buffer would draw, so a GPU learner trains
/// on exactly the CPU learner's minibatches.
pub struct DeviceMirror {
    rows: Tensor,
    /// How many of the buffer's pushes the rows hold.
    mirrored: u64,
}

impl DeviceMirror {
    /// Room for the whole buffer on `device` (capacity × (2m + n + 2) floats).
    pub fn new(buffer: &ReplayBuffer, device: tch::Device) -> Self {
        let width = Batch::row_width(buffer.obs_dim, buffer.action_dim) as i64;
        DeviceMirror { rows: Tensor::zeros([buffer.capacity as i64, width], (tch::Kind::Float, device)), mirrored: 0 }
    }

    /// Copies the rows pushed since the last call.
    fn catch_up(&mut self, buffer: &ReplayBuffer) {
        let capacity = buffer.capacity as u64;
        // Older pushes than the last `capacity` were overwritten.
        let mut k = self.mirrored.max(buffer.pushed.saturating_sub(capacity));
        while k < buffer.pushed {
            let first = (k % capacity) as usize;
            let count = (buffer.pushed - k).min(capacity - first as u64) as usize;
            let (m, n) = (buffer.obs_dim, buffer.action_dim);
            let mut packed = Vec::with_capacity(count * (2 * m + n + 2));
            for slot in first..first + count {
                packed.extend_from_slice(&buffer.obs[slot * m..(slot + 1) * m]);
                packed.extend_from_slice(&buffer.action[slot * n..(slot + 1) * n]);
                packed.push(buffer.reward[slot]);
                packed.extend_from_slice(&buffer.next_obs[slot * m..(slot + 1) * m]);
                packed.push(buffer.done[slot]);
            }
            let host = Tensor::from_slice(&packed).view([count as i64, -1]);
            let on_device = crate::device::torch::to_device_async(host, self.rows.device());
            self.rows.narrow(0, first as i64, count as i64).copy_(&on_device);
            k += count as u64;
        }
        self.mirrored = buffer.pushed;
    }

    /// What [`ReplayBuffer::sample`] draws with the same `rng`, gathered on
    /// the device.
    pub fn sample(&mut self, buffer: &ReplayBuffer, size: usize, rng: &mut impl Rng) -> Batch {
        let picks = self.picks(buffer, size, rng);
        let rows = self.rows.index_select(0, &picks);
        Batch::from_rows(&rows, buffer.obs_dim, buffer.action_dim)
    }

    /// The same draw as [`DeviceMirror::sample`], gathered into `rows`
    /// ([size, row width] on the device) in place: a captured update reads
    /// its minibatch from there (ddpg/graphs.rs).
    pub fn sample_into(&mut self, buffer: &ReplayBuffer, rows: &Tensor, rng: &mut impl Rng) {
        let picks = self.picks(buffer, rows.size()[0] as usize, rng);
        let _ = self.rows.index_select_out(rows, 0, &picks);
    }

    /// The slots of the next minibatch, on the device, after catching up.
    fn picks(&mut self, buffer: &ReplayBuffer, size: usize, rng: &mut impl Rng) -> Tensor {
        self.catch_up(buffer);
        let picks: Vec<i64> = buffer.picks(size, rng).into_iter().map(|k| k as i64).collect();
        crate::device::torch::to_device_async(Tensor::from_slice(&picks), self.rows.device())
    }
}

impl Batch {
    /// A minibatch as views of rows [obs | action | reward | next_obs | done].
    pub fn from_rows(rows: &Tensor, obs_dim: usize, action_dim: usize) -> Batch {
        let (m, n) = (obs_dim as i64, action_dim as i64);
        Batch {
            obs: rows.narrow(1, 0, m),
            action: rows.narrow(1, m, n),
            reward: rows.narrow(1, m + n, 1),
            next_obs: rows.narrow(1, m + n + 1, m),
            done: rows.narrow(1, 2 * m + n + 1, 1),
        }
    }

    /// The width of such a row.
    pub fn row_width(obs_dim: usize, action_dim: usize) -> usize {
        2 * obs_dim + action_dim + 2
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
            buffer.push(&[v, v], &[v], v, &[v + 1.0, v + 1.0], k == 4).unwrap();
        }
        assert_eq!(buffer.len(), 3);
        // Transitions 0 and 1 were overwritten by 3 and 4.
        assert_eq!(buffer.reward, vec![3.0, 4.0, 2.0]);
        let restored = ReplayBuffer::from_tensors(3, 2, 1, &buffer.to_tensors()).unwrap();
        // The restored count of pushes differs, but it maps the next push
        // to the same slot.
        assert_eq!(restored.pushed % 3, buffer.pushed % 3);
        assert_eq!(ReplayBuffer { pushed: buffer.pushed, ..restored }, buffer);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let batch = buffer.sample(8, &mut rng);
        assert_eq!(batch.obs.size(), vec![8, 2]);
        let rewards: Vec<f32> = Vec::try_from(batch.reward.flatten(0, -1)).unwrap();
        assert!(rewards.iter().all(|r| [2.0, 3.0, 4.0].contains(r)));
    }

    /// A transition whose fields do not have the buffer's widths is refused
    /// field by field, filling or full, and leaves the buffer as it was; so
    /// is a restored buffer whose `next_obs` or `done` is short (it used to
    /// be accepted when only obs and action matched, and panicked at the
    /// first minibatch that drew a row past the end).
    #[test]
    fn refuses_transitions_and_buffers_of_the_wrong_width() {
        let mut buffer = ReplayBuffer::new(2, 2, 1);
        for fill in 0..3 {
            let before = buffer.clone();
            for (field, (obs, action, next_obs)) in [
                ("obs", (&[1.0][..], &[0.5][..], &[1.0, 2.0][..])),
                ("action", (&[1.0, 2.0][..], &[][..], &[1.0, 2.0][..])),
                ("next_obs", (&[1.0, 2.0][..], &[0.5][..], &[1.0][..])),
                ("next_obs", (&[1.0, 2.0][..], &[0.5][..], &[1.0, 2.0, 3.0][..])),
            ] {
                let err = buffer.push(obs, action, 0.0, next_obs, false).expect_err(field);
                assert!(err.contains(field), "{err}");
                assert_eq!(buffer, before, "a refused transition leaves the buffer as it was");
            }
            // Fill the buffer, then overwrite: the checks hold in both modes.
            buffer.push(&[fill as f32; 2], &[0.0], 0.0, &[0.0; 2], false).unwrap();
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        assert_eq!(buffer.sample(4, &mut rng).next_obs.size(), vec![4, 2]);
        assert!(ReplayBuffer::new(0, 2, 1).push(&[0.0; 2], &[0.0], 0.0, &[0.0; 2], false).is_err());

        let saved = buffer.to_tensors();
        for (key, cut) in [("next_obs", Tensor::from_slice(&[1.0f32, 2.0, 3.0])), ("done", Tensor::from_slice(&[0.0f32])), ("obs", Tensor::from_slice(&[0.0f32; 5]))] {
            let named: Vec<(String, Tensor)> = saved.iter().map(|(n, t)| (n.clone(), if n == key { cut.shallow_clone() } else { t.shallow_clone() })).collect();
            let err = ReplayBuffer::from_tensors(2, 2, 1, &named).expect_err(key);
            assert!(err.contains(key), "{err}");
        }
        let negative: Vec<(String, Tensor)> = saved.iter().map(|(n, t)| (n.clone(), if n == "cursor" { Tensor::from(-1i64) } else { t.shallow_clone() })).collect();
        assert!(ReplayBuffer::from_tensors(2, 2, 1, &negative).is_err());
        assert!(ReplayBuffer::from_tensors(2, 2, 1, &saved).is_ok());
    }
}

/// The device mirror gathers what the host buffer samples: same seed, same
/// minibatch, through wrap-around, overwrites and a restore. On the CPU
/// device here; `cuda_updates_equal_cpu_updates` runs it on a GPU.
#[cfg(test)]
mod mirror_tests {
    use super::*;
    use rand::SeedableRng;

    fn values(t: &Tensor) -> Vec<f32> {
        Vec::try_from(t.contiguous().flatten(0, -1)).unwrap()
    }

    fn same(a: &Batch, b: &Batch) {
        for (x, y) in [(&a.obs, &b.obs), (&a.action, &b.action), (&a.reward, &b.reward), (&a.next_obs, &b.next_obs), (&a.done, &b.done)] {
            assert_eq!(x.size(), y.size());
            assert_eq!(values(x), values(y));
        }
    }

    #[test]
    fn the_mirror_samples_what_the_buffer_samples() {
        let mut buffer = ReplayBuffer::new(7, 3, 2);
        let (mut mirror, mut into) = (DeviceMirror::new(&buffer, tch::Device::Cpu), DeviceMirror::new(&buffer, tch::Device::Cpu));
        let (mut host_rng, mut mirror_rng) = (rand_chacha::ChaCha8Rng::seed_from_u64(3), rand_chacha::ChaCha8Rng::seed_from_u64(3));
        let mut into_rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        // Pushes of 1, 5 and 12 between samples: a partial fill, a wrap,
        // and more than the whole capacity at once.
        let mut k = 0;
        for burst in [1, 5, 12, 2, 3] {
            for _ in 0..burst {
                let v = k as f32;
                buffer.push(&[v, v + 0.1, v + 0.2], &[-v, v * 0.5], v * 10.0, &[v + 1.0, v + 1.1, v + 1.2], k % 4 == 0).unwrap();
                k += 1;
            }
            let host = buffer.sample(9, &mut host_rng);
            same(&host, &mirror.sample(&buffer, 9, &mut mirror_rng));
            // Gathered in place into a fixed tensor (captured updates).
            let rows = Tensor::full([9, Batch::row_width(3, 2) as i64], -7.0, (tch::Kind::Float, tch::Device::Cpu));
            into.sample_into(&buffer, &rows, &mut into_rng);
            same(&host, &Batch::from_rows(&rows, 3, 2));
        }
        // A restored buffer and a fresh mirror continue alike.
        let mut restored = ReplayBuffer::from_tensors(7, 3, 2, &buffer.to_tensors()).unwrap();
        let mut fresh = DeviceMirror::new(&restored, tch::Device::Cpu);
        for k in 100..104 {
            let v = k as f32;
            buffer.push(&[v; 3], &[v; 2], v, &[v; 3], false).unwrap();
            restored.push(&[v; 3], &[v; 2], v, &[v; 3], false).unwrap();
        }
        same(&buffer.sample(20, &mut host_rng), &fresh.sample(&restored, 20, &mut mirror_rng));
    }
}
