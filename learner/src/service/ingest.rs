//! What the learner accepts from actors: transition batches checked for
//! run id, dimensions and finiteness, deduplicated by (actor, sequence),
//! filtered for staleness (PPO), and converted to the agent's normalized
//! units. Plain Rust; the gRPC and shared-memory front ends both call it.

use crate::policy::action::ActionMap;
use crate::service::episode_sums::{OpenEpisodes, Stored};
use std::collections::{BTreeMap, HashMap};

use lcrl_proto::v1::{EpisodeSummary, TransitionBatch};
use lcrl_sim::Env;

/// A transition in the agent's units: normalized state, and the action u as
/// the agent sampled it (what `lcrl train` stores for the same step).
#[derive(Debug, Clone, PartialEq)]
pub struct AgentTransition {
    pub obs: Vec<f32>,
    pub action: Vec<f32>,
    /// The behaviour log π(u|s) the actor sent (PPO), if it sent one.
    pub log_prob: Option<f32>,
    pub reward: f32,
    pub next_obs: Vec<f32>,
    pub terminated: bool,
    /// The step cap ended the episode.
    pub truncated: bool,
    /// The actor's batch ended this environment's stream here, mid-episode
    /// (proto `Transition.cut`): the agent bootstraps as at a truncation,
    /// but no episode ended.
    pub cut: bool,
    /// The policy version that chose the action (the batch's when the
    /// actor did not say: version 0 is then indistinguishable from unset).
    pub policy_version: u64,
}

/// An accepted batch, ready for the training thread.
#[derive(Debug, Clone, PartialEq)]
pub struct Accepted {
    pub transitions: Vec<AgentTransition>,
    pub episodes: Vec<EpisodeSummary>,
    /// The policy version that produced the batch.
    pub policy_version: u64,
    /// The sending actor, as a number ([`stream_of`]): the stream that a
    /// cut at this batch's end goes on in.
    pub stream: u64,
}

/// An actor's name as a stream number for the agent (FNV-1a: stable
/// across builds, so that a checkpointed rollout resumes its streams).
pub fn stream_of(actor_id: &str) -> u64 {
    actor_id.bytes().fold(0xcbf2_9ce4_8422_2325, |hash, byte| (hash ^ u64::from(byte)).wrapping_mul(0x0100_0000_01b3))
}

impl Accepted {
    /// Keeps the batch's first `episodes` episodes: its transitions up to
    /// the end of the last one kept (a batch lists its episodes in the
    /// order their ends appear; a cut is not an end). Returns how many
    /// transitions were dropped.
    /// The learner's budget ends exactly at its last episode this way,
    /// as `lcrl train`'s does, even when a batch holds several ends.
    pub fn keep_episodes(&mut self, episodes: usize) -> usize {
        if self.episodes.len() <= episodes {
            return 0;
        }
        let mut ends = self.transitions.iter().enumerate().filter(|(_, t)| t.terminated || t.truncated).map(|(i, _)| i + 1);
        let cut = match episodes {
            0 => 0,
            k => ends.nth(k - 1).unwrap_or(self.transitions.len()),
        };
        let dropped = self.transitions.len() - cut;
        self.transitions.truncate(cut);
        self.episodes.truncate(episodes);
        dropped
    }
}

/// The outcome of checking one batch.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    Accept(Accepted),
    /// (actor_id, sequence) was stored before: acknowledged, not stored.
    Duplicate,
    /// PPO: produced by a policy older than the staleness bound; discarded.
    Stale,
    /// Malformed: rejected with INVALID_ARGUMENT. `reason` is the status key.
    Reject { reason: &'static str, message: String },
}

/// Distinct actor ids the learner keeps sequences for. A new id beyond
/// them takes the place of the longest-silent one if that has been silent
/// for [`ACTOR_SILENCE_TO_FORGET`]; otherwise it is refused ("actors"). A
/// restarted actor process comes back under a new id, so a long run sees
/// many; thousands at once are a flood.
pub const MAX_ACTORS: usize = 4096;

/// Actor ids one peer address may hold in the table (loopback, where
/// `lcrl run` starts its actors, is exempt): one host cannot lock out the
/// others by filling it (issue 71).
pub const MAX_ACTORS_PER_PEER: usize = MAX_ACTORS / 8;

/// Where a batch came from: the gRPC stream that carries it (0: none, as
/// on shared memory, which only processes of this host can reach) and
/// the peer's address.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Origin {
    pub stream: u64,
    pub peer: Option<std::net::IpAddr>,
}

