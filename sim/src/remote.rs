//! Environments served by another process over `lcrl.v1.Environment`
//! (proto/lcrl.proto), usually a Gymnasium environment behind
//! `python -m lcrl_env serve` (docs/environments.md). `--env grpc://HOST:PORT`
//! makes a [`RemoteEnv`] wherever a built-in environment name is accepted.
//!
//! Every [`RemoteEnv`] is one session on the server, opened at its first
//! reset (so making one only to read its spec costs no instance), closed
//! when dropped. [`Env::snapshot`] is the service's Fork. Calls block the
//! calling thread: they run on one small tokio runtime of this process and
//! hand the answer back over a channel, so they work from rayon's CS3
//! threads, an actor's environment thread and async code alike.

use std::future::Future;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock, Weak};
use std::time::Duration;

use lcrl_runtime::security::{AuthChannel, ClientSecurity};
use lcrl_proto::v1::environment_client::EnvironmentClient;
use lcrl_proto::v1::{CloseRequest, ForkRequest, GetSpecRequest, OpenRequest, ResetRequest, SessionReset, SessionStep, StepRequest};

use crate::env::{Env, EnvError, EnvSpec, Step};

/// How `--env` names a served environment.
pub const SCHEME: &str = "grpc://";
/// ... and one served over TLS (`python -m lcrl_env serve --tls-cert ...`).
pub const TLS_SCHEME: &str = "grpcs://";

/// The environment variables that give a process the CA to trust for
/// `grpcs://` servers and its own certificate for mutual TLS (`lcrl run
/// --tls-dir` sets them for every process it starts). The token comes from
/// $LCRL_TOKEN_FILE, as for every lcrl client.
pub const TLS_CA_ENV: &str = "LCRL_ENV_TLS_CA";
pub const TLS_CLIENT_CERT_ENV: &str = "LCRL_ENV_TLS_CLIENT_CERT";
pub const TLS_CLIENT_KEY_ENV: &str = "LCRL_ENV_TLS_CLIENT_KEY";

/// Whether `name` is a served environment's URL.
pub fn is_served(name: &str) -> bool {
    name.starts_with(SCHEME) || name.starts_with(TLS_SCHEME)
}

/// HOST:PORT of a served environment's URL.
pub fn address(name: &str) -> Option<&str> {
    name.strip_prefix(SCHEME).or_else(|| name.strip_prefix(TLS_SCHEME))
}

/// How long a server may take to accept a connection.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);
/// How long one call may take (a Fork of a large simulation, a slow step).
const CALL_TIMEOUT: Duration = Duration::from_secs(120);

/// A connection to a server, and how its calls fail.
struct Connection {
    url: String,
    client: EnvironmentClient<AuthChannel>,
}

/// What every session of one server shares.
struct Server {
    connection: Connection,
    spec: EnvSpec,
    /// Divisors of `normalize_state`: the larger bound's magnitude where the
    /// observation space bounds a component, else 1.
    state_scale: Vec<f64>,
    /// Why the server cannot fork; None when it can.
    fork_unavailable: Option<String>,
    dt: f64,
}

/// One instance of a served environment (one session).
pub struct RemoteEnv {
    server: Arc<Server>,
    session: Option<u64>,
    state: Vec<f64>,
}

/// The process's runtime for environment calls (one worker thread: the
/// calls are small and the environment server is the bottleneck).
fn runtime() -> Result<&'static tokio::runtime::Runtime, String> {
    static RUNTIME: OnceLock<Result<tokio::runtime::Runtime, String>> = OnceLock::new();
    RUNTIME
        .get_or_init(|| {
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(1)
                .thread_name("lcrl-env-client")
                .enable_all()
                .build()
                .map_err(|e| format!("cannot start the environment client's runtime: {e}"))
        })
        .as_ref()
        .map_err(Clone::clone)
}

/// Runs `call` on the runtime and waits for it on this thread.
fn blocking<T: Send + 'static>(call: impl Future<Output = T> + Send + 'static) -> Result<T, String> {
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    runtime()?.spawn(async move {
        let _ = tx.send(call.await);
    });
    rx.recv().map_err(|_| "the call was dropped (the process is shutting down)".to_string())
}

