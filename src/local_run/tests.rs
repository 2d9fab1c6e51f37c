//! `lcrl run`'s wiring driven in this process: the steps before any
//! process starts (the end-to-end suite, tests/e2e/run_cli.rs, runs whole
//! runs through the binary).

use std::path::Path;

use clap::Parser;

use super::{run, with_own_token, RunArgs};
use crate::run_security::RunSecurity;

#[derive(clap::Parser)]
struct Cli {
    #[command(flatten)]
    run: RunArgs,
}

/// `lcrl run` of the main job's preset with `extra`, parsed as the binary
/// parses it.
fn args(run_dir: &Path, extra: &[&str]) -> RunArgs {
    let run_dir = run_dir.to_str().expect("a UTF-8 temporary path");
    let line = ["lcrl-run", "--config", "configs/lti-paper.toml", "--run-dir", run_dir].into_iter().chain(extra.iter().copied());
    Cli::try_parse_from(line).expect("the test's command line parses").run
}

#[test]
fn a_checked_preset_with_its_overrides_starts_nothing_and_writes_nothing() {
    let work = tempfile::tempdir().unwrap();
    let dir = work.path().join("run");
    run(&args(&dir, &["--check", "--actors", "3", "--episodes", "7", "--eval-episodes", "4"])).expect("the main job's preset checks");
    assert!(!dir.exists(), "--check created the run directory");
}

#[test]
fn a_bad_preset_or_override_fails_before_the_run_directory_exists() {
    let work = tempfile::tempdir().unwrap();
    let dir = work.path().join("run");
    let too_many = run(&args(&dir, &["--actors", "100000"])).unwrap_err();
    assert!(format!("{too_many:#}").contains("job.actors (--actors) must be from 1 to"), "{too_many:#}");
    let missing = work.path().join("no-such-preset.toml");
    let mut missing_args = args(&dir, &[]);
    missing_args.config = missing.clone();
    let err = run(&missing_args).unwrap_err();
    assert!(format!("{err:#}").contains("no-such-preset.toml"), "the error does not name the preset: {err:#}");
    assert!(!dir.exists(), "a refused run created its directory");
    assert!(Cli::try_parse_from(["lcrl-run", "--config", "c.toml", "--eval-episodes", "0"]).is_err(), "--eval-episodes 0 was accepted");
}

/// Without a token, a run makes its own (issue 71): random, in the run
/// directory, readable by its owner only; a given one is kept.
#[test]
fn a_run_without_a_token_gets_its_own_that_only_its_owner_reads() {
    let work = tempfile::tempdir().unwrap();
    let (a, b) = (work.path().join("a"), work.path().join("b"));
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    let own = with_own_token(&RunSecurity::default(), false, &a).unwrap();
    let own_b = with_own_token(&RunSecurity::default(), false, &b).unwrap();
    let path = own.token_file.clone().expect("a run without a token was given none");
    assert_eq!(path, a.join("token"));
    let token = std::fs::read_to_string(&path).unwrap();
    assert!(token.trim_end().len() == 64 && token.trim_end().chars().all(|c| c.is_ascii_hexdigit()), "{token:?}");
    assert_ne!(token, std::fs::read_to_string(b.join("token")).unwrap(), "two runs were given the same token");
    assert!(own_b.token_file.is_some());
    use std::os::unix::fs::PermissionsExt;
    assert_eq!(std::fs::metadata(&path).unwrap().permissions().mode() & 0o777, 0o600);

    let given = RunSecurity { token_file: Some(work.path().join("given")), ..RunSecurity::default() };
    let (c, d) = (work.path().join("c"), work.path().join("d"));
    assert_eq!(with_own_token(&given, false, &c).unwrap().token_file, given.token_file);
    assert_eq!(with_own_token(&RunSecurity::default(), true, &d).unwrap().token_file, None, "$LCRL_TOKEN_FILE was overridden");
    assert!(!c.join("token").exists() && !d.join("token").exists());
}
