//! `lcrl experiment`: the publication's evaluation as one command. Many
//! seeds of LCRL against GCRL (and the full-subnets ablation), statistics
//! with confidence intervals, the publication's figures; on every core of
//! one machine (`run`) or as a Kubernetes Indexed Job (`k8s`).

mod against;
mod bars;
mod companion;
mod config;
mod draws;
mod figures;
mod k8s;
mod plan;
mod hypotheses;
mod inference;
mod named;
mod primary;
mod report;
mod runner;
mod safety;
mod speed;
mod study;
pub mod stats;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context};

use config::Experiment;
use plan::Task;

#[derive(Debug, clap::Subcommand)]
pub enum ExperimentCommand {
    /// Run a study: every (environment, algorithm, connection, seed) as a
    /// child `lcrl train`, N at a time, then write its report. Run the same
    /// command again to resume: finished runs are skipped, interrupted ones
    /// continue from their newest checkpoint.
    Run(RunArgs),
    /// Write report.json, report.md, curves.png and traces.png from the
    /// finished runs of a study.
    Report(ReportArgs),
    /// Write the study as a Kubernetes Indexed Job (one index per task) on a
    /// shared volume.
    K8s(K8sArgs),
    /// Run one task of a study by its index: what each pod of the
    /// Kubernetes Job runs.
    Task(TaskArgs),
}

#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// The experiment file (e.g. experiments/paper.toml).
    pub file: PathBuf,
    /// Output directory; one per experiment file.
    #[arg(long)]
    pub out: PathBuf,
    /// Runs at a time, each with one libtorch thread [default: the number of cores].
    #[arg(long)]
    pub jobs: Option<usize>,
    /// Run only the cells whose label ENV/ALGO/CONNECTION matches this
    /// pattern (`*` any text, `?` one character), with the graphs and best
    /// constants they need; repeat for several patterns. For running a
    /// study in parts, cheap cells first or on several machines sharing the
    /// folder: e.g. --only 'peg-group*/ppo/*' --only '*/ddpg/global'. The
    /// report always covers the whole study, listing what has not run.
    #[arg(long, value_name = "PATTERN")]
    pub only: Vec<String>,
    /// List the tasks and their commands; run nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Run the study on this environment in place of the file's (a
    /// registered name, a TOML file or grpc://HOST:PORT; repeat for
    /// several): the same cells, seeds and named contrasts, stratified over
    /// these. E.g. experiments/local-vs-global.toml --env my-task.toml asks
    /// whether LCRL pays on your task.
    #[arg(long = "env", value_name = "ENV")]
    pub environments: Vec<String>,
}

#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// The --out directory of `lcrl experiment run`.
    pub dir: PathBuf,
    /// Also compare every cell seed for seed with the same environment and
    /// algorithm in another finished study (its --out directory), and write
    /// DIR/against-NAME.json and .md (NAME: that study's name). Made for
    /// the base held still under the learner's own exploration
    /// (experiments/research/peg-group2-bar-base-exploring.toml): a run passes a seed
    /// when no training episode failed and its worst 10-episode mean is no
    /// lower than the reference's on that seed minus --margin. Against a
    /// study with one setting changed, the same tables are a paired
    /// comparison. See docs/experiment.md, "Against a reference study".
    #[arg(long, value_name = "REF_DIR", conflicts_with = "with")]
    pub against: Option<PathBuf>,
    /// A companion study (its --out directory; repeat for more): one of
    /// the same design with one setting changed, such as the global
    /// actor's learning rate. Its cells join this report as
    /// `CONNECTION [NAME]`, compared with this study's cell of the same
    /// connection and by the usual rules, in the report's one Holm family,
    /// and drawn in advantage.png. The report written without --with
    /// leaves them out again. See docs/experiment.md, "Companion studies".
    #[arg(long = "with", value_name = "DIR")]
    pub with: Vec<PathBuf>,
    /// How far below the reference's worst 10-episode mean a run's may fall
    /// and still pass (return units). The default, 1.0, is two standard
    /// deviations of the exploring base's own worst windows over seeds on
    /// peg-group2 (the twelfth round,
    /// docs/research/2026-11-27-peg-safety-12-exploring-base-bar.md).
    #[arg(long, default_value_t = 1.0, requires = "against")]
    pub margin: f64,
}

