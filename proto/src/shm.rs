//! The same-host wire format: transition batches and policies as
//! fixed-size `#[repr(C)]` samples in iceoryx2 shared memory, one
//! publish-subscribe service each per run (`lcrl/<run id>/transitions`,
//! `lcrl/<run id>/policy`), so two runs on one host never meet. A
//! transition sample converts to the same `TransitionBatch` the gRPC path
//! carries, and a policy sample to the same `PolicySnapshot`: the learner
//! checks both paths alike. Publishers of transitions block while the
//! learner's buffer is full: nothing is dropped and nothing queues without
//! bound. This module holds the format and the ports; the learner's loops
//! over them are in lcrl-learner's service/shm.rs.


use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;

use crate::v1::{EpisodeSummary, PolicySnapshot, Transition, TransitionBatch};

/// Limits of one sample: state and action lengths, transitions per batch,
/// episodes per batch, and bytes of the actor id.
pub const MAX_STATE: usize = 32;
pub const MAX_ACTION: usize = 16;
pub const MAX_TRANSITIONS: usize = 64;
pub const MAX_EPISODES: usize = 64;
const ID_BYTES: usize = 64;

/// One batch of transitions, laid out flat (row-major per transition).
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[repr(C)]
pub struct TransitionSample {
    pub actor_id: [u8; ID_BYTES],
    pub sequence: u64,
    pub episode_id: u64,
    pub policy_version: u64,
    /// TransitionBatch.incarnation.
    pub incarnation: u64,
    pub count: u32,
    pub state_dim: u32,
    pub action_dim: u32,
    pub episode_count: u32,
    pub states: [f32; MAX_TRANSITIONS * MAX_STATE],
    pub next_states: [f32; MAX_TRANSITIONS * MAX_STATE],
    pub actions: [f32; MAX_TRANSITIONS * MAX_ACTION],
    /// The agent's sampled u per transition (valid where flag bit 2 is set).
    pub sampled_actions: [f32; MAX_TRANSITIONS * MAX_ACTION],
    /// The behaviour log π(u|s) (valid where flag bit 3 is set).
    pub log_probs: [f32; MAX_TRANSITIONS],
    pub rewards: [f32; MAX_TRANSITIONS],
    /// bit 0: terminated, bit 1: truncated, bit 2: sampled action present,
    /// bit 3: log-probability present, bit 4: cut.
    pub flags: [u8; MAX_TRANSITIONS],
    /// The policy version that chose each action.
    pub versions: [u64; MAX_TRANSITIONS],
    pub episode_returns: [f64; MAX_EPISODES],
    pub episode_lengths: [u32; MAX_EPISODES],
    /// −1: unknown, 0: failed, 1: succeeded.
    pub episode_success: [i8; MAX_EPISODES],
    /// Per episode: peak force, peak moment, then the return's five terms
    /// (depth, force, moment, bonus, failure); NaN where not measured (a
    /// term's NaN in `depth` stands for all five).
    pub episode_measures: [[f64; MEASURES]; MAX_EPISODES],
}

/// Numbers per episode in [`TransitionSample::episode_measures`].
const MEASURES: usize = 7;

