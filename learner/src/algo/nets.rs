//! The networks: locally connected actor (LCRL, eq. 8), the full-subnets
//! ablation, the globally connected actor (GCRL), and the global critics.
//!
//! Every actor maps a normalized observation [B, m] to a normalized action
//! [B, n] in [−1, 1] (tanh); callers scale it to [lb, ub].
//!
//! The n subnetworks are computed at once as grouped (batched) matrix
//! products: layer k holds weights [n, in, out], and the first layer's
//! weights are multiplied by the mask G (as [n, m, 1]) on every forward
//! pass. A masked weight is exactly zero in the product, so action i gets
//! exactly zero gradient from every state j with G_ij = 0, and the result
//! equals n separate subnetworks on the gathered inputs (tested below).
//!
//! Every layer, of every network here, adds its bias inside the matrix
//! product (`addmm`, `baddbmm`) and applies its activation in place
//! (ELU with a gradient excepted, `super::elu`): the
//! locally connected actor has more hidden units than the global one
//! (n · 96 against 256 per layer at the defaults), so the passes over its
//! activations, not its products, decide its cost (docs/scaling.md,
//! "The sparse actor's cost").

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use tch::nn;
use tch::{Device, Tensor};

use crate::config::Activation;

/// The activation of a layer's fresh output, which nothing else holds:
/// ReLU and tanh in place (autograd differentiates them through their
/// output); ELU by `super::elu`, an exponential instead of libtorch's
/// costlier `expm1` (in place without a gradient).
fn activate(mut x: Tensor, act: Activation) -> Tensor {
    match act {
        Activation::Relu => x.relu_(),
        Activation::Tanh => x.tanh_(),
        Activation::Elu => super::elu::elu(x),
    }
}

/// x · w + b with the bias added inside the product where x is a batch of
/// rows (one pass over the output instead of two).
fn linear(x: &Tensor, w: &Tensor, b: &Tensor) -> Tensor {
    if x.dim() == 2 { b.addmm(x, w) } else { x.matmul(w) + b }
}

/// A trainable variable drawn from U(−bound, bound) per row of `bounds`
/// (one bound per leading index), from a seeded Rust RNG: initial weights
/// depend on the seed alone, never on libtorch's global generator (which
/// concurrent tests or threads would share).
fn uniform_var(path: &nn::Path, name: &str, shape: &[i64], bounds: &[f64], rng: &mut ChaCha8Rng) -> Tensor {
    let per_row = (shape.iter().product::<i64>() as usize) / bounds.len();
    let values: Vec<f32> = bounds
        .iter()
        .flat_map(|&b| (0..per_row).map(move |_| b))
        .map(|b| rng.random_range(-b..=b) as f32)
        .collect();
    let init = Tensor::from_slice(&values).view(shape).to_device(path.device());
    path.var_copy(name, &init)
}

/// PyTorch's default linear init bound, 1/√fan_in; the last layer of actors
/// and critics gets 3e-3 so initial outputs are near 0 (DDPG paper practice).
fn init_bound(fan_in: usize, last: bool) -> f64 {
    if last { 3e-3 } else { 1.0 / (fan_in.max(1) as f64).sqrt() }
}

/// A plain MLP: linear layers with `act` between them.
#[derive(Debug)]
pub struct Mlp {
    layers: Vec<(Tensor, Tensor)>,
    act: Activation,
}

impl Mlp {
    pub fn new(path: &nn::Path, sizes: &[usize], act: Activation, rng: &mut ChaCha8Rng) -> Self {
        let last = sizes.len() - 2;
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(k, w)| {
                let bound = [init_bound(w[0], k == last)];
                let weight = uniform_var(path, &format!("w{k}"), &[w[0] as i64, w[1] as i64], &bound, rng);
                let bias = uniform_var(path, &format!("b{k}"), &[w[1] as i64], &bound, rng);
                (weight, bias)
            })
            .collect();
        Mlp { layers, act }
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        let last = self.layers.len() - 1;
        let mut h = x.shallow_clone();
        for (k, (w, b)) in self.layers.iter().enumerate() {
            h = linear(&h, w, b);
            if k < last {
                h = activate(h, self.act);
            }
        }
        h
    }

    pub fn param_count(&self) -> usize {
        self.layers.iter().map(|(w, b)| w.numel() + b.numel()).sum()
    }
}

