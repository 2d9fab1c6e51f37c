//! Physics sanity: signs and magnitudes a robotics engineer would check.
//! Index reminders: state = [x, y, z, alpha, beta, gamma, Fx, Fy, Fz, Mx, My, Mz].

use super::*;

fn env(cfg: PegConfig) -> PegEnv {
    PegEnv::new("peg-test", cfg).unwrap()
}

/// Runs `action` until the episode ends; returns every step.
fn run(env: &mut PegEnv, action: [f64; 6]) -> Vec<Step> {
    let mut steps = Vec::new();
    loop {
        let step = env.step(&action).unwrap();
        let done = step.terminated || step.truncated;
        steps.push(step);
        if done {
            return steps;
        }
    }
}

/// Steps in which the peg touches the hole (any wrench component non-zero).
fn in_contact(steps: &[Step]) -> impl Iterator<Item = &Step> {
    steps.iter().filter(|s| s.state[6..12].iter().any(|&v| v != 0.0))
}

#[test]
fn no_contact_means_exactly_zero_wrench() {
    let mut cfg = PegConfig::group1();
    cfg.episode.start_height_mm = 10.0;
    let mut env = env(cfg);
    env.reset_to([0.1, -0.1, 10.0], [0.3, -0.2, 0.1]);
    // 10 steps of 0.6 mm keep the tip ≥ 4 mm above the block.
    for _ in 0..10 {
        let step = env.step(&[1.0, -0.5, 0.0, 2.0, 0.0, -1.0]).unwrap();
        assert_eq!(&step.state[6..12], &[0.0; 6]);
    }
}

/// With no pose error the constant controller (a = 0) inserts without
/// touching the walls; the only force is seating on the hole floor at the
/// end: the 5 kg moving mass arriving at the planned 30 mm/s and the
/// coupling's last millimetre of travel, about 11 N. Bound: 15 N.
#[test]
fn perfect_alignment_inserts_with_small_force() {
    for cfg in [PegConfig::group1(), PegConfig::group2()] {
        let mut env = env(cfg);
        env.reset_to([0.0, 0.0, 1.0], [0.0; 3]);
        let steps = run(&mut env, [0.0; 6]);
        assert_eq!(env.outcome(), Outcome::Inserted);
        let last = steps.last().unwrap();
        assert!(last.terminated && last.state[2] <= 0.1);
        let peak = env.episode_metrics().peak_force_n.unwrap();
        assert!(peak < 15.0, "peak force {peak} N");
        // Before seating nothing touches: forces stay at 0.
        for (t, s) in steps[..steps.len() - 1].iter().enumerate() {
            assert!(s.state[6..9].iter().all(|f| f.abs() < 1e-6), "step {t}: {:?}", s.state);
        }
        assert!(steps.len() <= 55, "took {} steps", steps.len());
    }
}

/// A lateral offset larger than the clearance lands the chamfer on the hole
/// edge: the hole pushes the peg back toward the axis (F opposite to the
/// offset) and up (Fz > 0), and the peg is centred.
#[test]
fn lateral_offset_gives_restoring_force() {
    for (axis, force) in [(0, 6), (1, 7)] {
        for sign in [1.0, -1.0] {
            let mut position = [0.0, 0.0, 0.3];
            position[axis] = 0.2 * sign;
            let mut env = env(PegConfig::group1());
            env.reset_to(position, [0.0; 3]);
            let steps = run(&mut env, [0.0; 6]);
            let first = in_contact(&steps).next().expect("the chamfer must engage");
            assert!(first.state[force] * sign < -0.1, "axis {axis} sign {sign}: F = {:?}", &first.state[6..9]);
            assert!(first.state[8] > 0.0, "the edge must push the peg up");
            assert!(first.state[axis].abs() < 0.2, "the peg must move toward the axis");
            assert_eq!(env.outcome(), Outcome::Inserted);
        }
    }
}

/// A tilt about y (beta) or x (alpha) ends in two-point contact, where the
/// walls straighten the peg: the moment about the flange opposes the tilt
/// and the tilt shrinks during insertion.
#[test]
fn tilt_gives_restoring_moment() {
    for (angle, moment) in [(4, 10), (3, 9)] {
        for sign in [1.0, -1.0] {
            let mut angles = [0.0; 3];
            angles[angle - 3] = 0.5 * sign;
            let mut env = env(PegConfig::group1());
            env.reset_to([0.0, 0.0, 0.5], angles);
            let steps = run(&mut env, [0.0; 6]);
            let contact: Vec<&Step> = in_contact(&steps).collect();
            assert!(contact.len() > 10, "the tilted peg must touch the walls");
            let mean: f64 = contact.iter().map(|s| s.state[moment]).sum::<f64>() / contact.len() as f64;
            assert!(mean * sign < 0.0, "angle {angle} sign {sign}: mean moment {mean}");
            let final_tilt = steps.last().unwrap().state[angle];
            assert!(final_tilt.abs() < 0.35, "tilt must shrink from 0.5°, ended at {final_tilt}");
            assert_eq!(env.outcome(), Outcome::Inserted);
        }
    }
}

