//! The imperfect wrist sensor (sensor.rs, docs/peg.md "A sensor that is
//! not perfect"): its statistics, its seeding, and that switching it off
//! leaves the published presets' episodes bit for bit as they were.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::sensor::{SensorConfig, CLASSES};
use super::*;

/// A full episode under a fixed, seeded action sequence: every observed
/// state and reward, as bits, hashed (FNV-1a), with the return.
fn fingerprint(env: &mut PegEnv, seed: u64) -> (u64, f64, usize) {
    let mut actions = ChaCha8Rng::seed_from_u64(1000 + seed);
    let (low, high) = (env.spec().action_low.clone(), env.spec().action_high.clone());
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    let mut eat = |v: f64| {
        for byte in v.to_bits().to_le_bytes() {
            hash = (hash ^ byte as u64).wrapping_mul(0x0100_0000_01b3);
        }
    };
    env.reset(seed).unwrap().iter().for_each(|&v| eat(v));
    let (mut total, mut steps) = (0.0, 0);
    loop {
        let action: Vec<f64> = (0..6).map(|k| actions.random_range(low[k]..=high[k]) * 0.5).collect();
        let step = env.step(&action).unwrap();
        step.state.iter().for_each(|&v| eat(v));
        eat(step.reward);
        total += step.reward;
        steps += 1;
        if step.terminated || step.truncated {
            return (hash, total, steps);
        }
    }
}

fn preset(name: &str) -> PegEnv {
    PegEnv::new(name, PegConfig::preset(name).unwrap()).unwrap()
}

/// Each channel's mean and standard deviation over `samples`.
fn moments(samples: &[[f64; 6]]) -> ([f64; 6], [f64; 6]) {
    let n = samples.len() as f64;
    let mean: [f64; 6] = std::array::from_fn(|i| samples.iter().map(|s| s[i]).sum::<f64>() / n);
    let std = std::array::from_fn(|i| (samples.iter().map(|s| (s[i] - mean[i]).powi(2)).sum::<f64>() / (n - 1.0)).sqrt());
    (mean, std)
}

/// 10,000 readings of a zero wrench: per channel, mean 0 and spread σ
/// (the class's resolution for forces, × 0.05 m for moments, or the
/// explicit figures). Tolerances: the mean within 0.05 σ (5 standard
/// errors), the spread within 3% (its standard error is 0.7%).
#[test]
fn sensor_noise_has_the_configured_mean_and_spread() {
    let configs = [
        (SensorConfig::noisy(), [0.1, 0.1, 0.1, 0.005, 0.005, 0.005]),
        (SensorConfig { class: "ati-gamma".into(), ..SensorConfig::noisy() }, [6.25e-3, 6.25e-3, 6.25e-3, 3.125e-4, 3.125e-4, 3.125e-4]),
        (SensorConfig { class: "onrobot-hexe".into(), moment_std_nm: Some(0.02), ..SensorConfig::noisy() }, [0.2, 0.2, 0.2, 0.02, 0.02, 0.02]),
        (SensorConfig { force_std_n: Some(0.5), lever_arm_m: 0.1, ..SensorConfig::noisy() }, [0.5, 0.5, 0.5, 0.05, 0.05, 0.05]),
    ];
    for (cfg, expected) in configs {
        cfg.validate().unwrap();
        assert!(cfg.stds().iter().zip(expected).all(|(a, b)| (a - b).abs() <= 1e-15), "{cfg:?}: {:?}", cfg.stds());
        let mut sensor = Sensor::new(&cfg).unwrap();
        sensor.start_episode(7);
        // dt = 0: no drift, white noise alone.
        let samples: Vec<[f64; 6]> = (0..10_000).map(|_| sensor.error(0.0)).collect();
        let (mean, std) = moments(&samples);
        for i in 0..6 {
            assert!(mean[i].abs() <= 0.05 * expected[i], "{}: channel {i} mean {} for σ {}", cfg.class, mean[i], expected[i]);
            assert!((std[i] / expected[i] - 1.0).abs() <= 0.03, "{}: channel {i} spread {} for σ {}", cfg.class, std[i], expected[i]);
        }
        // Channels are independent: no correlation between Fx and Fy.
        let corr = samples.iter().map(|s| (s[0] - mean[0]) * (s[1] - mean[1])).sum::<f64>() / (samples.len() as f64 * std[0] * std[1]);
        assert!(corr.abs() < 0.05, "corr(Fx, Fy) = {corr}");
    }
    // The published presets' sensor is off; the -noisy ones are on at the
    // Robotiq FT 300-S class (0.1 N).
    for name in ["peg-group1", "peg-group2", "peg-experiment", "peg-group1-rand", "peg-group2-rand"] {
        assert!(Sensor::new(&PegConfig::preset(name).unwrap().sensor).is_none(), "{name}");
    }
    for name in ["peg-group1-noisy", "peg-group2-noisy"] {
        let cfg = PegConfig::preset(name).unwrap().sensor;
        assert!(cfg.enabled && cfg.class == "robotiq-ft300s" && cfg.force_std() == 0.1, "{name}: {cfg:?}");
    }
}

