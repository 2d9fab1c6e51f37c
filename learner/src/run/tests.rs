//! Training-level tests: learning quality against the LQR ceilings, exact
//! resume, determinism, validation and selection, what a run records.

use std::path::Path;

use lcrl_sim::make_env;

use crate::config::{Algo, Connection, TrainConfig};
use crate::policy::trained::Policy;
use crate::run::files::EpisodeRow;
use crate::run::trainer::{train, TrainOutcome, TrainRequest};

fn lti_fast() -> TrainConfig {
    TrainConfig::load(Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../configs/lti-fast.toml"))).unwrap()
}

/// A very small DDPG setting for mechanics tests (not learning quality).
fn tiny() -> TrainConfig {
    let mut cfg = lti_fast();
    cfg.ddpg.warmup_steps = 40;
    cfg.ddpg.batch_size = 16;
    cfg.ppo.rollout_steps = 64;
    cfg.ppo.minibatch_size = 16;
    cfg.ppo.epochs = 2;
    cfg.run.episodes = 4;
    cfg.run.checkpoint_every = 2;
    cfg.run.eval_episodes = 2;
    cfg
}

fn run(algo: Algo, connection: Connection, cfg: TrainConfig, dir: &Path, resume: bool) -> TrainOutcome {
    run_until(algo, connection, cfg, dir, resume, None)
}

fn run_until(algo: Algo, connection: Connection, cfg: TrainConfig, dir: &Path, resume: bool, stop_after: Option<usize>) -> TrainOutcome {
    let request = TrainRequest {
        env: "lti-paper".into(),
        algo,
        connection,
        graph: None,
        config: cfg,
        settings_source: "test".into(),
        run_dir: dir.into(),
        resume,
        stop_after,
    };
    train(&request, &mut |_| {}).unwrap()
}

/// Rows without their wall-clock columns.
fn timeless(rows: &[EpisodeRow]) -> Vec<(usize, f64, usize)> {
    rows.iter().map(|r| (r.episode, r.episode_return, r.length)).collect()
}

fn within(value: f64, reference: f64, share: f64) -> bool {
    (value - reference).abs() <= share * reference.abs()
}

/// Budget: 1000 episodes of 50 steps (50k environment steps), ≈8 s each.
/// The global actor can represent the LQR controller, so it is held to
/// 10% of lqr_return (deterministic policy, 100 evaluation episodes).
#[test]
fn ppo_global_reaches_lqr() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = lti_fast();
    cfg.run.episodes = 1000;
    let s = run(Algo::Ppo, Connection::Global, cfg, dir.path(), false).summary;
    let lqr = s.evaluation.lqr_return.unwrap();
    assert!(within(s.evaluation.eval_return, lqr, 0.10), "eval {} vs LQR {lqr}", s.evaluation.eval_return);
}

/// The local actor cannot see s2 from a1 (G of eq. 10), and the LQR gain
/// uses it, so its ceiling is the best G-structured controller
/// (masked_lqr_return, about 26% below lqr_return here). Held to 10% of it.
#[test]
fn ppo_local_reaches_the_g_structured_optimum() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = lti_fast();
    cfg.run.episodes = 1000;
    let s = run(Algo::Ppo, Connection::Local, cfg, dir.path(), false).summary;
    let masked = s.evaluation.masked_lqr_return.unwrap();
    assert!(within(s.evaluation.eval_return, masked, 0.10), "eval {} vs masked LQR {masked}", s.evaluation.eval_return);
    assert!(masked < s.evaluation.lqr_return.unwrap());
}

/// DDPG, same budget as PPO: 1000 episodes (50k steps, ≈35 s), held to
/// the same bar: the local actor within 10% of its G-structured optimum
/// (seeds 0–4 with configs/lti-fast.toml end within 2.9%). The global
/// actor's run to LQR (seeds 0–4: within 3.6%) is the distributed
/// learner's test (e2e::distributed_learning::run_ddpg_global_one_actor_reaches_lqr),
/// and DDPG's update rule has its own (algo::ddpg::tests).
#[test]
fn ddpg_local_reaches_the_g_structured_optimum() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = lti_fast();
    cfg.run.episodes = 1000;
    let s = run(Algo::Ddpg, Connection::Local, cfg, dir.path(), false).summary;
    let masked = s.evaluation.masked_lqr_return.unwrap();
    assert!(within(s.evaluation.eval_return, masked, 0.10), "eval {} vs masked LQR {masked}", s.evaluation.eval_return);
}

