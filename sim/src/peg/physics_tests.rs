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
            env.reset(seed).unwrap();
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
    assert_eq!(env.step(&[0.0; 6]).unwrap_err().to_string(), EnvError::EpisodeOver.to_string());
}

#[test]
fn snapshot_restore_continues_bit_identically() {
    let mut env = env(PegConfig::group1());
    env.reset(3).unwrap();
    let actions = |k: usize| -> [f64; 6] { std::array::from_fn(|i| ((k * 7 + i * 3) % 5) as f64 * 0.5 - 1.0) };
    for k in 0..8 {
        env.step(&actions(k)).unwrap();
    }
    let mut copy = env.snapshot().unwrap();
    for k in 8..30 {
        assert_eq!(env.step(&actions(k)).unwrap(), copy.step(&actions(k)).unwrap(), "step {k}");
    }
}

#[test]
fn same_seed_same_episode_and_bad_actions_change_nothing() {
    let mut a = env(PegConfig::group1());
    let mut b = env(PegConfig::group1());
    assert_eq!(a.reset(11).unwrap(), b.reset(11).unwrap());
    assert_ne!(a.reset(11).unwrap(), a.clone().reset(12).unwrap());
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
fn reward_follows_eqs_16_and_17_in_si_units() {
    let mut env = env(PegConfig::group1());
    env.reset_to([0.0, 0.0, 1.0], [0.0; 3]);
    let step = env.step(&[0.0; 6]).unwrap();
    // No contact yet: only the depth term, z in metres with h_z = 1.
    assert!((step.reward + step.state[2] * 1e-3).abs() < 1e-15);
    let steps = run(&mut env, [0.0; 6]);
    let last = steps.last().unwrap();
    assert!(last.terminated && env.outcome() == Outcome::Inserted, "the a = 0 controller inserts from a centred start");
    let s = &last.state;
    let force = (s[6] * s[6] + s[7] * s[7] + s[8] * s[8]).sqrt();
    let moment = (s[9] * s[9] + s[10] * s[10] + s[11] * s[11]).sqrt();
    let expected = -s[2].max(0.0) * 1e-3 - 0.1 * force - moment + 2.0;
    assert!((last.reward - expected).abs() < 1e-12, "{} vs {expected}", last.reward);
    // The terms add up to the return, and the bonus is r_s once.
    let terms = env.episode_metrics().return_terms.unwrap();
    let total: f64 = step.reward + steps.iter().map(|s| s.reward).sum::<f64>();
    assert!((terms.total() - total).abs() < 1e-9, "{terms:?} vs {total}");
    assert_eq!((terms.bonus, terms.failure), (2.0, 0.0));
    assert!(terms.depth < 0.0 && terms.force < 0.0 && terms.moment < 0.0);
}

/// Failure never pays: a policy that jams on purpose (lateral compliance
/// off, rotational compliance at its maximum, so the peg cannot slide into
/// the hole and tips over on the chamfer until it wedges) exceeds a limit
/// and scores below every successful episode from the same start, however
/// quickly it failed.
#[test]
fn jamming_on_purpose_scores_below_every_success_from_the_same_start() {
    let mut jammed = 0;
    for seed in 0..12 {
        let mut jam_env = env(PegConfig::group1());
        jam_env.reset(seed).unwrap();
        let jam_steps = run(&mut jam_env, [-1.0, -1.0, 2.0, 4.0, 4.0, 4.0]);
        let jam_return: f64 = jam_steps.iter().map(|s| s.reward).sum();
        if !matches!(jam_env.outcome(), Outcome::ForceLimit | Outcome::MomentLimit) {
            continue;
        }
        jammed += 1;
        let terms = jam_env.episode_metrics().return_terms.unwrap();
        assert_eq!(terms.failure, -jam_env.config().failure_charge());
        assert_eq!(terms.bonus, 0.0);
        // Successful controllers from the same start: nominal and doubled
        // lateral compliance.
        for action in [[0.0; 6], [2.0, 2.0, 0.0, 0.0, 0.0, 0.0], [2.0, 2.0, 2.0, 4.0, 4.0, 4.0], [-1.0; 6]] {
            let mut ok_env = env(PegConfig::group1());
            ok_env.reset(seed).unwrap();
            let ok_return: f64 = run(&mut ok_env, action).iter().map(|s| s.reward).sum();
            if ok_env.outcome() == Outcome::Inserted {
                assert!(jam_return < ok_return, "seed {seed}: jam {jam_return} ≥ success {ok_return} with {action:?}");
            }
        }
    }
    assert!(jammed >= 8, "the jamming policy should fail from most starts, failed {jammed} of 12");
}

/// The bound behind the failure rule: no step within the limits costs more
/// than c_max, so C = max_steps · c_max covers any successful episode.
#[test]
fn failure_charge_bounds_every_step_within_limits() {
    let cfg = PegConfig::group1();
    let c_max = cfg.max_step_cost();
    // 31.2 mm · 1 + 50 N · 0.1 + 1.5 N·m · 1.
    assert!((c_max - (0.0312 + 5.0 + 1.5)).abs() < 1e-12, "{c_max}");
    assert!((cfg.failure_charge() - 100.0 * c_max).abs() < 1e-9);
    for action in [[0.0; 6], [2.0, 2.0, 2.0, 4.0, 4.0, 4.0], [-0.5; 6]] {
        for seed in 0..4 {
            let mut e = env(cfg.clone());
            e.reset(seed).unwrap();
            let steps = run(&mut e, action);
            let failed = matches!(e.outcome(), Outcome::ForceLimit | Outcome::MomentLimit);
            let within = if failed { &steps[..steps.len() - 1] } else { &steps[..] };
            for step in within {
                assert!(step.reward >= -c_max, "{} < −c_max = {}", step.reward, -c_max);
            }
        }
    }
}


/// A randomized preset draws its parts from the episode's seed: the same
/// seed gives the same parts and start, other seeds other parts, every draw
/// inside its range, and the ranges are covered. An unrandomized preset
/// keeps its parts in every episode.
#[test]
fn randomized_presets_draw_parts_per_episode_within_their_ranges() {
    let cfg = PegConfig::preset("peg-group1-rand").unwrap();
    let ranges = cfg.randomize.clone().unwrap();
    assert_eq!((cfg.episode.position_error_mm, cfg.episode.angle_error_deg), (0.4, 1.0));
    let mut env = env(cfg.clone());
    let mut twin = env.clone();
    let (mut frictions, mut clearances, mut chamfers) = (Vec::new(), Vec::new(), Vec::new());
    for seed in 0..200 {
        let s0 = env.reset(seed).unwrap();
        let parts = env.episode_config().clone();
        assert_eq!(twin.reset(seed).unwrap(), s0);
        assert_eq!(twin.episode_config(), &parts, "seed {seed}: the same seed must draw the same parts");
        assert!(parts.randomize.is_none());
        let clearance = parts.geometry.hole_side_mm - parts.geometry.peg_side_mm;
        let inside = |v: f64, [lo, hi]: [f64; 2]| (lo..=hi).contains(&v);
        assert!(inside(parts.contact.friction, ranges.friction), "{}", parts.contact.friction);
        assert!(inside(clearance, [ranges.clearance_mm[0] - 1e-12, ranges.clearance_mm[1] + 1e-12]), "{clearance}");
        assert!(inside(parts.geometry.peg_chamfer_mm, ranges.peg_chamfer_mm));
        assert_eq!(parts.geometry.peg_side_mm, cfg.geometry.peg_side_mm, "the peg keeps its size");
        frictions.push(parts.contact.friction);
        clearances.push(clearance);
        chamfers.push(parts.geometry.peg_chamfer_mm);
    }
    // 200 uniform draws span at least 90% of each range.
    for (values, [lo, hi]) in [(frictions, ranges.friction), (clearances, ranges.clearance_mm), (chamfers, ranges.peg_chamfer_mm)] {
        let spread = values.iter().cloned().fold(f64::MIN, f64::max) - values.iter().cloned().fold(f64::MAX, f64::min);
        assert!(spread > 0.9 * (hi - lo), "spread {spread} of [{lo}, {hi}]");
    }
    // The published preset keeps its parts.
    let mut plain = env_for("peg-group1");
    for seed in 0..5 {
        plain.reset(seed).unwrap();
        assert_eq!(plain.episode_config(), plain.config());
    }
}

fn env_for(name: &str) -> PegEnv {
    PegEnv::new(name, PegConfig::preset(name).unwrap()).unwrap()
}

/// Friction acts where it should: with the same start and controller, a
/// slippery part is inserted with less axial force than a sticky one
/// (the wall's normal force times μ resists the advance).
#[test]
fn more_friction_costs_more_axial_force() {
    let mean_peak_fz = |friction: f64| {
        let mut cfg = PegConfig::group1();
        cfg.contact.friction = friction;
        let mut env = env(cfg);
        let mut total = 0.0;
        for seed in 0..8 {
            env.reset(seed).unwrap();
            let steps = run(&mut env, [0.0; 6]);
            total += steps.iter().map(|s| s.state[8].abs()).fold(0.0, f64::max);
        }
        total / 8.0
    };
    let (low, high) = (mean_peak_fz(0.1), mean_peak_fz(0.6));
    assert!(high > low, "peak |Fz| with μ = 0.6: {high:.2} N, with μ = 0.1: {low:.2} N");
}

#[test]
fn bad_randomization_ranges_name_the_field() {
    let base = PegConfig::group1();
    let field = |text: &str| match base.with_overrides(&toml::from_str(text).unwrap(), "x.toml") {
        Err(EnvError::Invalid { field, .. }) => field,
        other => panic!("expected an invalid field, got {other:?}"),
    };
    let ranges = "[randomize]\nfriction = [0.1, 0.6]\nclearance_mm = [0.03, 0.2]\n";
    assert_eq!(field(&format!("{ranges}peg_chamfer_mm = [0.8, 0.4]\n")), "randomize.peg_chamfer_mm");
    assert_eq!(field("[randomize]\nfriction = [0.1, 0.6]\nclearance_mm = [0.0, 0.2]\npeg_chamfer_mm = [0.4, 0.8]\n"), "randomize.clearance_mm");
    // A chamfer at the range's top end wider than half the peg.
    assert_eq!(field(&format!("{ranges}peg_chamfer_mm = [0.4, 5.0]\n")), "randomize");
    let ok = base.with_overrides(&toml::from_str(&format!("{ranges}peg_chamfer_mm = [0.4, 0.8]\n")).unwrap(), "x.toml").unwrap();
    assert!(ok.randomize.is_some());
}

/// Each recorded best constant (controller.base = "best-constant") still
/// beats the constant compliance controller on its preset.
#[test]
fn recorded_best_constants_beat_a_zero() {
    for name in ["peg-group1", "peg-group2", "peg-group2-rand", "peg-group1-noisy", "peg-group2-noisy"] {
        let env = env_for(name);
        let best = measured_best_constant(name).unwrap();
        let b = crate::tune::constant_return(&env, &best, 16, 0).unwrap();
        let zero = crate::tune::constant_return(&env, &[0.0; 6], 16, 0).unwrap();
        assert!(b > zero + 1.0, "{name}: best constant {b:.2}, a = 0 {zero:.2}");
    }
}

/// The default physics against a 4× finer reference
/// (docs/research/2026-11-25-simulator-step-cost.md, "Cheaper physics,
/// checked for accuracy"): starts 0–9 under the best constant, 8 against 32
/// physics steps per control step. The tolerances come from what the
/// figures are for: the same outcome and length (±1 step); per episode, a
/// return within 0.2 (below the smallest difference between connections the
/// studies report as significant, +0.27); and a wrench trace whose RMS force
/// error is at most 20% of the reference's RMS force (the reading the agent
/// sees and the reward charges). Measured: return differences up to 0.14,
/// force errors of 10% on average and 14% at most; 4 physics steps with 4
/// solver iterations reach 41% and 0.33, so the test tells them apart.
#[test]
fn default_physics_tracks_a_32_substep_reference() {
    let best = measured_best_constant("peg-group1").unwrap();
    let episodes = |substeps: usize| {
        let mut cfg = PegConfig::group1();
        cfg.physics.substeps = substeps;
        let mut env = env(cfg);
        (0..10)
            .map(|seed| {
                env.reset(seed).unwrap();
                run(&mut env, best)
            })
            .collect::<Vec<_>>()
    };
    let default = PegConfig::group1().physics.substeps;
    assert_eq!(default, 8, "the stated tolerances were measured at 8 physics steps");
    let (coarse, fine) = (episodes(default), episodes(4 * default));
    let total = |steps: &[Step]| steps.iter().map(|s| s.reward).sum::<f64>();
    let force = |s: &Step| [s.state[6], s.state[7], s.state[8]];
    for (seed, (c, f)) in coarse.iter().zip(&fine).enumerate() {
        let (c_last, f_last) = (c.last().unwrap(), f.last().unwrap());
        assert_eq!(c_last.terminated, f_last.terminated, "seed {seed}: outcome");
        assert!(c.len().abs_diff(f.len()) <= 1, "seed {seed}: {} steps against the reference's {}", c.len(), f.len());
        let return_error = (total(c) - total(f)).abs();
        assert!(return_error <= 0.2, "seed {seed}: return {:.3} against the reference's {:.3}", total(c), total(f));
        let n = c.len().min(f.len());
        let squared = |v: [f64; 3]| v.iter().map(|x| x * x).sum::<f64>();
        let error: f64 = (0..n).map(|i| squared(std::array::from_fn(|j| force(&c[i])[j] - force(&f[i])[j]))).sum();
        let size: f64 = (0..n).map(|i| squared(force(&f[i]))).sum();
        let relative = (error / size).sqrt();
        assert!(relative <= 0.2, "seed {seed}: RMS force error {:.1}% of the reference's", 100.0 * relative);
    }
}
