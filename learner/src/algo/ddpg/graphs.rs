//! DDPG updates captured as CUDA graphs (cuda_graph.rs, `run.cuda_graphs`):
//! the inputs every captured update reads, refilled by the host before each
//! replay, and one graph per kind of update.
//!
//! An update reads three things that change from one update to the next:
//! its minibatch (gathered on the device into `rows`), the target policy's
//! noise, and its numbers (each optimizer's step size and bias correction,
//! the annealed preactivation weight). All of them live in tensors
//! allocated once; a graph captured over them replays the update exactly as
//! the eager code would run it with those inputs.

use std::collections::HashMap;

use tch::{Device, Kind, Tensor};

use crate::algo::adam::Coefficient;
use crate::device::cuda_graph::CudaGraph;
use crate::algo::replay::Batch;

/// What an update does besides the critics' step (from `policy_delay` and
/// the critic's head start): each kind is its own graph.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum UpdateKind {
    /// The critics alone (a delayed step).
    Critics,
    /// The critics and the soft target update (the actor still waits).
    CriticsAndTargets,
    /// Critics, actor and targets.
    Full,
}

/// The numbers one update uses that change between updates, as host
/// numbers (eager) or views of the staged tensor (captured).
pub struct UpdateNumbers {
    /// Per critic: Adam's step size and bias correction.
    pub critics: Vec<[Coefficient; 2]>,
    /// The actor's, in updates that step it.
    pub actor: Option<[Coefficient; 2]>,
    pub preactivation_l2: Coefficient,
}

/// This update's numbers as the host counts them (each Adam's
/// [`crate::algo::adam::Adam::advance`]), before they become [`UpdateNumbers`].
pub struct HostNumbers {
    pub critics: Vec<[f64; 2]>,
    pub actor: Option<[f64; 2]>,
    pub preactivation_l2: f64,
}

impl HostNumbers {
    /// The numbers as host coefficients, for an eager update.
    pub fn coefficients(&self) -> UpdateNumbers {
        let pair = |&[a, b]: &[f64; 2]| [Coefficient::Host(a), Coefficient::Host(b)];
        UpdateNumbers { critics: self.critics.iter().map(pair).collect(), actor: self.actor.as_ref().map(pair), preactivation_l2: Coefficient::Host(self.preactivation_l2) }
    }
}

/// The static inputs and the graphs captured over them.
pub struct CapturedUpdates {
    /// The minibatch, [batch, row width] (replay.rs's rows).
    rows: Tensor,
    /// [per critic: step size, bias correction | actor: the same | the
    /// preactivation weight | target noise, batch × actions].
    numbers: Tensor,
    critics: usize,
    noise: Option<Tensor>,
    graphs: HashMap<UpdateKind, CudaGraph>,
}

impl CapturedUpdates {
    /// Room for a minibatch of `batch` rows and the numbers of `critics`
    /// critics and an actor, with target noise for `actions` actions when
    /// `target_noise`. Fails where the CUDA graph shim is not available.
    pub fn new(batch: usize, obs_dim: usize, actions: usize, critics: usize, target_noise: bool, device: Device) -> Result<Self, String> {
        crate::device::cuda_graph::availability()?;
        let rows = Tensor::zeros([batch as i64, Batch::row_width(obs_dim, actions) as i64], (Kind::Float, device));
        let noise_len = if target_noise { batch * actions } else { 0 };
        let numbers = Tensor::zeros([(Self::fixed_len(critics) + noise_len) as i64], (Kind::Float, device));
        let noise = target_noise.then(|| numbers.narrow(0, Self::fixed_len(critics) as i64, noise_len as i64).view([batch as i64, actions as i64]));
        Ok(CapturedUpdates { rows, numbers, critics, noise, graphs: HashMap::new() })
    }

    fn fixed_len(critics: usize) -> usize {
        2 * (critics + 1) + 1
    }

    /// Where the next minibatch is gathered.
    pub fn rows(&self) -> &Tensor {
        &self.rows
    }

    /// Copies this update's numbers and target noise (empty without) to the
    /// device, in one copy that does not wait (device.rs).
    pub fn stage(&mut self, numbers: &HostNumbers, noise: &[f32]) {
        let actor = numbers.actor.unwrap_or([0.0; 2]);
        let mut host: Vec<f32> = numbers.critics.iter().chain([&actor]).flatten().map(|&v| v as f32).collect();
        host.push(numbers.preactivation_l2 as f32);
        host.extend_from_slice(noise);
        let staged = crate::device::torch::to_device_async(Tensor::from_slice(&host), self.numbers.device());
        self.numbers.copy_(&staged);
    }

    /// The inputs a captured update of `kind` reads: the minibatch, the
    /// target noise, and the numbers as views of the staged tensor.
    pub fn inputs(&self, obs_dim: usize, actions: usize, kind: UpdateKind) -> (Batch, Option<Tensor>, UpdateNumbers) {
        let at = |k: usize| Coefficient::Device(self.numbers.get(k as i64));
        let numbers = UpdateNumbers {
            critics: (0..self.critics).map(|c| [at(2 * c), at(2 * c + 1)]).collect(),
            actor: (kind == UpdateKind::Full).then(|| [at(2 * self.critics), at(2 * self.critics + 1)]),
            preactivation_l2: at(2 * self.critics + 2),
        };
        (Batch::from_rows(&self.rows, obs_dim, actions), self.noise.as_ref().map(Tensor::shallow_clone), numbers)
    }

    pub fn graph(&self, kind: UpdateKind) -> Option<&CudaGraph> {
        self.graphs.get(&kind)
    }

    pub fn insert(&mut self, kind: UpdateKind, graph: CudaGraph) {
        self.graphs.insert(kind, graph);
    }

    pub fn len(&self) -> usize {
        self.graphs.len()
    }

    /// Forgets the graphs (after a checkpoint is loaded: they are captured
    /// again on the next updates).
    pub fn clear(&mut self) {
        self.graphs.clear();
    }
}