/// 4 episodes straight, or interrupted after 2 then --resume: the same rows,
/// counters and final policy (one thread, same seed). DDPG also with twin
/// critics and annealed learning rates, whose second critic, its optimizer
/// and the schedules must come back from the checkpoint as well.
#[test]
fn resumed_run_continues_exactly() {
    let mut td3 = tiny();
    td3.ddpg.twin_critics = true;
    td3.ddpg.anneal_lr = true;
    for (algo, cfg) in [(Algo::Ddpg, tiny()), (Algo::Ddpg, td3), (Algo::Ppo, tiny())] {
        let straight_dir = tempfile::tempdir().unwrap();
        let straight = run(algo, Connection::Local, cfg.clone(), straight_dir.path(), false);
        let resumed_dir = tempfile::tempdir().unwrap();
        run_until(algo, Connection::Local, cfg.clone(), resumed_dir.path(), false, Some(2));
        if cfg.ddpg.twin_critics {
            assert!(crate::policy::checkpoint::latest_checkpoint(resumed_dir.path()).unwrap().join("critic2.safetensors").is_file());
        }
        let resumed = run(algo, Connection::Local, cfg, resumed_dir.path(), true);
        assert_eq!(timeless(&straight.rows), timeless(&resumed.rows), "{algo:?}");
        assert_eq!((straight.summary.env_steps, straight.summary.updates), (resumed.summary.env_steps, resumed.summary.updates));
        assert_eq!(straight.summary.evaluation.eval_return, resumed.summary.evaluation.eval_return, "{algo:?}: final policies differ");
    }
}

/// Validation every 2 episodes of 6 chooses the run's policy: the choice
/// is the best of the validations (the first of equals), RUN/selected/
/// holds exactly the policy that scored it (replayed on the validation
/// starts, it gives the recorded return), `Policy::load` of the run is
/// that policy, training is the same as without validation, and a run
/// interrupted at a validation resumes its selection exactly.
#[test]
fn validation_selects_the_best_policy_and_survives_resume() {
    let mut cfg = tiny();
    cfg.run.episodes = 6;
    cfg.run.validation_episodes = 3;
    cfg.run.validate_every = 2;
    let plain_dir = tempfile::tempdir().unwrap();
    let plain = run(Algo::Ddpg, Connection::Local, tiny_with_episodes(6), plain_dir.path(), false);
    assert!(plain.summary.selection.is_none() && plain.summary.evaluation.last_eval_return.is_none());
    let dir = tempfile::tempdir().unwrap();
    let straight = run(Algo::Ddpg, Connection::Local, cfg.clone(), dir.path(), false);
    assert_eq!(timeless(&plain.rows), timeless(&straight.rows), "validation changed training");
    assert_eq!(straight.summary.evaluation.last_eval_return, Some(plain.summary.evaluation.eval_return), "the last policy is the plain run's");

    let chosen = straight.summary.selection.clone().unwrap();
    let episodes: Vec<usize> = chosen.history.iter().map(|v| v.episode).collect();
    assert_eq!(episodes, [0, 2, 4, 6]);
    let best = chosen.history.iter().fold(f64::NEG_INFINITY, |b, v| b.max(v.mean_return));
    let first_best = chosen.history.iter().find(|v| v.mean_return == best).unwrap();
    assert_eq!((chosen.episode, chosen.validation_return), (first_best.episode, best));

    let policy = Policy::load(dir.path()).unwrap();
    assert_eq!(policy.episode, Some(chosen.episode), "Policy::load(run) is not the selected policy");
    let mut env = make_env("lti-paper").unwrap();
    let probe = env.fresh();
    let first = lcrl_sim::seeds::validation(cfg.run.seed, 0);
    let (replayed, _) = lcrl_sim::evaluate::evaluate(env.as_mut(), "selected", 3, first, &mut |s| policy.act(probe.as_ref(), s), &mut |_| {}).unwrap();
    assert_eq!(replayed.mean_return, chosen.validation_return);

    let resumed_dir = tempfile::tempdir().unwrap();
    run_until(Algo::Ddpg, Connection::Local, cfg.clone(), resumed_dir.path(), false, Some(2));
    let resumed = run(Algo::Ddpg, Connection::Local, cfg, resumed_dir.path(), true);
    assert_eq!(resumed.summary.selection, straight.summary.selection);
    assert_eq!(resumed.summary.evaluation.eval_return, straight.summary.evaluation.eval_return);
}

