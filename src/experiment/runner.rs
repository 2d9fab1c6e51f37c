//! Runs a study's tasks on this machine: child `lcrl` processes, N at a
//! time, each with one libtorch thread; finished tasks are skipped, so the
//! same command resumes a study after Ctrl-C, a crash or SIGKILL.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::Context;
use indicatif::ProgressBar;

use super::config::Experiment;
use super::plan::{run_dir, Task};

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    Waiting,
    Running,
    Done,
    Failed,
    /// Not started: the task it needs failed.
    Blocked,
}

/// What a local run did.
#[derive(Debug, Default)]
pub struct Outcome {
    /// Tasks found finished by an earlier invocation.
    pub skipped: usize,
    pub completed: usize,
    /// (task id, log file) of each failure.
    pub failed: Vec<(String, PathBuf)>,
    pub blocked: usize,
    pub wall_seconds: f64,
}

/// Progress units per task; a training run adds its finished episodes'
/// share while it runs.
const UNITS: u64 = 1000;

/// Runs every unfinished task, `jobs` at a time.
pub fn run_tasks(e: &Experiment, tasks: &[Task], out: &Path, jobs: usize) -> anyhow::Result<Outcome> {
    let started = Instant::now();
    let exe = std::env::current_exe().context("cannot find the lcrl executable to start runs with")?;
    let logs = out.join("logs");
    std::fs::create_dir_all(&logs).with_context(|| format!("cannot create {}", logs.display()))?;
    let mut state: Vec<State> = tasks.iter().map(|t| if t.is_done(out) { State::Done } else { State::Waiting }).collect();
    let mut outcome = Outcome { skipped: state.iter().filter(|s| **s == State::Done).count(), ..Outcome::default() };
    let index_of: BTreeMap<String, usize> = tasks.iter().enumerate().map(|(i, t)| (t.id(), i)).collect();
    let dependency: Vec<Option<usize>> = tasks.iter().map(|t| t.dependency().and_then(|d| index_of.get(&d.id()).copied())).collect();

    let bar = lcrl_graph_builder::progress::bar(tasks.len() as u64 * UNITS, "study [{bar:30}] {percent:>3}% {msg} ({elapsed}, eta {eta})");
    if outcome.skipped > 0 {
        say(&bar, format!("{} of {} tasks finished before; continuing the rest", outcome.skipped, tasks.len()));
    }
    let (finished_tx, finished_rx) = mpsc::channel::<(usize, std::io::Result<ExitStatus>)>();
    let mut running: BTreeMap<usize, Instant> = BTreeMap::new();
    loop {
        // Start what can start, in plan order.
        for i in 0..tasks.len() {
            if running.len() >= jobs {
                break;
            }
            if state[i] != State::Waiting {
                continue;
            }
            match dependency[i].map(|d| state[d]) {
                Some(State::Failed | State::Blocked) => {
                    state[i] = State::Blocked;
                    outcome.blocked += 1;
                    continue;
                }
                Some(State::Waiting | State::Running) => continue,
                _ => {}
            }
            let log = logs.join(format!("{}.log", tasks[i].id()));
            let dir = tasks[i].output_dir(out);
            std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
            let child = spawn(&exe, &tasks[i].args(e, out), &log).with_context(|| format!("starting {}", tasks[i].id()))?;
            state[i] = State::Running;
            running.insert(i, Instant::now());
            wait_in_thread(i, child, finished_tx.clone());
        }
        bar.set_message(format!("{} done, {} running, {} left", count(&state, State::Done), running.len(), count(&state, State::Waiting)));
        if running.is_empty() {
            break;
        }
        // Wake on a finished child, or each second to show the running
        // runs' episodes.
        match finished_rx.recv_timeout(Duration::from_secs(1)) {
            Ok((i, status)) => {
                let seconds = running.remove(&i).map_or(0.0, |t| t.elapsed().as_secs_f64());
                let log = logs.join(format!("{}.log", tasks[i].id()));
                match status {
                    Ok(status) if status.success() && tasks[i].is_done(out) => {
                        state[i] = State::Done;
                        outcome.completed += 1;
                        say(&bar, format!("finished {} ({seconds:.1} s)", tasks[i].id()));
                    }
                    result => {
                        state[i] = State::Failed;
                        let why = failure(result);
                        say(&bar, format!("FAILED {} ({why}); its log: {}\n{}", tasks[i].id(), log.display(), tail(&log, 5)));
                        outcome.failed.push((tasks[i].id(), log));
                    }
                }
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        }
        let settled = count(&state, State::Done) + count(&state, State::Failed) + count(&state, State::Blocked);
        let done_units = settled as u64 * UNITS;
        let partial: u64 = running.keys().map(|&i| running_fraction(e, &tasks[i], out)).sum();
        bar.set_position(done_units + partial);
    }
    bar.finish_and_clear();
    outcome.wall_seconds = started.elapsed().as_secs_f64();
    Ok(outcome)
}

/// Waits for task `i`'s child on a thread of its own, and sends its exit
/// to `finished`.
fn wait_in_thread(i: usize, mut child: Child, finished: mpsc::Sender<(usize, std::io::Result<ExitStatus>)>) {
    std::thread::spawn(move || {
        let _ = finished.send((i, child.wait()));
    });
}

/// Why a task that ended failed: its exit status, or that it exited
/// successfully without its result.
fn failure(result: std::io::Result<ExitStatus>) -> String {
    match result {
        Ok(status) if status.success() => "exited without its result".to_string(),
        Ok(status) => status.to_string(),
        Err(e) => e.to_string(),
    }
}

fn count(state: &[State], which: State) -> usize {
    state.iter().filter(|s| **s == which).count()
}

/// A running training run's finished share, in progress units.
fn running_fraction(e: &Experiment, task: &Task, out: &Path) -> u64 {
    let Task::Train { cell, seed } = task else { return 0 };
    let rows = std::fs::read_to_string(run_dir(out, cell, *seed).join("metrics.csv")).map_or(0, |t| t.lines().count().saturating_sub(1));
    (rows as u64 * UNITS / e.episodes(cell.algo).max(1) as u64).min(UNITS - 1)
}

/// Starts `lcrl ARGS` with its output appended to `log`. The child dies
/// with this process (Linux: PR_SET_PDEATHSIG), so a killed study leaves no
/// run behind that a resumed one would race with.
pub fn spawn(exe: &Path, args: &[String], log: &Path) -> anyhow::Result<Child> {
    let file = std::fs::OpenOptions::new().create(true).append(true).open(log).with_context(|| format!("opening {}", log.display()))?;
    let mut command = Command::new(exe);
    command.args(args).stdin(Stdio::null()).stdout(file.try_clone()?).stderr(file);
    crate::supervise::die_with_parent(&mut command);
    Ok(command.spawn()?)
}

/// The last `n` lines of a log, indented.
fn tail(path: &Path, n: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    lines[lines.len().saturating_sub(n)..].iter().map(|l| format!("    {l}")).collect::<Vec<_>>().join("\n")
}

/// A line above the progress bar (printed even when the bar is hidden,
/// e.g. with output to a file).
fn say(bar: &ProgressBar, line: String) {
    bar.suspend(|| println!("{line}"));
}
