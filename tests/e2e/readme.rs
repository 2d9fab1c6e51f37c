//! README.md and docs/usage.md as a newcomer runs them (issue 85): every
//! shell and Python block is marked quick (run here, as printed, against a
//! real lti-paper run, a standalone learner or a short peg run) or apart
//! (scripts/readme-apart.sh); scripts/readme_blocks.py does the running.

use super::common::repo;
use std::process::{Command, Output};

fn readme_blocks(args: &[&str]) -> Output {
    let root = repo();
    // The blocks' processes get this test's shared-memory namespace, as
    // every process the tests start does (common.rs, shm_namespace).
    Command::new("python3")
        .arg(root.join("scripts/readme_blocks.py"))
        .args(args)
        .current_dir(&root)
        .env(lcrl_proto::shm::NAMESPACE_ENV, super::common::shm_namespace())
        .output()
        .unwrap()
}

fn text(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

/// Every quick block runs as printed, the commands `lcrl run` prints to
/// paste included; every block carries a mark, and each apart block names
/// the script that runs it.
#[test]
fn every_quick_readme_block_runs_as_printed() {
    let listed = readme_blocks(&["list"]);
    assert!(listed.status.success(), "{}", text(&listed));
    let listing = String::from_utf8_lossy(&listed.stdout).into_owned();
    let quick = listing.lines().filter(|l| l.split('\t').nth(1).is_some_and(|m| m.starts_with("quick"))).count();
    assert!(quick >= 4, "the README's queries, the linear run, the export and usage.md's clients are quick blocks:\n{listing}");
    for line in listing.lines().filter(|l| l.contains("\tapart")) {
        assert!(line.ends_with("scripts/readme-apart.sh"), "{line}");
    }
    let out = readme_blocks(&["quick"]);
    assert!(out.status.success(), "{}", text(&out));
    let ran = String::from_utf8_lossy(&out.stdout).lines().filter(|l| l.starts_with("ok ")).count();
    assert_eq!(ran, quick, "{}", text(&out));
}

/// The harness fails on a failing quick block and on an unmarked one, and
/// names them: a README test that cannot fail would prove nothing.
#[test]
fn a_failing_or_unmarked_block_fails_the_readme_test() {
    let dir = tempfile::tempdir().unwrap();
    let failing = dir.path().join("failing.md");
    std::fs::write(&failing, "<!-- readme-test: quick -->\n```sh\ntrue\nfalse\n```\n").unwrap();
    let out = readme_blocks(&["quick", "--file", failing.to_str().unwrap()]);
    assert!(!out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("FAIL") && text(&out).contains("failing.md:2"), "{}", text(&out));
    let unmarked = dir.path().join("unmarked.md");
    std::fs::write(&unmarked, "Run:\n\n```sh\ntrue\n```\n").unwrap();
    let out = readme_blocks(&["quick", "--file", unmarked.to_str().unwrap()]);
    assert!(!out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("unmarked.md:3: a sh block without a mark"), "{}", text(&out));
}
