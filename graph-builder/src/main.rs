//! `lcrl-graph-builder`: builds the connection graph for one environment
//! with parallel CS3 rollouts, then serves it over gRPC (`lcrl.v1.Graph`,
//! grpc.health.v1, reflection) until SIGTERM or Ctrl-C.

use std::net::SocketAddr;
use std::sync::Arc;

use anyhow::Context;
use clap::Parser;
use lcrl_runtime::process::shutdown_signal;
use lcrl_graph_builder::cli::GraphArgs;
use lcrl_graph_builder::service::{self, GraphState};
use lcrl_runtime::security::{ServerSecurity, ServerSecurityArgs};
use tokio::sync::watch;

#[derive(Debug, Parser)]
#[command(version, about = "Build the LCRL connection graph with CS3, then serve it over gRPC")]
struct Args {
    #[command(flatten)]
    graph: GraphArgs,
    /// Address to serve on; port 0 picks a free port (the chosen address is
    /// printed as "listening on ADDR").
    #[arg(long, default_value = "127.0.0.1:50051")]
    listen: SocketAddr,
    #[command(flatten)]
    security: ServerSecurityArgs,
    #[command(flatten)]
    budget: lcrl_runtime::request_budget::RequestBudgetArgs,
    /// Log as JSON lines instead of human-readable text (level: RUST_LOG).
    #[arg(long)]
    log_json: bool,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    // CS3 runs on its own thread pool; the runtime only serves gRPC.
    lcrl_runtime::process::run_service("lcrl-graph-builder", args.log_json, 2, run(args))
}

async fn run(args: Args) -> anyhow::Result<()> {
    // Bad settings fail before the port is taken.
    args.graph.options().validate()?;
    lcrl_sim::make_env(&args.graph.env)?;
    let security = ServerSecurity::from_args(&args.security)?;
    let listener = tokio::net::TcpListener::bind(args.listen)
        .await
        .with_context(|| format!("cannot listen on {}; is another process using it?", args.listen))?;
    let addr = listener.local_addr()?;
    println!("listening on {addr}");
    security.warn_if_exposed(addr);
    tracing::info!(%addr, security = %security.describe(), "serving");

    let (state_tx, state_rx) = watch::channel(GraphState::Building);
    let (stop_tx, mut stop_rx) = watch::channel(false);
    let server = tokio::spawn(service::serve(listener, state_rx, security.clone(), args.budget.budget("graph builder"), async move {
        let _ = stop_rx.wait_for(|stop| *stop).await;
    }));

    let graph_args = args.graph.clone();
    let built = tokio::task::spawn_blocking(move || graph_args.run());
    let report = tokio::select! {
        built = built => built.context("the graph build panicked")??,
        _ = shutdown_signal() => {
            tracing::info!("stopped before the graph was built");
            return Ok(());
        }
    };
    tracing::info!(
        env = %report.env,
        edges = report.g.iter().flatten().filter(|&&v| v == 1).count(),
        seconds = report.elapsed_s,
        "graph built; serving it"
    );
    eprint!("{}", report.table());
    eprint!("{}", report.sweep_table());
    state_tx.send_replace(GraphState::Ready(Arc::new((&report).into())));

    shutdown_signal().await;
    tracing::info!("shutting down");
    let _ = stop_tx.send(true);
    server.await.context("the gRPC server task panicked")?.context("the gRPC server failed")?;
    Ok(())
}