impl TransitionSample {
    /// Packs a batch; fails when it exceeds the sample's limits.
    pub fn from_batch(batch: &TransitionBatch) -> Result<Self, String> {
        let first = batch.transitions.first();
        let (m, n) = (first.map_or(0, |t| t.state.len()), first.map_or(0, |t| t.action.len()));
        if batch.transitions.len() > MAX_TRANSITIONS || batch.episodes.len() > MAX_EPISODES || m > MAX_STATE || n > MAX_ACTION {
            return Err(format!(
                "a shared-memory batch holds at most {MAX_TRANSITIONS} transitions of states ≤ {MAX_STATE} and actions ≤ {MAX_ACTION}, and {MAX_EPISODES} episodes"
            ));
        }
        if batch.actor_id.len() > ID_BYTES {
            return Err(format!("actor ids over shared memory are at most {ID_BYTES} bytes"));
        }
        let mut s = TransitionSample {
            actor_id: [0; ID_BYTES],
            sequence: batch.sequence,
            episode_id: batch.episode_id,
            policy_version: batch.policy_version,
            incarnation: batch.incarnation,
            count: batch.transitions.len() as u32,
            state_dim: m as u32,
            action_dim: n as u32,
            episode_count: batch.episodes.len() as u32,
            states: [0.0; MAX_TRANSITIONS * MAX_STATE],
            next_states: [0.0; MAX_TRANSITIONS * MAX_STATE],
            actions: [0.0; MAX_TRANSITIONS * MAX_ACTION],
            sampled_actions: [0.0; MAX_TRANSITIONS * MAX_ACTION],
            log_probs: [0.0; MAX_TRANSITIONS],
            rewards: [0.0; MAX_TRANSITIONS],
            flags: [0; MAX_TRANSITIONS],
            versions: [0; MAX_TRANSITIONS],
            episode_returns: [0.0; MAX_EPISODES],
            episode_lengths: [0; MAX_EPISODES],
            episode_success: [-1; MAX_EPISODES],
            episode_measures: [[f64::NAN; MEASURES]; MAX_EPISODES],
        };
        s.actor_id[..batch.actor_id.len()].copy_from_slice(batch.actor_id.as_bytes());
        for (k, t) in batch.transitions.iter().enumerate() {
            let sampled = !t.sampled_action.is_empty();
            if t.state.len() != m || t.next_state.len() != m || t.action.len() != n || (sampled && t.sampled_action.len() != n) {
                return Err("every transition of a batch must have the same dimensions".into());
            }
            s.states[k * m..(k + 1) * m].copy_from_slice(&t.state);
            s.next_states[k * m..(k + 1) * m].copy_from_slice(&t.next_state);
            s.actions[k * n..(k + 1) * n].copy_from_slice(&t.action);
            if sampled {
                s.sampled_actions[k * n..(k + 1) * n].copy_from_slice(&t.sampled_action);
            }
            s.log_probs[k] = t.log_prob.unwrap_or(0.0);
            s.rewards[k] = t.reward;
            s.flags[k] = u8::from(t.terminated) | (u8::from(t.truncated) << 1) | (u8::from(sampled) << 2) | (u8::from(t.log_prob.is_some()) << 3) | (u8::from(t.cut) << 4);
            s.versions[k] = t.policy_version;
        }
        for (k, e) in batch.episodes.iter().enumerate() {
            s.episode_returns[k] = e.episode_return;
            s.episode_lengths[k] = e.length;
            s.episode_success[k] = e.success.map_or(-1, i8::from);
            let terms = e.return_terms.as_ref().map_or([f64::NAN; 5], |t| [t.depth, t.force, t.moment, t.bonus, t.failure]);
            s.episode_measures[k] = [e.peak_force_n.unwrap_or(f64::NAN), e.peak_moment_nm.unwrap_or(f64::NAN), terms[0], terms[1], terms[2], terms[3], terms[4]];
        }
        Ok(s)
    }

