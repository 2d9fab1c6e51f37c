//! `lcrl launch ROLE --config PRESET`: starts one role of a run (graph
//! builder, learner or actor) from a preset, replacing this process, so a
//! container or pod runs exactly one server with the same preset `lcrl run`
//! uses. Addresses come from flags (service names in compose/Kubernetes).
//!
//! Servers listen on loopback unless told otherwise; a non-loopback address
//! needs TLS (`--tls-dir`) or an explicit `--insecure`.
//!
//! One process tree: `lcrl launch` starts no child of its own, it becomes
//! the server (exec), so a container's or pod's stop signal reaches the
//! server itself, and a parent-death signal set by whoever started
//! `lcrl launch` (PR_SET_PDEATHSIG survives exec) holds for the server.

use std::ffi::OsString;
use std::net::SocketAddr;
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::Command;

use anyhow::{bail, Context};

use lcrl::binaries::sibling;
use lcrl::preset::Preset;
use lcrl::run_security::RunSecurity;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Role {
    /// lcrl-graph-builder: CS3 graph of the preset's environment, served.
    GraphBuilder,
    /// lcrl-learner: networks, replay, training, Policy service.
    Learner,
    /// lcrl-actor: job.envs_per_actor simulators streaming over gRPC.
    Actor,
}

#[derive(Debug, clap::Args)]
pub struct LaunchArgs {
    #[arg(value_enum)]
    pub role: Role,
    /// Preset (configs/*.toml).
    #[arg(long)]
    pub config: PathBuf,
    /// Address to serve on [default: loopback only, graph builder
    /// 127.0.0.1:50051, learner 127.0.0.1:50052]. In a container or pod,
    /// 0.0.0.0:PORT, which needs --tls-dir (or --insecure).
    #[arg(long)]
    pub listen: Option<String>,
    /// Allow serving plain text on a non-loopback --listen address (anyone
    /// who reaches it can read the traffic, the token included): only on a
    /// network nobody else joins, such as compose's.
    #[arg(long)]
    pub insecure: bool,
    /// Learner, connection local: the graph builder's URL.
    #[arg(long, default_value = "http://graph-builder:50051")]
    pub graph_builder: String,
    /// Actor: the learner's URL.
    #[arg(long, default_value = "http://learner:50052")]
    pub learner: String,
    /// Shared run directory (graph.json, train.toml, learner/).
    #[arg(long, default_value = "/runs")]
    pub run_dir: PathBuf,
    /// Run id: the learner and its actors must agree.
    #[arg(long, default_value = "default")]
    pub run_id: String,
    /// Learner and actor: serve Prometheus metrics on this address.
    #[arg(long)]
    pub metrics_listen: Option<String>,
    /// Log as JSON lines.
    #[arg(long)]
    pub log_json: bool,
    /// Print the command line instead of running it.
    #[arg(long)]
    pub dry_run: bool,
    /// Learner: the run's episode budget instead of the preset's
    /// `[job] episodes` (0: the preset's).
    #[arg(long, default_value_t = 0)]
    pub episodes: u64,
    #[command(flatten)]
    pub security: RunSecurity,
}

/// The binary and arguments `args` stands for.
pub fn command_line(args: &LaunchArgs) -> anyhow::Result<(&'static str, Vec<OsString>)> {
    let mut preset = Preset::load(&args.config)?;
    if let Some(server) = &preset.env_server {
        bail!(
            "{} serves its environment from Python ([env_server] {}), which `lcrl launch` cannot start in a container: \
             serve it yourself (`python -m lcrl_env serve --listen HOST:PORT`), set job.env = \"grpc://HOST:PORT\" and drop [env_server]",
            args.config.display(),
            server.gym.as_deref().or(server.entry_point.as_deref()).unwrap_or("")
        );
    }
    if args.episodes > 0 {
        preset.job.episodes = args.episodes;
    }
    let (binary, mut argv) = match args.role {
        Role::GraphBuilder => {
            let listen = args.listen.as_deref().unwrap_or("127.0.0.1:50051");
            check_listen(listen, args)?;
            ("lcrl-graph-builder", preset.graph_builder_args(listen, &args.run_dir))
        }
        Role::Learner => {
            let listen = args.listen.as_deref().unwrap_or("127.0.0.1:50052");
            check_listen(listen, args)?;
            std::fs::create_dir_all(&args.run_dir).with_context(|| format!("creating {}", args.run_dir.display()))?;
            let train = args.run_dir.join("train.toml");
            preset.write_train_config(&train)?;
            let url = args.security.url(&args.graph_builder);
            ("lcrl-learner", preset.learner_args(listen, &args.run_id, &train, &args.run_dir.join("learner"), Some(url.as_str()))?)
        }
        // Replicas name themselves (host name), which also sets their seeds apart.
        Role::Actor => {
            let url = args.security.url(&args.learner);
            ("lcrl-actor", preset.actor_args(&url, &args.run_id, "grpc", None, 0))
        }
    };
    argv.extend(match args.role {
        Role::GraphBuilder => args.security.server_args(false)?,
        Role::Learner => args.security.server_args(preset.job.connection == lcrl_learner::Connection::Local)?,
        Role::Actor => args.security.client_args()?,
    });
    if let (Some(addr), Role::Learner | Role::Actor) = (&args.metrics_listen, args.role) {
        argv.extend([OsString::from("--metrics-listen"), OsString::from(addr)]);
    }
    // The learner serves beyond loopback without a token only when told:
    // --insecure here says the network is nobody else's.
    if args.insecure && matches!(args.role, Role::Learner) {
        argv.push("--insecure".into());
    }
    if args.log_json {
        argv.push("--log-json".into());
    }
    Ok((binary, argv))
}

/// A server's --listen address: loopback, or served with TLS, or
/// `--insecure` said.
fn check_listen(listen: &str, args: &LaunchArgs) -> anyhow::Result<()> {
    let addr: SocketAddr = listen.parse().with_context(|| format!("--listen {listen}: not an IP:PORT address (e.g. 127.0.0.1:50052, or 0.0.0.0:50052 in a container)"))?;
    if !addr.ip().is_loopback() && args.security.tls_dir.is_none() && !args.insecure {
        bail!(
            "--listen {listen} is reachable from other hosts, and without TLS anyone who reaches it can read the traffic{}: \
             add --tls-dir DIR (a folder `lcrl certs` writes), or --insecure to serve plain text anyway (only on a network nobody else joins), \
             or listen on 127.0.0.1",
            if args.security.token_file.is_some() || std::env::var_os(lcrl_runtime::security::TOKEN_FILE_ENV).is_some() { ", the token included" } else { " and call every RPC" }
        );
    }
    Ok(())
}

pub fn run(args: &LaunchArgs) -> anyhow::Result<()> {
    let (binary, argv) = command_line(args)?;
    if args.dry_run {
        let words: Vec<String> = argv.iter().map(|a| a.to_string_lossy().into_owned()).collect();
        println!("{binary} {}", words.join(" "));
        return Ok(());
    }
    let path = sibling(binary)?;
    // exec: signals (docker stop, kubelet) reach the server itself.
    let error = Command::new(&path).args(&argv).exec();
    Err(error).with_context(|| format!("cannot start {}", path.display()))
}
