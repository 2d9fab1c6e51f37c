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

/// A file of this project (`scripts/...`), wherever the binary was built:
/// under the working directory, under a folder above the binary (a build
/// copied with its `target/` into another checkout, or release binaries
/// beside a checkout), or where this binary was built.
pub fn project_file(relative: &str) -> anyhow::Result<PathBuf> {
    let mut roots: Vec<PathBuf> = Vec::new();
    roots.extend(std::env::current_dir().ok());
    if let Ok(exe) = std::env::current_exe() {
        roots.extend(exe.ancestors().skip(1).take(4).map(Path::to_path_buf));
    }
    roots.push(PathBuf::from(env!("CARGO_MANIFEST_DIR")));
    match roots.iter().map(|root| root.join(relative)).find(|path| path.is_file()) {
        Some(path) => Ok(path),
        None => bail!(
            "{relative} is not under the working directory, the folders above this binary or {}; run from the project's root",
            env!("CARGO_MANIFEST_DIR")
        ),
    }
}

/// A workspace binary next to this one (`lcrl-learner`, ...).
pub fn sibling(name: &str) -> anyhow::Result<PathBuf> {
    let path = std::env::current_exe()?.with_file_name(name);
    if !path.is_file() {
        bail!("{} is missing; build it with `cargo build --workspace --bins`", path.display());
    }
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A project file is found (here under the working directory or where
    /// the binary was built); a missing one is named in the error.
    #[test]
    fn project_files_are_found_and_missing_ones_named() {
        let script = project_file("scripts/bench_torch_ddpg.py").expect("the PyTorch comparison script");
        assert!(script.ends_with("scripts/bench_torch_ddpg.py") && script.is_file());
        let missing = project_file("scripts/no-such-script.py").unwrap_err().to_string();
        assert!(missing.contains("scripts/no-such-script.py") && missing.contains("project's root"), "{missing}");
    }
}
