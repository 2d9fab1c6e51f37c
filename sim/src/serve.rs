//! lcrl's own environments served over `lcrl.v1.Environment`
//! (proto/lcrl.proto): the other side of [`crate::remote`]. `lcrl serve-env
//! --env peg-group1` hands the peg task to any language; the Python
//! package's Gymnasium face (clients/python/lcrl_env/gym.py) drives it.
//!
//! Each session is one instance, stepped exactly as in this process
//! (numbers travel as f64), so a served trajectory is bit-identical to a
//! local one, and Fork is [`Env::snapshot`]: CS3 can run against a server.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use lcrl_proto::v1::environment_server::Environment;
use lcrl_proto::v1::{
    CloseRequest, CloseResponse, EnvironmentSpec, EnvironmentState, EpisodeSoFar, ForkRequest, ForkResponse, GetSpecRequest, OpenRequest, OpenResponse,
    ResetRequest, ResetResponse, ReturnTerms, StepRequest, StepResponse, StepResult,
};
use tonic::{Request, Response, Status};

use crate::env::{Env, EnvError};

/// One instance and where its episode stands.
struct Session {
    env: Box<dyn Env>,
    reset: bool,
    ended: bool,
    last_used: Instant,
}

/// Instances of one environment, each in a session with a numeric id.
pub struct Sessions {
    prototype: Box<dyn Env>,
    sessions: Mutex<HashMap<u64, Arc<Mutex<Session>>>>,
    next_id: AtomicU64,
    settings: ServeSettings,
}

type Shared = Arc<Mutex<Session>>;

impl Sessions {
    /// Sessions of the environment `name` (anything [`crate::make_env`]
    /// takes but a served one: serving a server's environment again would
    /// only add a hop).
    pub fn new(name: &str, settings: ServeSettings) -> Result<Sessions, EnvError> {
        if crate::remote::is_served(name) {
            return Err(EnvError::invalid("env", format!("{name} is already served; serve a built-in name or an environment file")));
        }
        settings.check()?;
        Ok(Sessions { prototype: crate::make_env(name)?, sessions: Mutex::new(HashMap::new()), next_id: AtomicU64::new(1), settings })
    }

    fn table(&self) -> std::sync::MutexGuard<'_, HashMap<u64, Shared>> {
        self.sessions.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// What the environment is; state bounds are ±∞ (a simulator's states
    /// are not boxed), and `state_scale` gives its own scales.
    pub fn spec(&self) -> EnvironmentSpec {
        let env = self.prototype.as_ref();
        let spec = env.spec();
        let m = spec.state_dim();
        let (can_fork, fork_unavailable) = match env.check_snapshot() {
            Ok(()) => (true, String::new()),
            Err(e) => (false, e.to_string()),
        };
        EnvironmentSpec {
            env_id: spec.name.clone(),
            state_names: spec.state_names.clone(),
            action_names: spec.action_names.clone(),
            state_low: vec![f64::NEG_INFINITY; m],
            state_high: vec![f64::INFINITY; m],
            action_low: spec.action_low.clone(),
            action_high: spec.action_high.clone(),
            can_fork,
            fork_method: if can_fork { "snapshot".into() } else { String::new() },
            fork_unavailable,
            max_episode_steps: 0,
            dt: env.control_period_s(),
            max_sessions: self.settings.max_sessions,
            open_sessions: self.table().len() as u32,
            state_scale: env.state_scale().map_or_else(|| vec![1.0; m], <[f64]>::to_vec),
        }
    }

    /// Adds an instance in a new session, after closing sessions idle for
    /// longer than the idle timeout.
    fn add(&self, env: Box<dyn Env>, reset: bool, ended: bool) -> Result<u64, Status> {
        let mut table = self.table();
        self.close_idle(&mut table);
        if table.len() >= self.settings.max_sessions as usize {
            return Err(Status::resource_exhausted(format!(
                "{} sessions are open, the server's limit (--max-sessions {}); close some",
                table.len(),
                self.settings.max_sessions
            )));
        }
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        table.insert(id, Arc::new(Mutex::new(Session { env, reset, ended, last_used: Instant::now() })));
        Ok(id)
    }