/// Penetration stays below 10 µm (a fifth of group 1's 50 µm clearance;
/// rapier's slop is 5 µm) over random episodes of both groups, measured by
/// parry's contact query after every control step.
#[test]
fn penetration_stays_below_ten_micrometres() {
    for cfg in [PegConfig::group1(), PegConfig::group2()] {
        let mut env = env(cfg);
        for seed in 0..8 {
            env.reset(seed);
            let mut worst: f64 = 0.0;
            loop {
                let step = env.step(&[0.0; 6]).unwrap();
                worst = worst.max(env.penetration_mm());
                if step.terminated || step.truncated {
                    break;
                }
            }
            assert!(worst < 0.01, "seed {seed}: {worst} mm");
            assert_eq!(env.episode_metrics().max_penetration_mm, Some(worst));
        }
    }
}

/// A 3° tilt with the compliance switched off (a = −1) jams: the robot
/// keeps pushing, forces build up, and the episode ends on the force limit.
#[test]
fn jamming_ends_on_the_force_limit() {
    let mut env = env(PegConfig::group1());
    env.reset_to([0.0, 0.0, 0.5], [0.0, 3.0, 0.0]);
    let steps = run(&mut env, [-1.0; 6]);
    let last = steps.last().unwrap();
    assert!(last.terminated);
    assert!(matches!(env.outcome(), Outcome::ForceLimit | Outcome::MomentLimit), "{:?}", env.outcome());
    assert!(last.state[2] > 5.0, "jammed near the entrance, not inserted: z = {}", last.state[2]);
    assert!(env.episode_metrics().peak_force_n.unwrap() > 20.0);
    // Failing early must not pay: the jam costs more than a clean insertion.
    let jam_return: f64 = steps.iter().map(|s| s.reward).sum();
    let mut clean = PegEnv::new("peg-test", PegConfig::group1()).unwrap();
    clean.reset_to([0.0, 0.0, 0.5], [0.0; 3]);
    let clean_return: f64 = run(&mut clean, [0.0; 6]).iter().map(|s| s.reward).sum();
    assert!(jam_return < 2.0 * clean_return, "jam {jam_return} vs clean {clean_return}");
    assert_eq!(env.step(&[0.0; 6]).unwrap_err().to_string(), EnvError::EpisodeOver.to_string());
}

#[test]
fn snapshot_restore_continues_bit_identically() {
    let mut env = env(PegConfig::group1());
    env.reset(3);
    let actions = |k: usize| -> [f64; 6] { std::array::from_fn(|i| ((k * 7 + i * 3) % 5) as f64 * 0.5 - 1.0) };
    for k in 0..8 {
        env.step(&actions(k)).unwrap();
    }
    let mut copy = env.snapshot();
    for k in 8..30 {
        assert_eq!(env.step(&actions(k)).unwrap(), copy.step(&actions(k)).unwrap(), "step {k}");
    }
}

#[test]
fn same_seed_same_episode_and_bad_actions_change_nothing() {
    let mut a = env(PegConfig::group1());
    let mut b = env(PegConfig::group1());
    assert_eq!(a.reset(11), b.reset(11));
    assert_ne!(a.reset(11), a.clone().reset(12));
    a.step(&[0.5; 6]).unwrap();
    b.step(&[0.5; 6]).unwrap();
    let err = a.step(&[0.0, 0.0, f64::NAN, 0.0, 0.0, 0.0]).unwrap_err();
    assert!(matches!(err, EnvError::NonFiniteAction { index: 2, .. }));
    assert!(matches!(a.step(&[0.0; 5]).unwrap_err(), EnvError::ActionDim { expected: 6, got: 5 }));
    assert_eq!(a.state(), b.state());
    // Out-of-range actions are clipped: 10 behaves as ub = 2 on x.
    let big = a.step(&[10.0, 0.0, 0.0, 0.0, 0.0, 0.0]).unwrap();
    let clipped = b.step(&[2.0, 0.0, 0.0, 0.0, 0.0, 0.0]).unwrap();
    assert_eq!(big, clipped);
}

#[test]
fn reward_follows_eqs_16_and_17() {
    let mut env = env(PegConfig::group1());
    env.reset_to([0.0, 0.0, 1.0], [0.0; 3]);
    let step = env.step(&[0.0; 6]).unwrap();
    // No contact yet: only the depth term, z in cm with h_z = 1.
    assert!((step.reward + step.state[2] / 10.0).abs() < 1e-12);
    let steps = run(&mut env, [0.0; 6]);
    let last = steps.last().unwrap();
    let s = &last.state;
    let force = (s[6] * s[6] + s[7] * s[7] + s[8] * s[8]).sqrt();
    let moment = (s[9] * s[9] + s[10] * s[10] + s[11] * s[11]).sqrt();
    let expected = -s[2].max(0.0) / 10.0 - 0.1 * force - moment + 2.0;
    assert!((last.reward - expected).abs() < 1e-12, "{} vs {expected}", last.reward);
}
