//! `lcrl`: the command-line front end of Local Connection Reinforcement
//! Learning. Each subcommand is a thin layer over a library crate.

mod bench;
mod bench_env;
mod bench_transport;
mod certs_cmd;
mod compare_cmd;
mod doctor;
mod experiment;
mod probe_cmd;
mod launch_cmd;
mod output;
mod plots;
mod preset;
mod run_cmd;
mod run_summary;
mod scale_cmd;
mod sim_cmd;
mod train_cmd;
mod tune_cmd;

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
    Run(run_cmd::RunArgs),
    /// Measure throughput against actor processes (scale.json/csv/png).
    Scale(scale_cmd::ScaleArgs),
    /// Start one role of a run from a preset (for containers and pods).
    Launch(launch_cmd::LaunchArgs),
    /// Probe a server's gRPC health service (exit 0 when SERVING).
    Health(probe_cmd::HealthArgs),
    /// Print a learner's status (GetStatus) as one JSON line.
    Status(probe_cmd::StatusArgs),
    /// Build the connection graph G of an environment with CS3 and print it.
    Graph(GraphArgs),
    /// Run a controller on an environment: summary.json, trace.csv, trace.png.
    Sim(sim_cmd::SimArgs),
    /// Find the best constant action (CMA-ES): the bar a trained agent must beat.
    Tune(tune_cmd::TuneArgs),
    /// Train an actor (LCRL local, GCRL global, or full-subnets) with DDPG or PPO.
    Train(train_cmd::TrainArgs),
    /// Compare training runs: time split, final returns, reward curves.
    Compare(compare_cmd::CompareArgs),
    /// Many seeds of LCRL against GCRL: statistics, figures, resumable
    /// (experiments/*.toml; see `lcrl experiment run --help`).
    #[command(subcommand)]
    Experiment(experiment::ExperimentCommand),
    /// Make a CA, server and client certificates and a token (TLS across hosts).
    Certs(certs_cmd::CertsArgs),
    /// Check the installation: libtorch loads and computes, threads, CUDA.
    Doctor,
    /// Measure performance figures (see `lcrl bench --help`).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
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
        Command::Run(args) => run_cmd::run(&args),
        Command::Launch(args) => launch_cmd::run(&args),
        Command::Scale(args) => scale_cmd::run(&args),
        Command::Health(args) => probe_cmd::health(&args),
        Command::Status(args) => probe_cmd::status(&args),
        Command::Sim(args) => sim_cmd::run(&args),
        Command::Tune(args) => tune_cmd::run(&args),
        Command::Train(args) => train_cmd::run(&args),
        Command::Compare(args) => compare_cmd::run(&args),
        Command::Experiment(command) => experiment::run(&command),
        Command::Certs(args) => certs_cmd::run(&args),
        Command::Doctor => doctor::run(),
        Command::Bench(command) => bench::run(command),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("lcrl: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run_graph(args: &GraphArgs) -> anyhow::Result<()> {
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