    /// Closes sessions unused for the idle timeout; a session in use now
    /// (its lock held by a step) is not idle.
    fn close_idle(&self, table: &mut HashMap<u64, Shared>) {
        let timeout = Duration::from_secs(self.settings.idle_timeout_secs);
        table.retain(|_, s| match s.try_lock() {
            Ok(session) => session.last_used.elapsed() < timeout,
            Err(std::sync::TryLockError::WouldBlock) => true,
            Err(std::sync::TryLockError::Poisoned(_)) => false,
        });
    }

    fn get(&self, id: u64) -> Result<Shared, Status> {
        self.table().get(&id).cloned().ok_or_else(|| {
            Status::not_found(format!("no session {id} on this server (closed, or idle for over {} s)", self.settings.idle_timeout_secs))
        })
    }

    pub fn open(&self, count: u32) -> Result<Vec<u64>, Status> {
        if count < 1 {
            return Err(Status::invalid_argument("Open needs count >= 1"));
        }
        // All or none: sessions opened before a refusal would be orphans.
        {
            let mut table = self.table();
            self.close_idle(&mut table);
            let free = (self.settings.max_sessions as usize).saturating_sub(table.len());
            if count as usize > free {
                return Err(Status::resource_exhausted(format!(
                    "{count} sessions asked for, {free} free of the server's {} (--max-sessions); close some",
                    self.settings.max_sessions
                )));
            }
        }
        (0..count).map(|_| self.add(self.prototype.fresh(), false, false)).collect()
    }

    pub fn close(&self, ids: &[u64]) {
        let mut table = self.table();
        for id in ids {
            table.remove(id);
        }
    }

    /// Gymnasium's reset(seed): the environment's own `reset`.
    pub fn reset(&self, id: u64, seed: u64) -> Result<Vec<f64>, Status> {
        let shared = self.get(id)?;
        let mut session = shared.lock().unwrap_or_else(|p| p.into_inner());
        let state = session.env.reset(seed).map_err(|e| Status::internal(format!("session {id}: {e}")))?;
        (session.reset, session.ended, session.last_used) = (true, false, Instant::now());
        Ok(state)
    }

    /// One step, with what the episode achieved so far.
    pub fn step(&self, id: u64, action: &[f64]) -> Result<StepResult, Status> {
        let shared = self.get(id)?;
        let mut session = shared.lock().unwrap_or_else(|p| p.into_inner());
        session.last_used = Instant::now();
        session.env.spec().check_action(action).map_err(|e| Status::invalid_argument(format!("session {id}: {e}")))?;
        if !session.reset {
            return Err(Status::failed_precondition(format!("session {id} has not been reset; call Reset before Step")));
        }
        if session.ended {
            return Err(Status::failed_precondition(format!("session {id}: the episode has ended; call Reset before stepping again")));
        }
        let step = session.env.step(action).map_err(|e| Status::internal(format!("session {id}: {e}")))?;
        session.ended = step.terminated || step.truncated;
        let m = session.env.episode_metrics();
        let so_far = EpisodeSoFar {
            success: m.success,
            peak_force_n: m.peak_force_n,
            peak_moment_nm: m.peak_moment_nm,
            max_penetration_mm: m.max_penetration_mm,
            return_terms: m.return_terms.map(|t| ReturnTerms { depth: t.depth, force: t.force, moment: t.moment, bonus: t.bonus, failure: t.failure }),
        };
        Ok(StepResult { state: step.state, reward: step.reward, terminated: step.terminated, truncated: step.truncated, so_far: Some(so_far) })
    }

    /// An exact copy in a new session ([`Env::snapshot`]).
    pub fn fork(&self, id: u64) -> Result<u64, Status> {
        let shared = self.get(id)?;
        let (copy, reset, ended) = {
            let session = shared.lock().unwrap_or_else(|p| p.into_inner());
            let copy = session.env.snapshot().map_err(|e| Status::failed_precondition(format!("this environment cannot fork: {e}")))?;
            (copy, session.reset, session.ended)
        };
        self.add(copy, reset, ended)
    }
}