#[derive(Debug, clap::Args)]
pub struct K8sArgs {
    pub file: PathBuf,
    /// Directory for kustomization.yaml, job.yaml and report-job.yaml.
    #[arg(long)]
    pub out: PathBuf,
    /// Pods at a time (each asks for one core).
    #[arg(long, default_value_t = 16)]
    pub parallelism: usize,
    /// The image (built by deploy/build-image.sh).
    #[arg(long, default_value = "lcrl:local")]
    pub image: String,
    /// Size of the shared ReadWriteMany volume claim.
    #[arg(long, default_value = "20Gi")]
    pub storage: String,
}

#[derive(Debug, clap::Args)]
pub struct TaskArgs {
    pub file: PathBuf,
    /// Output directory shared by all tasks of the study.
    #[arg(long)]
    pub out: PathBuf,
    /// Task index [default: $JOB_COMPLETION_INDEX, which Kubernetes sets in
    /// an Indexed Job].
    #[arg(long)]
    pub index: Option<usize>,
    /// Print the command(s) the task runs; run nothing.
    #[arg(long)]
    pub dry_run: bool,
}

pub fn run(command: &ExperimentCommand) -> anyhow::Result<()> {
    match command {
        ExperimentCommand::Run(args) => run_study(args),
        ExperimentCommand::Report(args) => {
            let e = plan::recorded_experiment(&args.dir)?;
            let study = write_report(&e, &args.dir, &args.with)?;
            match &args.against {
                Some(reference) => write_against(&study, &args.dir, reference, args.margin),
                None => Ok(()),
            }
        }
        ExperimentCommand::K8s(args) => write_k8s(args),
        ExperimentCommand::Task(args) => run_task(args),
    }
}

fn run_study(args: &RunArgs) -> anyhow::Result<()> {
    let e = Experiment::load_on(&args.file, &args.environments)?;
    let jobs = args.jobs.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    if jobs == 0 {
        bail!("--jobs must be at least 1");
    }
    let tasks = plan::only(&e, plan::tasks(&e), &args.only)?;
    if args.dry_run {
        for (i, task) in tasks.iter().enumerate() {
            println!("{i:>4} {:<48} lcrl {}", task.id(), task.args(&e, &args.out).join(" "));
        }
        return Ok(());
    }
    plan::prepare_out(&e, &args.file, &args.out, false)?;
    if !args.environments.is_empty() {
        // The study as run, not the file as written: its environments moved.
        let text = format!("# {} on --env {}\n{}", args.file.display(), args.environments.join(", "), toml::to_string(&e.file)?);
        crate::output::write_atomic(&args.out.join("experiment.toml"), &text)?;
    }
    // One study per directory at a time; the lock goes with the process.
    let lock_path = args.out.join(".lock");
    let lock = std::fs::File::create(&lock_path).with_context(|| format!("creating {}", lock_path.display()))?;
    if lock.try_lock().is_err() {
        bail!("another `lcrl experiment run` is working in {}; wait for it or stop it first", args.out.display());
    }
    let runs = tasks.iter().filter(|t| matches!(t, Task::Train { .. })).count();
    println!("experiment {}: {} tasks ({runs} training runs) in {}, {jobs} at a time", e.file.name, tasks.len(), args.out.display());
    let outcome = runner::run_tasks(&e, &tasks, &args.out, jobs)?;
    println!(
        "{} tasks finished now, {} before, {} failed, {} not started (their graph failed); wall time {:.1} s",
        outcome.completed,
        outcome.skipped,
        outcome.failed.len(),
        outcome.blocked,
        outcome.wall_seconds
    );
    write_report(&e, &args.out, &[])?;
    if !outcome.failed.is_empty() {
        let list: Vec<String> = outcome.failed.iter().map(|(id, log)| format!("  {id}: {}", log.display())).collect();
        bail!(
            "{} task(s) failed (logs below); the report covers the finished runs. Fix the cause and run the same command again to retry only those:\n{}",
            outcome.failed.len(),
            list.join("\n")
        );
    }
    Ok(())
}