/// The bias is a random walk from 0: after k steps of dt its spread is
/// d·σ·√(k·dt), its mean 0 (2,000 sensors × 6 channels, 100 steps of the
/// groups' 20 ms; the spread within 5%, its standard error 0.7%).
#[test]
fn sensor_bias_drifts_as_a_random_walk() {
    let cfg = SensorConfig::noisy();
    let (k, dt) = (100, 0.02);
    let mut biases = Vec::new();
    for seed in 0..2_000 {
        let mut sensor = Sensor::new(&cfg).unwrap();
        sensor.start_episode(seed);
        for _ in 0..k {
            sensor.error(dt);
        }
        biases.push(sensor.bias());
        sensor.tare();
        assert_eq!(sensor.bias(), [0.0; 6]);
    }
    let (mean, std) = moments(&biases);
    for i in 0..6 {
        let expected = cfg.drift_per_sqrt_s * cfg.stds()[i] * (k as f64 * dt).sqrt();
        assert!(mean[i].abs() <= 0.1 * expected, "channel {i}: mean bias {} against spread {expected}", mean[i]);
        assert!((std[i] / expected - 1.0).abs() <= 0.05, "channel {i}: bias spread {} against {expected}", std[i]);
    }
    // No drift: the bias stays 0.
    let mut still = Sensor::new(&SensorConfig { drift_per_sqrt_s: 0.0, ..cfg }).unwrap();
    (0..50).for_each(|_| _ = still.error(dt));
    assert_eq!(still.bias(), [0.0; 6]);
}

/// Out of contact the true wrench is exactly 0 (physics_tests), so what a
/// noisy preset reports there is the sensor's error, draw for draw: the
/// state carries the reading in N and N·m, first at the start (no drift),
/// then one control period apart.
#[test]
fn the_state_reports_the_sensor_reading() {
    let mut env = preset("peg-group1-noisy");
    let cfg = env.config().sensor.clone();
    let mut replica = Sensor::new(&cfg).unwrap();
    replica.start_episode(3);
    env.reset(3).unwrap();
    // The same stream, started over at an exact pose 10 mm up.
    env.sensor.as_mut().unwrap().start_episode(3);
    let s0 = env.reset_to([0.0, 0.0, 10.0], [0.0; 3]);
    let close = |state: &[f64], e: [f64; 6]| (0..6).all(|i| (state[6 + i] - e[i]).abs() <= 1e-12 * e[i].abs().max(1e-3));
    let e0 = replica.error(0.0);
    assert!(close(&s0, e0), "{:?} against {e0:?}", &s0[6..]);
    for k in 0..5 {
        let step = env.step(&[0.0; 6]).unwrap();
        let e = replica.error(env.config().controller.control_period_s);
        assert!(close(&step.state, e), "step {k}: {:?} against {e:?}", &step.state[6..]);
        assert!(step.state[6..].iter().all(|&v| v != 0.0));
    }
    // The physical figures stay exact: out of contact, no peak force.
    let metrics = env.episode_metrics();
    assert_eq!((metrics.peak_force_n, metrics.peak_moment_nm), (Some(0.0), Some(0.0)));
}