impl Origin {
    /// The peer whose ids count against [`MAX_ACTORS_PER_PEER`].
    fn counted_peer(&self) -> Option<std::net::IpAddr> {
        self.peer.and_then(lcrl_runtime::limits::counted_peer)
    }
}

/// The stream an actor id is bound to, and the key its actor drew
/// (TransitionBatch.actor_key; 0: none).
#[derive(Debug, Clone, Copy)]
struct Holder {
    stream: u64,
    key: u64,
}

impl Holder {
    /// The holder itself, or the same actor on a new stream (its old one
    /// broke without this learner noticing: it shows the holder's key).
    fn admits(&self, stream: u64, key: u64) -> bool {
        self.stream == stream || (self.key != 0 && self.key == key)
    }
}

/// How long an actor must have sent nothing before a new one may take its
/// place among [`MAX_ACTORS`] (its replayed batches would then count as
/// new: it is long gone).
pub const ACTOR_SILENCE_TO_FORGET: std::time::Duration = std::time::Duration::from_secs(600);

/// The ingestion state of a run.
pub struct Ingest {
    run_id: String,
    /// This learner process's incarnation (PolicySnapshot.incarnation).
    incarnation: u64,
    env: Box<dyn Env>,
    /// Actors send environment actions; the agent learns normalized ones.
    actions: ActionMap,
    /// Highest sequence stored per actor; sequences increase per actor.
    last_sequence: HashMap<String, u64>,
    /// When each actor was last heard from (since this process started).
    last_seen: HashMap<String, std::time::Instant>,
    /// The live stream (gRPC, or a shared-memory publisher) each actor id
    /// is bound to: while it lives, no other stream may send under that id
    /// (a hijacker's sequence would otherwise decide what the honest
    /// actor's batches are), unless it carries the holder's key.
    holders: HashMap<String, Holder>,
    /// The peer that brought each id into the table, and how many each
    /// peer holds there (loopback and shared memory uncounted).
    brought_by: HashMap<String, std::net::IpAddr>,
    ids_of_peer: HashMap<std::net::IpAddr, usize>,
    /// Maximum accepted age (in policy versions) of a batch; None: any.
    max_staleness: Option<u64>,
    /// Transitions rejected or dropped, by reason.
    pub rejected: BTreeMap<String, u64>,
    /// Transitions accepted (handed to the training thread).
    pub accepted: u64,
    /// Every actor's unfinished episodes, so claims are checked against all
    /// their stored steps (episode_sums.rs).
    open: OpenEpisodes,
}

impl Ingest {
    pub fn new(run_id: &str, env: Box<dyn Env>, max_staleness: Option<u64>) -> Self {
        let actions = ActionMap::plain(env.spec());
        Ingest {
            run_id: run_id.to_string(),
            incarnation: 0,
            env,
            actions,
            last_sequence: HashMap::new(),
            last_seen: HashMap::new(),
            holders: HashMap::new(),
            brought_by: HashMap::new(),
            ids_of_peer: HashMap::new(),
            max_staleness,
            rejected: BTreeMap::new(),
            accepted: 0,
            open: OpenEpisodes::default(),
        }
    }

    /// The learner's incarnation: an on-policy learner drops batches that
    /// name another (0: none checked).
    pub fn with_incarnation(mut self, incarnation: u64) -> Self {
        self.incarnation = incarnation;
        self
    }

    /// The run's action map (its base controller): actions arrive in the
    /// environment's units and are stored as the agent's u.
    pub fn with_actions(mut self, actions: ActionMap) -> Self {
        self.actions = actions;
        self
    }

    /// Resumes deduplication from a checkpoint (its actors count as heard
    /// from now: their silence starts with this process).
    pub fn with_sequences(mut self, last_sequence: HashMap<String, u64>) -> Self {
        let now = std::time::Instant::now();
        self.last_seen = last_sequence.keys().map(|id| (id.clone(), now)).collect();
        self.last_sequence = last_sequence;
        self
    }

    /// Makes room for a new actor id: true when there is a place (freeing
    /// the longest-silent actor's if it has been silent long enough).
    fn place_for(&mut self, actor_id: &str) -> bool {
        if self.last_sequence.contains_key(actor_id) || self.last_sequence.len() < MAX_ACTORS {
            return true;
        }
        let oldest = self.last_seen.iter().min_by_key(|(_, seen)| **seen).map(|(id, seen)| (id.clone(), seen.elapsed()));
        match oldest {
            Some((id, silent)) if silent >= ACTOR_SILENCE_TO_FORGET => {
                self.open.forget(&id);
                self.last_sequence.remove(&id);
                self.last_seen.remove(&id);
                self.holders.remove(&id);
                if let Some(peer) = self.brought_by.remove(&id) {
                    if let Some(n) = self.ids_of_peer.get_mut(&peer) {
                        *n = n.saturating_sub(1);
                    }
                }
                true
            }
            _ => false,
        }
    }