/// `run.confirm_candidates`: at the end the best validated policies and
/// the starting one run the confirmation starts, and the best of them is
/// handed over. On 1 validation start per validation the ranking is noise,
/// so the confirmation, on 8 starts, can overturn it (PPO, whose policies
/// change gradually, so that several are close). The candidates are
/// the 2 best validations and the first; `RUN/candidates/` keeps exactly
/// them; each recorded score replays from its folder on the confirmation
/// starts; RUN/selected/ and the hand-over are the best score; training and
/// the validations are those of the run without it; and a run interrupted
/// at a validation confirms the same.
#[test]
fn confirmation_hands_over_the_best_candidate_on_more_starts() {
    let mut cfg = tiny();
    cfg.run.episodes = 10;
    // Of run seeds 0–6 here, 3 and 5 are those whose confirmation
    // overturns the validations' choice.
    cfg.run.seed = 3;
    cfg.run.validation_episodes = 1;
    cfg.run.validate_every = 1;
    let unconfirmed_dir = tempfile::tempdir().unwrap();
    let unconfirmed = run(Algo::Ppo, Connection::Local, cfg.clone(), unconfirmed_dir.path(), false);
    (cfg.run.confirm_candidates, cfg.run.confirm_episodes) = (2, 8);
    let dir = tempfile::tempdir().unwrap();
    let straight = run(Algo::Ppo, Connection::Local, cfg.clone(), dir.path(), false);
    assert_eq!(timeless(&unconfirmed.rows), timeless(&straight.rows), "confirmation changed training");
    let (plain, chosen) = (unconfirmed.summary.selection.unwrap(), straight.summary.selection.clone().unwrap());
    assert_eq!(plain.history, chosen.history);
    assert!(plain.confirmation.is_none() && !unconfirmed_dir.path().join("candidates").exists());

    let mut ranked = chosen.history.clone();
    ranked.sort_by(|a, b| b.mean_return.total_cmp(&a.mean_return));
    let mut expected: Vec<usize> = ranked[..2].iter().map(|v| v.episode).collect();
    if !expected.contains(&0) {
        expected.push(0);
    }
    let confirmation = chosen.confirmation.clone().expect("the run confirms its choice");
    let candidates: Vec<usize> = confirmation.candidates.iter().map(|c| c.episode).collect();
    assert_eq!(candidates, expected);
    let mut kept: Vec<String> = std::fs::read_dir(dir.path().join("candidates")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    kept.sort();
    let mut sorted = expected.clone();
    sorted.sort();
    assert_eq!(kept, sorted.iter().map(|e| format!("episode-{e:07}")).collect::<Vec<_>>());

    let mut env = make_env("lti-paper").unwrap();
    let probe = env.fresh();
    let first = lcrl_sim::seeds::confirmation(cfg.run.seed, 0);
    for c in &confirmation.candidates {
        let policy = Policy::load(&dir.path().join(format!("candidates/episode-{:07}", c.episode))).unwrap();
        assert_eq!(policy.episode, Some(c.episode));
        let (replayed, _) = lcrl_sim::evaluate::evaluate(env.as_mut(), "candidate", 8, first, &mut |s| policy.act(probe.as_ref(), s), &mut |_| {}).unwrap();
        assert_eq!(replayed.mean_return, c.mean_return, "candidate after {} episodes", c.episode);
        assert_eq!(c.validation_return, chosen.history.iter().find(|v| v.episode == c.episode).unwrap().mean_return);
    }
    let best = confirmation.candidates.iter().fold(f64::NEG_INFINITY, |b, c| b.max(c.mean_return));
    let pick = confirmation.candidates.iter().find(|c| c.mean_return == best).unwrap();
    assert_eq!(chosen.episode, pick.episode);
    assert_ne!(chosen.episode, plain.episode, "the setting must let the confirmation overturn the validations: {chosen:?}");
    assert_eq!(Policy::load(dir.path()).unwrap().episode, Some(pick.episode), "RUN/selected/ is not the confirmed policy");
    assert_eq!(crate::run::selection::read_record(&dir.path().join("selected")).unwrap(), Some(chosen.clone()));
    assert_ne!(straight.summary.evaluation.eval_return, unconfirmed.summary.evaluation.eval_return, "another policy is evaluated");

    let resumed_dir = tempfile::tempdir().unwrap();
    run_until(Algo::Ppo, Connection::Local, cfg.clone(), resumed_dir.path(), false, Some(3));
    let resumed = run(Algo::Ppo, Connection::Local, cfg, resumed_dir.path(), true);
    assert_eq!(resumed.summary.selection, straight.summary.selection);
    assert_eq!(resumed.summary.evaluation.eval_return, straight.summary.evaluation.eval_return);
}

/// The final evaluation runs on the run's own starts by default, and on
/// the given ones with `run.eval_seed` (a study's: the best constant's),
/// and says which: a = 0 on those starts matches a direct evaluation.
#[test]
fn evaluation_starts_are_the_runs_own_or_the_given_ones() {
    tch::set_num_threads(1);
    let env = make_env("lti-paper").unwrap();
    let zeros = vec![0.0; env.spec().action_names.len()];
    let zero = |first: u64| lcrl_sim::tune::constant_return(env.as_ref(), &zeros, 2, first).unwrap();
    let close = |a: Option<f64>, b: f64| a.is_some_and(|a| (a - b).abs() <= 1e-9 * b.abs().max(1.0));
    let dir = tempfile::tempdir().unwrap();
    let own = run(Algo::Ppo, Connection::Global, tiny(), &dir.path().join("own"), false).summary;
    let first = lcrl_sim::seeds::run_evaluation(0, 0);
    assert_eq!(own.evaluation.eval_seed, Some(first));
    assert!(close(own.evaluation.zero_action_return, zero(first)), "{:?} against {}", own.evaluation.zero_action_return, zero(first));
    let mut cfg = tiny();
    cfg.run.eval_seed = Some(0);
    let given = run(Algo::Ppo, Connection::Global, cfg, &dir.path().join("given"), false).summary;
    assert_eq!(given.evaluation.eval_seed, Some(0));
    assert!(close(given.evaluation.zero_action_return, zero(0)), "{:?} against {}", given.evaluation.zero_action_return, zero(0));
    assert_ne!(zero(0), zero(first), "the two sets of starts must differ for this test to tell them apart");
}

fn tiny_with_episodes(episodes: usize) -> TrainConfig {
    let mut cfg = tiny();
    cfg.run.episodes = episodes;
    cfg
}

#[test]
fn same_seed_gives_identical_metrics() {
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    let first = run(Algo::Ddpg, Connection::Global, tiny(), a.path(), false);
    let second = run(Algo::Ddpg, Connection::Global, tiny(), b.path(), false);
    assert_eq!(timeless(&first.rows), timeless(&second.rows));
    let mut other = tiny();
    other.run.seed = 1;
    let third = run(Algo::Ddpg, Connection::Global, other, tempfile::tempdir().unwrap().path(), false);
    assert_ne!(timeless(&first.rows), timeless(&third.rows));
}

#[test]
fn refuses_to_overwrite_a_run_and_rejects_mismatched_graphs() {
    let dir = tempfile::tempdir().unwrap();
    run(Algo::Ddpg, Connection::Global, tiny(), dir.path(), false);
    let request = TrainRequest {
        env: "lti-paper".into(),
        algo: Algo::Ddpg,
        connection: Connection::Global,
        graph: None,
        config: tiny(),
        settings_source: "test".into(),
        run_dir: dir.path().into(),
        resume: false,
        stop_after: None,
    };
    let err = train(&request, &mut |_| {}).err().unwrap().to_string();
    assert!(err.contains("--resume"), "{err}");
    let resume_other = TrainRequest { algo: Algo::Ppo, resume: true, ..request.clone() };
    assert!(train(&resume_other, &mut |_| {}).err().unwrap().to_string().contains("same --env, --algo"));

    // A graph built for lti-paper (3×3) does not fit peg-group1 (6×12).
    let graph = dir.path().join("graph.json");
    let options = lcrl_graph_builder::GraphOptions {
        cs3: lcrl_graph_builder::Cs3Config { samples: 8, seed: 0, threads: 1, start: None },
        rule: lcrl_graph_builder::Rule::Threshold(0.1),
        bootstrap: 0,
    };
    let env = make_env("lti-paper").unwrap();
    lcrl_graph_builder::build_graph(env.as_ref(), &options, &|| {}).unwrap().write_json(&graph).unwrap();
    let peg = TrainRequest {
        env: "peg-group1".into(),
        connection: Connection::Local,
        graph: Some(graph),
        run_dir: dir.path().join("peg"),
        ..request
    };
    let err = train(&peg, &mut |_| {}).err().unwrap().to_string();
    assert!(err.contains("3×3") && err.contains("6 actions"), "{err}");
}

/// Residual RL (learner/src/policy/action.rs): a run around a base controller
/// records its numbers in config.toml and the checkpoint, its untrained
/// policy is the base controller, and the evaluation returns match the
/// base's own. DDPG and PPO alike (each with its own reach); warm-up
/// longer than the run, so the policy is the freshly built one.
#[test]
fn a_base_controller_is_recorded_and_is_the_first_policy() {
    tch::set_num_threads(1);
    let dir = tempfile::tempdir().unwrap();
    let base = [2.0, 2.0, 0.2, 0.1, 0.1, 1.5];
    let file = dir.path().join("best_constant.json");
    std::fs::write(&file, serde_json::json!({ "env": "peg-group1", "action": base }).to_string()).unwrap();
    for algo in [Algo::Ddpg, Algo::Ppo] {
        let (mut cfg, _) = TrainConfig::for_env("peg-group1");
        cfg.base.action = crate::config::BaseController::BestConstant;
        cfg.base.best_constant_file = Some(file.clone());
        cfg.run.episodes = 1;
        cfg.run.eval_episodes = 3;
        cfg.ddpg.warmup_steps = 10_000;
        cfg.ppo.rollout_steps = 10_000;
        // DDPG's own reach (configs/peg-group2.toml): PPO's stays 1.
        cfg.ddpg.residual_scale = Some(0.5);
        let run_dir = dir.path().join(format!("{algo:?}"));
        let request = TrainRequest {
            env: "peg-group1".into(),
            algo,
            connection: Connection::Global,
            graph: None,
            config: cfg,
            settings_source: "test".into(),
            run_dir: run_dir.clone(),
            resume: false,
            stop_after: None,
        };
        let outcome = train(&request, &mut |_| {}).unwrap();
        let recorded: TrainConfig = toml::from_str(&std::fs::read_to_string(run_dir.join("config.toml")).unwrap()).unwrap();
        assert_eq!(recorded.base.action, crate::config::BaseController::Action(base.to_vec()), "{algo:?}");
        assert_eq!(recorded.base.best_constant_file, None);
        let policy = Policy::load(&run_dir).unwrap();
        assert_eq!(policy.architecture.base.as_deref(), Some(&base[..]));
        assert_eq!(policy.architecture.residual_scale, if algo == Algo::Ddpg { 0.5 } else { 1.0 }, "{algo:?}");
        let mut env = make_env("peg-group1").unwrap();
        let state = env.reset(5).unwrap();
        let action = policy.act(env.as_ref(), &state);
        // The actor's last layer starts within ±3e-3: u ≈ 0, a ≈ base.
        for (a, b) in action.iter().zip(base) {
            assert!((a - b).abs() < 0.05, "{algo:?}: {action:?} against the base {base:?}");
        }
        // And it scores as the base does on the same starts.
        let constant = lcrl_sim::tune::constant_return(env.as_ref(), &base, 3, lcrl_sim::seeds::run_evaluation(0, 0)).unwrap();
        assert!((outcome.summary.evaluation.eval_return - constant).abs() < 0.05 * constant.abs(), "{algo:?}: {} vs {constant}", outcome.summary.evaluation.eval_return);
        // No update happened, so both validations held the same weights:
        // the end's confirmation (on in the peg settings) has nothing to
        // choose between and runs nothing.
        let selection = outcome.summary.selection.expect("the peg settings validate");
        assert_eq!((selection.history.len(), selection.confirmation), (2, None), "{algo:?}");
        assert!(run_dir.join("candidates").is_dir(), "{algo:?}: the candidates are kept");
    }
}

/// A simulator that blows up (x ← 30x + u, from x = 1): every episode of
/// `lcrl train` ends at its first step beyond the bounds, counted as
/// diverged_env, and training goes on with finite weights (issue 71).
#[test]
fn a_diverging_environment_ends_episodes_and_training_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let env = dir.path().join("diverging.toml");
    std::fs::write(&env, "kind = \"lti\"\ne = [[30.0]]\nf = [[1.0]]\ninitial_state_low = [1.0]\ninitial_state_high = [1.0]\nepisode_steps = 20\n").unwrap();
    for algo in [Algo::Ddpg, Algo::Ppo] {
        let mut cfg = tiny_with_episodes(30);
        cfg.ddpg.warmup_steps = 8;
        cfg.ddpg.batch_size = 4;
        cfg.ppo.rollout_steps = 8;
        cfg.ppo.minibatch_size = 4;
        let run_dir = dir.path().join(format!("{algo:?}"));
        let request = TrainRequest { env: env.to_string_lossy().into(), algo, connection: Connection::Global, graph: None, config: cfg, settings_source: "test".into(), run_dir: run_dir.clone(), resume: false, stop_after: None };
        let outcome = train(&request, &mut |_| {}).unwrap();
        assert_eq!(outcome.summary.diverged_env, 30, "{algo:?}");
        // Two sound steps an episode (x ≈ 30, then ≈ 900), all stored.
        assert!(outcome.rows.iter().all(|r| r.length == 2 && r.episode_return > -1e6), "{algo:?}");
        assert_eq!(outcome.summary.env_steps, 60, "{algo:?}");
        assert!(outcome.summary.updates > 0, "{algo:?}: training went on");
        let last = crate::policy::checkpoint::latest_checkpoint(&run_dir).unwrap();
        let tensors = tch::Tensor::read_safetensors(last.join("actor.safetensors")).unwrap();
        assert!(tensors.iter().all(|(_, t)| t.isfinite().all().int64_value(&[]) == 1), "{algo:?}: finite weights");
    }
}

