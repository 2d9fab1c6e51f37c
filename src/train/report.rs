//! What `lcrl train` shows at its end: the run's figures on stdout beside
//! its references, and its reward curve.

use anyhow::Context;
use lcrl_learner::run::files::EpisodeRow;
use lcrl_learner::{Connection, TrainConfig};

use super::TrainArgs;
use crate::connection::ConnectionSpec;
use crate::plots::{line_panels, Panel};

/// The run's figures on stdout, beside its references.
pub(super) fn print_summary(s: &lcrl_learner::run::summary::RunSummary, config: &TrainConfig, args: &TrainArgs) -> anyhow::Result<()> {
    let global_equivalent = lcrl_learner::algo::nets::global_actor_params(&config.network, args.env_state_dims(s)?);
    println!(
        "{:?} / {:?} on {} — {} episodes, {} env steps, {} actor updates, {} critic updates",
        s.algo, s.connection, s.env, s.episodes, s.env_steps, s.updates, s.critic_updates
    );
    println!("  actor parameters      {} (a global actor of the configured size: {})", s.actor_params, global_equivalent);
    println!("  final return          {:.3} (mean of the last 10 episodes)", s.final_return);
    match (&s.selection, s.evaluation.last_eval_return) {
        (Some(chosen), Some(last)) => {
            let which = if chosen.episode == 0 { "the starting policy".to_string() } else { format!("episode {}'s policy", chosen.episode) };
            println!("  eval return           {:.3} (the selected policy, {} episodes)", s.evaluation.eval_return, config.run.eval_episodes.max(1));
            println!("  selected              {which}: {}", chosen.how_chosen());
            println!("  last policy           {last:.3} (same evaluation episodes)");
            if chosen.episode == 0 {
                println!("  no learned policy beat the starting one on the validation starts; {}", budget_hint(s));
            }
        }
        _ => println!("  eval return           {:.3} (deterministic policy, {} episodes)", s.evaluation.eval_return, config.run.eval_episodes.max(1)),
    }
    if let Some(zero) = s.evaluation.zero_action_return {
        println!("  a = 0 return          {zero:.3} (the neutral constant action, same episodes)");
    }
    // The best constant and the headroom reference, where the environment
    // has them, evaluated on the run's own starts (never another command's).
    for r in s.evaluation.references.iter().filter(|r| r.controller != lcrl_sim::evaluate::ZERO_ACTION) {
        println!("  {:<21} {:.3} (same episodes)", r.controller, r.mean_return);
    }
    if let Some(bar) = s.evaluation.references.iter().find(|r| r.controller == crate::run_summary::BEST_CONSTANT) {
        println!("  {}", crate::local_run::report::verdict_against_best_constant(s.evaluation.eval_return, bar.mean_return));
    }
    if let (Some(rate), Some(force)) = (s.evaluation.eval_success_rate, s.evaluation.eval_peak_force_n) {
        println!("  eval success          {:.0}%, mean peak force {force:.2} N", 100.0 * rate);
    }
    crate::output::print_terms(&s.evaluation.eval_terms);
    if let Some(lqr) = s.evaluation.lqr_return {
        println!("  LQR return            {lqr:.3} (the optimum)");
    }
    if let (Some(masked), Connection::Local) = (s.evaluation.masked_lqr_return, s.connection) {
        println!("  masked LQR return     {masked:.3} (the best controller that sees only G's states)");
    }
    println!("  time: graph {:.2} s, optimization {:.2} s, total {:.2} s", s.graph_seconds, s.optimization_seconds, s.total_seconds);
    println!("wrote {}", args.run_dir.display());
    Ok(())
}

/// How many episodes the shipped preset of this environment and algorithm
/// trains (configs/ENV-ALGO-local.toml, read where it is found), else the
/// environment's default budget.
fn budget_hint(s: &lcrl_learner::run::summary::RunSummary) -> String {
    let algo = crate::preset::algo_name(s.algo);
    let path = std::path::PathBuf::from(format!("configs/{}-{algo}-local.toml", s.env));
    match crate::preset::Preset::load(&path) {
        Ok(preset) => format!("this run trained {} episodes; {} trains {} (docs/peg.md)", s.episodes, path.display(), preset.job.episodes),
        Err(_) => format!("this run trained {} episodes; {}'s default budget is {}", s.episodes, s.env, TrainConfig::for_env(&s.env).0.run.episodes),
    }
}

impl TrainArgs {
    fn env_state_dims(&self, _s: &lcrl_learner::run::summary::RunSummary) -> anyhow::Result<(usize, usize)> {
        let env = lcrl_sim::make_env(&self.env)?;
        Ok((env.spec().state_dim(), env.spec().action_dim()))
    }
}

/// Returns per episode with a 10-episode moving average, and the run's
/// references as horizontal lines.
pub(super) fn plot_rewards(rows: &[EpisodeRow], summary: &lcrl_learner::run::summary::RunSummary, args: &TrainArgs, connection: &ConnectionSpec) -> anyhow::Result<()> {
    let env = &summary.env;
    let x: Vec<f64> = rows.iter().map(|r| r.episode as f64).collect();
    let returns: Vec<f64> = rows.iter().map(|r| r.episode_return).collect();
    let average: Vec<f64> = (0..returns.len())
        .map(|k| {
            let window = &returns[k.saturating_sub(9)..=k];
            window.iter().sum::<f64>() / window.len() as f64
        })
        .collect();
    let title = format!("{env} — {:?} with {} connection", args.algo, connection.label());
    let panel = Panel::rewards(
        "episode return",
        vec![("return".into(), returns), ("moving average (10)".into(), average)],
        crate::run_summary::references(summary),
    );
    let path = args.run_dir.join("reward_curve.png");
    line_panels(&path, &title, &x, "episode", &[panel]).with_context(|| format!("drawing {}", path.display()))
}