/// The gRPC face of [`Sessions`]. Steps and resets run off the event loop
/// (a peg step takes about a millisecond).
#[derive(Clone)]
pub struct EnvironmentService {
    sessions: Arc<Sessions>,
}

impl EnvironmentService {
    pub fn new(sessions: Sessions) -> Self {
        EnvironmentService { sessions: Arc::new(sessions) }
    }

    async fn blocking<T: Send + 'static>(&self, work: impl FnOnce(&Sessions) -> Result<T, Status> + Send + 'static) -> Result<T, Status> {
        let sessions = self.sessions.clone();
        tokio::task::spawn_blocking(move || work(&sessions)).await.map_err(|e| Status::internal(format!("the environment panicked: {e}")))?
    }
}

#[tonic::async_trait]
impl Environment for EnvironmentService {
    async fn get_spec(&self, _request: Request<GetSpecRequest>) -> Result<Response<EnvironmentSpec>, Status> {
        Ok(Response::new(self.sessions.spec()))
    }

    async fn open(&self, request: Request<OpenRequest>) -> Result<Response<OpenResponse>, Status> {
        let count = request.into_inner().count;
        let sessions = self.blocking(move |s| s.open(count)).await?;
        Ok(Response::new(OpenResponse { sessions }))
    }

    async fn close(&self, request: Request<CloseRequest>) -> Result<Response<CloseResponse>, Status> {
        self.sessions.close(&request.into_inner().sessions);
        Ok(Response::new(CloseResponse {}))
    }

    async fn reset(&self, request: Request<ResetRequest>) -> Result<Response<ResetResponse>, Status> {
        let resets = request.into_inner().resets;
        if resets.is_empty() {
            return Err(Status::invalid_argument("Reset needs at least one session"));
        }
        let states = self
            .blocking(move |s| resets.iter().map(|r| s.reset(r.session, r.seed).map(|state| EnvironmentState { state })).collect::<Result<Vec<_>, _>>())
            .await?;
        Ok(Response::new(ResetResponse { states }))
    }

    async fn step(&self, request: Request<StepRequest>) -> Result<Response<StepResponse>, Status> {
        let steps = request.into_inner().steps;
        if steps.is_empty() {
            return Err(Status::invalid_argument("Step needs at least one session"));
        }
        let results = self.blocking(move |s| steps.iter().map(|step| s.step(step.session, &step.action)).collect::<Result<Vec<_>, _>>()).await?;
        Ok(Response::new(StepResponse { results }))
    }

    async fn fork(&self, request: Request<ForkRequest>) -> Result<Response<ForkResponse>, Status> {
        let id = request.into_inner().session;
        let session = self.blocking(move |s| s.fork(id)).await?;
        Ok(Response::new(ForkResponse { session }))
    }
}

/// How many sessions a server holds, and for how long an idle one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ServeSettings {
    /// Most sessions open at once (Open and Fork beyond it get
    /// RESOURCE_EXHAUSTED).
    pub max_sessions: u32,
    /// A session unused this long is closed when a new one is opened.
    pub idle_timeout_secs: u64,
}

impl Default for ServeSettings {
    fn default() -> Self {
        ServeSettings { max_sessions: 256, idle_timeout_secs: 600 }
    }
}

impl ServeSettings {
    /// The ranges `lcrl serve-env` accepts.
    pub fn check(&self) -> Result<(), EnvError> {
        if !(1..=65_536).contains(&self.max_sessions) {
            return Err(EnvError::invalid("max_sessions", format!("{} is outside 1..=65536", self.max_sessions)));
        }
        if !(1..=86_400).contains(&self.idle_timeout_secs) {
            return Err(EnvError::invalid("idle_timeout_secs", format!("{} is outside 1..=86400 s", self.idle_timeout_secs)));
        }
        Ok(())
    }
}
