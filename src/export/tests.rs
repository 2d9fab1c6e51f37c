//! The traced module is the served policy, for every connection pattern,
//! with and without a base controller and a residual reach: written,
//! loaded back, and run beside `Policy::act` on the same states.

use lcrl_learner::algo::agent::build_actor;
use lcrl_learner::config::{Algo, Connection, TrainConfig};
use lcrl_learner::policy::architecture::{ActorShape, Architecture};
use lcrl_learner::policy::snapshot::encode_weights;
use lcrl_learner::policy::trained::Policy;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::{nn, Device, Tensor};

use super::model::{state_scale, Pipeline};
use super::file::{max_difference, run_module, TOLERANCE};

/// An actor of `architecture` with weights drawn at twice the default
/// init's bound, 2/√fan_in, the last layer's too (a trained actor's
/// outputs spread over [−1, 1]; the initial last layer's 3e-3 would hide
/// a wrong scale). Far larger weights would make the float32 rounding of
/// a batched product (the served policy computes one row at a time)
/// larger than the tolerance; trained actors are far from that.
fn weights(architecture: &Architecture, seed: u64) -> Vec<u8> {
    let vs = nn::VarStore::new(Device::Cpu);
    let s = &architecture.shape;
    build_actor(&vs.root(), s.layout(), &architecture.network, seed);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut named: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    let named: Vec<(String, Tensor)> = named
        .into_iter()
        .map(|(name, t)| {
            let size = t.size();
            let bound = if size.len() >= 2 { 2.0 / (size[size.len() - 2] as f32).sqrt() } else { 0.5 };
            let values: Vec<f32> = (0..t.numel()).map(|_| rng.random_range(-bound..bound)).collect();
            (name, Tensor::from_slice(&values).view(t.size().as_slice()))
        })
        .collect();
    encode_weights(&named).unwrap()
}

fn architecture(env: &str, connection: Connection, base: Option<Vec<f64>>, residual_scale: f64) -> Architecture {
    let e = lcrl_sim::make_env(env).unwrap();
    let (m, n) = (e.spec().state_dim(), e.spec().action_dim());
    // A sparse mask with an empty row (an action CS3 found unconnected).
    let mask: Vec<Vec<u8>> = (0..n).map(|i| (0..m).map(|j| u8::from(i != 1 && (i + j) % 3 != 0)).collect()).collect();
    Architecture {
        shape: ActorShape { env: env.into(), algo: Algo::Ppo, connection, state_dim: m, action_dim: n, mask },
        network: TrainConfig::for_env(env).0.network,
        base,
        residual_scale,
    }
}

/// States a controller meets and states far beyond them, as f32 rows.
fn states(scale: &[f64], count: usize) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    (0..count * scale.len()).map(|k| (rng.random_range(-3.0..3.0) * scale[k % scale.len()]) as f32).collect()
}

fn served(policy: &Policy, env: &dyn lcrl_sim::Env, states: &[f32], m: usize) -> Vec<f32> {
    states.chunks(m).flat_map(|row| policy.act(env, &row.iter().map(|&v| f64::from(v)).collect::<Vec<_>>())).map(|a| a as f32).collect()
}

#[test]
fn the_written_module_acts_as_the_served_policy_for_every_actor() {
    let dir = tempfile::tempdir().unwrap();
    let peg_base = lcrl_sim::peg::measured_best_constant("peg-group1").map(|b| b.to_vec());
    let cases = [
        ("peg-group1", Connection::Local, peg_base.clone(), 1.0),
        ("peg-group1", Connection::Global, peg_base.clone(), 0.5),
        ("peg-group1", Connection::FullSubnets, None, 1.0),
        ("lti-paper", Connection::Local, None, 1.0),
        ("lti-paper", Connection::Global, Some(vec![0.1, -0.2, 0.0]), 0.25),
    ];
    for (k, (env_name, connection, base, reach)) in cases.into_iter().enumerate() {
        let env = lcrl_sim::make_env(env_name).unwrap();
        let architecture = architecture(env_name, connection, base, reach);
        let bytes = weights(&architecture, k as u64);
        let policy = Policy::from_snapshot(&serde_json::to_string(&architecture).unwrap(), &bytes, 7).unwrap();
        let pipeline = Pipeline::new(&architecture, &bytes, env.as_ref()).unwrap();
        let m = architecture.shape.state_dim;
        let probes = states(&pipeline.scale, 500);
        let module = pipeline.trace(&Tensor::from_slice(&probes[..2 * m]).view([2, m as i64])).unwrap();
        let path = dir.path().join(format!("policy-{k}.pt"));
        module.save(&path).unwrap();
        let loaded = tch::CModule::load(&path).unwrap();
        let exported = run_module(&loaded, &probes, m).unwrap();
        let reference = served(&policy, env.as_ref(), &probes, m);
        let difference = max_difference(&exported, &reference);
        assert!(difference <= TOLERANCE, "{env_name} {connection:?}: {difference:e}");
        // One state alone (batch of 1) is the same too.
        assert!(max_difference(&run_module(&loaded, &probes[..m], m).unwrap(), &reference[..reference.len() / 500]) <= TOLERANCE);
        // The check is not trivial: actions spread over the box.
        let n = architecture.shape.action_dim;
        let (low, high) = (&env.spec().action_low, &env.spec().action_high);
        let at_edge = reference.chunks(n).flatten().zip((0..n).cycle()).filter(|(a, i)| f64::from(**a) == low[*i] || f64::from(**a) == high[*i]).count();
        let column = |i: usize| reference.chunks(n).map(move |a| f64::from(a[i]));
        // (Each component's span as a share of what the reach allows.)
        let spread = (0..n)
            .map(|i| (column(i).fold(f64::MIN, f64::max) - column(i).fold(f64::MAX, f64::min)) / (reach * (high[i] - low[i])))
            .fold(0.0, f64::max);
        assert!(spread > 0.3, "{env_name} {connection:?}: actions spread {spread}");
        // Around an off-centre base with the full reach the box clips.
        if architecture.base.is_some() && reach == 1.0 {
            assert!(at_edge > 0, "{env_name} {connection:?}: no action reached the box's edge");
        }
    }
}

#[test]
fn the_normalization_is_read_back_exactly() {
    let peg = lcrl_sim::make_env("peg-group1").unwrap();
    let scale = state_scale(peg.as_ref()).unwrap();
    assert_eq!(scale, [0.05, 0.05, 30.0, 0.3, 0.3, 0.3, 1.0, 1.0, 2.0, 0.015, 0.015, 0.01]);
    let state = [0.013, -0.2, 17.0, 0.1, -0.07, 0.9, 3.5, -1.25, 12.0, 0.02, -0.004, 0.0007];
    let normalized = peg.normalize_state(&state);
    for j in 0..12 {
        assert_eq!((state[j] / scale[j]).to_bits(), normalized[j].to_bits());
    }
    let lti = lcrl_sim::make_env("lti-paper").unwrap();
    assert_eq!(state_scale(lti.as_ref()).unwrap(), [1.0; 3]);
}

#[test]
fn policy_json_sits_beside_the_file_and_never_replaces_it() {
    assert_eq!(super::manifest_path(std::path::Path::new("out/policy.pt")).unwrap(), std::path::Path::new("out/policy.json"));
    assert_eq!(super::manifest_path(std::path::Path::new("policy.onnx")).unwrap(), std::path::Path::new("policy.json"));
    let err = super::manifest_path(std::path::Path::new("policy.json")).unwrap_err().to_string();
    assert!(err.contains("must name the policy file"), "{err}");
}
