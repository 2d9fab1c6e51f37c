//! The run room: a training run and its records. How a run starts, the
//! single-process loop (`lcrl train`), the files every run writes
//! (metrics.csv, the selection record, summary.json, TensorBoard events), and
//! the choice of the run's policy on held-out starts.
//!
//! May import: [`crate::policy`], [`crate::algo`], [`crate::device`],
//! [`crate::config`]. Nothing here knows of the service, which uses this
//! room for its own run records.
//!
//! - [`start`]: how a run starts (`prepare`: the checkpoint to resume or the new settings, the mask, the base controller, the agent), for both loops.
//! - [`files`]: metrics.csv, the selection record and the one atomic writer, for both loops.
//! - [`summary`]: summary.json of every loop, and the one evaluation of a handed-over policy.
//! - [`tensorboard`]: TensorBoard event files of a run.
//! - [`selection`]: the run's policy chosen on held-out validation starts.
//! - [`trainer`]: the single-process loop: episodes, metrics.csv, summary.json, resume.

pub mod files;
pub mod lock;
pub mod selection;
pub mod start;
pub mod summary;
pub mod tensorboard;
pub mod trainer;

// Training-level tests of the loop: learning quality, determinism, what a
// run records. Selection's and resume's tests are beside their rooms.
#[cfg(test)]
mod tests;
// The test helpers of this room: a run of the loop, its rows.
#[cfg(test)]
mod test_run;
