//! What a study runs: its tasks (best constants, graphs, training runs),
//! where each writes, the `lcrl` command line of each, and when one counts
//! as finished. The local scheduler and the Kubernetes Indexed Job both
//! run these tasks, so a study means the same work everywhere.
//!
//! Layout of the output directory:
//!   experiment.toml, experiment.json   the file as given, and as parsed
//!   configs/ENV.toml                   training settings of ENV's runs
//!   best_constant/ENV/best_constant.json
//!   graphs/ENV/T0.1/graph.json         one graph per (ENV, T), shared by seeds
//!   graphs/ENV/T1+dz=0.1/seed3/graph.json   a run's own graph (+per-seed),
//!                                      with a row rule (crate::connection)
//!   runs/ENV/ALGO/CONNECTION/seedK/    `lcrl train` run directories
//!   logs/TASK.log                      each task's output
//!   report.json, report.md, curves.png, traces.png

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use lcrl_learner::run::summary::RunSummary;
use lcrl_learner::Algo;

use super::config::{algo_name, env_slug, ConnectionSpec, Experiment};
use crate::connection::MadeGraph;
use crate::output::write_atomic;

/// One (environment, algorithm, connection): a row of the report.
#[derive(Debug, Clone, PartialEq)]
pub struct Cell {
    pub env: String,
    pub algo: Algo,
    pub connection: ConnectionSpec,
}

impl Cell {
    pub fn label(&self) -> String {
        format!("{}/{}/{}", self.env, algo_name(self.algo), self.connection.label())
    }
}

#[derive(Debug, Clone, PartialEq)]
pub enum Task {
    /// `lcrl tune`: the best constant action of an environment.
    Tune { env: String },
    /// `lcrl graph`: CS3 at a threshold (with any row rules) or a random
    /// draw; with the study's [graph] seed, shared by every seed of its
    /// cells (seed None), or with one run's seed (`+per-seed`).
    Graph { env: String, made: MadeGraph, seed: Option<u64> },
    /// `lcrl train` of one cell with one seed.
    Train { cell: Cell, seed: u64 },
}

/// All tasks of a study, in the order they start: graphs first (training
/// runs wait for them), then runs seed by seed (so an interrupted study
/// has whole seeds of every cell), best constants last.
pub fn tasks(e: &Experiment) -> Vec<Task> {
    let mut tasks = Vec::new();
    for env in &e.file.environments {
        for connection in &e.connections {
            let Some((made, per_seed)) = connection.made_graph() else { continue };
            // Random rows are drawn from a measured graph: that one first.
            if let Some(source) = made.source() {
                let task = Task::Graph { env: env.clone(), made: source, seed: None };
                if !tasks.contains(&task) {
                    tasks.push(task);
                }
            }
            let seeds: Vec<Option<u64>> = if per_seed {
                e.seeds_for(connection).into_iter().map(|s| Some(connection.draw_of(s).unwrap_or(s))).collect()
            } else {
                vec![None]
            };
            for seed in seeds {
                let task = Task::Graph { env: env.clone(), made: made.clone(), seed };
                if !tasks.contains(&task) {
                    tasks.push(task);
                }
            }
        }
    }
    for &seed in &e.seeds {
        for cell in cells(e).into_iter().filter(|c| e.seeds_for(&c.connection).contains(&seed)) {
            tasks.push(Task::Train { cell, seed });
        }
    }
    if e.file.best_constant.enabled {
        tasks.extend(e.file.environments.iter().map(|env| Task::Tune { env: env.clone() }));
    }
    tasks
}