    /// Unpacks into the batch the ingestion checks take (counts clamped to
    /// the sample's limits, whatever a peer wrote).
    pub fn to_batch(&self, run_id: &str) -> TransitionBatch {
        let (m, n) = ((self.state_dim as usize).min(MAX_STATE), (self.action_dim as usize).min(MAX_ACTION));
        let count = (self.count as usize).min(MAX_TRANSITIONS);
        let id_len = self.actor_id.iter().position(|&b| b == 0).unwrap_or(ID_BYTES);
        TransitionBatch {
            run_id: run_id.to_string(),
            actor_id: String::from_utf8_lossy(&self.actor_id[..id_len]).into_owned(),
            sequence: self.sequence,
            episode_id: self.episode_id,
            policy_version: self.policy_version,
            incarnation: self.incarnation,
            // Shared memory binds an id to its publisher, not to a key.
            actor_key: 0,
            transitions: (0..count)
                .map(|k| Transition {
                    state: self.states[k * m..(k + 1) * m].to_vec(),
                    action: self.actions[k * n..(k + 1) * n].to_vec(),
                    sampled_action: if self.flags[k] & 4 != 0 { self.sampled_actions[k * n..(k + 1) * n].to_vec() } else { Vec::new() },
                    log_prob: (self.flags[k] & 8 != 0).then_some(self.log_probs[k]),
                    reward: self.rewards[k],
                    next_state: self.next_states[k * m..(k + 1) * m].to_vec(),
                    terminated: self.flags[k] & 1 != 0,
                    truncated: self.flags[k] & 2 != 0,
                    cut: self.flags[k] & 16 != 0,
                    policy_version: self.versions[k],
                })
                .collect(),
            episodes: (0..(self.episode_count as usize).min(MAX_EPISODES))
                .map(|k| {
                    let [force, moment, depth, force_term, moment_term, bonus, failure] = self.episode_measures[k];
                    let measured = |v: f64| (!v.is_nan()).then_some(v);
                    EpisodeSummary {
                        episode_return: self.episode_returns[k],
                        length: self.episode_lengths[k],
                        success: (self.episode_success[k] >= 0).then_some(self.episode_success[k] == 1),
                        peak_force_n: measured(force),
                        peak_moment_nm: measured(moment),
                        return_terms: measured(depth).map(|depth| crate::v1::ReturnTerms { depth, force: force_term, moment: moment_term, bonus, failure }),
                    }
                })
                .collect(),
        }
    }
}

/// The service of a run's transitions.
pub fn service_name(run_id: &str) -> String {
    format!("lcrl/{run_id}/transitions")
}

/// The environment variable that names a namespace of this host's shared
/// memory: processes started with different values never meet, whatever
/// their run ids (iceoryx2's file prefix, `iox2_<namespace>_`). Unset: the
/// host's one namespace. Letters, digits and `-` are kept, 32 at most.
pub const NAMESPACE_ENV: &str = "LCRL_SHM_NAMESPACE";

/// iceoryx2's configuration for `namespace` (None: the default one).
fn config_in(namespace: Option<&str>) -> Config {
    let mut config = Config::global_config().clone();
    if let Some(ns) = namespace {
        let ns: String = ns.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' { c } else { '-' }).take(32).collect();
        if let Ok(prefix) = FileName::new(format!("iox2_{ns}_").as_bytes()) {
            config.global.prefix = prefix;
        }
    }
    config
}

/// This process's configuration: the namespace [`NAMESPACE_ENV`] names.
fn shm_config() -> &'static Config {
    static CONFIG: std::sync::OnceLock<Config> = std::sync::OnceLock::new();
    CONFIG.get_or_init(|| config_in(std::env::var(NAMESPACE_ENV).ok().as_deref()))
}

/// iceoryx2 logs to stderr on its own; keep it to errors (the default
/// configuration is intended, so its "no config file" warning is noise).
pub fn quiet_iceoryx2() {
    set_log_level_from_env_or(LogLevel::Error);
}

/// Removes what crashed peers left in shared memory (iceoryx2's dead-node
/// cleanup); returns how many nodes were cleaned.
pub fn remove_dead_nodes() -> usize {
    remove_dead_nodes_in(shm_config())
}

/// [`remove_dead_nodes`] in another process's namespace ([`NAMESPACE_ENV`]).
pub fn remove_dead_nodes_of(namespace: &str) -> usize {
    remove_dead_nodes_in(&config_in(Some(namespace)))
}

fn remove_dead_nodes_in(config: &Config) -> usize {
    quiet_iceoryx2();
    let mut removed = 0;
    let _ = Node::<ipc::Service>::list(config, |state| {
        if let NodeState::Dead(view) = state {
            if view.try_remove_stale_resources().is_ok() {
                removed += 1;
            }
        }
        CallbackProgression::Continue
    });
    removed
}

/// The names of the shared-memory services of `run_id` that still exist
/// (after dead-node cleanup): empty once every process of a run is gone.
pub fn services_of(run_id: &str) -> Vec<String> {
    services_in(shm_config(), run_id)
}

/// [`services_of`] in another process's namespace ([`NAMESPACE_ENV`]).
pub fn services_of_in(namespace: &str, run_id: &str) -> Vec<String> {
    services_in(&config_in(Some(namespace)), run_id)
}