/// n subnetworks as grouped matrix products, first layer masked by G.
#[derive(Debug)]
pub struct SubnetActor {
    /// Per layer: weights [n, in, out] and biases [n, 1, out].
    layers: Vec<(Tensor, Tensor)>,
    /// G as [n, m, 1] (1.0 where action i sees state j).
    mask: Tensor,
    /// Inputs of each subnetwork (row sums of G).
    inputs: Vec<usize>,
    act: Activation,
}

impl SubnetActor {
    /// `g` is the n × m 0/1 connection graph (all ones for full-subnets).
    pub fn new(path: &nn::Path, g: &[Vec<u8>], hidden: &[usize], act: Activation, rng: &mut ChaCha8Rng) -> Self {
        let n = g.len();
        let m = g.first().map_or(0, Vec::len);
        let inputs: Vec<usize> = g.iter().map(|row| row.iter().map(|&v| usize::from(v)).sum()).collect();
        let mask_values: Vec<f32> = g.iter().flatten().map(|&v| f32::from(v)).collect();
        let mask = Tensor::from_slice(&mask_values).view([n as i64, m as i64, 1]).to_device(path.device());
        let mut sizes = vec![m];
        sizes.extend_from_slice(hidden);
        sizes.push(1);
        let last = sizes.len() - 2;
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(k, w)| {
                // Each subnetwork gets the init of its own fan-in: the first
                // layer's fan-in is its number of connected states.
                let bounds: Vec<f64> = (0..n).map(|i| init_bound(if k == 0 { inputs[i] } else { w[0] }, k == last)).collect();
                let weight = uniform_var(path, &format!("w{k}"), &[n as i64, w[0] as i64, w[1] as i64], &bounds, rng);
                let bias = uniform_var(path, &format!("b{k}"), &[n as i64, 1, w[1] as i64], &bounds, rng);
                (weight, bias)
            })
            .collect();
        SubnetActor { layers, mask, inputs, act }
    }

    /// The raw outputs [B, n] (before tanh).
    ///
    /// Computed feature-major, [n, units, B]: the first layer is one
    /// product for all subnetworks, (G-masked weights as [n·h, m]) × xᵀ,
    /// whose [n·h, B] output is already [n, h, B] without a copy, and each
    /// later layer is one grouped product of the transposed weights with
    /// it. No activation is ever transposed, and each bias gradient sums
    /// along contiguous memory (docs/scaling.md, "The sparse actor's cost").
    pub fn forward_raw(&self, x: &Tensor) -> Tensor {
        let n = self.inputs.len() as i64;
        let x = if x.dim() == 1 { x.unsqueeze(0) } else { x.shallow_clone() };
        // Layer 0: w [n, m, h] masked, as [n·h, m]; b [n, 1, h] as [n·h, 1].
        // (-1 keeps the batch size: a traced export serves any batch.)
        let (w, b) = &self.layers[0];
        let units = w.size()[2];
        let masked = (w * &self.mask).transpose(1, 2).reshape([n * units, -1]);
        let mut h = b.reshape([n * units, 1]).addmm(&masked, &x.transpose(0, 1)).view([n, units, -1]);
        // Later layers: w [n, in, out] as [n, out, in], b [n, 1, out] as [n, out, 1].
        for (w, b) in &self.layers[1..] {
            h = activate(h, self.act);
            h = b.transpose(1, 2).baddbmm(&w.transpose(1, 2), &h, 1.0, 1.0);
        }
        // [n, 1, B] → [B, n]
        h.squeeze_dim(1).transpose(0, 1)
    }

    /// Parameters that can be non-zero: masked first-layer weights excluded.
    pub fn param_count(&self) -> usize {
        let hidden0 = self.layers[0].0.size()[2] as usize;
        let first: usize = self.inputs.iter().map(|&m_i| m_i * hidden0).sum::<usize>() + self.layers[0].1.numel();
        first + self.layers[1..].iter().map(|(w, b)| w.numel() + b.numel()).sum::<usize>()
    }

    /// Subnetwork i's parameters, with only its connected input rows of the
    /// first layer: what a separate subnetwork i would hold (for tests and
    /// for inspection).
    pub fn subnet_params(&self, i: usize, connected: &[i64]) -> Vec<(Tensor, Tensor)> {
        let index = Tensor::from_slice(connected).to_device(self.mask.device());
        self.layers
            .iter()
            .enumerate()
            .map(|(k, (w, b))| {
                let w_i = w.get(i as i64);
                let w_i = if k == 0 { w_i.index_select(0, &index) } else { w_i };
                (w_i, b.get(i as i64).squeeze_dim(0))
            })
            .collect()
    }

    pub fn activation(&self) -> Activation {
        self.act
    }
}