    /// Forgets the ids `peer` brought that have been silent for
    /// [`ACTOR_SILENCE_TO_FORGET`].
    fn forget_silent_ids_of(&mut self, peer: std::net::IpAddr) {
        let silent: Vec<String> = self
            .brought_by
            .iter()
            .filter(|(id, by)| **by == peer && self.last_seen.get(*id).is_none_or(|seen| seen.elapsed() >= ACTOR_SILENCE_TO_FORGET))
            .map(|(id, _)| id.clone())
            .collect();
        for id in silent {
            self.open.forget(&id);
            self.last_sequence.remove(&id);
            self.last_seen.remove(&id);
            self.holders.remove(&id);
            self.brought_by.remove(&id);
            if let Some(n) = self.ids_of_peer.get_mut(&peer) {
                *n = n.saturating_sub(1);
            }
        }
    }

    pub fn sequences(&self) -> &HashMap<String, u64> {
        &self.last_sequence
    }

    fn count(&mut self, reason: &str, transitions: usize) {
        *self.rejected.entry(reason.to_string()).or_insert(0) += transitions.max(1) as u64;
    }

    /// Counts a message refused before it could be read as a batch
    /// ("oversize", "undecodable").
    pub fn refuse(&mut self, reason: &str) {
        self.count(reason, 1);
    }

    /// Frees the ids a gRPC stream held: they may come back on another
    /// (an actor that reconnects), and their sequences stay.
    pub fn release_stream(&mut self, stream: u64) {
        self.release_streams(|s| s == stream);
    }

    /// Frees the ids of every stream that `ended` says is gone (shared
    /// memory: publishers that left).
    pub fn release_streams(&mut self, ended: impl Fn(u64) -> bool) {
        self.holders.retain(|_, holder| !ended(holder.stream));
    }

    /// Whether any id is bound to a stream `of_kind` accepts (the
    /// shared-memory thread checks its publishers only then).
    pub fn holds_streams(&self, of_kind: impl Fn(u64) -> bool) -> bool {
        self.holders.values().any(|holder| of_kind(holder.stream))
    }

    /// Checks `batch` against the run and the current policy version, as
    /// from no stream (it can take no id another stream holds).
    pub fn check(&mut self, batch: &TransitionBatch, policy_version: u64) -> Verdict {
        self.check_from(batch, policy_version, Origin::default())
    }

    /// Checks `batch` from `origin`: an id is bound to the first live
    /// stream that sent it, and one peer holds at most
    /// [`MAX_ACTORS_PER_PEER`] ids.
    pub fn check_from(&mut self, batch: &TransitionBatch, policy_version: u64, origin: Origin) -> Verdict {
        let count = batch.transitions.len();
        let door = self.check_names(batch).and_then(|()| self.check_values(batch)).and_then(|()| check_episodes(batch)).and_then(|()| self.check_sender(batch, origin));
        match door {
            Err(Door::Reject(reason, message)) => {
                self.count(reason, count);
                return Verdict::Reject { reason, message };
            }
            Err(Door::Duplicate) => {
                self.count("duplicate", count);
                return Verdict::Duplicate;
            }
            Ok(()) => {}
        }
        self.admit_sender(batch, origin);
        // Each episode's return and length from the steps received for it,
        // in this batch and the actor's earlier ones (what metrics.csv, the
        // budget and the summary count, episode_sums.rs). Settled before
        // the stale check: a stale batch's steps are still its episodes'.
        let (episodes, rewritten) = self.open.settle(batch);
        if rewritten > 0 {
            tracing::debug!(actor = %batch.actor_id, rewritten, "episode claims rewritten to the steps received for them");
        }
        // On-policy: versions of another learner process are not this
        // one's (after a restart they count from the checkpoint again), so
        // its data is stale whatever its number says.
        let other_incarnation = self.incarnation != 0 && batch.incarnation != 0 && batch.incarnation != self.incarnation;
        if self.max_staleness.is_some() && other_incarnation {
            self.count("stale_incarnation", count);
            return Verdict::Stale;
        }
        if self.max_staleness.is_some_and(|bound| policy_version.saturating_sub(batch.policy_version) > bound) {
            self.count("stale", count);
            return Verdict::Stale;
        }
        let transitions = self.normalize(batch);
        self.accepted += transitions.len() as u64;
        Verdict::Accept(Accepted { transitions, episodes, policy_version: batch.policy_version, stream: stream_of(&batch.actor_id) })
    }

