//! Output files written completely or not at all, so an interrupted
//! command never leaves a half-written result that looks finished.

use std::path::Path;

use anyhow::Context;

/// Writes `text` to `path` whole or not at all, with the runs' one atomic
/// writer (`lcrl_proto::files::write_atomically`: temp file, fsync,
/// rename; the folder is created if needed).
pub fn write_atomic(path: &Path, text: &str) -> anyhow::Result<()> {
    lcrl_proto::files::write_atomically(path, text.as_bytes()).with_context(|| format!("writing {}", path.display()))
}