/// The same seed gives the same noisy episode (fresh or reused
/// environment, and a snapshot steps on identically); another seed another
/// one; the pose draws are the noise-free preset's.
#[test]
fn noisy_episodes_are_reproducible_per_seed() {
    let mut a = preset("peg-group1-noisy");
    let mut b = preset("peg-group1-noisy");
    let first = fingerprint(&mut a, 3);
    fingerprint(&mut a, 4);
    assert_eq!(fingerprint(&mut a, 3), first, "reused environment");
    assert_eq!(fingerprint(&mut b, 3), first, "fresh environment");
    assert_ne!(fingerprint(&mut b, 4).0, first.0, "another seed");
    assert_ne!(fingerprint(&mut preset("peg-group1"), 3).0, first.0, "the noise-free preset");

    let mut plain = preset("peg-group1");
    for seed in 0..5 {
        let (noisy, exact) = (a.reset(seed).unwrap(), plain.reset(seed).unwrap());
        assert_eq!(noisy[..6], exact[..6], "seed {seed}: the pose draw");
        assert_ne!(noisy[6..], exact[6..], "seed {seed}: the first reading");
    }
    a.reset(9).unwrap();
    a.step(&[0.5; 6]).unwrap();
    let mut copy = a.snapshot().unwrap();
    for k in 0..10 {
        assert_eq!(a.step(&[0.3; 6]).unwrap(), copy.step(&[0.3; 6]).unwrap(), "step {k}");
    }
    // CS3's branches: re-seeding changes the draws, not the bias or pose.
    assert!(a.is_stochastic() && !plain.is_stochastic());
    let mut other = a.snapshot().unwrap();
    other.reseed_noise(1);
    a.reseed_noise(2);
    assert_ne!(a.step(&[0.0; 6]).unwrap().state, other.step(&[0.0; 6]).unwrap().state);
}

/// `[sensor]` off leaves the published presets' episodes bit for bit as
/// they were before the sensor existed: full episodes under a fixed action
/// sequence hash to the figures recorded with the code before it (commit
/// 1f13aaf), and an off section with other parameters changes nothing. If
/// the physics is changed on purpose, record the new figures here.
#[test]
fn sensor_off_gives_bit_identical_episodes() {
    let recorded = [
        ("peg-group1", 0, 0xbd4c_3b4e_2802_ad72u64, 0xc016_e14f_0037_e727u64, 52),
        ("peg-group1", 5, 0x0f5b_df2b_6162_fba0, 0xc018_feea_6fb7_ec4a, 52),
        ("peg-group2", 0, 0x5756_b3ee_3e68_ada1, 0xc017_458a_9e02_ea04, 53),
        ("peg-group2", 5, 0xa1a1_82ad_65b6_7e85, 0xc013_80bd_515a_9f8e, 53),
    ];
    let off: toml::Table = toml::from_str("[sensor]\nenabled = false\nclass = \"onrobot-hexe\"\nforce_std_n = 3.0\nmoment_std_nm = 0.3\ndrift_per_sqrt_s = 4.0\n").unwrap();
    for (name, seed, hash, return_bits, steps) in recorded {
        let (h, total, n) = fingerprint(&mut preset(name), seed);
        assert_eq!((h, total.to_bits(), n), (hash, return_bits, steps), "{name} seed {seed}: return {total}");
        let cfg = PegConfig::preset(name).unwrap().with_overrides(&off, "off.toml").unwrap();
        assert!(!cfg.sensor.enabled);
        let mut env = PegEnv::new(name, cfg).unwrap();
        assert!(!env.is_stochastic());
        assert_eq!(fingerprint(&mut env, seed), (h, total, n), "{name} seed {seed}: an off [sensor] section");
    }
}

