//! A network's variables moved into one contiguous buffer, each variable a
//! view of its slice ("flat parameters", as apex's fused optimizers and
//! PyTorch's `_flatten_dense_tensors` do it).
//!
//! Why: an Adam step or a soft target update is a handful of elementwise
//! operations per variable. Per variable, that is a dozen kernel launches
//! (GPU) or operator dispatches (CPU) each, for tensors of a few thousand
//! numbers; on the whole buffer, a dozen in all. Elementwise arithmetic
//! does not depend on how the elements are grouped, so the flat step gives
//! the same numbers, bit for bit, as the per-variable one (tested in
//! `adam.rs`).
//!
//! The variables stay the VarStore's own leaves (`set_data` points them at
//! their slice), so the networks, autograd, checkpoints (which copy into
//! the variables in place) and every other holder of a variable see the
//! buffer.

use tch::{Kind, Tensor};

/// One variable's place in the buffer.
struct Slot {
    name: String,
    var: Tensor,
    offset: i64,
    numel: i64,
}

pub struct FlatParams {
    flat: Tensor,
    /// In name order.
    slots: Vec<Slot>,
}

impl FlatParams {
    /// Moves `vars` (name, variable) into one buffer on their device, in
    /// name order. All must share one device and be f32.
    pub fn new(vars: impl IntoIterator<Item = (String, Tensor)>) -> Self {
        let mut vars: Vec<(String, Tensor)> = vars.into_iter().collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        let total: i64 = vars.iter().map(|(_, t)| t.numel() as i64).sum();
        let device = vars.first().map_or(tch::Device::Cpu, |(_, t)| t.device());
        let flat = Tensor::zeros([total], (Kind::Float, device));
        let mut offset = 0;
        let slots = vars
            .into_iter()
            .map(|(name, mut var)| {
                let numel = var.numel() as i64;
                let mut view = flat.narrow(0, offset, numel).view(var.size().as_slice());
                tch::no_grad(|| view.copy_(&var));
                var.set_data(&view);
                let slot = Slot { name, var, offset, numel };
                offset += numel;
                slot
            })
            .collect();
        FlatParams { flat, slots }
    }

    /// The buffer every variable is a view of.
    pub fn flat(&self) -> &Tensor {
        &self.flat
    }

    /// Variable names, in buffer order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.slots.iter().map(|s| s.name.as_str())
    }

    /// The variables, in buffer order.
    pub fn variables(&self) -> impl Iterator<Item = &Tensor> {
        self.slots.iter().map(|s| &s.var)
    }

    /// (name, variable, the same slice of `buffer` shaped as the variable)
    /// per variable: for state kept beside the parameters (Adam's moments).
    pub fn slices<'a>(&'a self, buffer: &'a Tensor) -> impl Iterator<Item = (&'a str, &'a Tensor, Tensor)> + 'a {
        self.slots.iter().map(move |s| (s.name.as_str(), &s.var, buffer.narrow(0, s.offset, s.numel).view(s.var.size().as_slice())))
    }

    /// The variables' gradients as one flat tensor (one copy), or None when
    /// a variable has none (it took no part in the last backward pass).
    pub fn gradients(&self) -> Option<Tensor> {
        let grads: Vec<Tensor> = self.variables().map(Tensor::grad).collect();
        if grads.iter().any(|g| !g.defined()) {
            return None;
        }
        let flat: Vec<Tensor> = grads.iter().map(|g| g.reshape([-1])).collect();
        Some(Tensor::cat(&flat, 0))
    }

    /// Same names and sizes in the same order: a soft update may mix the
    /// two buffers element by element.
    pub fn same_layout(&self, other: &FlatParams) -> bool {
        self.slots.len() == other.slots.len()
            && self.slots.iter().zip(&other.slots).all(|(a, b)| a.name == b.name && a.numel == b.numel && a.var.size() == b.var.size())
    }

    pub fn zero_grad(&mut self) {
        for slot in &mut self.slots {
            slot.var.zero_grad();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::nn;

    #[test]
    fn variables_become_views_of_the_buffer_and_keep_their_values() {
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let b = vs.root().var_copy("b", &Tensor::from_slice(&[1.0f32, 2.0]));
        let a = vs.root().var_copy("a", &Tensor::from_slice(&[3.0f32, 4.0, 5.0, 6.0]).view([2, 2]));
        let flat = FlatParams::new(vs.variables());
        // Name order: a's four values, then b's two.
        assert_eq!(Vec::<f32>::try_from(flat.flat()).unwrap(), vec![3.0, 4.0, 5.0, 6.0, 1.0, 2.0]);
        assert_eq!(flat.names().collect::<Vec<_>>(), vec!["a", "b"]);
        // Writing the buffer changes the variables, and the other way round.
        tch::no_grad(|| {
            let _ = flat.flat().shallow_clone().g_mul_scalar_(2.0);
        });
        assert_eq!(Vec::<f32>::try_from(&b).unwrap(), vec![2.0, 4.0]);
        assert_eq!(a.size(), vec![2, 2]);
        assert!(a.requires_grad() && a.is_leaf());
        // Gradients gather in buffer order.
        let loss = (&a * 3.0).sum(Kind::Float) + (&b * 5.0).sum(Kind::Float);
        loss.backward();
        assert_eq!(Vec::<f32>::try_from(flat.gradients().unwrap()).unwrap(), vec![3.0, 3.0, 3.0, 3.0, 5.0, 5.0]);
    }
}
