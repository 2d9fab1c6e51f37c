//! `lcrl experiment`: the smoke study run, killed with SIGKILL and resumed;
//! its report checked against itself; bad input refused without losing
//! finished runs; the Kubernetes Indexed Job checked against the real CLI.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant, SystemTime};

use serde_json::Value;

use super::common::{assert_clean_failure, lcrl, load_docs, repo, seq, stderr, stdout, str_of};

fn smoke() -> PathBuf {
    repo().join("experiments/smoke.toml")
}

/// Every finished run (summary.json) under `out`, with its bytes and mtime.
fn finished_runs(out: &Path) -> BTreeMap<PathBuf, (Vec<u8>, SystemTime)> {
    let mut found = BTreeMap::new();
    let mut stack = vec![out.join("runs")];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).into_iter().flatten().flatten() {
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else if path.file_name().is_some_and(|n| n == "summary.json") {
                let bytes = std::fs::read(&path).unwrap();
                found.insert(path.clone(), (bytes, entry.metadata().unwrap().modified().unwrap()));
            }
        }
    }
    found
}

/// Run folders with a checkpoint and no summary.json: interrupted runs.
fn checkpointed_unfinished(out: &Path) -> Vec<PathBuf> {
    let root = out.join("runs/lti-paper/ppo");
    let mut found = Vec::new();
    for connection in std::fs::read_dir(root).into_iter().flatten().flatten() {
        for run in std::fs::read_dir(connection.path()).into_iter().flatten().flatten() {
            let dir = run.path();
            // A staging folder (`.NAME.partial`) holds checkpoint.json before
            // its rename; a kill then leaves no checkpoint, so hidden folders
            // do not count.
            let checkpoints = std::fs::read_dir(dir.join("checkpoints"))
                .into_iter()
                .flatten()
                .flatten()
                .any(|c| !c.file_name().to_string_lossy().starts_with('.') && c.path().join("checkpoint.json").is_file());
            if checkpoints && !dir.join("summary.json").exists() {
                found.push(dir);
            }
        }
    }
    found
}

/// Processes whose command line mentions `needle` (the study's folder).
fn processes_mentioning(needle: &str) -> Vec<String> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        if let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) {
            let text = String::from_utf8_lossy(&cmdline).replace('\0', " ");
            if text.contains(needle) {
                found.push(text);
            }
        }
    }
    found
}

fn num(x: &Value) -> String {
    format!("{:.3}", x.as_f64().unwrap())
}