fn services_in(config: &Config, run_id: &str) -> Vec<String> {
    remove_dead_nodes_in(config);
    // A token-protected run's services go by the run id and a digest
    // (lcrl_runtime::security::shm_run_key): "lcrl/RUN.HEX/...".
    let (prefix, keyed) = (format!("lcrl/{run_id}/"), format!("lcrl/{run_id}."));
    let mut names = Vec::new();
    let _ = <ipc::Service as iceoryx2::service::Service>::list(config, |service| {
        let name = service.static_details.name().to_string();
        if name.starts_with(&prefix) || name.starts_with(&keyed) {
            names.push(name);
        }
        CallbackProgression::Continue
    });
    names
}

/// Most transition samples the learner's subscriber may hold.
pub const SUBSCRIBER_MAX_BUFFER: usize = 4;

type Service = iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, TransitionSample, ()>;

fn open_service(node: &Node<ipc::Service>, run_id: &str) -> Result<Service, String> {
    let name: ServiceName = service_name(run_id).as_str().try_into().map_err(|e| format!("service name: {e:?}"))?;
    node.service_builder(&name)
        .publish_subscribe::<TransitionSample>()
        .enable_safe_overflow(false)
        // A few batches of slack at most: every batch buffered here is
        // policy lag, and the replay-ratio limiter holds actors back
        // through it.
        .subscriber_max_buffer_size(SUBSCRIBER_MAX_BUFFER)
        .max_publishers(64)
        // One learner a run: its subscriber is the only one the service
        // takes, so a second learner under a live one's run id cannot
        // open it (TransitionSubscriber::open, SubscriberError::RunTaken).
        .max_subscribers(1)
        .open_or_create()
        .map_err(|e| format!("cannot open the shared-memory service {}: {e:?}", service_name(run_id)))
}

/// A node of this process and `run_id`'s service opened on it, after
/// removing what crashed processes left (a half-made service would
/// otherwise hang its opening for good: HangsInCreation).
fn node_and<S>(run_id: &str, open: impl Fn(&Node<ipc::Service>, &str) -> Result<S, String>) -> Result<(Node<ipc::Service>, S), String> {
    remove_dead_nodes();
    let node = NodeBuilder::new().config(shm_config()).create::<ipc::Service>().map_err(|e| format!("iceoryx2 node: {e:?}"))?;
    let service = open(&node, run_id)?;
    Ok((node, service))
}

/// An actor's end: publishes batches, blocking while the learner is behind.
pub struct ShmPublisher {
    publisher: iceoryx2::port::publisher::Publisher<ipc::Service, TransitionSample, ()>,
    _service: Service,
    _node: Node<ipc::Service>,
}

impl ShmPublisher {
    pub fn open(run_id: &str) -> Result<Self, String> {
        let (node, service) = node_and(run_id, open_service)?;
        let publisher = service
            .publisher_builder()
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .create()
            .map_err(|e| format!("iceoryx2 publisher: {e:?}"))?;
        Ok(ShmPublisher { publisher, _service: service, _node: node })
    }

    pub fn send(&self, batch: &TransitionBatch) -> Result<(), String> {
        let sample = TransitionSample::from_batch(batch)?;
        let slot = self.publisher.loan_uninit().map_err(|e| format!("loan: {e:?}"))?;
        slot.write_payload(sample).send().map(|_| ()).map_err(|e| format!("send: {e:?}"))
    }
}

/// Why the learner's end of a run's transitions did not open.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SubscriberError {
    /// A live learner on this host already subscribes to the run's
    /// transitions (the service takes one subscriber).
    RunTaken(String),
    /// Shared memory is unavailable here (the learner goes on over gRPC).
    Unavailable(String),
}

impl std::fmt::Display for SubscriberError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SubscriberError::RunTaken(run_id) => write!(
                f,
                "another live learner on this host already serves run id '{run_id}' (it holds the shared-memory service {}); give this learner another --run-id",
                service_name(run_id)
            ),
            SubscriberError::Unavailable(e) => f.write_str(e),
        }
    }
}

impl std::error::Error for SubscriberError {}