/// The noisy presets load by name and from a file, step to the end of an
/// episode, and report the physical peaks; a file over a noisy preset can
/// change its class.
#[test]
fn noisy_presets_load_and_step() {
    for name in ["peg-group1-noisy", "peg-group2-noisy"] {
        assert!(crate::known_env_names().contains(&name));
        let mut env = crate::make_env(name).unwrap();
        assert_eq!((env.spec().state_dim(), env.spec().action_dim(), env.spec().name.as_str()), (12, 6, name));
        assert!(env.is_stochastic());
        env.reset(0).unwrap();
        let best = measured_best_constant(name).unwrap();
        let mut steps = 0;
        loop {
            let step = env.step(&best).unwrap();
            assert!(step.state.iter().all(|v| v.is_finite()));
            steps += 1;
            if step.terminated || step.truncated {
                break;
            }
        }
        let metrics = env.episode_metrics();
        assert!(steps > 10 && metrics.peak_force_n.unwrap() > 0.0, "{name}: {steps} steps, {metrics:?}");
    }
    let text = "kind = \"peg\"\npreset = \"peg-group2-noisy\"\n[sensor]\nclass = \"ati-gamma\"\n";
    let env = crate::env_from_toml(text, "ati.toml").unwrap();
    let peg = env.as_any().downcast_ref::<PegEnv>().unwrap();
    assert!(peg.config().sensor.enabled);
    assert_eq!(peg.config().sensor.force_std(), 6.25e-3);
    assert_eq!(peg.config().geometry, PegConfig::group2().geometry);
}

/// `[sensor]` is checked on load: an unknown class names the accepted ones,
/// a bad number its field, an unknown key is refused.
#[test]
fn bad_sensor_settings_name_the_field() {
    let base = PegConfig::group1();
    let error = |text: &str| match base.with_overrides(&toml::from_str(text).unwrap(), "x.toml") {
        Err(EnvError::Invalid { field, message }) => format!("{field}: {message}"),
        Err(EnvError::Parse { message, .. }) => format!("parse: {message}"),
        other => panic!("expected an error for {text:?}, got {other:?}"),
    };
    let unknown = error("[sensor]\nenabled = true\nclass = \"ati-nano\"\n");
    assert!(unknown.starts_with("sensor.class") && unknown.contains("ati-nano"), "{unknown}");
    for class in ["robotiq-ft300s", "ati-gamma", "bota-sensone", "onrobot-hexe"] {
        assert!(unknown.contains(class), "{unknown}");
    }
    // Checked even while off.
    assert!(error("[sensor]\nclass = \"x\"\n").starts_with("sensor.class"));
    for (key, value) in [("force_std_n", "-0.1"), ("moment_std_nm", "nan"), ("lever_arm_m", "inf"), ("drift_per_sqrt_s", "-1.0")] {
        let e = error(&format!("[sensor]\nenabled = true\n{key} = {value}\n"));
        assert!(e.starts_with(&format!("sensor.{key}")), "{e}");
    }
    assert!(error("[sensor]\nnoise_std = 0.1\n").contains("noise_std"));
    assert!(error("[sensor]\nenabled = \"yes\"\n").starts_with("parse"));
    // Every accepted class loads, on or off.
    for class in CLASSES {
        let cfg = base.with_overrides(&toml::from_str(&format!("[sensor]\nenabled = true\nclass = \"{}\"\n", class.name)).unwrap(), "x.toml").unwrap();
        assert_eq!(cfg.sensor.force_std(), class.resolution_n);
    }
}