#[test]
fn smoke_study_survives_sigkill_resumes_and_reports_consistently() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("smoke");
    let out_str = out.display().to_string();

    // First attempt, one run at a time, killed once a run has finished and
    // the next has written a checkpoint but not finished.
    let mut first = lcrl()
        .args(["experiment", "run"])
        .arg(smoke())
        .args(["--out", &out_str, "--jobs", "1"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(300);
    let (before, interrupted) = loop {
        let runs = finished_runs(&out);
        let midway = checkpointed_unfinished(&out);
        if !runs.is_empty() && !midway.is_empty() {
            break (runs, midway);
        }
        assert!(first.try_wait().unwrap().is_none(), "the study exited before finishing a run");
        assert!(Instant::now() < deadline, "no run finished within 300 s");
        std::thread::sleep(Duration::from_millis(20));
    };
    first.kill().unwrap(); // SIGKILL
    first.wait().unwrap();
    assert!(before.len() < 4, "all runs finished before the kill; the test needs an interrupted study");
    assert!(checkpointed_unfinished(&out).iter().all(|d| interrupted.contains(d)));
    // Its child runs die with it (nothing left to race with the resumed study).
    let deadline = Instant::now() + Duration::from_secs(20);
    while !processes_mentioning(&out_str).is_empty() {
        assert!(Instant::now() < deadline, "processes outlived the killed study: {:?}", processes_mentioning(&out_str));
        std::thread::sleep(Duration::from_millis(20));
    }

    // The same command resumes: finished runs untouched, the rest completed.
    let second = lcrl().args(["experiment", "run"]).arg(smoke()).args(["--out", &out_str, "--jobs", "2"]).output().unwrap();
    assert!(second.status.success(), "resumed study failed: {}\n{}", stdout(&second), stderr(&second));
    let text = stdout(&second);
    assert!(text.contains("finished before"), "{text}");
    let after = finished_runs(&out);
    assert_eq!(after.len(), 4, "2 connections × 2 seeds");
    for (path, (bytes, modified)) in &before {
        assert_eq!(&after[path], &(bytes.clone(), *modified), "{} was run again", path.display());
    }
    // The interrupted run continued from its checkpoint.
    for dir in &interrupted {
        let id = dir.strip_prefix(out.join("runs")).unwrap().iter().map(|p| p.to_string_lossy().into_owned()).collect::<Vec<_>>().join("-");
        let log = std::fs::read_to_string(out.join("logs").join(format!("train-{id}.log"))).unwrap();
        assert!(log.contains("resuming from checkpoint"), "{id} started afresh:\n{log}");
    }
    for summary in after.keys() {
        let rows = std::fs::read_to_string(summary.with_file_name("metrics.csv")).unwrap();
        let episodes: Vec<usize> = rows.lines().skip(1).map(|l| l.split(',').next().unwrap().parse().unwrap()).collect();
        assert_eq!(episodes, (1..=150).collect::<Vec<_>>(), "{}: every episode exactly once", summary.display());
    }

    // report.json parses and report.md shows its numbers.
    let report: Value = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    let cells = report["cells"].as_array().unwrap();
    assert_eq!(cells.len(), 2);
    for cell in cells {
        assert_eq!(cell["seeds"], serde_json::json!([0, 1]));
        let connection = cell["connection"].as_str().unwrap();
        let row = md.lines().find(|l| l.starts_with(&format!("| {connection} |"))).unwrap_or_else(|| panic!("no row for {connection} in\n{md}"));
        for key in ["final_return", "eval_return", "optimization_seconds", "total_seconds"] {
            let e = &cell[key];
            let shown = format!("{} [{}, {}]", num(&e["mean"]), num(&e["ci95"][0]), num(&e["ci95"][1]));
            assert!(row.contains(&shown), "{key} {shown} not in {row}");
            let (lo, hi) = (e["ci95"][0].as_f64().unwrap(), e["ci95"][1].as_f64().unwrap());
            assert!(lo <= e["mean"].as_f64().unwrap() && e["mean"].as_f64().unwrap() <= hi);
        }
        let reach = &cell["episodes_to_threshold"];
        let (reached, censored) = (reach["reached"].as_u64().unwrap(), reach["censored"].as_u64().unwrap());
        assert_eq!(reached + censored, 2);
        assert!(row.contains(&format!("{} [", num(&reach["mean"]))) && row.contains(&format!("({censored} of 2 censored)")), "{row}");
        assert!(row.contains(&format!("| {} |", num(&cell["graph_seconds"]))), "{row}");
        let local = connection.starts_with("local");
        assert_eq!(cell["graph_seconds"].as_f64().unwrap() > 0.0, local, "graph time belongs to local cells only");
    }
    let comparisons = report["comparisons"].as_array().unwrap();
    // local − global on final and eval return and the area under the
    // curve, and on the episodes to the best constant (log-rank) when a
    // run got there.
    let reached: u64 = report["cells"].as_array().unwrap().iter().map(|c| c["speed"]["reached_best_constant"].as_u64().unwrap()).sum();
    let metrics: Vec<&str> = comparisons.iter().map(|c| c["metric"].as_str().unwrap()).collect();
    let mut expected = vec!["final_return", "eval_return", "auc_100"];
    if reached > 0 {
        expected.push("episodes_to_best_constant");
    }
    assert_eq!(metrics, expected, "local − global");
    for c in comparisons {
        let (p, holm) = (c["p_value"].as_f64().unwrap(), c["p_holm"].as_f64().unwrap());
        assert!((0.0..=1.0).contains(&p) && (p..=1.0).contains(&holm), "p {p}, Holm {holm}");
        let row = format!(
            "| {} − {} | {} | {} | [{}, {}] | {} | {} | {} | {} |",
            c["a"].as_str().unwrap(),
            c["b"].as_str().unwrap(),
            c["metric"].as_str().unwrap(),
            num(&c["difference"]),
            num(&c["ci95"][0]),
            num(&c["ci95"][1]),
            c["test"].as_str().unwrap(),
            lcrl::experiment::stats::format_p(p),
            lcrl::experiment::stats::format_p(holm),
            c["reading"].as_str().unwrap()
        );
        assert!(md.contains(&row), "{row} not in\n{md}");
    }
    let bar = &report["best_constant"]["lti-paper"];
    assert!(md.contains(&format!("| best constant | — | — | {} |", num(&bar["mean_return"]))), "{md}");
    for png in ["curves.png", "traces.png"] {
        let bytes = std::fs::read(out.join(png)).unwrap();
        assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 10_000, "{png}");
    }
    // The report is a function of the runs: written again, it is the same.
    let again = lcrl().args(["experiment", "report", &out_str]).output().unwrap();
    assert!(again.status.success(), "{}", stderr(&again));
    assert_eq!(std::fs::read_to_string(out.join("report.md")).unwrap(), md);

    // Archived (scripts/archive-study.sh: results, no policies or logs), the
    // study reports the same and resumes as finished: nothing runs again.
    let archive = tmp.path().join("archive");
    let archived = std::process::Command::new("bash").arg(repo().join("scripts/archive-study.sh")).arg(&out).arg(&archive).output().unwrap();
    assert!(archived.status.success(), "{}", stderr(&archived));
    assert!(stdout(&archived).contains("4 finished runs"), "{}", stdout(&archived));
    assert!(!archive.join("logs").exists() && !archive.join("runs/lti-paper/ppo/global/seed0/checkpoints").exists());
    let from_archive = lcrl().args(["experiment", "report"]).arg(&archive).output().unwrap();
    assert!(from_archive.status.success(), "{}", stderr(&from_archive));
    assert!(stderr(&from_archive).contains("traces.png: leaving out"), "{}", stderr(&from_archive));
    assert_eq!(std::fs::read_to_string(archive.join("report.md")).unwrap(), md);
    // Against a reference study (here its own archive), seed for seed: every
    // difference is 0, so every seed passes, in both files; a folder with no
    // study and a negative margin are refused, the report already written kept.
    let against = lcrl().args(["experiment", "report", &out_str, "--against"]).arg(&archive).output().unwrap();
    assert!(against.status.success(), "{}", stderr(&against));
    let paired: Value = serde_json::from_str(&std::fs::read_to_string(out.join("against-smoke.json")).unwrap()).unwrap();
    assert_eq!(paired["cells"].as_array().map(Vec::len), Some(2), "{paired}");
    for cell in paired["cells"].as_array().unwrap() {
        assert_eq!((cell["connection"].clone(), cell["passing"].as_u64()), (cell["reference_connection"].clone(), Some(2)), "{cell}");
        assert_eq!(cell["worst_difference"]["mean"].as_f64(), Some(0.0), "{cell}");
    }
    assert!(std::fs::read_to_string(out.join("against-smoke.md")).unwrap().contains("| 2 of 2 |"));
    let nowhere = lcrl().args(["experiment", "report", &out_str, "--against"]).arg(tmp.path().join("nowhere")).output().unwrap();
    assert_clean_failure(&nowhere, "holds no experiment");
    let negative = lcrl().args(["experiment", "report", &out_str, "--margin=-1", "--against"]).arg(&archive).output().unwrap();
    assert_clean_failure(&negative, "--margin");
    // A companion study (--with) must be another study of the same design.
    let with = |dir: &Path| lcrl().args(["experiment", "report", &out_str, "--with"]).arg(dir).output().unwrap();
    assert_clean_failure(&with(&archive), "names the study smoke itself");
    assert_clean_failure(&with(&tmp.path().join("nowhere")), "holds no experiment");
    assert_eq!(std::fs::read_to_string(out.join("report.md")).unwrap(), md);
    let resumed = lcrl().args(["experiment", "run"]).arg(smoke()).arg("--out").arg(&archive).output().unwrap();
    assert!(resumed.status.success(), "{}", stderr(&resumed));
    assert_eq!(finished_runs(&archive).len(), 4);
    let logs = std::fs::read_dir(archive.join("logs")).map(|d| d.count()).unwrap_or(0);
    assert_eq!(logs, 0, "a finished archive ran a task again");
}