    /// The run id, and the actor id's length (names are kept: sequences,
    /// checkpoint.json).
    fn check_names(&self, batch: &TransitionBatch) -> Result<(), Door> {
        if batch.run_id != self.run_id {
            return Err(Door::Reject("unknown_run", // A peer's string in the log: at most 64 characters of it.
                format!("run id '{}' is not this learner's run ('{}')", batch.run_id.chars().take(64).collect::<String>(), self.run_id)));
        }
        if batch.actor_id.len() > lcrl_runtime::limits::MAX_ACTOR_ID_BYTES {
            return Err(Door::Reject("actor_id", format!("actor_id is {} bytes; at most {} are kept", batch.actor_id.len(), lcrl_runtime::limits::MAX_ACTOR_ID_BYTES)));
        }
        Ok(())
    }

    /// Every transition's dimensions, finite values and bounds.
    fn check_values(&self, batch: &TransitionBatch) -> Result<(), Door> {
        let (m, n) = (self.env.spec().state_dim(), self.env.spec().action_dim());
        for (k, t) in batch.transitions.iter().enumerate() {
            let sampled_ok = t.sampled_action.is_empty() || t.sampled_action.len() == n;
            if t.state.len() != m || t.next_state.len() != m || t.action.len() != n || !sampled_ok {
                return Err(Door::Reject("dimensions", format!(
                        "transition {k}: state {}, next_state {}, action {}, sampled_action {}; this run needs states of {m} and actions \
                         of {n} (sampled_action: {n} or none)",
                        t.state.len(),
                        t.next_state.len(),
                        t.action.len(),
                        t.sampled_action.len()
                    )));
            }
            let all = t.state.iter().chain(&t.next_state).chain(&t.action).chain(&t.sampled_action).chain(std::iter::once(&t.reward)).chain(&t.log_prob);
            if all.clone().any(|v| !v.is_finite()) {
                return Err(Door::Reject("non_finite", format!("transition {k} holds a non-finite number")));
            }
        }
        // Finite is not enough: one batch of 3e38 states turned every
        // weight to NaN within 1.5 s (issue 71). Values are refused beyond
        // the environment's scale by the stated factors (lcrl_sim::STATE_LIMIT, ...).
        if let Some((k, why)) = batch.transitions.iter().enumerate().find_map(|(k, t)| self.out_of_bounds(t).map(|why| (k, why))) {
            return Err(Door::Reject("bounds", format!("transition {k}: {why}")));
        }
        Ok(())
    }

    /// Who sends: a sequence not far ahead of the clock, an id not bound to
    /// another live stream, not a duplicate, and a place in the id table
    /// (within the peer's share).
    fn check_sender(&mut self, batch: &TransitionBatch, origin: Origin) -> Result<(), Door> {
        // Actors number batches from the clock (µs); a sequence far ahead
        // of it would make every later batch of that actor a "duplicate".
        let ahead = now_micros().saturating_add(SEQUENCE_AHEAD.as_micros() as u64);
        if batch.sequence > ahead {
            return Err(Door::Reject("sequence", format!("sequence {} is more than {} s ahead of this learner's clock in µs ({ahead}); number batches from 0 or from the clock", batch.sequence, SEQUENCE_AHEAD.as_secs())));
        }
        if self.holders.get(&batch.actor_id).is_some_and(|holder| !holder.admits(origin.stream, batch.actor_key)) {
            return Err(Door::Reject("actor_id_bound", "this actor id is in use by another live stream of this learner; give each actor its own --actor-id".into()));
        }
        if self.last_sequence.get(&batch.actor_id).is_some_and(|&last| batch.sequence <= last) {
            return Err(Door::Duplicate);
        }
        let new_id = !self.last_sequence.contains_key(&batch.actor_id);
        let at_cap = |ingest: &Self, p: &std::net::IpAddr| ingest.ids_of_peer.get(p).copied().unwrap_or(0) >= MAX_ACTORS_PER_PEER;
        if let Some(peer) = origin.counted_peer().filter(|p| new_id && at_cap(self, p)) {
            // Restarted actors come back under new ids: the peer's silent
            // ones make room, whether or not the whole table is full.
            self.forget_silent_ids_of(peer);
        }
        if let Some(peer) = origin.counted_peer().filter(|p| new_id && at_cap(self, p)) {
            return Err(Door::Reject("actors_per_peer", format!("{peer} holds {MAX_ACTORS_PER_PEER} actor ids of this learner, its most; reuse ids or wait for silent ones to be forgotten ({} s)", ACTOR_SILENCE_TO_FORGET.as_secs())));
        }
        if !self.place_for(&batch.actor_id) {
            return Err(Door::Reject("actors", format!("this learner keeps {MAX_ACTORS} actor ids and none has been silent for {} s; try again later", ACTOR_SILENCE_TO_FORGET.as_secs())));
        }
        Ok(())
    }