impl Connection {
    fn error(&self, message: impl Into<String>) -> EnvError {
        EnvError::Remote { url: self.url.clone(), message: message.into() }
    }

    /// A failed call as an error that says what to do.
    fn status(&self, what: &str, status: tonic::Status) -> EnvError {
        match status.code() {
            tonic::Code::Unavailable => self.error(format!("{what}: the server is unreachable ({}); is `python -m lcrl_env serve` still running there?", status.message())),
            tonic::Code::DeadlineExceeded => self.error(format!("{what}: no answer within {} s", CALL_TIMEOUT.as_secs())),
            tonic::Code::Unauthenticated => self.error(format!("{what}: the server refused this client: {} (give its token with $LCRL_TOKEN_FILE)", status.message())),
            code => self.error(format!("{what}: {} ({code:?})", status.message())),
        }
    }

    /// Runs one call of the client, mapping transport and status errors.
    fn call<T: Send + 'static, F>(&self, what: &str, call: impl FnOnce(EnvironmentClient<AuthChannel>) -> F) -> Result<T, EnvError>
    where
        F: Future<Output = Result<tonic::Response<T>, tonic::Status>> + Send + 'static,
    {
        match blocking(call(self.client.clone())) {
            Ok(Ok(response)) => Ok(response.into_inner()),
            Ok(Err(status)) => Err(self.status(what, status)),
            Err(message) => Err(self.error(message)),
        }
    }
}

/// This process as a client of environment servers: the token of
/// $LCRL_TOKEN_FILE, and for `grpcs://` the CA (and client certificate)
/// of [`TLS_CA_ENV`] and its companions.
fn client_security(tls: bool) -> Result<ClientSecurity, String> {
    let path = |name: &str| std::env::var_os(name).map(std::path::PathBuf::from);
    let ca = if tls {
        Some(path(TLS_CA_ENV).ok_or_else(|| format!("a {TLS_SCHEME} server needs the CA to trust: set ${TLS_CA_ENV} to its PEM file (`lcrl run --tls-dir` does)"))?)
    } else {
        None
    };
    let (cert, key) = (path(TLS_CLIENT_CERT_ENV), path(TLS_CLIENT_KEY_ENV));
    let identity = cert.as_deref().zip(key.as_deref()).filter(|_| tls);
    ClientSecurity::new(ca.as_deref(), identity, None).map_err(|e| e.to_string())
}

impl RemoteEnv {
    /// An instance of the environment at `url` (`grpc://HOST:PORT`), not
    /// opened yet. Instances of one URL share one connection and spec (so
    /// an actor's K environments are stepped in one call, [`crate::step_all`]);
    /// the first connects and reads the spec.
    pub fn connect(url: &str) -> Result<RemoteEnv, EnvError> {
        static SERVERS: OnceLock<Mutex<HashMap<String, Weak<Server>>>> = OnceLock::new();
        let servers = SERVERS.get_or_init(Default::default);
        let mut servers = servers.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        let server = match servers.get(url).and_then(Weak::upgrade) {
            Some(server) => server,
            None => {
                let server = Arc::new(Self::connect_server(url)?);
                servers.retain(|_, weak| weak.strong_count() > 0);
                servers.insert(url.to_string(), Arc::downgrade(&server));
                server
            }
        };
        Ok(RemoteEnv { state: vec![0.0; server.spec.state_dim()], server, session: None })
    }