/// A replay buffer damaged so that its file still matches the manifest
/// (a tensor renamed in place: same size, valid header) cannot be loaded:
/// the resume falls back to the checkpoint before it, instead of stopping
/// (issue 71).
#[test]
fn a_resume_falls_back_past_a_checkpoint_whose_replay_cannot_load() {
    let dir = tempfile::tempdir().unwrap();
    run_until(Algo::Ddpg, Connection::Global, tiny(), dir.path(), false, Some(4));
    let newest = crate::policy::checkpoint::latest_checkpoint(dir.path()).unwrap();
    assert!(newest.ends_with("ep000004"), "{}", newest.display());
    let replay = newest.join("replay.safetensors");
    let bytes = std::fs::read(&replay).unwrap();
    let at = bytes.windows(9).position(|w| w == b"\"next_obs").expect("the header names next_obs");
    let mut damaged = bytes.clone();
    damaged[at + 1..at + 9].copy_from_slice(b"next_obz");
    std::fs::write(&replay, &damaged).unwrap();
    crate::policy::checkpoint::check_intact(&newest).expect("still consistent with its manifest");
    let resumed = run_until(Algo::Ddpg, Connection::Global, tiny_with_episodes(6), dir.path(), true, None);
    // Episodes 3 and 4 trained again from ep000002, then 5 and 6; the
    // unloadable one was set aside, never to be taken for the newest.
    assert_eq!(resumed.rows.len(), 6);
    assert_eq!(resumed.summary.episodes, 6);
    assert!(dir.path().join("checkpoints/.ep000004.unloadable").is_dir());
}
