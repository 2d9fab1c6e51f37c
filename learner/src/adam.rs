//! Adam over a VarStore's variables, with its state (moments and step
//! count) kept as named tensors so a checkpoint can store and restore it
//! exactly. tch's built-in optimizer hides that state.

use std::collections::BTreeMap;

use tch::{nn::VarStore, Tensor};

pub struct Adam {
    lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
    step: i64,
    /// Variable name → (parameter, first moment, second moment), in name order.
    slots: BTreeMap<String, (Tensor, Tensor, Tensor)>,
}

impl Adam {
    pub fn new(vs: &VarStore, lr: f64) -> Self {
        let slots = vs
            .variables()
            .into_iter()
            .filter(|(_, t)| t.requires_grad())
            .map(|(name, p)| {
                let (m, v) = (p.zeros_like(), p.zeros_like());
                (name, (p, m, v))
            })
            .collect();
        Adam { lr, beta1: 0.9, beta2: 0.999, eps: 1e-8, step: 0, slots }
    }

    pub fn set_lr(&mut self, lr: f64) {
        self.lr = lr;
    }

    pub fn zero_grad(&mut self) {
        for (p, _, _) in self.slots.values_mut() {
            p.zero_grad();
        }
    }

    /// Scales all gradients so their global L2 norm is at most `max_norm`.
    pub fn clip_grad_norm(&mut self, max_norm: f64) {
        let total: f64 = self
            .slots
            .values()
            .filter(|(p, _, _)| p.grad().defined())
            .map(|(p, _, _)| f64::try_from(p.grad().square().sum(tch::Kind::Double)).unwrap_or(0.0))
            .sum::<f64>()
            .sqrt();
        if total > max_norm {
            let scale = max_norm / (total + 1e-6);
            tch::no_grad(|| {
                for (p, _, _) in self.slots.values() {
                    let mut g = p.grad();
                    if g.defined() {
                        let _ = g.g_mul_scalar_(scale);
                    }
                }
            });
        }
    }

    /// One Adam step on the accumulated gradients.
    pub fn step(&mut self) {
        self.step += 1;
        let bias1 = 1.0 - self.beta1.powi(self.step as i32);
        let bias2 = 1.0 - self.beta2.powi(self.step as i32);
        let step_size = self.lr / bias1;
        tch::no_grad(|| {
            for (p, m, v) in self.slots.values_mut() {
                let g = p.grad();
                if !g.defined() {
                    continue;
                }
                let _ = m.g_mul_scalar_(self.beta1).g_add_(&(&g * (1.0 - self.beta1)));
                let _ = v.g_mul_scalar_(self.beta2).g_add_(&(&g * &g * (1.0 - self.beta2)));
                let denom = (&*v / bias2).sqrt() + self.eps;
                let _ = p.g_sub_(&(&*m / denom * step_size));
            }
        });
    }

    /// The state as named tensors: `<name>.m`, `<name>.v`, and `step`.
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let mut out: Vec<(String, Tensor)> = self
            .slots
            .iter()
            .flat_map(|(name, (_, m, v))| [(format!("{name}.m"), m.shallow_clone()), (format!("{name}.v"), v.shallow_clone())])
            .collect();
        out.push(("step".into(), Tensor::from(self.step)));
        out
    }

    /// Restores a state written by [`Adam::state`]; names must match.
    pub fn load_state(&mut self, named: &[(String, Tensor)]) -> Result<(), String> {
        let find = |key: &str| named.iter().find(|(n, _)| n == key).map(|(_, t)| t);
        let step = find("step").ok_or("optimizer state lacks `step`")?;
        self.step = i64::try_from(step).map_err(|e| e.to_string())?;
        for (name, (_, m, v)) in self.slots.iter_mut() {
            let saved_m = find(&format!("{name}.m")).ok_or_else(|| format!("optimizer state lacks {name}.m"))?;
            let saved_v = find(&format!("{name}.v")).ok_or_else(|| format!("optimizer state lacks {name}.v"))?;
            if saved_m.size() != m.size() {
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
