//! The exported computation: raw state → applied action, as tensor
//! operations only, so that libtorch can trace it into TorchScript.
//!
//! ```text
//! ŝ = f32(f64(s) / scale)                       (agent::observe)
//! u = clip(f64(actor(ŝ)), −1, 1)                (the actor's tanh output)
//! a = f32(min(max(u · reach + centre, lb), ub))  (ActionMap::to_env)
//! ```
//!
//! Each step is the served path's own arithmetic in its own precision:
//! the state is normalized in f64 and rounded to f32 as `observe` does,
//! the actor is the learner's own network (`build_actor`, its forward
//! pass) in f32, and the action map computes in f64 as
//! `ActionMap::to_env` does, rounded to f32 as `Policy.Act` answers. One
//! exception: a trace records only libtorch's ops, so ELU is libtorch's
//! here where a served CPU policy may use lcrl's kernel (values within
//! 1.2e-7, learner/src/algo/elu.rs; `file::TOLERANCE` allows for it).

use anyhow::{bail, Context};
use lcrl_learner::algo::agent::build_actor;
use lcrl_learner::algo::elu;
use lcrl_learner::algo::nets::ActorNet;
use lcrl_learner::policy::architecture::Architecture;
use lcrl_learner::policy::snapshot::decode_weights;
use lcrl_sim::Env;
use tch::{nn, Device, Kind, Tensor};

/// Everything the traced function reads besides its input.
pub struct Pipeline {
    /// Holds the actor's weights (frozen: constants of the trace).
    _vs: nn::VarStore,
    actor: ActorNet,
    /// Per state component: what `Env::normalize_state` divides it by.
    pub scale: Vec<f64>,
    /// Per action component: b (the base, or the box centre) and
    /// s·(ub − lb)/2, as `ActionMap` holds them.
    pub centre: Vec<f64>,
    pub reach: Vec<f64>,
    pub low: Vec<f64>,
    pub high: Vec<f64>,
    /// The same as f64 tensors, made before tracing: a tensor made from
    /// data inside the traced function would be recorded as zeros.
    tensors: [Tensor; 5],
}

impl Pipeline {
    /// The pipeline of the actor `architecture` describes, with the
    /// weights of `actor.safetensors` bytes, on `env` (its normalization
    /// and action box).
    pub fn new(architecture: &Architecture, weights: &[u8], env: &dyn Env) -> anyhow::Result<Self> {
        let shape = &architecture.shape;
        let mut vs = nn::VarStore::new(Device::Cpu);
        // The seed is irrelevant: every weight is overwritten below.
        let actor = build_actor(&vs.root(), shape.layout(), &architecture.network, 0);
        let named = decode_weights(weights)?;
        for (name, target) in vs.variables().iter_mut() {
            let source = named.iter().find(|(n, _)| n == name).map(|(_, t)| t).with_context(|| format!("actor.safetensors lacks the weights {name}"))?;
            if source.size() != target.size() {
                bail!("actor.safetensors holds {name} of shape {:?}, the architecture needs {:?}", source.size(), target.size());
            }
            tch::no_grad(|| target.copy_(source));
        }
        // Weights that need no gradient become constants of the trace.
        vs.freeze();
        let spec = env.spec();
        let half: Vec<f64> = spec.action_low.iter().zip(&spec.action_high).map(|(lo, hi)| 0.5 * (hi - lo)).collect();
        let centre = match &architecture.base {
            Some(base) => base.clone(),
            None => spec.action_low.iter().zip(&spec.action_high).map(|(lo, hi)| 0.5 * (lo + hi)).collect(),
        };
        let reach: Vec<f64> = half.iter().map(|h| architecture.residual_scale * h).collect();
        let scale = state_scale(env)?;
        let (low, high) = (spec.action_low.clone(), spec.action_high.clone());
        let tensors = [&scale, &reach, &centre, &low, &high].map(|v| Tensor::from_slice(v));
        Ok(Pipeline { _vs: vs, actor, scale, centre, reach, low, high, tensors })
    }

    /// Raw states [B, m] (f32 or f64) → applied actions [B, n] (f32).
    pub fn forward(&self, states: &Tensor) -> Tensor {
        let [scale, reach, centre, low, high] = &self.tensors;
        let normalized = (states.to_kind(Kind::Double) / scale).to_kind(Kind::Float);
        let u = self.actor.forward(&normalized).to_kind(Kind::Double).clamp(-1.0, 1.0);
        let a = (u * reach + centre).maximum(low).minimum(high);
        a.to_kind(Kind::Float)
    }

    /// The traced module: `forward(states [B, m]) -> actions [B, n]`.
    pub fn trace(&self, example: &Tensor) -> anyhow::Result<tch::CModule> {
        // `traceable`: every activation as a libtorch op the trace records.
        let mut module = tch::no_grad(|| {
            elu::traceable(|| tch::CModule::create_by_tracing("LcrlPolicy", "forward", std::slice::from_ref(example), &mut |inputs| vec![self.forward(&inputs[0])]))
        })
        .context("tracing the policy into TorchScript")?;
        module.set_eval();
        Ok(module)
    }
}

/// The divisors of `env`'s normalization, `normalize_state(s) = s / scale`
/// component by component, read back from the environment and checked
/// bit for bit on probe states: an environment whose normalization is not
/// such a division cannot be exported as one.
pub fn state_scale(env: &dyn Env) -> anyhow::Result<Vec<f64>> {
    let m = env.spec().state_dim();
    let reciprocal = env.normalize_state(&vec![1.0; m]);
    let probes = probe_rows(m);
    let normalized: Vec<Vec<f64>> = probes.iter().map(|row| env.normalize_state(row)).collect();
    let fits = |j: usize, s: f64| probes.iter().zip(&normalized).all(|(row, out)| (row[j] / s).to_bits() == out[j].to_bits());
    let mut scale = Vec::with_capacity(m);
    for (j, &r) in reciprocal.iter().enumerate() {
        if !(r.is_finite() && r != 0.0) {
            bail!("{}'s normalization maps state {} = 1 to {r}: not a division by a finite scale, which is all `lcrl export` can write", env.spec().name, env.spec().state_names[j]);
        }
        // 1 / (1 / s) is s or a neighbouring float: take the one that
        // reproduces the environment's own division.
        let guess = 1.0 / r;
        let found = [0i64, 1, -1, 2, -2].into_iter().map(|k| f64::from_bits((guess.to_bits() as i64 + k) as u64)).find(|&s| fits(j, s));
        match found {
            Some(s) => scale.push(s),
            None => bail!(
                "{}'s normalization of state {} is not a division by one number: `lcrl export` can only write a per-component scale",
                env.spec().name,
                env.spec().state_names[j]
            ),
        }
    }
    Ok(scale)
}

/// States of every sign and magnitude, components differing within a row
/// (a normalization that mixes components fails the check).
fn probe_rows(m: usize) -> Vec<Vec<f64>> {
    let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = move || {
        // xorshift64*: a fixed, dependency-free sequence.
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        (x.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..64).map(|_| (0..m).map(|_| (next() - 0.5) * 10f64.powf(next() * 8.0 - 4.0)).collect()).collect()
}