/// The tasks of the cells whose label matches one of `patterns` (glob
/// syntax, e.g. `peg-group*/ppo/*`), with the graphs those runs need and
/// the best constants of their environments; all tasks when there are no
/// patterns. A pattern that matches no cell is an error (a typo would
/// otherwise run nothing).
pub fn only(e: &Experiment, tasks: Vec<Task>, patterns: &[String]) -> anyhow::Result<Vec<Task>> {
    if patterns.is_empty() {
        return Ok(tasks);
    }
    let labels: Vec<String> = cells(e).iter().map(Cell::label).collect();
    let mut globs = Vec::new();
    for text in patterns {
        let pattern = glob::Pattern::new(text).with_context(|| format!("--only \"{text}\" is not a pattern"))?;
        if !labels.iter().any(|l| pattern.matches(l)) {
            bail!("--only \"{text}\" matches no cell of experiment {}; its cells are: {}", e.file.name, labels.join(", "));
        }
        globs.push(pattern);
    }
    let chosen: Vec<Cell> = cells(e).into_iter().filter(|c| globs.iter().any(|g| g.matches(&c.label()))).collect();
    // What the chosen runs need, and what that needs (a random-rows draw
    // needs its measured graph).
    let mut needed: Vec<Task> = tasks.iter().filter(|t| matches!(t, Task::Train { cell, .. } if chosen.contains(cell))).filter_map(Task::dependency).collect();
    while let Some(more) = needed.iter().filter_map(Task::dependency).find(|d| !needed.contains(d)) {
        needed.push(more);
    }
    Ok(tasks
        .into_iter()
        .filter(|t| match t {
            Task::Train { cell, .. } => chosen.contains(cell),
            Task::Graph { .. } => needed.contains(t),
            Task::Tune { env } => chosen.iter().any(|c| &c.env == env),
        })
        .collect())
}

/// Every cell, environment by environment, algorithm by algorithm.
pub fn cells(e: &Experiment) -> Vec<Cell> {
    let mut cells = Vec::new();
    for env in &e.file.environments {
        for &algo in &e.file.algorithms {
            for connection in &e.connections {
                cells.push(Cell { env: env.clone(), algo, connection: connection.clone() });
            }
        }
    }
    cells
}

pub fn config_path(out: &Path, env: &str) -> PathBuf {
    out.join("configs").join(format!("{}.toml", env_slug(env)))
}

pub fn best_constant_path(out: &Path, env: &str) -> PathBuf {
    out.join("best_constant").join(env_slug(env)).join("best_constant.json")
}

/// graphs/ENV/FOLDER/graph.json, or graphs/ENV/FOLDER/seedK/graph.json
/// for one run's own graph.
pub fn graph_path(out: &Path, env: &str, made: &MadeGraph, seed: Option<u64>) -> PathBuf {
    let dir = out.join("graphs").join(env_slug(env)).join(made.folder());
    match seed {
        Some(seed) => dir.join(made.instance(seed)),
        None => dir,
    }
    .join("graph.json")
}

/// The graph task a cell's run with `seed` needs, if the study makes one.
pub fn graph_task(cell: &Cell, seed: u64) -> Option<Task> {
    let (made, per_seed) = cell.connection.made_graph()?;
    let instance = cell.connection.draw_of(seed).unwrap_or(seed);
    Some(Task::Graph { env: cell.env.clone(), made, seed: per_seed.then_some(instance) })
}

/// The graph file a cell's run with `seed` trains with, if it has one.
pub fn cell_graph(out: &Path, cell: &Cell, seed: u64) -> Option<PathBuf> {
    match (cell.connection.graph_file(), graph_task(cell, seed)) {
        (Some(path), _) => Some(path.to_path_buf()),
        (_, Some(Task::Graph { env, made, seed })) => Some(graph_path(out, &env, &made, seed)),
        _ => None,
    }
}

pub fn run_dir(out: &Path, cell: &Cell, seed: u64) -> PathBuf {
    out.join("runs").join(env_slug(&cell.env)).join(algo_name(cell.algo)).join(cell.connection.slug()).join(format!("seed{seed}"))
}

/// A finished run's summary, if it has one that parses.
pub fn finished_run(dir: &Path) -> Option<RunSummary> {
    let text = std::fs::read_to_string(dir.join("summary.json")).ok()?;
    serde_json::from_str(&text).ok()
}

impl Task {
    /// A name for progress lines and log files.
    pub fn id(&self) -> String {
        match self {
            Task::Tune { env } => format!("tune-{}", env_slug(env)),
            Task::Graph { env, made, seed } => {
                format!("graph-{}-{}{}", env_slug(env), made.folder(), seed.map(|s| format!("-{}", made.instance(s))).unwrap_or_default())
            }
            Task::Train { cell, seed } => {
                format!("train-{}-{}-{}-seed{seed}", env_slug(&cell.env), algo_name(cell.algo), cell.connection.slug())
            }
        }
    }