/// The learner's end of the transitions: samples as batches, in arrival order.
pub struct TransitionSubscriber {
    subscriber: iceoryx2::port::subscriber::Subscriber<ipc::Service, TransitionSample, ()>,
    run_id: String,
    service: Service,
    _node: Node<ipc::Service>,
}

impl TransitionSubscriber {
    /// `buffer`: samples that may wait in shared memory (1 to
    /// [`SUBSCRIBER_MAX_BUFFER`]); each is policy lag.
    pub fn open(run_id: &str, buffer: usize) -> Result<Self, SubscriberError> {
        let (node, service) = node_and(run_id, open_service).map_err(SubscriberError::Unavailable)?;
        let subscriber = service.subscriber_builder().buffer_size(buffer.clamp(1, SUBSCRIBER_MAX_BUFFER)).create().map_err(|e| match e {
            iceoryx2::port::subscriber::SubscriberCreateError::ExceedsMaxSupportedSubscribers => SubscriberError::RunTaken(run_id.to_string()),
            e => SubscriberError::Unavailable(format!("iceoryx2 subscriber: {e:?}")),
        })?;
        Ok(TransitionSubscriber { subscriber, run_id: run_id.into(), service, _node: node })
    }

    /// The next batch, if one is waiting (its sample is released at once),
    /// with the publisher that sent it ([`publisher_stream`]).
    pub fn receive(&self) -> Result<Option<(TransitionBatch, u64)>, String> {
        let sample = self.subscriber.receive().map_err(|e| format!("receiving from shared memory: {e:?}"))?;
        Ok(sample.map(|sample| (sample.payload().to_batch(&self.run_id), publisher_stream(sample.header().publisher_id().value()))))
    }

    /// The publishers attached now, as [`publisher_stream`] numbers (a
    /// crashed actor's stays until [`remove_dead_nodes`] removes it).
    pub fn live_publishers(&self) -> std::collections::HashSet<u64> {
        let mut live = std::collections::HashSet::new();
        self.service.dynamic_config().list_publishers(|details| {
            live.insert(publisher_stream(details.publisher_id.value()));
            CallbackProgression::Continue
        });
        live
    }
}

/// Marks the stream numbers of shared-memory publishers, apart from the
/// learner's gRPC streams (numbered from 1).
pub const PUBLISHER_STREAM: u64 = 1 << 63;

/// A publisher's stream number: its unique id folded to 63 bits, marked
/// with [`PUBLISHER_STREAM`]. The learner binds an actor id to it as to a
/// gRPC stream.
pub fn publisher_stream(publisher_id: u128) -> u64 {
    PUBLISHER_STREAM | ((publisher_id as u64) ^ ((publisher_id >> 64) as u64))
}

/// Largest policy weights (safetensors bytes) and architecture (JSON) a
/// broadcast sample carries: 2 MiB is ~500k f32 parameters, eight times the
/// default peg actor; a larger actor needs a larger constant.
pub const MAX_POLICY_BYTES: usize = 2 << 20;
pub const MAX_ARCHITECTURE_BYTES: usize = 16 << 10;

/// A policy version in shared memory (`lcrl/<run id>/policy`).
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[repr(C)]
pub struct PolicySample {
    pub version: u64,
    /// How actors explore with this version (see `PolicySnapshot`).
    pub exploration_noise: f64,
    pub explore_uniform: u8,
    /// PolicySnapshot.training_finished (0 or 1).
    pub training_finished: u8,
    /// PolicySnapshot.incarnation.
    pub incarnation: u64,
    pub weights_len: u32,
    pub architecture_len: u32,
    pub architecture: [u8; MAX_ARCHITECTURE_BYTES],
    pub weights: [u8; MAX_POLICY_BYTES],
}

type PolicyService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, PolicySample, ()>;

fn open_policy_service(node: &Node<ipc::Service>, run_id: &str) -> Result<PolicyService, String> {
    let name = format!("lcrl/{run_id}/policy");
    let service_name: ServiceName = name.as_str().try_into().map_err(|e| format!("service name: {e:?}"))?;
    // Only the newest version matters: overwrite, and keep one for late joiners.
    node.service_builder(&service_name)
        .publish_subscribe::<PolicySample>()
        .enable_safe_overflow(true)
        .history_size(1)
        .subscriber_max_buffer_size(1)
        .max_subscribers(64)
        .open_or_create()
        .map_err(|e| format!("cannot open the shared-memory service {name}: {e:?}"))
}