    fn connect_server(url: &str) -> Result<Server, EnvError> {
        let unreachable = |message: String| EnvError::Remote { url: url.to_string(), message };
        let address = address(url)
            .filter(|rest| rest.rsplit_once(':').is_some_and(|(host, port)| !host.is_empty() && port.parse::<u16>().is_ok()))
            .ok_or_else(|| unreachable(format!("not a server address; write {SCHEME}HOST:PORT (or {TLS_SCHEME}HOST:PORT under TLS), e.g. {SCHEME}127.0.0.1:50070")))?;
        let tls = url.starts_with(TLS_SCHEME);
        let security = client_security(tls).map_err(unreachable)?;
        let http = if tls { "https" } else { "http" };
        let endpoint = security.endpoint(&format!("{http}://{address}")).map_err(|e| unreachable(e.to_string()))?.connect_timeout(CONNECT_TIMEOUT).timeout(CALL_TIMEOUT);
        let bearer = security.bearer().map_err(|e| unreachable(e.to_string()))?;
        let channel = blocking(async move { endpoint.connect().await })
            .map_err(unreachable)?
            .map_err(|e| {
                unreachable(format!(
                    "cannot connect ({}); start the environment server first, e.g. `.venv/bin/python -m lcrl_env serve --env Pendulum-v1 --listen {address}`",
                    lcrl_runtime::security::error_chain(&e)
                ))
            })?;
        let channel = tonic::service::interceptor::InterceptedService::new(channel, bearer);
        let client = EnvironmentClient::new(channel).max_decoding_message_size(16 << 20).max_encoding_message_size(16 << 20);
        let connection = Connection { url: url.to_string(), client };
        let spec = connection.call("GetSpec", |mut c| async move { c.get_spec(GetSpecRequest {}).await })?;
        let (m, n) = (spec.state_names.len(), spec.action_names.len());
        if m == 0 || n == 0 {
            return Err(connection.error(format!("the server reports {m} states and {n} actions; both must be at least 1")));
        }
        if spec.action_low.len() != n || spec.action_high.len() != n || spec.state_low.len() != m || spec.state_high.len() != m {
            return Err(connection.error("the spec's bounds do not match its names (a server of another version?)"));
        }
        if let Some(i) = (0..n).find(|&i| !(spec.action_low[i].is_finite() && spec.action_high[i].is_finite() && spec.action_low[i] < spec.action_high[i])) {
            return Err(connection.error(format!("action {i} has bounds [{}, {}]; they must be finite and increasing", spec.action_low[i], spec.action_high[i])));
        }
        if !spec.state_scale.is_empty() && (spec.state_scale.len() != m || spec.state_scale.iter().any(|s| !(s.is_finite() && *s > 0.0))) {
            return Err(connection.error("the spec's state_scale must hold one finite, positive divisor per state"));
        }
        let derived: Vec<f64> = spec
            .state_low
            .iter()
            .zip(&spec.state_high)
            .map(|(lo, hi)| {
                let bound = lo.abs().max(hi.abs());
                if lo.is_finite() && hi.is_finite() && bound > 0.0 { bound } else { 1.0 }
            })
            .collect();
        let state_scale = if spec.state_scale.is_empty() { derived } else { spec.state_scale };
        Ok(Server {
            connection,
            spec: EnvSpec { name: url.to_string(), state_names: spec.state_names, action_names: spec.action_names, action_low: spec.action_low, action_high: spec.action_high },
            state_scale,
            fork_unavailable: (!spec.can_fork).then(|| if spec.fork_unavailable.is_empty() { "the server cannot fork".to_string() } else { spec.fork_unavailable }),
            dt: spec.dt,
        })
    }

    /// This instance's session, opened on first use.
    fn session(&mut self) -> Result<u64, EnvError> {
        if let Some(session) = self.session {
            return Ok(session);
        }
        let opened = self.server.connection.call("Open", |mut c| async move { c.open(OpenRequest { count: 1 }).await })?;
        let session = *opened.sessions.first().ok_or_else(|| self.server.connection.error("Open returned no session"))?;
        self.session = Some(session);
        Ok(session)
    }

    fn checked_state(server: &Server, state: Vec<f64>) -> Result<Vec<f64>, EnvError> {
        check_state(&server.spec, &state).map_err(|message| server.connection.error(message))?;
        Ok(state)
    }