/// The actor, in one of the three connection patterns.
#[derive(Debug)]
pub enum ActorNet {
    Subnets(SubnetActor),
    Global(Mlp),
}

impl ActorNet {
    /// Normalized action in [−1, 1], [B, n].
    pub fn forward(&self, obs: &Tensor) -> Tensor {
        self.forward_raw(obs).tanh()
    }

    /// The pre-tanh outputs [B, n].
    pub fn forward_raw(&self, obs: &Tensor) -> Tensor {
        match self {
            ActorNet::Subnets(net) => net.forward_raw(obs),
            ActorNet::Global(net) => net.forward(obs),
        }
    }

    pub fn param_count(&self) -> usize {
        match self {
            ActorNet::Subnets(net) => net.param_count(),
            ActorNet::Global(net) => net.param_count(),
        }
    }
}

/// Parameters of a global actor with the configured hidden sizes for an
/// environment of (m states, n actions): for comparing with a local actor.
pub fn global_actor_params(cfg: &crate::config::NetworkConfig, (m, n): (usize, usize)) -> usize {
    let mut sizes = vec![m];
    sizes.extend_from_slice(&cfg.global_hidden);
    sizes.push(n);
    sizes.windows(2).map(|w| w[0] * w[1] + w[1]).sum()
}

/// Parameters of a local actor on graph `g` (n × m) with the configured
/// subnetwork widths, counted as [`SubnetActor::param_count`] counts them
/// (masked first-layer weights excluded).
pub fn local_actor_params(cfg: &crate::config::NetworkConfig, g: &[Vec<u8>]) -> usize {
    let inputs: usize = g.iter().flatten().map(|&v| usize::from(v)).sum();
    let hidden0 = cfg.subnet_hidden.first().copied().unwrap_or(1);
    let mut rest = cfg.subnet_hidden.clone();
    rest.push(1);
    let later: usize = rest.windows(2).map(|w| w[0] * w[1] + w[1]).sum();
    inputs * hidden0 + g.len() * (hidden0 + later)
}

/// Hidden widths for a global actor with as many parameters as `target`
/// (a local actor's, [`local_actor_params`]): the depth of the configured
/// `global_hidden`, every layer one width, the width whose count is
/// nearest `target`. The matched-size control of docs/lcrl-value.md: a
/// local actor's lead is then not its size.
pub fn matched_global_hidden(cfg: &crate::config::NetworkConfig, (m, n): (usize, usize), target: usize) -> Vec<usize> {
    let depth = cfg.global_hidden.len().max(1);
    let count = |width: usize| global_actor_params(&crate::config::NetworkConfig { global_hidden: vec![width; depth], ..cfg.clone() }, (m, n));
    // The count grows with the width: walk up to the first width at or
    // over the target, then take the nearer of it and the one before.
    let mut width = 1;
    while count(width) < target {
        width += 1;
    }
    if width > 1 && target - count(width - 1) < count(width) - target {
        width -= 1;
    }
    vec![width; depth]
}