/// Writes the report and figures, with the cells of the companion studies
/// in `with`; returns the study they were drawn from.
fn write_report(e: &Experiment, out: &Path, with: &[PathBuf]) -> anyhow::Result<report::Study> {
    let mut study = report::gather(e, out)?;
    for dir in with {
        let companion = plan::recorded_experiment(dir).with_context(|| format!("the --with study {}", dir.display()))?;
        companion::join(&mut study, report::gather(&companion, dir)?, dir)?;
    }
    let report = study.report();
    report::write(&report, out)?;
    figures::curves(&study, &out.join("curves.png"))?;
    figures::traces(&study, &out.join("traces.png"))?;
    let advantage = figures::advantage(&study, &out.join("advantage.png"))?;
    print!("{}", report::markdown(&report));
    println!("wrote {}/report.json, report.md, curves.png, traces.png{}", out.display(), if advantage { ", advantage.png" } else { "" });
    Ok(study)
}

/// against-NAME.json and .md: the study seed for seed against a reference study.
fn write_against(study: &report::Study, out: &Path, reference_dir: &Path, margin: f64) -> anyhow::Result<()> {
    let reference = plan::recorded_experiment(reference_dir).context("the --against study")?;
    let against = against::compare(study, &report::gather(&reference, reference_dir)?, reference_dir, margin)?;
    let stem = format!("against-{}", config::env_slug(&reference.file.name));
    crate::output::write_atomic(&out.join(format!("{stem}.json")), &(serde_json::to_string_pretty(&against)? + "\n"))?;
    let md = against::markdown(&against);
    crate::output::write_atomic(&out.join(format!("{stem}.md")), &md)?;
    print!("{md}");
    println!("wrote {}/{stem}.json, {stem}.md", out.display());
    Ok(())
}

fn write_k8s(args: &K8sArgs) -> anyhow::Result<()> {
    let e = Experiment::load(&args.file)?;
    if args.parallelism == 0 {
        bail!("--parallelism must be at least 1");
    }
    let tasks = plan::tasks(&e);
    let opts = k8s::K8sOptions { parallelism: args.parallelism, image: args.image.clone(), storage: args.storage.clone() };
    k8s::write(&e, &args.file, &tasks, &args.out, &opts)?;
    println!("wrote {}: an Indexed Job of {} tasks, {} pods at a time, results in {} on claim lcrl-experiments", args.out.display(), tasks.len(), args.parallelism, k8s::out_in_pod(&e));
    println!("  kubectl apply -k {}", args.out.display());
    println!("  kubectl wait --for=condition=complete --timeout=48h job/lcrl-experiment-{}", e.file.name);
    println!("  kubectl apply -f {}", args.out.join("report-job.yaml").display());
    Ok(())
}

/// One task, with the graph it needs built first if no other pod has.
fn run_task(args: &TaskArgs) -> anyhow::Result<()> {
    let e = Experiment::load(&args.file)?;
    let tasks = plan::tasks(&e);
    let index = match args.index {
        Some(i) => i,
        None => std::env::var("JOB_COMPLETION_INDEX")
            .context("give --index, or set JOB_COMPLETION_INDEX (Kubernetes does in an Indexed Job)")?
            .parse()
            .context("JOB_COMPLETION_INDEX is not a number")?,
    };
    let Some(task) = tasks.get(index) else {
        bail!("task index {index} is out of range: experiment {} has {} tasks (0–{})", e.file.name, tasks.len(), tasks.len() - 1);
    };
    // The task after what it needs, and what that needs (a random-rows
    // draw needs its measured graph), first things first.
    let mut steps: Vec<Task> = vec![task.clone()];
    while let Some(before) = steps.first().and_then(Task::dependency) {
        steps.insert(0, before);
    }
    if args.dry_run {
        for t in &steps {
            println!("lcrl {}", t.args(&e, &args.out).join(" "));
        }
        return Ok(());
    }
    plan::prepare_out(&e, &args.file, &args.out, true)?;
    let exe = std::env::current_exe().context("cannot find the lcrl executable")?;
    for t in steps.iter().filter(|t| !t.is_done(&args.out)) {
        println!("task {index}: {}", t.id());
        let dir = t.output_dir(&args.out);
        std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let mut command = Command::new(&exe);
        command.args(t.args(&e, &args.out)).stdin(Stdio::null());
        crate::supervise::die_with_parent(&mut command);
        let status = command.status().with_context(|| format!("starting {}", t.id()))?;
        if !status.success() {
            bail!("{} failed ({status})", t.id());
        }
    }
    Ok(())
}
