//! `lcrl`: the command-line front end of Local Connection Reinforcement
//! Learning. Each subcommand is a thin layer over a library crate.

mod cmd;

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use lcrl_graph_builder::cli::GraphArgs;

#[derive(Debug, Parser)]
#[command(
    name = "lcrl",
    version,
    about = "Local Connection Reinforcement Learning for robot controllers",
    long_about = "Local Connection Reinforcement Learning for robot controllers.\n\n\
        LCRL measures which state components each action component moves (CS3),\n\
        turns that into a connection graph G, and gives every action component a\n\
        small policy that sees only its connected states. See docs/method.md."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run graph builder, learner and actors from one preset (configs/).
    ///
    /// Budgets and times on 2 cores (measured this round): the peg PPO
    /// presets train 900 episodes in about 50 s (the main job), the peg DDPG
    /// presets 200 episodes in about 3–4 minutes, lti-paper 1,000 episodes
    /// in about 10 s.
    Run(lcrl::local_run::RunArgs),
    /// Measure throughput against actor processes (scale.json/csv/png).
    Scale(cmd::scale::ScaleArgs),
    /// Start one role of a run from a preset (for containers and pods).
    Launch(cmd::launch::LaunchArgs),
    /// Probe a server's gRPC health service (exit 0 when SERVING).
    Health(cmd::probe::HealthArgs),
    /// Print a learner's status (GetStatus) as one JSON line.
    Status(cmd::probe::StatusArgs),
    /// Build the connection graph G of an environment with CS3 and print it.
    Graph(GraphArgs),
    /// Serve one of lcrl's environments over gRPC (lcrl.v1.Environment), for
    /// Python's Gymnasium (`lcrl_env.make`) or any other client.
    ServeEnv(cmd::serve_env::ServeEnvArgs),
    /// Run a controller on an environment: summary.json, trace.csv, trace.png.
    Sim(cmd::sim::SimArgs),
    /// Find the best constant action (CMA-ES): the bar a trained agent must beat.
    Tune(cmd::tune::TuneArgs),
    /// Train an actor (LCRL local, GCRL global, or full-subnets) with DDPG or PPO.
    Train(lcrl::train::TrainArgs),
    /// Compare training runs: time split, final returns, reward curves.
    Compare(cmd::compare::CompareArgs),
    /// Write a trained policy as one TorchScript (or ONNX) file for a
    /// controller: raw state in, applied action out (docs/export.md).
    Export(cmd::export::ExportArgs),
    /// Many seeds of LCRL against GCRL: statistics, figures, resumable
    /// (experiments/*.toml; see `lcrl experiment run --help`).
    #[command(subcommand)]
    Experiment(lcrl::experiment::ExperimentCommand),
    /// Make a CA, server and client certificates and a token (TLS across hosts).
    Certs(cmd::certs::CertsArgs),
    /// Check the installation: libtorch loads and computes, threads, CUDA.
    Doctor,
    /// Measure performance figures (see `lcrl bench --help`).
    #[command(subcommand)]
    Bench(cmd::bench::BenchCommand),
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Graph(args) => run_graph(&args),
        Command::Run(args) => lcrl::local_run::run(&args),
        Command::Launch(args) => cmd::launch::run(&args),
        Command::Scale(args) => cmd::scale::run(&args),
        Command::Health(args) => cmd::probe::health(&args),
        Command::Status(args) => cmd::probe::status(&args),
        Command::Sim(args) => cmd::sim::run(&args),
        Command::ServeEnv(args) => cmd::serve_env::run(&args),
        Command::Tune(args) => cmd::tune::run(&args),
        Command::Train(args) => lcrl::train::run(&args),
        Command::Compare(args) => cmd::compare::run(&args),
        Command::Export(args) => cmd::export::run(&args),
        Command::Experiment(command) => lcrl::experiment::run(&command),
        Command::Certs(args) => cmd::certs::run(&args),
        Command::Doctor => cmd::doctor::run(),
        Command::Bench(command) => cmd::bench::run(command),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("lcrl: error: {}", lcrl_runtime::process::error_chain(&e));
            ExitCode::FAILURE
        }
    }
}

fn run_graph(args: &GraphArgs) -> anyhow::Result<()> {
    if let Some(pair) = &args.explain {
        print!("{}", args.run_explain(pair)?.text());
        return Ok(());
    }
    if args.choose_t {
        let (choice, actions) = args.run_choose_t()?;
        print!("{}", choice.text(&args.env, args.samples, &actions));
        if let Some(path) = &args.out {
            println!("\nwrote {}", path.display());
        }
        return Ok(());
    }
    let report = args.run()?;
    print!("{}", report.table());
    print!("{}", report.sweep_table());
    if let Some(path) = &args.out {
        println!("\nwrote {}", path.display());
    }
    if let Some(path) = &args.plot {
        println!("wrote {}", path.display());
    }
    Ok(())
}
