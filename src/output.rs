//! Output files written completely or not at all, so an interrupted
//! command never leaves a half-written result that looks finished.

use std::path::Path;

use anyhow::Context;

/// Writes `text` to `path` whole or not at all, with the runs' one atomic
/// writer (`lcrl_runtime::files::write_atomically`: temp file, fsync,
/// rename; the folder is created if needed).
pub fn write_atomic(path: &Path, text: &str) -> anyhow::Result<()> {
    lcrl_runtime::files::write_atomically(path, text.as_bytes()).with_context(|| format!("writing {}", path.display()))
}

/// The return split into its terms, where the task has them.
pub fn print_terms(t: &lcrl_sim::ReturnColumns) {
    if let (Some(d), Some(f), Some(m), Some(b), Some(x)) = (t.return_depth, t.return_force, t.return_moment, t.return_bonus, t.return_failure) {
        println!("    = depth {d:.3} + force {f:.3} + moment {m:.3} + bonus {b:.3} + failure {x:.3}");
    }
}
