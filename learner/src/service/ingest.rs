//! What the learner accepts from actors: transition batches checked for
//! run id, dimensions and finiteness, deduplicated by (actor, sequence),
//! filtered for staleness (PPO), and converted to the agent's normalized
//! units. Plain Rust; the gRPC and shared-memory front ends both call it.

use crate::policy::action::ActionMap;
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
    /// Maximum accepted age (in policy versions) of a batch; None: any.
    max_staleness: Option<u64>,
    /// Transitions rejected or dropped, by reason.
    pub rejected: BTreeMap<String, u64>,
    /// Transitions accepted (handed to the training thread).
    pub accepted: u64,
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
            max_staleness,
            rejected: BTreeMap::new(),
            accepted: 0,
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
                self.last_sequence.remove(&id);
                self.last_seen.remove(&id);
                true
            }
            _ => false,
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

    /// Checks `batch` against the run and the current policy version.
    pub fn check(&mut self, batch: &TransitionBatch, policy_version: u64) -> Verdict {
        let count = batch.transitions.len();
        if batch.run_id != self.run_id {
            self.count("unknown_run", count);
            return Verdict::Reject {
                reason: "unknown_run",
                // A peer's string in the log: at most 64 characters of it.
                message: format!("run id '{}' is not this learner's run ('{}')", batch.run_id.chars().take(64).collect::<String>(), self.run_id),
            };
        }
        // Names are kept (sequences, checkpoint.json): bounded in length
        // and number.
        if batch.actor_id.len() > lcrl_proto::limits::MAX_ACTOR_ID_BYTES {
            self.count("actor_id", count);
            return Verdict::Reject {
                reason: "actor_id",
                message: format!("actor_id is {} bytes; at most {} are kept", batch.actor_id.len(), lcrl_proto::limits::MAX_ACTOR_ID_BYTES),
            };
        }
        let (m, n) = (self.env.spec().state_dim(), self.env.spec().action_dim());
        for (k, t) in batch.transitions.iter().enumerate() {
            let sampled_ok = t.sampled_action.is_empty() || t.sampled_action.len() == n;
            if t.state.len() != m || t.next_state.len() != m || t.action.len() != n || !sampled_ok {
                self.count("dimensions", count);
                return Verdict::Reject {
                    reason: "dimensions",
                    message: format!(
                        "transition {k}: state {}, next_state {}, action {}, sampled_action {}; this run needs states of {m} and actions \
                         of {n} (sampled_action: {n} or none)",
                        t.state.len(),
                        t.next_state.len(),
                        t.action.len(),
                        t.sampled_action.len()
                    ),
                };
            }
            let all = t.state.iter().chain(&t.next_state).chain(&t.action).chain(&t.sampled_action).chain(std::iter::once(&t.reward)).chain(&t.log_prob);
            if all.clone().any(|v| !v.is_finite()) {
                self.count("non_finite", count);
                return Verdict::Reject { reason: "non_finite", message: format!("transition {k} holds a non-finite number") };
            }
        }
        // An episode's return feeds the training curve, its statistics and
        // selection's record: a NaN there poisons every mean after it.
        if let Some(k) = batch.episodes.iter().position(|e| !e.episode_return.is_finite()) {
            self.count("non_finite", count);
            return Verdict::Reject { reason: "non_finite", message: format!("episode {k} has a non-finite return") };
        }
        // Likewise its measurements, which feed the safety figures.
        let measured = |e: &EpisodeSummary| {
            let terms = e.return_terms.iter().flat_map(|t| [t.depth, t.force, t.moment, t.bonus, t.failure]);
            e.peak_force_n.into_iter().chain(e.peak_moment_nm).chain(terms).all(f64::is_finite)
        };
        if let Some(k) = batch.episodes.iter().position(|e| !measured(e)) {
            self.count("non_finite", count);
            return Verdict::Reject { reason: "non_finite", message: format!("episode {k} has a non-finite peak force, moment or return term") };
        }
        // One summary per episode end, in the order of the ends (the
        // contract, proto/lcrl.proto): the budget counts summaries and
        // `keep_episodes` cuts at ends, so a batch whose two counts differ
        // would end the run early or run past its budget.
        let ends = batch.transitions.iter().filter(|t| t.terminated || t.truncated).count();
        if ends != batch.episodes.len() {
            self.count("episodes", count);
            return Verdict::Reject {
                reason: "episodes",
                message: format!(
                    "{} episode summaries for {ends} episode ends (transitions terminated or truncated); send one summary per end, in \
                     the order of the ends (a batch end inside an episode is `cut`, not an end)",
                    batch.episodes.len()
                ),
            };
        }
        if self.last_sequence.get(&batch.actor_id).is_some_and(|&last| batch.sequence <= last) {
            self.count("duplicate", count);
            return Verdict::Duplicate;
        }
        if !self.place_for(&batch.actor_id) {
            self.count("actors", count);
            return Verdict::Reject {
                reason: "actors",
                message: format!("this learner keeps {MAX_ACTORS} actor ids and none has been silent for {} s; try again later", ACTOR_SILENCE_TO_FORGET.as_secs()),
            };
        }
        self.last_sequence.insert(batch.actor_id.clone(), batch.sequence);
        self.last_seen.insert(batch.actor_id.clone(), std::time::Instant::now());
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
        let to_action = |a: &[f32]| -> Vec<f32> { self.actions.to_normalized(&a.iter().map(|&v| f64::from(v)).collect::<Vec<_>>()) };
        let to_obs = |s: &[f32]| crate::algo::agent::observe(self.env.as_ref(), &s.iter().map(|&v| f64::from(v)).collect::<Vec<_>>());
        let transitions = batch
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
            .collect::<Vec<_>>();
        self.accepted += transitions.len() as u64;
        Verdict::Accept(Accepted { transitions, episodes: batch.episodes.clone(), policy_version: batch.policy_version, stream: stream_of(&batch.actor_id) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lcrl_proto::v1::Transition;

    fn batch(actor: &str, sequence: u64, state: Vec<f32>) -> TransitionBatch {
        TransitionBatch {
            run_id: "run-a".into(),
            actor_id: actor.into(),
            sequence,
            episode_id: 1,
            policy_version: 3,
            transitions: vec![Transition { state: state.clone(), action: vec![0.5, -1.0, 1.0], reward: -1.0, next_state: state, terminated: false, truncated: false, policy_version: 0, ..Default::default() }],
            ..Default::default()
        }
    }

    fn ingest(staleness: Option<u64>) -> Ingest {
        Ingest::new("run-a", lcrl_sim::make_env("lti-paper").unwrap(), staleness)
    }

    #[test]
    fn a_batch_is_cut_after_the_last_episode_the_budget_allows() {
        let t = |end: bool| AgentTransition { obs: vec![], action: vec![], log_prob: None, reward: 0.0, next_obs: vec![], terminated: end, truncated: false, cut: false, policy_version: 0 };
        let e = || EpisodeSummary { episode_return: -1.0, length: 2, ..Default::default() };
        // Two episode ends (after transitions 2 and 4) and a started third.
        let batch = || Accepted { transitions: vec![t(false), t(true), t(false), t(true), t(false)], episodes: vec![e(), e()], policy_version: 1, stream: 0 };
        let mut one = batch();
        assert_eq!(one.keep_episodes(1), 3);
        assert_eq!((one.transitions.len(), one.episodes.len()), (2, 1));
        let mut all = batch();
        assert_eq!(all.keep_episodes(2), 0);
        assert_eq!(all.transitions.len(), 5, "within the budget nothing is cut");
        // A cut (the actor's batch end, mid-episode) is not an end.
        let mut cut = batch();
        cut.transitions[0].cut = true;
        assert_eq!(cut.keep_episodes(1), 3);
        let mut none = batch();
        assert_eq!(none.keep_episodes(0), 5);
        assert!(none.transitions.is_empty() && none.episodes.is_empty());
    }

    #[test]
    fn accepts_and_normalizes() {
        let mut ingest = ingest(None);
        match ingest.check(&batch("a1", 1, vec![0.1, 0.2, 0.3]), 3) {
            Verdict::Accept(accepted) => {
                assert_eq!(accepted.transitions[0].action, vec![0.5, -1.0, 1.0]); // bounds are ±1
                assert_eq!(accepted.transitions[0].obs, vec![0.1, 0.2, 0.3]);
            }
            other => panic!("{other:?}"),
        }
        assert!(ingest.rejected.is_empty());
    }

    #[test]
    fn the_sampled_action_is_stored_as_sent_and_the_applied_one_only_without_it() {
        let mut ingest = ingest(None);
        // u outside [−1, 1] (a PPO sample) whose applied action the box clipped.
        let mut sent = batch("a1", 1, vec![0.1, 0.2, 0.3]);
        sent.transitions[0].sampled_action = vec![1.7, -1.0, 0.25];
        sent.transitions[0].log_prob = Some(-2.5);
        match ingest.check(&sent, 3) {
            Verdict::Accept(accepted) => {
                assert_eq!(accepted.transitions[0].action, vec![1.7, -1.0, 0.25]);
                assert_eq!(accepted.transitions[0].log_prob, Some(-2.5));
            }
            other => panic!("{other:?}"),
        }
        let mut short = batch("a1", 2, vec![0.0; 3]);
        short.transitions[0].sampled_action = vec![0.5];
        assert!(matches!(ingest.check(&short, 3), Verdict::Reject { reason: "dimensions", .. }));
        let mut nan = batch("a1", 3, vec![0.0; 3]);
        nan.transitions[0].log_prob = Some(f32::NAN);
        assert!(matches!(ingest.check(&nan, 3), Verdict::Reject { reason: "non_finite", .. }));
    }

    #[test]
    fn rejects_bad_batches_and_counts_them() {
        let mut ingest = ingest(None);
        let mut wrong_run = batch("a1", 1, vec![0.0; 3]);
        wrong_run.run_id = "run-b".into();
        assert!(matches!(ingest.check(&wrong_run, 3), Verdict::Reject { reason: "unknown_run", .. }));
        assert!(matches!(ingest.check(&batch("a1", 2, vec![0.0; 4]), 3), Verdict::Reject { reason: "dimensions", .. }));
        assert!(matches!(ingest.check(&batch("a1", 3, vec![0.0, f32::NAN, 0.0]), 3), Verdict::Reject { reason: "non_finite", .. }));
        let mut nan_return = batch("a1", 4, vec![0.0; 3]);
        nan_return.transitions[0].terminated = true;
        nan_return.episodes.push(EpisodeSummary { episode_return: f64::NAN, length: 1, ..Default::default() });
        assert!(matches!(ingest.check(&nan_return, 3), Verdict::Reject { reason: "non_finite", .. }));
        let mut nan_force = batch("a1", 4, vec![0.0; 3]);
        nan_force.transitions[0].terminated = true;
        nan_force.episodes.push(EpisodeSummary { episode_return: -1.0, length: 1, peak_force_n: Some(f64::INFINITY), ..Default::default() });
        assert!(matches!(ingest.check(&nan_force, 3), Verdict::Reject { reason: "non_finite", .. }));
        let mut nan_term = batch("a1", 4, vec![0.0; 3]);
        nan_term.transitions[0].terminated = true;
        let terms = lcrl_proto::v1::ReturnTerms { failure: f64::NAN, ..Default::default() };
        nan_term.episodes.push(EpisodeSummary { episode_return: -1.0, length: 1, return_terms: Some(terms), ..Default::default() });
        assert!(matches!(ingest.check(&nan_term, 3), Verdict::Reject { reason: "non_finite", .. }));
        // Summaries and ends must pair up: a summary without an end, an end
        // without a summary (a cut is not an end and needs none).
        let mut no_end = batch("a1", 5, vec![0.0; 3]);
        no_end.episodes.push(EpisodeSummary { episode_return: -1.0, length: 1, ..Default::default() });
        assert!(matches!(ingest.check(&no_end, 3), Verdict::Reject { reason: "episodes", .. }));
        let mut no_summary = batch("a1", 6, vec![0.0; 3]);
        no_summary.transitions[0].truncated = true;
        assert!(matches!(ingest.check(&no_summary, 3), Verdict::Reject { reason: "episodes", .. }));
        assert_eq!(ingest.rejected.values().sum::<u64>(), 8);
        assert_eq!(ingest.rejected["episodes"], 2);
        // A rejected batch does not consume its sequence number.
        assert!(matches!(ingest.check(&batch("a1", 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
        let mut cut = batch("a1", 2, vec![0.0; 3]);
        cut.transitions[0].cut = true;
        assert!(matches!(ingest.check(&cut, 3), Verdict::Accept(_)), "a cut needs no summary");
    }

    /// A restarted learner's versions count from its checkpoint again:
    /// an on-policy learner drops a batch of its previous process however
    /// new its version looks; an off-policy one stores it; a client that
    /// names no incarnation is not checked.
    #[test]
    fn batches_of_another_incarnation_are_stale_for_an_on_policy_learner() {
        let mut ppo = ingest(Some(0)).with_incarnation(77);
        let mut old = batch("a1", 1, vec![0.0; 3]);
        old.incarnation = 76;
        old.policy_version = 9;
        assert_eq!(ppo.check(&old, 3), Verdict::Stale);
        assert_eq!(ppo.rejected.get("stale_incarnation"), Some(&1));
        let mut own = batch("a1", 2, vec![0.0; 3]);
        own.incarnation = 77;
        assert!(matches!(ppo.check(&own, 3), Verdict::Accept(_)));
        assert!(matches!(ppo.check(&batch("a2", 1, vec![0.0; 3]), 3), Verdict::Accept(_)), "0: not said, not checked");
        let mut ddpg = ingest(None).with_incarnation(77);
        old.sequence = 3;
        assert!(matches!(ddpg.check(&old, 3), Verdict::Accept(_)));
    }

    /// Actor ids are kept: one too long is refused, and beyond MAX_ACTORS
    /// a new one is refused until an old one has been silent long enough.
    #[test]
    fn actor_ids_are_bounded_in_length_and_number() {
        let mut ingest = ingest(None);
        let long = "x".repeat(lcrl_proto::limits::MAX_ACTOR_ID_BYTES + 1);
        assert!(matches!(ingest.check(&batch(&long, 1, vec![0.0; 3]), 3), Verdict::Reject { reason: "actor_id", .. }));
        assert!(matches!(ingest.check(&batch(&long[1..], 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
        for k in 1..MAX_ACTORS {
            assert!(matches!(ingest.check(&batch(&format!("a{k}"), 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
        }
        assert!(matches!(ingest.check(&batch("one-too-many", 1, vec![0.0; 3]), 3), Verdict::Reject { reason: "actors", .. }));
        assert!(matches!(ingest.check(&batch("a7", 2, vec![0.0; 3]), 3), Verdict::Accept(_)), "known actors go on");
        // An actor silent past the limit gives its place up.
        let forgotten = ingest.last_seen.get_mut("a1").unwrap();
        *forgotten = forgotten.checked_sub(ACTOR_SILENCE_TO_FORGET).expect("a machine up for ten minutes");
        assert!(matches!(ingest.check(&batch("one-too-many", 1, vec![0.0; 3]), 3), Verdict::Accept(_)));
        assert!(!ingest.sequences().contains_key("a1"));
        assert_eq!(ingest.sequences().len(), MAX_ACTORS);
        assert_eq!(ingest.rejected.get("actors"), Some(&1));
    }

    #[test]
    fn duplicates_and_stale_batches_are_not_stored() {
        let mut ingest = ingest(Some(1));
        assert!(matches!(ingest.check(&batch("a1", 5, vec![0.0; 3]), 3), Verdict::Accept(_)));
        assert_eq!(ingest.check(&batch("a1", 5, vec![0.0; 3]), 3), Verdict::Duplicate);
        assert_eq!(ingest.check(&batch("a1", 4, vec![0.0; 3]), 3), Verdict::Duplicate);
        assert!(matches!(ingest.check(&batch("a2", 5, vec![0.0; 3]), 3), Verdict::Accept(_)));
        // Version 3 batches are two versions old at version 5: beyond the bound.
        assert_eq!(ingest.check(&batch("a1", 6, vec![0.0; 3]), 5), Verdict::Stale);
        assert_eq!(ingest.rejected.get("duplicate"), Some(&2));
        assert_eq!(ingest.rejected.get("stale"), Some(&1));
    }
}