    /// Records the accepted sender: its sequence, when it was heard, its
    /// stream's binding and its peer's share.
    fn admit_sender(&mut self, batch: &TransitionBatch, origin: Origin) {
        let new_id = !self.last_sequence.contains_key(&batch.actor_id);
        let peer = origin.counted_peer();
        self.last_sequence.insert(batch.actor_id.clone(), batch.sequence);
        self.last_seen.insert(batch.actor_id.clone(), std::time::Instant::now());
        if origin.stream != 0 {
            self.holders.insert(batch.actor_id.clone(), Holder { stream: origin.stream, key: batch.actor_key });
        }
        if let Some(peer) = peer.filter(|_| new_id) {
            self.brought_by.insert(batch.actor_id.clone(), peer);
            *self.ids_of_peer.entry(peer).or_insert(0) += 1;
        }
    }

    /// The batch as the agent stores it: observations, normalized actions.
    fn normalize(&self, batch: &TransitionBatch) -> Vec<AgentTransition> {
        let to_action = |a: &[f32]| -> Vec<f32> { self.actions.to_normalized(&a.iter().map(|&v| f64::from(v)).collect::<Vec<_>>()) };
        let to_obs = |s: &[f32]| crate::algo::agent::observe(self.env.as_ref(), &s.iter().map(|&v| f64::from(v)).collect::<Vec<_>>());
        batch
            .transitions
            .iter()
            .map(|t| AgentTransition {
                obs: to_obs(&t.state),
                // The agent's own u when the actor sent it; otherwise the
                // inverse of the action map (a client that knows only the
                // applied action).
                action: if t.sampled_action.is_empty() { to_action(&t.action) } else { t.sampled_action.clone() },
                log_prob: t.log_prob,
                reward: t.reward,
                next_obs: to_obs(&t.next_state),
                terminated: t.terminated,
                truncated: t.truncated,
                cut: t.cut,
                policy_version: if t.policy_version > 0 { t.policy_version } else { batch.policy_version },
            })
            .collect::<Vec<_>>()
    }
}

impl Ingest {
    /// Why a transition lies beyond the environment's bounds (state, next
    /// state, reward, the action as the agent's u), if it does.
    fn out_of_bounds(&self, t: &lcrl_proto::v1::Transition) -> Option<String> {
        let wide = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<_>>();
        if f64::from(t.reward).abs() > lcrl_sim::REWARD_LIMIT {
            return Some(format!("reward {} is beyond ±{:e}", t.reward, lcrl_sim::REWARD_LIMIT));
        }
        for (name, state) in [("state", &t.state), ("next_state", &t.next_state)] {
            if let Some(why) = lcrl_sim::state_out_of_bounds(self.env.as_ref(), &wide(state)) {
                return Some(format!("{name}: {why}"));
            }
        }
        let u = if t.sampled_action.is_empty() { self.actions.to_normalized(&wide(&t.action)) } else { t.sampled_action.clone() };
        let limit = lcrl_sim::SAMPLED_ACTION_BOUND;
        u.iter().position(|v| f64::from(v.abs()) > limit).map(|k| format!("action component {k} is {} in the agent's units [−1, 1]; at most ±{limit}", u[k]))
    }
}