/// The learner's policy broadcaster: overwrites the one sample actors read.
pub struct PolicyPublisher {
    publisher: iceoryx2::port::publisher::Publisher<ipc::Service, PolicySample, ()>,
    _service: PolicyService,
    _node: Node<ipc::Service>,
}

impl PolicyPublisher {
    pub fn open(run_id: &str) -> Result<Self, String> {
        let (node, service) = node_and(run_id, open_policy_service)?;
        let publisher = service.publisher_builder().create().map_err(|e| format!("iceoryx2 publisher: {e:?}"))?;
        Ok(PolicyPublisher { publisher, _service: service, _node: node })
    }

    /// Actors that subscribe later get the newest version (history) only
    /// when the publisher refreshes its connections.
    pub fn update_connections(&self) -> Result<(), String> {
        self.publisher.update_connections().map_err(|e| format!("{e:?}"))
    }

    pub fn publish(&self, snapshot: &PolicySnapshot) -> Result<(), String> {
        if snapshot.weights.len() > MAX_POLICY_BYTES || snapshot.architecture.len() > MAX_ARCHITECTURE_BYTES {
            return Err(format!("policy of {} bytes exceeds the shared-memory sample ({MAX_POLICY_BYTES}); use gRPC actors", snapshot.weights.len()));
        }
        let mut slot = self.publisher.loan_uninit().map_err(|e| format!("loan: {e:?}"))?;
        // Zero the whole sample in place (2 MiB never lives on a stack),
        // then fill it: every byte is initialized before assume_init.
        let payload = slot.payload_mut().as_mut_ptr();
        let sample = unsafe {
            std::ptr::write_bytes(payload, 0, 1);
            (*payload).version = snapshot.version;
            (*payload).exploration_noise = snapshot.exploration_noise;
            (*payload).explore_uniform = u8::from(snapshot.explore_uniform);
            (*payload).incarnation = snapshot.incarnation;
            (*payload).training_finished = u8::from(snapshot.training_finished);
            (*payload).weights_len = snapshot.weights.len() as u32;
            (*payload).architecture_len = snapshot.architecture.len() as u32;
            (&mut (*payload).weights)[..snapshot.weights.len()].copy_from_slice(&snapshot.weights);
            (&mut (*payload).architecture)[..snapshot.architecture.len()].copy_from_slice(snapshot.architecture.as_bytes());
            slot.assume_init()
        };
        sample.send().map(|_| ()).map_err(|e| format!("send: {e:?}"))
    }
}

/// An actor's view of the broadcast policy.
pub struct PolicySubscriber {
    subscriber: iceoryx2::port::subscriber::Subscriber<ipc::Service, PolicySample, ()>,
    _service: PolicyService,
    _node: Node<ipc::Service>,
}

impl PolicySubscriber {
    pub fn open(run_id: &str) -> Result<Self, String> {
        let (node, service) = node_and(run_id, open_policy_service)?;
        let subscriber = service.subscriber_builder().create().map_err(|e| format!("iceoryx2 subscriber: {e:?}"))?;
        Ok(PolicySubscriber { subscriber, _service: service, _node: node })
    }

