//! Finding the programs a command starts: the workspace binaries built
//! beside this one, and the Python with lcrl_env.

use std::path::{Path, PathBuf};

use anyhow::bail;

/// The Python with lcrl_env installed: $LCRL_PYTHON, else this project's
/// .venv (scripts/setup.sh installs lcrl_env there).
pub fn lcrl_python() -> anyhow::Result<PathBuf> {
    let python = match std::env::var_os("LCRL_PYTHON") {
        Some(p) => PathBuf::from(p),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python"),
    };
    if !python.is_file() {
        bail!("{} is missing: run `bash scripts/setup.sh` (it installs lcrl_env into .venv), or set $LCRL_PYTHON to a Python with lcrl_env", python.display());
    }
    Ok(python)
}

/// A workspace binary next to this one (`lcrl-learner`, ...).
pub fn sibling(name: &str) -> anyhow::Result<PathBuf> {
    let path = std::env::current_exe()?.with_file_name(name);
    if !path.is_file() {
        bail!("{} is missing; build it with `cargo build --workspace --bins`", path.display());
    }
    Ok(path)
}
