//! Adam over a VarStore's variables, with its state (moments and step
//! count) kept as named tensors so a checkpoint can store and restore it
//! exactly. tch's built-in optimizer hides that state.

use tch::{nn::VarStore, Tensor};

use crate::algo::flat::FlatParams;

/// A number an update uses that changes from one update to the next (a
/// step size, a bias correction, an annealed weight): a host number in an
/// eager update, or a one-element tensor on the device in a captured one,
/// which the host refills before each replay (a CUDA graph bakes host
/// numbers in: cuda_graph.rs).
pub enum Coefficient {
    Host(f64),
    Device(Tensor),
}

impl Coefficient {
    /// t × c
    pub fn scale(&self, t: &Tensor) -> Tensor {
        match self {
            Coefficient::Host(c) => t * *c,
            Coefficient::Device(c) => t * c,
        }
    }

    /// t / c
    pub fn divide(&self, t: &Tensor) -> Tensor {
        match self {
            Coefficient::Host(c) => t / *c,
            Coefficient::Device(c) => t / c,
        }
    }
}

pub struct Adam {
    lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
    step: i64,
    /// The trainable variables, moved into one buffer (`flat.rs`), so a
    /// step is a dozen operations on the whole network, not per variable.
    params: FlatParams,
    /// First and second moments, laid out as `params`.
    m: Tensor,
    v: Tensor,
}

impl Adam {
    pub fn new(vs: &VarStore, lr: f64) -> Self {
        let params = FlatParams::new(vs.variables().into_iter().filter(|(_, t)| t.requires_grad()));
        let (m, v) = (params.flat().zeros_like(), params.flat().zeros_like());
        Adam { lr, beta1: 0.9, beta2: 0.999, eps: 1e-8, step: 0, params, m, v }
    }

    /// The parameters as one buffer (for a soft update of a target copy).
    pub fn params(&self) -> &FlatParams {
        &self.params
    }

    /// Everything an update changes: the parameters and both moments
    /// (for undoing an update that left a non-finite number).
    pub fn buffers(&self) -> [&Tensor; 3] {
        [self.params.flat(), &self.m, &self.v]
    }

    pub fn set_lr(&mut self, lr: f64) {
        self.lr = lr;
    }

    pub fn zero_grad(&mut self) {
        self.params.zero_grad();
    }

    /// Scales all gradients so their global L2 norm is at most `max_norm`,
    /// and returns the norm before scaling: NaN or ∞ when a gradient holds
    /// a non-finite number (then nothing is scaled; the caller skips the
    /// step, ppo/mod.rs).
    pub fn clip_grad_norm(&mut self, max_norm: f64) -> f64 {
        let grads: Vec<Tensor> = self.params.variables().map(Tensor::grad).filter(Tensor::defined).collect();
        if grads.is_empty() {
            return 0.0;
        }
        // Squared in f64: an f32 square overflows for |g| > 1.8e19, a
        // finite gradient the clip handles. All variables in one sum and
        // one read (a few operations, not four and a read per variable).
        let flat: Vec<Tensor> = grads.iter().map(|g| g.reshape([-1])).collect();
        let squares = Tensor::cat(&flat, 0).to_kind(tch::Kind::Double).square().sum(tch::Kind::Double);
        let total = f64::try_from(squares).unwrap_or(f64::NAN).sqrt();
        if total.is_finite() && total > max_norm {
            let scale = max_norm / (total + 1e-6);
            tch::no_grad(|| {
                for mut g in grads {
                    let _ = g.g_mul_scalar_(scale);
                }
            });
        }
        total
    }

    /// One Adam step on the accumulated gradients: [`Adam::advance`], then
    /// [`Adam::apply`] with its numbers.
    pub fn step(&mut self) {
        let [step_size, bias2] = self.advance();
        self.apply(&Coefficient::Host(step_size), &Coefficient::Host(bias2));
    }

