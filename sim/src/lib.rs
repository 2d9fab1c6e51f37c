//! Environments for lcrl.
//!
//! - [`env`]: the [`Env`] contract every environment implements (dimensions,
//!   bounds, names, reset/step with Gymnasium-style end flags, exact
//!   snapshots for CS3's paired branches).
//! - [`lti`]: linear time-invariant systems s' = E s + F a (+ noise), the
//!   systems with a known connection graph (docs/method.md §4).
//! - [`mod@overlay`]: how an override file lays onto its base (TOML tables merged key by key).
//! - [`peg`]: the peg-in-hole assembly simulator on rapier3d (docs/method.md §6).
//! - [`evaluate`]: whole episodes with a policy, traces and summaries.
//! - [`registry`]: environments by name, TOML file or server URL.
//! - [`remote`]: environments served by another process (`grpc://HOST:PORT`,
//!   e.g. any Gymnasium environment behind `python -m lcrl_env serve`).
//! - [`serve`]: the other direction: these environments served over
//!   `lcrl.v1.Environment` (`lcrl serve-env`), for any language.
//! - [`seeds`]: which episode starts training, validation and evaluation use (disjoint ranges).
//! - [`tune`]: the best constant action (CMA-ES), the bar for learned agents.

pub mod env;
pub mod evaluate;
pub mod lti;
pub mod overlay;
pub mod peg;
pub mod registry;
pub mod remote;
pub mod seeds;
pub mod serve;
pub mod tune;

pub use env::{diverged, state_out_of_bounds, Env, EnvError, EnvSpec, EpisodeMetrics, ReturnColumns, ReturnTerms, Step, REWARD_LIMIT, SAMPLED_ACTION_BOUND, SAMPLED_ACTION_LIMIT, STATE_LIMIT};
pub use remote::step_all;
pub use overlay::overlay;
pub use registry::{env_from_toml, known_env_names, make_env};