/// Why a batch does not pass the door.
enum Door {
    /// Malformed or not this sender's: refused, with the status key.
    Reject(&'static str, String),
    /// Already stored (a batch sent again after a reconnect).
    Duplicate,
}

/// The batch's episode summaries: finite, one per episode end, their
/// returns those of the rewards.
fn check_episodes(batch: &TransitionBatch) -> Result<(), Door> {
        // An episode's return feeds the training curve, its statistics and
        // selection's record: a NaN there poisons every mean after it.
        if let Some(k) = batch.episodes.iter().position(|e| !e.episode_return.is_finite()) {
            return Err(Door::Reject("non_finite", format!("episode {k} has a non-finite return")));
        }
        // Likewise its measurements, which feed the safety figures.
        let measured = |e: &EpisodeSummary| {
            let terms = e.return_terms.iter().flat_map(|t| [t.depth, t.force, t.moment, t.bonus, t.failure]);
            e.peak_force_n.into_iter().chain(e.peak_moment_nm).chain(terms).all(f64::is_finite)
        };
        if let Some(k) = batch.episodes.iter().position(|e| !measured(e)) {
            return Err(Door::Reject("non_finite", format!("episode {k} has a non-finite peak force, moment or return term")));
        }
        // One summary per episode end, in the order of the ends (the
        // contract, proto/lcrl.proto): the budget counts summaries and
        // `keep_episodes` cuts at ends, so a batch whose two counts differ
        // would end the run early or run past its budget.
        let ends = batch.transitions.iter().filter(|t| t.terminated || t.truncated).count();
        if ends != batch.episodes.len() {
            return Err(Door::Reject("episodes", format!(
                    "{} episode summaries for {ends} episode ends (transitions terminated or truncated); send one summary per end, in \
                     the order of the ends (a batch end inside an episode is `cut`, not an end)",
                    batch.episodes.len()
                )));
        }
        if let Err(message) = returns_agree(batch) {
            return Err(Door::Reject("returns", message));
        }
    Ok(())
}

/// How far ahead of the learner's clock (in µs, where actors start their
/// sequences) a batch's sequence may be. An actor numbers its batches from
/// its clock and adds one a batch, so an honest sequence is ahead only by
/// the hosts' clock skew; a forged one can make an actor's later batches
/// duplicates for at most this long (it was an hour, issue 82: 472k
/// transitions discarded). Hosts of one run keep their clocks within it.
pub const SEQUENCE_AHEAD: std::time::Duration = std::time::Duration::from_secs(10);

/// The longest episode a summary may claim (steps).
pub const MAX_EPISODE_STEPS: u32 = 1_000_000;

/// Transitions that arrived but were not trained on for being staler than
/// PPO's lag bound, from refusal counts by reason (`stale`, and
/// `stale_incarnation`: acted by a previous learner process). One reading
/// for the learner's summary, `lcrl run`'s and `lcrl scale`.
pub fn discarded_stale<'a>(counts: impl IntoIterator<Item = (&'a String, &'a u64)>) -> u64 {
    counts.into_iter().filter(|(reason, _)| reason.starts_with("stale")).map(|(_, n)| n).sum()
}

/// The wall clock in µs since the Unix epoch (0 before it): where actors
/// number their batches from, and what SEQUENCE_AHEAD is measured against.
pub fn now_micros() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_micros() as u64)
}

/// Checks each episode summary against the rewards the batch holds for
/// it (its steps since the previous end or cut): it claims at least those
/// steps, and a return within [`lcrl_sim::REWARD_LIMIT`] per step it
/// claims beyond them of their sum (exactly their sum when it claims no
/// more). The learner cannot tell an episode that began in this batch from
/// one that continues (an actor's K segments follow each other, and one
/// that ended on an end leaves no cut), so the bound is all it can check.
/// The budget counts these episodes and the training curve shows their
/// returns: one batch of 1,000 one-step episodes claiming 1e30 each ended
/// a run and its summary (issue 71).
fn returns_agree(batch: &TransitionBatch) -> Result<(), String> {
    let mut summaries = batch.episodes.iter().enumerate();
    let mut stored = Stored::default();
    for t in &batch.transitions {
        stored.add(t.reward);
        if t.terminated || t.truncated {
            // Counts agree (checked before): one summary per end.
            let Some((k, e)) = summaries.next() else { break };
            if e.length > MAX_EPISODE_STEPS || !stored.admits(e.episode_return, e.length) {
                return Err(format!(
                    "episode {k} claims return {} over {} steps; this batch holds {} of its steps with rewards summing to {} \
                     (each step not in the batch adds at most ±{:e}, and an episode has at most {MAX_EPISODE_STEPS} steps)",
                    e.episode_return,
                    e.length,
                    stored.steps,
                    stored.sum,
                    lcrl_sim::REWARD_LIMIT
                ));
            }
        }
        if t.terminated || t.truncated || t.cut {
            stored = Stored::default();
        }
    }
    Ok(())
}

#[cfg(test)]
#[path = "ingest_tests.rs"]
mod tests;