    /// Counts a step and returns its two numbers: the step size
    /// lr / (1 − β₁ᵗ) and the second moment's bias correction 1 − β₂ᵗ.
    pub fn advance(&mut self) -> [f64; 2] {
        self.step += 1;
        let bias1 = 1.0 - self.beta1.powi(self.step as i32);
        let bias2 = 1.0 - self.beta2.powi(self.step as i32);
        [self.lr / bias1, bias2]
    }

    /// Steps taken, for rewinding to an earlier state: the bias
    /// corrections then count only the steps that stand.
    pub fn steps_taken(&self) -> i64 {
        self.step
    }

    pub fn set_steps_taken(&mut self, step: i64) {
        self.step = step;
    }

    /// The step's arithmetic, with the numbers [`Adam::advance`] gave (as
    /// host numbers, or read from the device in a captured update). With
    /// every variable's gradient at hand, on the whole buffer at once;
    /// otherwise per variable, skipping those without one (PyTorch's
    /// rule). Both give the same numbers per element.
    pub fn apply(&mut self, step_size: &Coefficient, bias2: &Coefficient) {
        let update = |p: &mut Tensor, m: &mut Tensor, v: &mut Tensor, g: &Tensor| {
            let _ = m.g_mul_scalar_(self.beta1).g_add_(&(g * (1.0 - self.beta1)));
            let _ = v.g_mul_scalar_(self.beta2).g_add_(&(g * g * (1.0 - self.beta2)));
            let denom = bias2.divide(v).sqrt() + self.eps;
            let _ = p.g_sub_(&step_size.scale(&(&*m / denom)));
        };
        tch::no_grad(|| match self.params.gradients() {
            Some(g) => update(&mut self.params.flat().shallow_clone(), &mut self.m, &mut self.v, &g),
            None => {
                for ((_, p, mut m), (_, _, mut v)) in self.params.slices(&self.m).zip(self.params.slices(&self.v)) {
                    let g = p.grad();
                    if g.defined() {
                        update(&mut p.shallow_clone(), &mut m, &mut v, &g);
                    }
                }
            }
        });
    }