    /// The task this one needs finished first.
    pub fn dependency(&self) -> Option<Task> {
        match self {
            Task::Train { cell, seed } => graph_task(cell, *seed),
            Task::Graph { env, made, .. } => made.source().map(|source| Task::Graph { env: env.clone(), made: source, seed: None }),
            Task::Tune { .. } => None,
        }
    }

    /// Whether its result is on disk (then it is never run again).
    pub fn is_done(&self, out: &Path) -> bool {
        match self {
            Task::Tune { env } => best_constant_path(out, env).is_file(),
            Task::Graph { env, made, seed } => graph_path(out, env, made, *seed).is_file(),
            Task::Train { cell, seed } => finished_run(&run_dir(out, cell, *seed)).is_some(),
        }
    }

    /// The folder its result goes to (created before it starts).
    pub fn output_dir(&self, out: &Path) -> PathBuf {
        let file = match self {
            Task::Tune { env } => best_constant_path(out, env),
            Task::Graph { env, made, seed } => graph_path(out, env, made, *seed),
            Task::Train { cell, seed } => run_dir(out, cell, *seed).join("summary.json"),
        };
        file.parent().map(Path::to_path_buf).unwrap_or_else(|| out.to_path_buf())
    }

    /// The `lcrl` arguments that do it. Every output is written atomically
    /// by the command (complete or absent), and a training run always
    /// passes --resume: it continues from its newest checkpoint if an
    /// interrupted attempt left one, and starts afresh otherwise.
    pub fn args(&self, e: &Experiment, out: &Path) -> Vec<String> {
        let s = |p: &Path| p.display().to_string();
        match self {
            Task::Tune { env } => {
                let b = &e.file.best_constant;
                let dir = best_constant_path(out, env).parent().map(Path::to_path_buf).unwrap_or_default();
                vec![
                    "tune".into(), "--env".into(), env.clone(), "--out".into(), s(&dir),
                    "--evaluations".into(), b.evaluations.to_string(), "--episodes".into(), b.episodes.to_string(),
                    "--eval-episodes".into(), b.eval_episodes.to_string(),
                ]
            }
            Task::Graph { env, made, seed } => {
                let path = graph_path(out, env, made, *seed);
                let draw_seed = seed.unwrap_or(e.file.graph.seed).to_string();
                match made {
                    MadeGraph::Measured { threshold, rows } => {
                        let mut args = vec![
                            "graph".into(), "--env".into(), env.clone(), "--samples".into(), e.file.graph.samples.to_string(),
                            "--threshold".into(), threshold.to_string(), "--seed".into(), draw_seed,
                            "--threads".into(), "1".into(), "--out".into(), s(&path), "--plot".into(), s(&path.with_extension("png")),
                        ];
                        args.extend(rows.iter().flat_map(|r| ["--row".to_string(), r.text()]));
                        args
                    }
                    MadeGraph::Drawn { edges } => vec![
                        "graph".into(), "--env".into(), env.clone(), "--random".into(), edges.to_string(),
                        "--seed".into(), draw_seed, "--out".into(), s(&path),
                    ],
                    // Draw k of random rows: its seed from the environment
                    // and k (never a run's seed), its degrees from the
                    // measured graph.
                    MadeGraph::RowsDrawn { .. } => {
                        let source = made.source().map(|m| graph_path(out, env, &m, None)).unwrap_or_default();
                        let draw_seed = lcrl_graph_builder::given::draw_seed(env, seed.unwrap_or(0)).to_string();
                        vec![
                            "graph".into(), "--env".into(), env.clone(), "--random-rows".into(), s(&source),
                            "--seed".into(), draw_seed, "--draw".into(), seed.unwrap_or(0).to_string(), "--out".into(), s(&path),
                        ]
                    }
                }
            }
            Task::Train { cell, seed } => {
                let mut args = vec![
                    "train".into(), "--env".into(), cell.env.clone(), "--algo".into(), algo_name(cell.algo).into(),
                    "--connection".into(), crate::preset::connection_name(cell.connection.connection()).into(), "--episodes".into(), e.episodes(cell.algo).to_string(),
                    "--seed".into(), seed.to_string(), "--threads".into(), "1".into(), "--config".into(), s(&config_path(out, &cell.env)),
                    "--run-dir".into(), s(&run_dir(out, cell, *seed)), "--resume".into(),
                ];
                if let Some(graph) = cell_graph(out, cell, *seed) {
                    // A matched global sizes itself to the local actor of
                    // this graph; every other cell with a graph trains on it.
                    let flag = if matches!(cell.connection, ConnectionSpec::MatchedGlobal { .. }) { "--match-params" } else { "--graph" };
                    args.extend([flag.into(), s(&graph)]);
                }
                args
            }
        }
    }
}