    /// Steps every environment of `envs` by its action in one call. All must
    /// be sessions of one server and reset (see [`crate::step_all`]).
    pub(crate) fn step_batch(envs: &mut [&mut RemoteEnv], actions: &[Vec<f64>]) -> Result<Vec<Step>, EnvError> {
        let Some(first) = envs.first() else { return Ok(Vec::new()) };
        let server = first.server.clone();
        let mut steps = Vec::with_capacity(envs.len());
        for (env, action) in envs.iter().zip(actions) {
            server.spec.check_action(action)?;
            steps.push(SessionStep { session: env.session.ok_or(EnvError::NotReset)?, action: server.spec.clip_action(action) });
        }
        let reply = server.connection.call("Step", |mut c| async move { c.step(StepRequest { steps }).await })?;
        let steps = read_step_reply(&server.spec, envs.len(), reply).map_err(|message| server.connection.error(message))?;
        for (env, step) in envs.iter_mut().zip(&steps) {
            env.state.clone_from(&step.state);
        }
        Ok(steps)
    }

    /// Whether `other` is a session of the same server (one batch).
    pub(crate) fn same_server(&self, other: &RemoteEnv) -> bool {
        Arc::ptr_eq(&self.server, &other.server)
    }
}

/// What a server's state must be: `spec`'s length, every component finite
/// (a NaN from a peer would reach the replay buffer and every update).
fn check_state(spec: &EnvSpec, state: &[f64]) -> Result<(), String> {
    if state.len() != spec.state_dim() {
        return Err(format!("a state of {} components arrived; the spec has {}", state.len(), spec.state_dim()));
    }
    if let Some(i) = state.iter().position(|v| !v.is_finite()) {
        return Err(format!("state component {i} ({}) is {}; a state must be finite", spec.state_names[i], state[i]));
    }
    Ok(())
}

/// Reads a server's answer to a Step of `sessions` sessions: one result per
/// session, each a finite state of the spec's length and a finite reward.
/// Everything a peer sends passes here before training sees it (fuzzed by
/// fuzz/fuzz_targets/step_reply.rs).
pub fn read_step_reply(spec: &EnvSpec, sessions: usize, reply: lcrl_proto::v1::StepResponse) -> Result<Vec<Step>, String> {
    if reply.results.len() != sessions {
        return Err(format!("Step answered {} results for {sessions} sessions", reply.results.len()));
    }
    reply
        .results
        .into_iter()
        .map(|r| {
            check_state(spec, &r.state)?;
            if !r.reward.is_finite() {
                return Err(format!("a reward of {} arrived; rewards must be finite", r.reward));
            }
            Ok(Step { state: r.state, reward: r.reward, terminated: r.terminated, truncated: r.truncated })
        })
        .collect()
}

/// Steps each environment by its action, in order. Environments served by
/// one server (this module) go in one call (the service's batched
/// Step), which is what makes K environments per actor cheap.
pub fn step_all(envs: &mut [Box<dyn Env>], actions: &[Vec<f64>]) -> Result<Vec<Step>, EnvError> {
    if envs.len() != actions.len() {
        return Err(EnvError::invalid("actions", format!("{} actions for {} environments", actions.len(), envs.len())));
    }
    if envs.len() > 1 {
        let remotes: Option<Vec<&mut RemoteEnv>> = envs.iter_mut().map(|e| e.as_any_mut().downcast_mut::<RemoteEnv>()).collect();
        if let Some(mut remotes) = remotes {
            if remotes.iter().all(|r| r.same_server(remotes[0])) {
                return RemoteEnv::step_batch(&mut remotes, actions);
            }
        }
    }
    envs.iter_mut().zip(actions).map(|(env, action)| env.step(action)).collect()
}