    /// The state as named tensors: `<name>.m`, `<name>.v`, and `step`.
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let mut out: Vec<(String, Tensor)> = self
            .params
            .slices(&self.m)
            .zip(self.params.slices(&self.v))
            .flat_map(|((name, _, m), (_, _, v))| [(format!("{name}.m"), m), (format!("{name}.v"), v)])
            .collect();
        out.push(("step".into(), Tensor::from(self.step)));
        out
    }

    /// Restores a state written by [`Adam::state`]; names must match.
    pub fn load_state(&mut self, named: &[(String, Tensor)]) -> Result<(), String> {
        let find = |key: &str| named.iter().find(|(n, _)| n == key).map(|(_, t)| t);
        let step = find("step").ok_or("optimizer state lacks `step`")?;
        self.step = i64::try_from(step).map_err(|e| e.to_string())?;
        for ((name, _, mut m), (_, _, mut v)) in self.params.slices(&self.m).zip(self.params.slices(&self.v)) {
            let saved_m = find(&format!("{name}.m")).ok_or_else(|| format!("optimizer state lacks {name}.m"))?;
            let saved_v = find(&format!("{name}.v")).ok_or_else(|| format!("optimizer state lacks {name}.v"))?;
            if saved_m.size() != m.size() || saved_v.size() != v.size() {
                return Err(format!("optimizer state for {name} has shape {:?}, expected {:?}", saved_m.size(), m.size()));
            }
            tch::no_grad(|| {
                m.copy_(saved_m);
                v.copy_(saved_v);
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{nn, Kind};

    /// A store with `w` [3, 4] and `b` [4] from fixed values, and, with
    /// `idle`, a variable that takes no part in the loss.
    fn store(idle: bool) -> (nn::VarStore, Tensor, Tensor) {
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let w = vs.root().var_copy("w", &Tensor::from_slice(&(0..12).map(|k| (k as f32 * 0.7).sin()).collect::<Vec<_>>()).view([3, 4]));
        let b = vs.root().var_copy("b", &Tensor::from_slice(&[0.1f32, -0.2, 0.3, -0.4]));
        if idle {
            let _ = vs.root().var_copy("c_idle", &Tensor::from_slice(&[5.0f32, 6.0]));
        }
        (vs, w, b)
    }

    fn train(idle: bool) -> (Vec<f32>, Vec<(String, Vec<f32>)>) {
        let (vs, w, b) = store(idle);
        let mut adam = Adam::new(&vs, 0.01);
        let x = Tensor::from_slice(&(0..6).map(|k| k as f32 * 0.3 - 1.0).collect::<Vec<_>>()).view([2, 3]);
        for _ in 0..5 {
            let loss = (x.matmul(&w) + &b).tanh().square().mean(Kind::Float);
            adam.zero_grad();
            loss.backward();
            adam.step();
        }
        let values = [&w, &b].iter().flat_map(|t| Vec::<f32>::try_from(t.flatten(0, -1)).unwrap()).collect();
        let state = adam.state().into_iter().filter(|(n, _)| !n.starts_with("c_idle") && n != "step").map(|(n, t)| (n, Vec::<f32>::try_from(t.flatten(0, -1)).unwrap())).collect();
        (values, state)
    }

    /// The norm is every gradient's together, squared in f64 (a finite
    /// gradient of 1e20, whose f32 square overflows, has a finite norm);
    /// above `max_norm` the gradients are scaled to it, and a non-finite
    /// norm leaves them as they were.
    #[test]
    fn gradients_are_clipped_to_their_global_norm() {
        let (vs, w, b) = store(false);
        let mut adam = Adam::new(&vs, 0.01);
        let norm_of_grads = || [&w, &b].iter().map(|v| f64::try_from(v.grad().to_kind(Kind::Double).square().sum(Kind::Double)).unwrap()).sum::<f64>().sqrt();
        // ∂/∂w = 3 (12 numbers), ∂/∂b = 4 (4 numbers): √(12·9 + 4·16).
        (w.sum(Kind::Float) * 3.0 + b.sum(Kind::Float) * 4.0).backward();
        let norm = adam.clip_grad_norm(100.0);
        assert!((norm - 172f64.sqrt()).abs() < 1e-9 && (norm_of_grads() - norm).abs() < 1e-9, "below max_norm nothing is scaled");
        assert!((adam.clip_grad_norm(1.0) - norm).abs() < 1e-9);
        assert!((norm_of_grads() - 1.0).abs() < 1e-5, "scaled to max_norm");
        adam.zero_grad();
        (w.sum(Kind::Float) * 1e20).backward();
        let huge = adam.clip_grad_norm(1.0);
        assert!((huge / (12f64.sqrt() * 1e20) - 1.0).abs() < 1e-6, "norm {huge}");
        adam.zero_grad();
        (w.sum(Kind::Float) * f64::NAN).backward();
        assert!(adam.clip_grad_norm(1.0).is_nan());
        assert!(f64::try_from(w.grad().isnan().all()).is_ok_and(|all| all == 1.0), "a non-finite norm scales nothing");
    }

    /// The whole-buffer step (every gradient there) and the per-variable
    /// step (one variable without a gradient) give the same bits, and the
    /// variable without a gradient does not move.
    #[test]
    fn the_flat_step_equals_the_per_variable_step() {
        let (flat, flat_state) = train(false);
        let (per_variable, per_variable_state) = train(true);
        assert_eq!(flat, per_variable);
        assert_eq!(flat_state, per_variable_state);
        let (vs, _, _) = store(true);
        let mut adam = Adam::new(&vs, 0.01);
        let idle = vs.variables()["c_idle"].shallow_clone();
        let loss = vs.variables()["w"].sum(Kind::Float);
        loss.backward();
        adam.step();
        assert_eq!(Vec::<f32>::try_from(&idle).unwrap(), vec![5.0, 6.0]);
    }
}
