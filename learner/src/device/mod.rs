//! The device room: where the learner computes. The libtorch device
//! (CUDA's library loaded at run time), the intra-op thread count, and CUDA
//! graphs of a training step.
//!
//! May import: [`crate::config`] only.
//!
//! - [`torch`]: the libtorch device (`run.device`, CUDA loaded at run time) and intra-op threads (`run.threads`).
//! - [`cuda_graph`]: a captured CUDA graph of an update, replayed instead of launching its kernels one by one.

pub mod cuda_graph;
pub mod torch;