impl Env for RemoteEnv {
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }

    fn as_any_mut(&mut self) -> &mut dyn std::any::Any {
        self
    }

    fn spec(&self) -> &EnvSpec {
        &self.server.spec
    }

    fn reset(&mut self, seed: u64) -> Result<Vec<f64>, EnvError> {
        let session = self.session()?;
        let reply = self.server.connection.call("Reset", |mut c| async move { c.reset(ResetRequest { resets: vec![SessionReset { session, seed }] }).await })?;
        let state = reply.states.into_iter().next().ok_or_else(|| self.server.connection.error("Reset returned no state"))?;
        self.state = Self::checked_state(&self.server, state.state)?;
        Ok(self.state.clone())
    }

    fn state(&self) -> &[f64] {
        &self.state
    }

    fn step(&mut self, action: &[f64]) -> Result<Step, EnvError> {
        let mut envs = [&mut *self];
        // step_batch checked that one result came back for the one session.
        let mut steps = Self::step_batch(&mut envs, &[action.to_vec()])?;
        steps.pop().ok_or_else(|| self.server.connection.error("Step returned no result"))
    }

    fn fresh(&self) -> Box<dyn Env> {
        Box::new(RemoteEnv { server: self.server.clone(), session: None, state: vec![0.0; self.server.spec.state_dim()] })
    }

    fn snapshot(&self) -> Result<Box<dyn Env>, EnvError> {
        let Some(session) = self.session else {
            // Nothing to copy yet: a new, unopened instance is the same.
            return Ok(self.fresh());
        };
        self.check_snapshot()?;
        let fork = self.server.connection.call("Fork", |mut c| async move { c.fork(ForkRequest { session }).await })?;
        Ok(Box::new(RemoteEnv { server: self.server.clone(), session: Some(fork.session), state: self.state.clone() }))
    }

    fn check_snapshot(&self) -> Result<(), EnvError> {
        match &self.server.fork_unavailable {
            Some(reason) => Err(EnvError::ForkUnavailable { url: self.server.connection.url.clone(), reason: reason.clone() }),
            None => Ok(()),
        }
    }

    fn state_scale(&self) -> Option<&[f64]> {
        Some(&self.server.state_scale)
    }

    fn control_period_s(&self) -> f64 {
        if self.server.dt > 0.0 { self.server.dt } else { 1.0 }
    }

}

impl Drop for RemoteEnv {
    /// Closes the session without waiting (a fork in CS3 is dropped every
    /// sample); the server also closes sessions that stay idle.
    fn drop(&mut self) {
        if let (Some(session), Ok(runtime)) = (self.session, runtime()) {
            let mut client = self.server.connection.client.clone();
            runtime.spawn(async move {
                let _ = client.close(CloseRequest { sessions: vec![session] }).await;
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lcrl_proto::v1::{StepResponse, StepResult};

    fn spec() -> EnvSpec {
        EnvSpec {
            name: "grpc://test".into(),
            state_names: vec!["x".into(), "v".into()],
            action_names: vec!["f".into()],
            action_low: vec![-1.0],
            action_high: vec![1.0],
        }
    }

    fn result(state: Vec<f64>, reward: f64) -> StepResult {
        StepResult { state, reward, terminated: true, truncated: false, so_far: None }
    }

    #[test]
    fn a_step_reply_is_read_in_session_order() {
        let reply = StepResponse { results: vec![result(vec![1.0, 2.0], -0.5), result(vec![3.0, 4.0], 0.25)] };
        let steps = read_step_reply(&spec(), 2, reply).unwrap();
        assert_eq!(steps.iter().map(|s| (s.state.clone(), s.reward)).collect::<Vec<_>>(), vec![(vec![1.0, 2.0], -0.5), (vec![3.0, 4.0], 0.25)]);
        assert!(steps.iter().all(|s| s.terminated && !s.truncated));
    }

    #[test]
    fn a_step_reply_a_peer_got_wrong_is_refused_with_the_reason() {
        let cases = [
            (StepResponse { results: vec![result(vec![1.0, 2.0], 0.0)] }, "1 results for 2 sessions"),
            (StepResponse { results: vec![result(vec![1.0], 0.0), result(vec![1.0, 2.0], 0.0)] }, "1 components"),
            (StepResponse { results: vec![result(vec![1.0, f64::NAN], 0.0), result(vec![1.0, 2.0], 0.0)] }, "component 1 (v) is NaN"),
            (StepResponse { results: vec![result(vec![1.0, 2.0], f64::INFINITY), result(vec![1.0, 2.0], 0.0)] }, "a reward of inf"),
        ];
        for (reply, expected) in cases {
            let message = read_step_reply(&spec(), 2, reply).unwrap_err();
            assert!(message.contains(expected), "{message:?} should say {expected:?}");
        }
    }
}
