//! The policy room: a trained actor as it is stored, sent and served. What
//! identifies an actor, the map from its outputs to the environment's box,
//! the checkpoint store, the snapshot on the wire, and the loaded policy.
//!
//! May import: [`crate::algo`], [`crate::device`], [`crate::config`].
//! Nothing here knows of runs or the service.
//!
//! - [`architecture`]: what identifies an actor, held by snapshots and checkpoints alike.
//! - [`action`]: normalized actions to the environment's box, around an optional base controller (residual RL).
//! - [`checkpoint`]: the checkpoint store (atomic writes, newest kept, resume).
//! - [`finite`]: whether weights hold only finite numbers (never served, written or resumed otherwise).
//! - [`snapshot`]: a policy on the wire (architecture + safetensors weights).
//! - [`trained`]: a trained actor ([`trained::Policy`]) loaded from a checkpoint or a snapshot, and its evaluation.

pub mod action;
pub mod architecture;
pub mod checkpoint;
pub mod finite;
pub mod snapshot;
pub mod trained;

#[cfg(test)]
mod tests;