/// Claims `out` for this experiment, or refuses if it holds another one,
/// and writes the files every task reads (experiment copy, configs).
/// Comments and layout of the file may change; its content may not.
/// `shared`: many pods prepare the same folder at once (Kubernetes), so a
/// folder with files but no experiment.json yet is not refused.
pub fn prepare_out(e: &Experiment, file: &Path, out: &Path, shared: bool) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create output directory {}", out.display()))?;
    let parsed = serde_json::to_string_pretty(&e.file)? + "\n";
    let recorded = out.join("experiment.json");
    match std::fs::read_to_string(&recorded) {
        Ok(existing) if existing != parsed && !extends(&existing, e) => {
            let other: Option<String> = serde_json::from_str::<serde_json::Value>(&existing).ok().and_then(|v| v["name"].as_str().map(String::from));
            bail!(
                "{} belongs to a different experiment ({}); {} describes another study. Nothing was changed: \
                 run it with another --out, or restore the file that made this directory to continue it \
                 (a study folder takes only changes that keep its finished runs' meaning: more seeds, a connection's own seeds growing, added connections, a primary contrast named where there was none)",
                out.display(),
                other.map_or("unreadable experiment.json".into(), |n| format!("\"{n}\", see {}", out.join("experiment.toml").display())),
                file.display()
            );
        }
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if !shared && std::fs::read_dir(out)?.next().is_some() {
                bail!("{} is not empty and holds no experiment; choose an empty or new --out", out.display());
            }
        }
        Err(e) => return Err(e).with_context(|| format!("reading {}", recorded.display())),
    }
    write_atomic(&recorded, &parsed)?;
    write_atomic(&out.join("experiment.toml"), &std::fs::read_to_string(file)?)?;
    for env in &e.file.environments {
        let config = e.train_config(env)?;
        let header = format!("# Training settings of every run on {env} in experiment \"{}\" (written by lcrl experiment).\n", e.file.name);
        write_atomic(&config_path(out, env), &(header + &toml::to_string_pretty(&config)?))?;
    }
    Ok(())
}

/// The experiment a directory was made for (experiment.json).
pub fn recorded_experiment(out: &Path) -> anyhow::Result<Experiment> {
    let path = out.join("experiment.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{} holds no experiment (no experiment.json); give the --out of `lcrl experiment run`", out.display()))?;
    let file = serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
    Experiment::check(file).with_context(|| format!("{}", path.display()))
}