/// A study of one short run, for the error paths.
const TINY: &str = "name = \"tiny\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"global\"]\nseeds = 1\nepisodes = { ppo = 4 }\neval_episodes = 2\n[best_constant]\nenabled = false\n";

#[test]
fn bad_experiments_are_refused_and_finished_runs_kept() {
    let tmp = tempfile::tempdir().unwrap();
    let write = |name: &str, text: &str| {
        let path = tmp.path().join(name);
        std::fs::write(&path, text).unwrap();
        path
    };
    let run = |file: &Path, out: &Path| lcrl().args(["experiment", "run"]).arg(file).arg("--out").arg(out).output().unwrap();

    let unknown = write("unknown.toml", &TINY.replace("\"global\"", "\"glob\""));
    assert_clean_failure(&run(&unknown, &tmp.path().join("a")), "unknown connection \"glob\"");
    let zero = write("zero.toml", &TINY.replace("seeds = 1", "seeds = 0"));
    assert_clean_failure(&run(&zero, &tmp.path().join("b")), "`seeds` is zero");
    assert!(!tmp.path().join("a").exists() && !tmp.path().join("b").exists(), "nothing is written for a bad file");

    let tiny = write("tiny.toml", TINY);
    let out = tmp.path().join("tiny");
    let done = run(&tiny, &out);
    assert!(done.status.success(), "{}", stderr(&done));
    let finished = finished_runs(&out);
    assert_eq!(finished.len(), 1);

    // Another experiment file into the same folder: refused, nothing lost.
    let other = write("other.toml", &TINY.replace("ppo = 4", "ppo = 5"));
    assert_clean_failure(&run(&other, &out), "belongs to a different experiment (\"tiny\"");
    assert_eq!(finished_runs(&out), finished);
    // Dropping a seed is another study too.
    let fewer = write("fewer.toml", &TINY.replace("seeds = 1", "seeds = [1]"));
    assert_clean_failure(&run(&fewer, &out), "a study folder takes only changes that keep its finished runs");
    assert_eq!(finished_runs(&out), finished);
    // More seeds extend the study: only the new seed runs, and the report
    // covers both.
    let more = write("more.toml", &TINY.replace("seeds = 1", "seeds = 2"));
    let extended = run(&more, &out);
    assert!(extended.status.success() && stdout(&extended).contains("1 of 2 tasks finished before"), "{}", stdout(&extended));
    let both = finished_runs(&out);
    assert_eq!(both.len(), 2);
    assert!(finished.iter().all(|(run, file)| both.get(run) == Some(file)), "a finished run was touched");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("| global | 2 |"), "{report}");
    let finished = both;
    // The same file again (comments may change): everything is finished.
    let commented = write("tiny-commented.toml", &format!("# the same study\n{}", TINY.replace("seeds = 1", "seeds = 2")));
    let again = run(&commented, &out);
    assert!(again.status.success() && stdout(&again).contains("2 of 2 tasks finished before"), "{}", stdout(&again));
    assert_eq!(finished_runs(&out), finished);
    // A new connection adds cells: only their runs run, the old ones stay.
    let wider = write("tiny-wider.toml", &TINY.replace("seeds = 1", "seeds = 2").replace("[\"global\"]", "[\"global\", \"full-subnets\"]"));
    let widened = run(&wider, &out);
    assert!(widened.status.success() && stdout(&widened).contains("2 of 4 tasks finished before"), "{}", stdout(&widened));
    let all = finished_runs(&out);
    assert_eq!(all.len(), 4);
    assert!(finished.iter().all(|(run, file)| all.get(run) == Some(file)), "a finished run was touched");
    // Dropping a connection is another study.
    assert_clean_failure(&run(&commented, &out), "belongs to a different experiment");
    // A folder that holds something else is not taken over.
    assert_clean_failure(&run(&tiny, tmp.path()), "holds no experiment");
    assert_clean_failure(&lcrl().args(["experiment", "report"]).arg(tmp.path()).output().unwrap(), "holds no experiment");
}

