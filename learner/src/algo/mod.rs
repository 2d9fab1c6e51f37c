//! The algorithms room: the networks, the algorithm interface and its two
//! implementations (DDPG, PPO), and what they train with: Adam over flat
//! parameter buffers, the replay buffer and its rate limiter, exploration
//! noise, and the LQR ceiling the linear environments are measured against.
//!
//! May import: [`crate::config`], [`crate::device`]. Nothing here knows of
//! checkpoints, policies, runs or the service.
//!
//! - [`nets`]: locally connected (batched, masked), full-subnets and global actors; critics.
//! - [`flat`]: one parameter buffer per network; [`adam`]: Adam with savable state over it.
//! - [`agent`]: the algorithm interface and the state normalization; [`ddpg`] and [`ppo`] implement it, [`algorithms`] builds one by name.
//! - [`replay`]: the replay buffer (mirrored on a GPU); [`rate_limiter`]: the replay-ratio limiter of the distributed learner (Reverb's semantics).
//! - [`exploration`]: how a training action is sampled, for `lcrl train` and the actors alike.
//! - [`lqr`]: the LQR ceiling for linear environments.

pub mod adam;
pub mod agent;
pub mod algorithms;
pub mod ddpg;
pub mod elu;
pub mod exploration;
pub mod flat;
pub mod lqr;
pub mod nets;
pub mod ppo;
pub mod rate_limiter;
pub mod replay;

#[cfg(test)]
mod cuda_tests;
