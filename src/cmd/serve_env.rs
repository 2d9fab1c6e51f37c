//! `lcrl serve-env`: one of lcrl's environments (peg-group1/2, the noisy
//! presets, lti-*, an environment file) served over `lcrl.v1.Environment`,
//! so that any language can drive it: the Python package's Gymnasium face
//! (`lcrl_env.make`, docs/environments.md), or lcrl itself with
//! `--env grpc://HOST:PORT`. Secured like every lcrl server (TLS, mutual
//! TLS, a token).

use std::net::SocketAddr;

use anyhow::Context;
use lcrl_runtime::security::{ServerSecurity, ServerSecurityArgs};
use lcrl_proto::v1::environment_server::EnvironmentServer;
use lcrl_sim::serve::{EnvironmentService, ServeSettings, Sessions};
use tonic::service::interceptor::InterceptedService;

#[derive(Debug, Clone, clap::Args)]
pub struct ServeEnvArgs {
    /// The environment: a built-in name (peg-group1, peg-group2,
    /// peg-group1-noisy, lti-paper, ...) or an environment file.
    #[arg(long)]
    pub env: String,
    /// Address to serve on; port 0 picks a free port (printed as
    /// "listening on ADDR").
    #[arg(long, default_value = "127.0.0.1:50070")]
    pub listen: SocketAddr,
    /// Most sessions (environment instances) open at once.
    #[arg(long, default_value_t = ServeSettings::default().max_sessions)]
    pub max_sessions: u32,
    /// A session unused this long is closed when another is opened (s).
    #[arg(long, default_value_t = ServeSettings::default().idle_timeout_secs)]
    pub session_idle_secs: u64,
    #[command(flatten)]
    pub security: ServerSecurityArgs,
    #[command(flatten)]
    pub budget: lcrl_runtime::request_budget::RequestBudgetArgs,
}

pub fn run(args: &ServeEnvArgs) -> anyhow::Result<()> {
    let settings = ServeSettings { max_sessions: args.max_sessions, idle_timeout_secs: args.session_idle_secs };
    // Bad settings and an unknown environment fail before the port is taken.
    let sessions = Sessions::new(&args.env, settings)?;
    let security = ServerSecurity::from_args(&args.security)?;
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    runtime.block_on(serve(args, sessions, security))
}

async fn serve(args: &ServeEnvArgs, sessions: Sessions, security: ServerSecurity) -> anyhow::Result<()> {
    let listener = tokio::net::TcpListener::bind(args.listen).await.with_context(|| format!("cannot listen on {}; is another process using it?", args.listen))?;
    let addr = listener.local_addr()?;
    println!("listening on {addr}");
    security.warn_if_exposed(addr);
    eprintln!("serving {} over lcrl.v1.Environment ({}); Ctrl-C stops", args.env, security.describe());
    let (health, health_service) = lcrl_runtime::process::health_service();
    health.set_serving::<EnvironmentServer<EnvironmentService>>().await;
    let check = security.token_check();
    // Requests carry a few actions of a few numbers each; 4 MiB holds
    // thousands of sessions' steps.
    let environment = EnvironmentServer::new(EnvironmentService::new(sessions)).max_decoding_message_size(4 << 20).max_encoding_message_size(16 << 20);
    // Every request stream takes from one budget (issue 82: unfinished
    // streams once held 4 MiB each, 2 GiB at 512).
    let budget = args.budget.budget("environment server");
    use lcrl_runtime::request_budget::Budgeted;
    let router = security
        .server_builder()
        .trace_fn(|req| tracing::info_span!("grpc", path = %req.uri().path()))
        .add_service(Budgeted::new(health_service, budget.clone()))
        .add_service(InterceptedService::new(Budgeted::new(environment, budget.clone()), check.clone()));
    lcrl_runtime::process::add_reflection(router, &check, &budget)
        .serve_with_incoming_shutdown(security.incoming(listener), lcrl_runtime::process::shutdown_signal())
        .await
        .context("the environment server failed")
}