#[test]
fn kubernetes_job_covers_every_task_and_its_commands_are_accepted() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("k8s");
    let paper = repo().join("experiments/paper.toml");
    let out = lcrl().args(["experiment", "k8s"]).arg(&paper).arg("--out").arg(&dir).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));

    let plan = lcrl().args(["experiment", "run"]).arg(&paper).args(["--out", "unused", "--dry-run"]).output().unwrap();
    let tasks = stdout(&plan).lines().count();
    assert_eq!(tasks, 2 * 2 * 2 * 5 + 2 + 2, "40 runs, 2 graphs, 2 best constants");

    let kustomization = &load_docs(&dir.join("kustomization.yaml"))[0];
    let generator = &seq(kustomization, "configMapGenerator")[0];
    let config_map = str_of(generator, &["name"]);
    let keys: Vec<&str> = seq(generator, "files").iter().map(|f| f.as_str().unwrap()).collect();
    for key in &keys {
        assert_eq!(std::fs::read(dir.join(key)).unwrap(), std::fs::read(&paper).unwrap(), "{key} is the experiment file");
    }
    let build_script = std::fs::read_to_string(repo().join("deploy/build-image.sh")).unwrap();
    let mut docs: Vec<serde_yaml::Value> = Vec::new();
    for resource in seq(kustomization, "resources") {
        docs.extend(load_docs(&dir.join(resource.as_str().unwrap())));
    }
    let report_docs = load_docs(&dir.join("report-job.yaml"));
    let claims: Vec<&str> = docs.iter().filter(|d| d["kind"].as_str() == Some("PersistentVolumeClaim")).map(|d| str_of(d, &["metadata", "name"])).collect();
    let jobs: Vec<&serde_yaml::Value> = docs.iter().chain(&report_docs).filter(|d| d["kind"].as_str() == Some("Job")).collect();
    assert_eq!(jobs.len(), 2, "the Indexed Job and the report Job");
    let data = tmp.path().join("data");
    for job in jobs {
        let name = str_of(job, &["metadata", "name"]);
        let pod = &job["spec"]["template"]["spec"];
        let volumes: BTreeMap<&str, &serde_yaml::Value> = seq(pod, "volumes").into_iter().map(|v| (str_of(v, &["name"]), v)).collect();
        for volume in volumes.values() {
            if let Some(cm) = volume["configMap"]["name"].as_str() {
                assert_eq!(cm, config_map, "{name}: ConfigMap");
            }
            if let Some(claim) = volume["persistentVolumeClaim"]["claimName"].as_str() {
                assert!(claims.contains(&claim), "{name}: claim {claim} is not declared");
            }
        }
        let container = seq(pod, "containers")[0];
        let image = str_of(container, &["image"]);
        assert!(build_script.contains(&format!("tag=\"${{1:-{image}}}\"")), "{name}: image {image} is not the one build-image.sh builds");
        // Mount paths, to map the pod's paths onto this machine's.
        let mut mounts: BTreeMap<String, PathBuf> = BTreeMap::new();
        for mount in seq(container, "volumeMounts") {
            let volume = volumes.get(str_of(mount, &["name"])).unwrap_or_else(|| panic!("{name}: mounts an undeclared volume"));
            let local = if volume["configMap"].is_mapping() { dir.clone() } else { data.clone() };
            mounts.insert(str_of(mount, &["mountPath"]).to_string(), local);
        }
        let args: Vec<String> = seq(container, "args")
            .iter()
            .map(|a| {
                let a = a.as_str().unwrap();
                mounts.iter().find_map(|(path, local)| a.strip_prefix(path.as_str()).map(|rest| format!("{}{rest}", local.display()))).unwrap_or(a.to_string())
            })
            .collect();
        if job["spec"]["completionMode"].as_str() == Some("Indexed") {
            assert_eq!(job["spec"]["completions"].as_u64(), Some(tasks as u64), "{name}: one index per task");
            let file = PathBuf::from(&args[2]);
            assert!(keys.contains(&file.file_name().unwrap().to_str().unwrap()), "{name}: reads {} which the ConfigMap lacks", file.display());
            // Kubernetes gives each pod its index in JOB_COMPLETION_INDEX.
            let last = lcrl().args(&args).arg("--dry-run").env("JOB_COMPLETION_INDEX", (tasks - 1).to_string()).output().unwrap();
            assert!(last.status.success(), "{}", stderr(&last));
            assert!(stdout(&last).starts_with("lcrl tune --env peg-group2"), "{}", stdout(&last));
            let local_run = lcrl().args(&args).args(["--dry-run", "--index", "2"]).output().unwrap();
            let commands = stdout(&local_run);
            assert!(commands.lines().next().unwrap().starts_with("lcrl graph --env peg-group1") && commands.contains("lcrl train --env peg-group1"), "a local run builds its graph first if needed: {commands}");
            let beyond = lcrl().args(&args).args(["--dry-run", "--index", &tasks.to_string()]).output().unwrap();
            assert_clean_failure(&beyond, "out of range");
        } else {
            assert_eq!(&args[..2], ["experiment", "report"]);
            // Before the study has run, the report Job's command is refused clearly.
            assert_clean_failure(&lcrl().args(&args).output().unwrap(), "holds no experiment");
        }
    }
}