    /// The newest version received since the last call, as the snapshot
    /// the gRPC path carries.
    pub fn newest(&self) -> Result<Option<crate::v1::PolicySnapshot>, String> {
        let mut newest = None;
        while let Some(sample) = self.subscriber.receive().map_err(|e| format!("receive: {e:?}"))? {
            let p = sample.payload();
            newest = Some(crate::v1::PolicySnapshot {
                version: p.version,
                weights: p.weights[..(p.weights_len as usize).min(MAX_POLICY_BYTES)].to_vec().into(),
                architecture: String::from_utf8_lossy(&p.architecture[..(p.architecture_len as usize).min(MAX_ARCHITECTURE_BYTES)]).into_owned(),
                explore_uniform: p.explore_uniform != 0,
                exploration_noise: p.exploration_noise,
                incarnation: p.incarnation,
                training_finished: p.training_finished != 0,
            });
        }
        Ok(newest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The subscriber names each batch's publisher, apart from every other
    /// publisher and from gRPC streams, and stops listing a publisher once
    /// it is dropped (the learner then frees the ids bound to it).
    #[test]
    fn batches_name_their_publisher_until_it_leaves() {
        let run_id = format!("shm-publishers-{}", std::process::id());
        let subscriber = TransitionSubscriber::open(&run_id, 4).expect("subscriber");
        let (first, second) = (ShmPublisher::open(&run_id).expect("publisher"), ShmPublisher::open(&run_id).expect("publisher"));
        let batch = |actor: &str| TransitionBatch { run_id: run_id.clone(), actor_id: actor.into(), sequence: 1, transitions: vec![Transition { state: vec![0.0; 2], action: vec![0.0], next_state: vec![0.0; 2], ..Default::default() }], ..Default::default() };
        first.send(&batch("a")).expect("send");
        second.send(&batch("b")).expect("send");
        let (a, from_first) = subscriber.receive().expect("receive").expect("a batch waits");
        let (b, from_second) = subscriber.receive().expect("receive").expect("a batch waits");
        assert_eq!((a.actor_id.as_str(), b.actor_id.as_str()), ("a", "b"));
        assert_ne!(from_first, from_second);
        assert!(from_first & PUBLISHER_STREAM != 0 && from_second & PUBLISHER_STREAM != 0);
        assert_eq!(subscriber.live_publishers(), [from_first, from_second].into_iter().collect());
        drop(first);
        assert_eq!(subscriber.live_publishers(), [from_second].into_iter().collect());
    }

    /// One learner a run id on a host: while a subscriber lives, a second
    /// is refused as RunTaken (naming the run), and once it is gone the
    /// run id is free again.
    #[test]
    fn a_run_id_takes_one_subscriber() {
        let run_id = format!("shm-one-learner-{}", std::process::id());
        let first = TransitionSubscriber::open(&run_id, 4).expect("subscriber");
        let second = TransitionSubscriber::open(&run_id, 4).err().expect("a second subscriber is refused");
        assert_eq!(second, SubscriberError::RunTaken(run_id.clone()));
        assert!(second.to_string().contains(&format!("run id '{run_id}'")), "{second}");
        drop(first);
        TransitionSubscriber::open(&run_id, 4).expect("free again");
    }

    #[test]
    fn sample_round_trips_a_batch() {
        // With and without the sampled action and the log-probability.
        let t = |v: f32| Transition {
            state: vec![v; 12],
            action: vec![-v; 6],
            reward: v,
            next_state: vec![v + 1.0; 12],
            terminated: v > 2.0,
            truncated: v < 1.0,
            policy_version: v as u64,
            sampled_action: if v > 1.0 { vec![1.5 * v; 6] } else { vec![] },
            log_prob: (v > 2.0).then_some(-v),
            cut: (1.0..2.0).contains(&v),
        };
        let batch = TransitionBatch {
            run_id: "r".into(),
            actor_id: "actor-7".into(),
            sequence: 9,
            episode_id: 3,
            policy_version: 2,
            incarnation: 0x5eed,
            actor_key: 0,
            transitions: vec![t(0.5), t(1.5), t(2.5)],
            episodes: vec![
                EpisodeSummary {
                    episode_return: -4.5,
                    length: 50,
                    success: Some(true),
                    peak_force_n: Some(12.5),
                    peak_moment_nm: Some(0.25),
                    return_terms: Some(crate::v1::ReturnTerms { depth: -1.0, force: -5.0, moment: -0.5, bonus: 2.0, failure: 0.0 }),
                },
                EpisodeSummary { episode_return: -1.0, length: 3, success: None, ..Default::default() },
            ],
        };
        assert_eq!(TransitionSample::from_batch(&batch).unwrap().to_batch("r"), batch);
        let too_long = TransitionBatch { transitions: vec![t(0.1); MAX_TRANSITIONS + 1], ..batch };
        assert!(TransitionSample::from_batch(&too_long).is_err());
    }
}