/// Whether `e` continues the study recorded in `existing` (its
/// experiment.json): the same study once checked (deprecated names
/// renamed), or the same study widened: more seeds, more connections (new
/// cells), or a primary contrast named where it had none (before the runs
/// of the cells it adds). Each leaves every finished run what it was, so
/// the folder takes them (the report then covers them all); any other
/// change would mix two studies in one report. A connection's own seeds
/// (`[seeds_of]`) may grow the same way.
fn extends(existing: &str, e: &Experiment) -> bool {
    let Some(old) = serde_json::from_str(existing).ok().and_then(|file| Experiment::check(file).ok()) else { return false };
    let mut widened = old.file.clone();
    widened.seeds = e.file.seeds.clone();
    widened.seeds_of = e.file.seeds_of.clone();
    widened.connections = e.file.connections.clone();
    if widened.primary.is_none() {
        widened.primary = e.file.primary.clone();
    }
    widened == e.file
        && old.connections.iter().all(|c| e.connections.contains(c) && old.seeds_for(c).iter().all(|seed| e.seeds_for(c).contains(seed)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tasks_of(e: &Experiment) -> Vec<String> {
        tasks(e).iter().map(Task::id).collect()
    }

    #[test]
    fn graphs_come_first_and_local_runs_use_them() {
        let text = "name = \"t\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"local@0.1\", \"global\"]\nseeds = [3, 5]\nepisodes = { ppo = 7 }\n";
        let e = Experiment::parse(text).unwrap();
        let tasks = tasks(&e);
        let ids: Vec<String> = tasks.iter().map(Task::id).collect();
        assert_eq!(
            ids,
            [
                "graph-lti-paper-T0.1",
                "train-lti-paper-ppo-local@0.1-seed3",
                "train-lti-paper-ppo-global-seed3",
                "train-lti-paper-ppo-local@0.1-seed5",
                "train-lti-paper-ppo-global-seed5",
                "tune-lti-paper"
            ]
        );
        let out = Path::new("/study");
        let local = tasks[1].args(&e, out).join(" ");
        assert!(local.contains("--graph /study/graphs/lti-paper/T0.1/graph.json") && local.contains("--resume"), "{local}");
        assert!(local.contains("--episodes 7 --seed 3 --threads 1"), "{local}");
        assert_eq!(tasks[1].dependency(), Some(tasks[0].clone()));
        assert!(!tasks[2].args(&e, out).contains(&"--graph".to_string()));
        assert_eq!(tasks[2].dependency(), None);
    }

    /// random-rows: the measured graph first, then one draw task per draw
    /// index (seed mod draws) seeded by environment and draw, never by the
    /// run; each run trains on its draw; --only keeps the whole chain.
    #[test]
    fn random_rows_draw_from_the_measured_graph_by_draw_index() {
        let text = "name = \"t\"\nenvironments = [\"peg-group1\", \"peg-group2\"]\nalgorithms = [\"ddpg\"]\n\
                    connections = [\"global\", \"random-rows@local@0.5+draws=2\"]\n\
                    seeds = [4, 5, 6, 7]\nepisodes = { ddpg = 7 }\n[best_constant]\nenabled = false\n";
        let e = Experiment::parse(text).unwrap();
        let tasks = tasks(&e);
        let ids: Vec<String> = tasks.iter().map(Task::id).collect();
        assert_eq!(ids[..6], [
            "graph-peg-group1-T0.5",
            "graph-peg-group1-random-rows@T0.5-draw0",
            "graph-peg-group1-random-rows@T0.5-draw1",
            "graph-peg-group2-T0.5",
            "graph-peg-group2-random-rows@T0.5-draw0",
            "graph-peg-group2-random-rows@T0.5-draw1",
        ]);
        let out = Path::new("/study");
        let draw = &tasks[2];
        assert_eq!(draw.dependency(), Some(tasks[0].clone()));
        let args = draw.args(&e, out).join(" ");
        let seed = lcrl_graph_builder::given::draw_seed("peg-group1", 1);
        assert!(args.contains(&format!("--random-rows /study/graphs/peg-group1/T0.5/graph.json --seed {seed} --draw 1 --out /study/graphs/peg-group1/random-rows@T0.5/draw1/graph.json")), "{args}");
        assert_ne!(tasks[5].args(&e, out).join(" ").split("--seed ").nth(1), args.split("--seed ").nth(1), "draws differ by environment");
        let run = tasks.iter().find(|t| t.id() == "train-peg-group2-ddpg-random-rows@local@0.5+draws=2-seed7").unwrap();
        assert_eq!(run.dependency().map(|t| t.id()), Some("graph-peg-group2-random-rows@T0.5-draw1".to_string()));
        assert!(run.args(&e, out).join(" ").contains("--graph /study/graphs/peg-group2/random-rows@T0.5/draw1/graph.json"));
        let chosen: Vec<String> = only(&e, tasks.clone(), &["peg-group1/ddpg/random*".to_string()]).unwrap().iter().map(Task::id).collect();
        assert_eq!(chosen.iter().filter(|id| id.starts_with("graph-")).collect::<Vec<_>>(), ["graph-peg-group1-T0.5", "graph-peg-group1-random-rows@T0.5-draw0", "graph-peg-group1-random-rows@T0.5-draw1"]);
    }

    /// `+per-seed` gives each run its own graph task (CS3 or draw seeded by
    /// the run's seed); a row rule reaches `lcrl graph` as `--row`; a graph
    /// two cells share is made once.
    #[test]
    fn per_seed_graphs_and_row_rules_are_their_own_tasks() {
        let text = "name = \"t\"\nenvironments = [\"peg-group1\"]\nalgorithms = [\"ddpg\"]\n\
                    connections = [\"local@1\", \"local@1+per-seed\", \"local@1+dz=0.1\", \"random@23+per-seed\"]\n\
                    seeds = [3, 5]\nepisodes = { ddpg = 7 }\n[best_constant]\nenabled = false\n";
        let e = Experiment::parse(text).unwrap();
        let tasks = tasks(&e);
        let ids: Vec<String> = tasks.iter().map(Task::id).collect();
        assert_eq!(ids[..6], [
            "graph-peg-group1-T1",
            "graph-peg-group1-T1-seed3",
            "graph-peg-group1-T1-seed5",
            "graph-peg-group1-T1+dz=0.1",
            "graph-peg-group1-random@23-seed3",
            "graph-peg-group1-random@23-seed5",
        ]);
        let out = Path::new("/study");
        let graph_args = |id: &str| tasks[ids.iter().position(|i| i == id).unwrap()].args(&e, out).join(" ");
        assert!(graph_args("graph-peg-group1-T1-seed5").contains("--threshold 1 --seed 5 "), "{}", graph_args("graph-peg-group1-T1-seed5"));
        assert!(graph_args("graph-peg-group1-T1").contains("--seed 0 "));
        assert!(graph_args("graph-peg-group1-T1+dz=0.1").ends_with("--row dz=0.1"));
        assert!(graph_args("graph-peg-group1-random@23-seed3").contains("--random 23 --seed 3 --out /study/graphs/peg-group1/random@23/seed3/graph.json"));
        let train = |id: &str| tasks.iter().find(|t| t.id() == id).unwrap();
        let run = train("train-peg-group1-ddpg-local@1+per-seed-seed5");
        assert_eq!(run.dependency().map(|d| d.id()).as_deref(), Some("graph-peg-group1-T1-seed5"));
        assert!(run.args(&e, out).join(" ").contains("--graph /study/graphs/peg-group1/T1/seed5/graph.json"));
        let matched = Experiment::parse(&text.replace("\"local@1\", ", "\"local@1\", \"global+match=local@1\", ")).unwrap();
        let matched_run = Task::Train { cell: cells(&matched)[1].clone(), seed: 5 };
        assert_eq!(matched_run.dependency().map(|d| d.id()).as_deref(), Some("graph-peg-group1-T1"));
        let matched_args = matched_run.args(&matched, out).join(" ");
        assert!(matched_args.contains("--connection global ") && matched_args.ends_with("--match-params /study/graphs/peg-group1/T1/graph.json"), "{matched_args}");
        let shared = train("train-peg-group1-ddpg-local@1+dz=0.1-seed5");
        assert!(shared.args(&e, out).join(" ").contains("--graph /study/graphs/peg-group1/T1+dz=0.1/graph.json"));
        // --only takes the per-seed graphs of the chosen cell, no others.
        let chosen: Vec<String> = only(&e, tasks.clone(), &["*/local@1+per-seed".to_string()]).unwrap().iter().map(Task::id).collect();
        assert_eq!(chosen, ["graph-peg-group1-T1-seed3", "graph-peg-group1-T1-seed5", "train-peg-group1-ddpg-local@1+per-seed-seed3", "train-peg-group1-ddpg-local@1+per-seed-seed5"]);
        // A connection's own seeds: only its cell runs the extra seed, with
        // its own draw.
        let more = Experiment::parse(&text.replace("[best_constant]", "[seeds_of]\n\"random@23+per-seed\" = [3, 5, 8]\n[best_constant]")).unwrap();
        let more_ids: Vec<String> = tasks_of(&more);
        assert!(more_ids.contains(&"graph-peg-group1-random@23-seed8".to_string()) && !more_ids.contains(&"graph-peg-group1-T1-seed8".to_string()));
        assert_eq!(more_ids.iter().filter(|id| id.ends_with("-seed8")).collect::<Vec<_>>(), ["graph-peg-group1-random@23-seed8", "train-peg-group1-ddpg-random@23+per-seed-seed8"]);
        assert_eq!(more.seeds, [3, 5, 8]);
        let bad = format!("{:#}", Experiment::parse(&text.replace("[best_constant]", "[seeds_of]\n\"random@9\" = 10\n[best_constant]")).unwrap_err());
        assert!(bad.contains("random@9 is not one of `connections`"), "{bad}");
        // A row rule for an action the environment lacks fails at load.
        let bad = Experiment::parse(&text.replace("dz=0.1", "dq=0.1")).unwrap_err();
        assert!(format!("{bad:#}").contains("has no action dq"), "{bad:#}");
    }

    /// A study folder takes a connection's own seeds growing, and refuses
    /// them shrinking (its finished runs would leave the report).
    #[test]
    fn a_folder_takes_own_seeds_growing_not_shrinking() {
        let base = "name = \"t\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"random@4+per-seed\", \"global\"]\nseeds = 2\nepisodes = { ppo = 7 }\n";
        let study = |own: &str| Experiment::parse(&format!("{base}[seeds_of]\n\"random@4+per-seed\" = {own}\n")).unwrap();
        let recorded = |e: &Experiment| serde_json::to_string_pretty(&e.file).unwrap() + "\n";
        let plain = Experiment::parse(base).unwrap();
        assert!(extends(&recorded(&plain), &study("[0, 1, 2]")), "more draws for one connection");
        assert!(extends(&recorded(&study("[0, 1, 2]")), &study("[0, 1, 2, 3]")));
        assert!(!extends(&recorded(&study("[0, 1, 2]")), &study("[0, 2]")), "seed 1's finished draw would leave the report");
        assert!(!extends(&recorded(&plain), &study("[1]")), "seed 0's finished draw would leave the report");
        // Growing them adds the runs of the new seeds to that cell alone.
        let ids: Vec<String> = tasks(&study("[0, 1, 2]")).iter().map(Task::id).filter(|id| id.ends_with("seed2")).collect();
        assert_eq!(ids, ["graph-lti-paper-random@4-seed2", "train-lti-paper-ppo-random@4+per-seed-seed2"]);
    }

    #[test]
    fn only_keeps_the_chosen_cells_with_their_graphs_and_constants() {
        let text = "name = \"t\"\nenvironments = [\"lti-paper\", \"peg-group1\"]\nalgorithms = [\"ppo\", \"ddpg\"]\nconnections = [\"local@0.1\", \"global\"]\nseeds = 2\nepisodes = { ppo = 7, ddpg = 3 }\n";
        let e = Experiment::parse(text).unwrap();
        let ids = |patterns: &[&str]| -> Vec<String> {
            let patterns: Vec<String> = patterns.iter().map(|p| p.to_string()).collect();
            only(&e, tasks(&e), &patterns).unwrap().iter().map(Task::id).collect()
        };
        assert_eq!(ids(&[]).len(), tasks(&e).len());
        assert_eq!(ids(&["peg-group1/ddpg/*"]), [
            "graph-peg-group1-T0.1",
            "train-peg-group1-ddpg-local@0.1-seed0",
            "train-peg-group1-ddpg-global-seed0",
            "train-peg-group1-ddpg-local@0.1-seed1",
            "train-peg-group1-ddpg-global-seed1",
            "tune-peg-group1",
        ]);
        // A global cell needs no graph; two patterns add up.
        assert_eq!(ids(&["lti-paper/ppo/global", "peg-group1/ppo/global"]), [
            "train-lti-paper-ppo-global-seed0",
            "train-peg-group1-ppo-global-seed0",
            "train-lti-paper-ppo-global-seed1",
            "train-peg-group1-ppo-global-seed1",
            "tune-lti-paper",
            "tune-peg-group1",
        ]);
        let err = only(&e, tasks(&e), &["lti-paper/sac/*".to_string()]).unwrap_err().to_string();
        assert!(err.contains("matches no cell") && err.contains("lti-paper/ppo/local@0.1"), "{err}");
    }
}
