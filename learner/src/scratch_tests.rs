use tch::{nn, Device, Kind, Tensor};
use crate::adam::Adam;
use crate::nets::Mlp;
use crate::config::Activation;

#[test]
fn scratch_adam_fits_square() {
    tch::manual_seed(0);
    let vs = nn::VarStore::new(Device::Cpu);
    let net = Mlp::new(&vs.root(), &[1, 64, 64, 1], Activation::Relu);
    let mut opt = Adam::new(&vs, 1e-3);
    let x = Tensor::rand([256, 1], (Kind::Float, Device::Cpu)) * 4.0 - 2.0;
    let y = x.square();
    for it in 0..2000 {
        let loss = (net.forward(&x) - &y).square().mean(Kind::Float);
        opt.zero_grad(); loss.backward(); opt.step();
        if it % 500 == 0 || it == 1999 { println!("it {it} loss {}", f64::try_from(&loss).unwrap()); }
    }
}

#[test]
fn scratch_ddpg_1d() {
    use crate::agent::{Agent, Transition};
    use crate::config::{Connection, TrainConfig};
    use rand::{Rng, SeedableRng};
    let mut cfg: TrainConfig = toml::from_str(&std::fs::read_to_string("../configs/lti-fast.toml").unwrap()).unwrap();
    let get = |k: &str, d: f64| std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d);
    cfg.ddpg.actor_lr = get("ALR", cfg.ddpg.actor_lr); cfg.ddpg.critic_lr = get("CLR", cfg.ddpg.critic_lr);
    cfg.ddpg.tau = get("TAU", cfg.ddpg.tau); cfg.ddpg.noise_end = get("NEND", cfg.ddpg.noise_end);
    cfg.ddpg.batch_size = get("BS", cfg.ddpg.batch_size as f64) as usize; cfg.ddpg.gamma = get("GAMMA", cfg.ddpg.gamma);
    cfg.ddpg.policy_delay = get("PD", 1.0) as usize; cfg.ddpg.target_noise = get("TN", 0.0); cfg.ddpg.preactivation_l2 = get("L2", 0.0);
    tch::manual_seed(0);
    let mut agent = crate::ddpg::Ddpg::new(&cfg.ddpg, &cfg.network, Connection::Global, &[vec![1]], 1, 1, 0);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    for ep in 0..150 {
        let mut s: f32 = rng.random_range(-1.0..1.0);
        let mut ret = 0.0;
        for t in 0..50 {
            let u = agent.explore(&[s], ep);
            let a = u[0].clamp(-1.0, 1.0);
            let r = -(s * s + 0.1 * a * a);
            let s2 = s + a;
            agent.observe(Transition { obs: &[s], action: &u, reward: r, next_obs: &[s2], terminated: false, truncated: t == 49 });
            ret += r; s = s2;
        }
        if ep % 30 == 29 || ep < 30 && ep % 3 == 0 { println!("ep {ep} return {ret:.3} act(0.5)={:?} act(-0.5)={:?} dQda(0.5,0)={:?} dQda(-0.5,0)={:?}", agent.act(&[0.5]), agent.act(&[-0.5]), agent.critic_action_gradient(&[0.5],&[0.0]), agent.critic_action_gradient(&[-0.5],&[0.0])); }
    }
}

#[test]
fn scratch_ops() {
    let d = Tensor::from_slice(&[0.0f32, 1.0]).view([2, 1]);
    let q = Tensor::from_slice(&[10.0f32, 20.0]).view([2, 1]);
    let r = Tensor::from_slice(&[1.0f32, 2.0]).view([2, 1]);
    let y: Tensor = &r + 0.5 * (1.0 - &d) * &q;
    let one_minus: Tensor = 1.0 - &d;
    println!("1-d = {:?}", Vec::<f32>::try_from(one_minus.flatten(0, -1)).unwrap());
    println!("y = {:?}", Vec::<f32>::try_from(y.flatten(0, -1)).unwrap());
}

#[test]
fn scratch_critic_eval() {
    use rand::{Rng, SeedableRng};
    tch::manual_seed(0);
    let gamma = 0.95f32; let k = -0.5f32;
    let vs = nn::VarStore::new(Device::Cpu);
    let critic = Mlp::new(&vs.root(), &[2, 64, 64, 1], Activation::Relu);
    let mut tvs = nn::VarStore::new(Device::Cpu);
    let target = Mlp::new(&tvs.root(), &[2, 64, 64, 1], Activation::Relu);
    tvs.copy(&vs).unwrap();
    let mut opt = Adam::new(&vs, 1e-3);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let pairs: Vec<(Tensor, Tensor)> = { let src = vs.variables(); tvs.variables().into_iter().map(|(n, t)| (t, src[&n].shallow_clone())).collect() };
    for it in 0..6000 {
        let s: Vec<f32> = (0..128).map(|_| rng.random_range(-2.0..2.0)).collect();
        let a: Vec<f32> = (0..128).map(|_| rng.random_range(-1.0..1.0)).collect();
        let st = Tensor::from_slice(&s).view([128, 1]); let at = Tensor::from_slice(&a).view([128, 1]);
        let r: Tensor = -(&st * &st) - 0.1 * (&at * &at);
        let s2: Tensor = &st + &at;
        let y: Tensor = tch::no_grad(|| &r + gamma as f64 * target.forward(&Tensor::cat(&[&s2, &(&s2 * k as f64)], 1)));
        let q = critic.forward(&Tensor::cat(&[&st, &at], 1));
        let loss = (q - y).square().mean(Kind::Float);
        opt.zero_grad(); loss.backward(); opt.step();
        tch::no_grad(|| for (t, src) in pairs.iter() { let mut t = t.shallow_clone(); t.copy_(&(src * 0.01 + &t * 0.99)); });
        if it % 1500 == 1499 {
            let q = |s: f32, a: f32| f64::try_from(critic.forward(&Tensor::from_slice(&[s, a]).view([1, 2]))).unwrap();
            let p = 1.025 / 0.7625;
            let truth = |s: f64, a: f64| -s * s - 0.1 * a * a - 0.95 * p * (s + a) * (s + a);
            println!("it {it}: Q(0.5,-0.25)={:.3} (true {:.3})  dQ/da≈{:.3} (true -0.588)  Q(-1,0.5)={:.3} (true {:.3})", q(0.5, -0.25), truth(0.5, -0.25), (q(0.5, -0.2) - q(0.5, -0.3)) / 0.1, q(-1.0, 0.5), truth(-1.0, 0.5));
        }
    }
}