/// `--env` runs a study on another environment (its named contrast then
/// stratifies over that one), and every random-rows run records its draw:
/// index, draw seed and graph file in config.toml and summary.json, and
/// the report names each run's draw.
#[test]
fn a_study_moves_to_another_environment_and_random_rows_record_their_draw() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("rows.toml");
    let study = TINY.replace("[\"global\"]", "[\"local@0.5\", \"random-rows@local@0.5+draws=2\"]").replace("seeds = 1", "seeds = 2")
        + "[graph]\nsamples = 8\n[primary]\nmetric = \"eval_return\"\na = \"local@0.5\"\nb = \"random-rows@local@0.5+draws=2\"\nalgorithm = \"ppo\"\nenvironments = [\"lti-paper\"]\n";
    std::fs::write(&file, study).unwrap();
    let out = tmp.path().join("out");
    let run = |env: &str| lcrl().args(["experiment", "run"]).arg(&file).arg("--out").arg(&out).args(["--env", env]).output().unwrap();
    assert_clean_failure(&run("no-such-env"), "no-such-env");
    let done = run("lti-blocks-4");
    assert!(done.status.success(), "{}", stderr(&done));
    let recorded = std::fs::read_to_string(out.join("experiment.toml")).unwrap();
    assert!(recorded.contains("on --env lti-blocks-4") && recorded.contains("\"lti-blocks-4\""), "{recorded}");
    let seed1 = out.join("runs/lti-blocks-4/ppo/random-rows@local@0.5+draws=2/seed1");
    let summary: Value = serde_json::from_str(&std::fs::read_to_string(seed1.join("summary.json")).unwrap()).unwrap();
    let origin = summary["graph"]["origin"].as_str().unwrap_or_default().to_string();
    let seed = lcrl_graph_builder::given::draw_seed("lti-blocks-4", 1);
    assert!(origin.starts_with(&format!("draw 1, random rows of degrees")) && origin.contains(&format!("draw seed {seed}")), "{origin}");
    assert!(summary["graph"]["file"].as_str().unwrap_or_default().ends_with("random-rows@T0.5/draw1/graph.json"), "{summary}");
    let config = std::fs::read_to_string(seed1.join("config.toml")).unwrap();
    assert!(config.contains(&format!("# graph origin: {origin}")), "{config}");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains(&format!("1 (draw 1, draw seed {seed}): ")), "{report}");
    assert!(report.contains("stratified by environment over lti-blocks-4"), "{report}");
}

/// Every path README.md and docs/ cite exists (scripts/check_paths.py):
/// studies moved to experiments/research/ left no link behind.
#[test]
fn every_path_the_pages_cite_exists() {
    let root = repo();
    let out = std::process::Command::new("python3").arg(root.join("scripts/check_paths.py")).current_dir(&root).output().unwrap();
    assert!(out.status.success(), "{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
}

/// No function a newcomer must scroll (scripts/long_functions.py): every
/// non-test function is at most 80 lines and takes at most 6 arguments,
/// or says why in a `// long:` or `// args:` comment above it.
#[test]
fn no_function_is_long_without_a_reason() {
    let root = repo();
    let out = std::process::Command::new("python3").arg(root.join("scripts/long_functions.py")).current_dir(&root).output().unwrap();
    assert!(out.status.success(), "{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
}