/// A [B, width] tensor from flat f32 rows.
pub fn batch(rows: &[f32], width: usize, device: Device) -> Tensor {
    Tensor::from_slice(rows).view([(rows.len() / width.max(1)) as i64, width as i64]).to_device(device)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use tch::Kind;

    fn rng() -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(7)
    }

    /// A graph with an empty row, a full row and a partial row.
    fn graph() -> Vec<Vec<u8>> {
        vec![vec![1, 0, 0, 1, 0], vec![1, 1, 1, 1, 1], vec![0, 0, 1, 0, 0], vec![0, 0, 0, 0, 0]]
    }

    /// Subnetwork i as a separate MLP on its gathered inputs.
    fn separate(net: &SubnetActor, g: &[Vec<u8>], x: &Tensor) -> Tensor {
        let columns: Vec<Tensor> = (0..g.len())
            .map(|i| {
                let connected: Vec<i64> = (0..g[i].len() as i64).filter(|&j| g[i][j as usize] == 1).collect();
                let params = net.subnet_params(i, &connected);
                let last = params.len() - 1;
                let mut h = x.index_select(1, &Tensor::from_slice(&connected));
                for (k, (w, b)) in params.iter().enumerate() {
                    h = h.matmul(w) + b;
                    if k < last {
                        h = reference_activation(&h, net.activation());
                    }
                }
                h
            })
            .collect();
        Tensor::cat(&columns, 1)
    }

    /// The activation out of place, as the reference computes it (not the
    /// in-place code under test).
    fn reference_activation(h: &Tensor, act: Activation) -> Tensor {
        match act {
            Activation::Relu => h.relu(),
            Activation::Tanh => h.tanh(),
            Activation::Elu => h.elu(),
        }
    }

    /// Every trainable variable's gradient after `loss.backward()`, in the
    /// store's order, and the gradients zeroed again.
    fn gradients(vs: &nn::VarStore, loss: Tensor) -> Vec<Tensor> {
        loss.backward();
        let mut variables: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
        variables.sort_by(|a, b| a.0.cmp(&b.0));
        variables
            .into_iter()
            .map(|(_, v)| {
                let g = v.grad().copy();
                let _ = v.grad().zero_();
                g
            })
            .collect()
    }

    /// The largest difference between two lists of tensors, below `tol`.
    fn assert_all_close(a: &[Tensor], b: &[Tensor], tol: f64, what: &str) {
        for (a, b) in a.iter().zip(b) {
            let diff = f64::try_from((a - b).abs().max()).unwrap();
            assert!(diff < tol, "{what} differ by {diff}");
        }
    }

    /// For every activation: the batched actor (biases inside the products,
    /// activations in place) gives the outputs and the weight gradients of
    /// separate subnetworks computed out of place, and the global MLP those
    /// of plain products and additions.
    #[test]
    fn in_place_layers_equal_out_of_place_ones_for_every_activation() {
        for act in [Activation::Relu, Activation::Tanh, Activation::Elu] {
            tch::manual_seed(3);
            let g = graph();
            let x = Tensor::randn([16, 5], (Kind::Float, Device::Cpu));
            let vs = nn::VarStore::new(Device::Cpu);
            let net = SubnetActor::new(&vs.root(), &g, &[8, 6], act, &mut rng());
            let batched = net.forward_raw(&x);
            let reference = separate(&net, &g, &x);
            assert_all_close(&[batched.shallow_clone()], &[reference.shallow_clone()], 1e-6, &format!("{act:?}: outputs"));
            let from_batched = gradients(&vs, (&batched * &batched).sum(Kind::Float));
            let from_reference = gradients(&vs, (&reference * &reference).sum(Kind::Float));
            assert_all_close(&from_batched, &from_reference, 1e-5, &format!("{act:?}: weight gradients"));

            let vs = nn::VarStore::new(Device::Cpu);
            let mlp = Mlp::new(&vs.root(), &[5, 8, 6, 3], act, &mut rng());
            let fused = mlp.forward(&x);
            let mut h = x.shallow_clone();
            for (k, (w, b)) in mlp.layers.iter().enumerate() {
                h = h.matmul(w) + b;
                if k + 1 < mlp.layers.len() {
                    h = reference_activation(&h, act);
                }
            }
            assert_all_close(&[fused.shallow_clone()], &[h.shallow_clone()], 1e-6, &format!("{act:?}: MLP outputs"));
            let from_fused = gradients(&vs, (&fused * &fused).sum(Kind::Float));
            let from_plain = gradients(&vs, (&h * &h).sum(Kind::Float));
            assert_all_close(&from_fused, &from_plain, 1e-5, &format!("{act:?}: MLP weight gradients"));
        }
    }

    #[test]
    fn batched_actor_equals_separate_subnetworks() {
        // Every activation: ELU is computed by `super::elu` (its kernel at
        // one thread), not libtorch, and the reference below uses libtorch's.
        tch::set_num_threads(1);
        for act in [Activation::Relu, Activation::Tanh, Activation::Elu] {
            tch::manual_seed(1);
            let vs = nn::VarStore::new(Device::Cpu);
            let g = graph();
            let net = SubnetActor::new(&vs.root(), &g, &[16, 8], act, &mut rng());
            let x = Tensor::randn([32, 5], (Kind::Float, Device::Cpu));
            let batched = net.forward_raw(&x);
            let reference = separate(&net, &g, &x);
            assert_eq!(batched.size(), vec![32, 4]);
            let diff = f64::try_from((batched - reference).abs().max()).unwrap();
            assert!(diff < 1e-6, "{act:?}: max difference {diff}");
        }
    }

    #[test]
    fn masked_states_get_exactly_zero_gradient() {
        // ReLU and ELU (lcrl's own kernel on the CPU at one thread).
        tch::set_num_threads(1);
        for act in [Activation::Relu, Activation::Elu] {
            tch::manual_seed(2);
            let vs = nn::VarStore::new(Device::Cpu);
            let g = graph();
            let net = SubnetActor::new(&vs.root(), &g, &[16, 8], act, &mut rng());
            let x = Tensor::randn([7, 5], (Kind::Float, Device::Cpu)).set_requires_grad(true);
            let out = ActorNet::Subnets(net).forward(&x);
            for (i, row) in g.iter().enumerate() {
                let grads = Tensor::run_backward(&[out.select(1, i as i64).sum(Kind::Float)], &[&x], true, false);
                let grad: Vec<f32> = Vec::try_from(grads[0].abs().sum_dim_intlist(0, false, Kind::Float)).unwrap();
                for (j, &connected) in row.iter().enumerate() {
                    if connected == 0 {
                        assert_eq!(grad[j], 0.0, "{act:?}: action {i} must not see state {j}");
                    } else {
                        assert!(grad[j] > 0.0, "{act:?}: action {i} must see state {j}");
                    }
                }
            }
        }
    }

    #[test]
    fn shapes_and_parameter_counts() {
        let vs = nn::VarStore::new(Device::Cpu);
        let g = graph();
        let local = SubnetActor::new(&vs.root().sub("local"), &g, &[16, 8], Activation::Relu, &mut rng());
        // First layer: (2 + 5 + 1 + 0) connected inputs × 16, plus 4 × 16 biases;
        // then 4 × (16·8 + 8) and 4 × (8·1 + 1).
        assert_eq!(local.param_count(), 8 * 16 + 4 * 16 + 4 * (16 * 8 + 8) + 4 * (8 + 1));
        let full = SubnetActor::new(&vs.root().sub("full"), &vec![vec![1; 5]; 4], &[16, 8], Activation::Relu, &mut rng());
        assert_eq!(full.param_count(), 4 * (5 * 16 + 16 + 16 * 8 + 8 + 8 + 1));
        let global = Mlp::new(&vs.root().sub("global"), &[5, 32, 32, 4], Activation::Relu, &mut rng());
        assert_eq!(global.param_count(), 5 * 32 + 32 + 32 * 32 + 32 + 32 * 4 + 4);
        let x = Tensor::randn([3, 5], (Kind::Float, Device::Cpu));
        for actor in [ActorNet::Subnets(full), ActorNet::Global(global)] {
            let a = actor.forward(&x);
            assert_eq!(a.size(), vec![3, 4]);
            assert!(f64::try_from(a.abs().max()).unwrap() <= 1.0);
        }
    }

    /// The formula counts what the built actor holds, and the matched
    /// global actor lands nearest the target (lti-blocks-8: G has 3 edges a
    /// row, subnetworks [32, 32], global depth 2).
    #[test]
    fn local_and_matched_global_parameter_counts() {
        let cfg = crate::config::NetworkConfig { subnet_hidden: vec![16, 8], ..Default::default() };
        let vs = nn::VarStore::new(Device::Cpu);
        let built = SubnetActor::new(&vs.root(), &graph(), &cfg.subnet_hidden, Activation::Tanh, &mut rng());
        assert_eq!(local_actor_params(&cfg, &graph()), built.param_count());
        let cfg = crate::config::NetworkConfig { subnet_hidden: vec![32, 32], global_hidden: vec![64, 64], ..Default::default() };
        let g: Vec<Vec<u8>> = (0..8).map(|i| (0..16).map(|j| u8::from(j / 2 == i || j == (2 * i + 2) % 16)).collect()).collect();
        let target = local_actor_params(&cfg, &g);
        assert_eq!(target, 8 * (3 * 32 + 32 + 32 * 32 + 32 + 32 + 1));
        let hidden = matched_global_hidden(&cfg, (16, 8), target);
        assert_eq!(hidden, vec![86, 86]);
        let matched = global_actor_params(&crate::config::NetworkConfig { global_hidden: hidden, ..cfg.clone() }, (16, 8)) as f64;
        for other in [85, 87] {
            let off = global_actor_params(&crate::config::NetworkConfig { global_hidden: vec![other; 2], ..cfg.clone() }, (16, 8)) as f64;
            assert!((off - target as f64).abs() >= (matched - target as f64).abs());
        }
    }
}
