//! A file's recorded environment is data, never an address (issue 82): the
//! environment a checkpoint or graph names is used only when it is one of
//! lcrl's own (a registered name) or a TOML file inside the folder the user
//! named. A served environment's address, or a file elsewhere, must be
//! given on the command line (--env): nothing is connected to, and no token
//! is sent, because a file said so, and no file content is echoed.

use std::path::Path;

use anyhow::bail;

/// The environment to build for a policy loaded from `folder` that
/// records `recorded`: `given` (--env) when the user named one, else
/// `recorded` when it is safe to follow without asking.
pub fn environment_to_build(recorded: &str, given: Option<&str>, folder: &Path) -> anyhow::Result<String> {
    if let Some(given) = given {
        return Ok(given.to_string());
    }
    let registered = lcrl_sim::known_env_names().contains(&recorded) || lcrl_sim::lti::LtiConfig::blocks_size(recorded).is_some_and(|n| lcrl_sim::lti::LtiConfig::blocks(n).is_some());
    if registered {
        return Ok(recorded.to_string());
    }
    if lcrl_sim::remote::is_served(recorded) {
        bail!(
            "the policy in {} was trained on a served environment; a file never chooses where lcrl connects or sends a token: \
             name the server with --env grpc://HOST:PORT (or grpcs://)",
            folder.display()
        );
    }
    let inside = |path: &Path| -> Option<bool> { Some(path.canonicalize().ok()?.starts_with(run_of(folder).canonicalize().ok()?)) };
    if recorded.ends_with(".toml") && inside(Path::new(recorded)) == Some(true) {
        return Ok(recorded.to_string());
    }
    bail!(
        "the policy in {} names an environment that is neither one of lcrl's ({}) nor a TOML file inside its run; \
         name it with --env (a preset, a TOML file or grpc://HOST:PORT)",
        folder.display(),
        lcrl_sim::known_env_names().join(", ")
    )
}

/// The run a policy folder belongs to: RUN for RUN/checkpoints/epN,
/// RUN/candidates/epN and RUN/selected (also under RUN/learner/), else the
/// folder itself.
fn run_of(folder: &Path) -> &Path {
    let mut run = folder;
    for _ in 0..3 {
        match run.file_name().and_then(|n| n.to_str()) {
            Some("selected" | "learner") => run = run.parent().unwrap_or(run),
            Some(name) if name.starts_with("ep") && run.parent().and_then(|p| p.file_name()).is_some_and(|p| p == "checkpoints" || p == "candidates") => {
                run = run.parent().and_then(Path::parent).unwrap_or(run);
            }
            _ => break,
        }
    }
    run
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Registered names are followed; an address or a file outside the run
    /// is refused without echoing it; --env always wins; a TOML inside the
    /// run is followed.
    #[test]
    fn only_own_environments_and_files_inside_the_run_are_followed() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("run");
        let folder = run.join("checkpoints/ep000010");
        std::fs::create_dir_all(&folder).unwrap();
        assert_eq!(environment_to_build("peg-group1", None, &folder).unwrap(), "peg-group1");
        assert_eq!(environment_to_build("lti-blocks-6", None, &folder).unwrap(), "lti-blocks-6");
        let served = environment_to_build("grpc://203.0.113.7:9999", None, &folder).unwrap_err().to_string();
        assert!(served.contains("--env grpc://HOST:PORT") && !served.contains("203.0.113.7"), "{served}");
        let outside = dir.path().join("elsewhere.toml");
        std::fs::write(&outside, "secret = 1\n").unwrap();
        let refused = environment_to_build(&outside.display().to_string(), None, &folder).unwrap_err().to_string();
        assert!(refused.contains("name it with --env") && !refused.contains("elsewhere") && !refused.contains("secret"), "{refused}");
        let inside = run.join("env.toml");
        std::fs::write(&inside, "").unwrap();
        assert_eq!(environment_to_build(&inside.display().to_string(), None, &folder).unwrap(), inside.display().to_string());
        assert_eq!(environment_to_build("grpc://x:1", Some("grpc://127.0.0.1:5"), &folder).unwrap(), "grpc://127.0.0.1:5");
        assert_eq!(run_of(&run.join("learner/selected")), run.as_path());
    }
}
