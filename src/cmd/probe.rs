//! `lcrl health` and `lcrl status`: probes for scripts and container health
//! checks. `health` asks grpc.health.v1 (exit 0 when SERVING); `status`
//! prints a learner's GetStatus as JSON.

use std::time::Duration;

use anyhow::bail;
use lcrl_runtime::security::{ClientSecurity, ClientSecurityArgs};
use lcrl::supervise::is_serving;

#[derive(Debug, clap::Args)]
pub struct HealthArgs {
    /// The server's gRPC URL, e.g. http://127.0.0.1:50052.
    pub url: String,
    /// The service to ask about (lcrl.v1.Graph, lcrl.v1.Learner,
    /// lcrl.v1.Policy); empty: the server as a whole.
    #[arg(long, default_value = "")]
    pub service: String,
    /// Give up after this many seconds (above 0, at most 3600).
    #[arg(long, default_value_t = 5.0, value_parser = timeout_secs)]
    pub timeout: f64,
    #[command(flatten)]
    pub security: ClientSecurityArgs,
}

/// The longest `--timeout`, seconds: an hour is already far past any
/// health check's patience (and 1e300 s would not fit a `Duration`).
const MAX_TIMEOUT_S: f64 = 3600.0;

/// `--timeout`: seconds above 0 and at most [`MAX_TIMEOUT_S`].
fn timeout_secs(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 && v <= MAX_TIMEOUT_S => Ok(v),
        _ => Err(format!("expected a number of seconds above 0 and at most {MAX_TIMEOUT_S}")),
    }
}

pub fn health(args: &HealthArgs) -> anyhow::Result<()> {
    // Checked again here (without a panic) for callers that build the
    // arguments themselves.
    let Some(timeout) = Duration::try_from_secs_f64(args.timeout).ok().filter(|t| !t.is_zero() && t.as_secs_f64() <= MAX_TIMEOUT_S) else {
        bail!("--timeout must be a number of seconds above 0 and at most {MAX_TIMEOUT_S}, got {}", args.timeout);
    };
    let security = ClientSecurity::from_args(&args.security)?;
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let what = if args.service.is_empty() { args.url.clone() } else { format!("{} at {}", args.service, args.url) };
    match runtime.block_on(async { tokio::time::timeout(timeout, is_serving(&args.url, &args.service, &security)).await }) {
        Ok(Ok(true)) => {
            println!("{what}: SERVING");
            Ok(())
        }
        Ok(Ok(false)) => bail!("{what}: not serving (yet)"),
        Ok(Err(e)) => Err(e),
        Err(_) => bail!("{what}: no answer within {} s", args.timeout),
    }
}

#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// The learner's gRPC URL, e.g. http://127.0.0.1:50052.
    pub url: String,
    #[command(flatten)]
    pub security: ClientSecurityArgs,
}

/// `lcrl status`: the learner's GetStatus as one JSON line, for scripts.
pub fn status(args: &StatusArgs) -> anyhow::Result<()> {
    use lcrl_proto::v1::{learner_client::LearnerClient, GetStatusRequest};
    let security = ClientSecurity::from_args(&args.security)?;
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let s = runtime.block_on(async {
        let fetch = async {
            let mut client = LearnerClient::new(security.connect(&args.url).await?);
            let status = client.get_status(GetStatusRequest {}).await.map_err(|s| refused_call(&args.url, &s))?;
            anyhow::Ok(status.into_inner())
        };
        tokio::time::timeout(Duration::from_secs(10), fetch).await.map_err(|_| anyhow::anyhow!("no answer from {} within 10 s", args.url))?
    })?;
    let json = serde_json::json!({
        "run_id": s.run_id, "algo": s.algo, "connection": s.connection,
        "episodes": s.episodes, "env_steps": s.env_steps, "updates": s.updates,
        "replay_size": s.replay_size, "policy_version": s.policy_version,
        "connected_actors": s.connected_actors, "rejected": s.rejected,
        "recent_return": s.recent_return, "unauthenticated": s.unauthenticated,
    });
    println!("{json}");
    Ok(())
}

/// A failed call as one line with the status's causes: a refused client
/// certificate shows only as the transport's own error (a closed
/// connection), which `error_chain` then names (issue 71).
fn refused_call(url: &str, status: &tonic::Status) -> anyhow::Error {
    let causes = std::iter::successors(std::error::Error::source(status), |c| c.source());
    anyhow::anyhow!(lcrl_runtime::process::with_causes(format!("{url}: {}", status.message()), causes))
}
