//! The experiment file (experiments/*.toml): which environments,
//! algorithms, connections and seeds a study runs, with their budgets and
//! data-efficiency thresholds. Checked on load, unknown keys rejected by name.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context};
use lcrl_learner::{Algo, TrainConfig};
use serde::{Deserialize, Serialize};

pub(crate) use crate::preset::algo_name;

pub use crate::connection::ConnectionSpec;
pub use super::hypotheses::{Equivalence, Factorial, Primary, PrimaryContrast};

/// One experiment file, as written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExperimentFile {
    /// Names the study (Kubernetes objects, report titles); letters, digits
    /// and '-'.
    pub name: String,
    /// Registered names (peg-group1, lti-paper, …) or .toml paths.
    pub environments: Vec<String>,
    pub algorithms: Vec<Algo>,
    /// `local` (T_rule = 1), `local@T`, `graph:PATH`, `random@K`, `global`,
    /// `full-subnets` (crate::connection).
    pub connections: Vec<String>,
    /// A count n (seeds 0 … n−1) or an explicit list.
    pub seeds: Seeds,
    /// A connection's own seeds in place of `seeds`, e.g.
    /// `[seeds_of]` `"random@23+per-seed" = 10`: more draws of a random
    /// graph than the study has seeds.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub seeds_of: BTreeMap<String, Seeds>,
    /// Training episodes per algorithm, e.g. `{ ddpg = 200, ppo = 900 }`.
    pub episodes: BTreeMap<String, usize>,
    /// Episodes of the deterministic policy evaluated after training.
    #[serde(default = "default_eval_episodes")]
    pub eval_episodes: usize,
    /// Data efficiency: per environment, per algorithm, the average return
    /// (10-episode mean) a run must reach; e.g.
    /// `[reward_threshold.peg-group1]` `ddpg = -5.0`.
    #[serde(default)]
    pub reward_threshold: BTreeMap<String, BTreeMap<String, f64>>,
    #[serde(default)]
    pub graph: GraphSettings,
    #[serde(default)]
    pub best_constant: BestConstantSettings,
    /// Training settings shared by every run, laid over each environment's
    /// defaults (`lcrl train` without --config): `[train.ddpg]`, `[train.run]`, …
    #[serde(default)]
    pub train: toml::Table,
    /// The one comparison named before any run ([`PrimaryContrast`]):
    /// reported first, on its own; every other comparison is Holm-adjusted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub primary: Option<Primary>,
    /// Equivalence tests with their margins, named before the runs.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub equivalence: Vec<Equivalence>,
    /// 2 × 2 factorial designs over the study's cells.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub factorial: Vec<Factorial>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Seeds {
    Count(u64),
    List(Vec<u64>),
}

impl Seeds {
    /// The seeds, checked: at least one, none twice (`key` names the field).
    fn checked(&self, key: &str) -> anyhow::Result<Vec<u64>> {
        let seeds: Vec<u64> = match self {
            Seeds::Count(n) => (0..*n).collect(),
            Seeds::List(list) => list.clone(),
        };
        if seeds.is_empty() {
            bail!("`{key}` is zero: give a count (5 runs seeds 0–4) or a list ([0, 7, 9])");
        }
        if seeds.iter().collect::<std::collections::BTreeSet<_>>().len() != seeds.len() {
            bail!("`{key}` lists a seed twice: {seeds:?}");
        }
        Ok(seeds)
    }
}

/// CS3 settings of the graphs (one per environment and threshold).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GraphSettings {
    /// ST, CS3 samples per action component.
    pub samples: usize,
    pub seed: u64,
}

impl Default for GraphSettings {
    fn default() -> Self {
        GraphSettings { samples: 256, seed: 0 }
    }
}

/// The best constant controller (`lcrl tune`), the bar beside every cell.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BestConstantSettings {
    pub enabled: bool,
    /// Candidate actions CMA-ES may evaluate.
    pub evaluations: usize,
    /// Tuning episodes per candidate.
    pub episodes: usize,
    /// Evaluation episodes of the winner and of a = 0.
    pub eval_episodes: usize,
}

impl Default for BestConstantSettings {
    fn default() -> Self {
        let tune = lcrl_sim::tune::TuneOptions::default();
        BestConstantSettings { enabled: true, evaluations: tune.evaluations, episodes: tune.episodes, eval_episodes: tune.eval_episodes }
    }
}

fn default_eval_episodes() -> usize {
    100
}

/// A checked experiment: the file plus what follows from it.
#[derive(Debug, Clone)]
pub struct Experiment {
    pub file: ExperimentFile,
    pub connections: Vec<ConnectionSpec>,
    /// Every seed of the study: `seeds` and those of `[seeds_of]`.
    pub seeds: Vec<u64>,
    /// `seeds` as checked: the seeds of every connection without its own.
    study_seeds: Vec<u64>,
    /// The seeds of each connection with its own (`[seeds_of]`), by label.
    pub seeds_of: BTreeMap<String, Vec<u64>>,
}

impl Experiment {
    /// Reads and checks an experiment file.
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read experiment file {}", path.display()))?;
        Self::parse(&text).with_context(|| format!("experiment file {}", path.display()))
    }

    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let file: ExperimentFile = toml::from_str(text)?;
        Self::check(file)
    }

    /// The study of `path` on `environments` in place of the file's (all
    /// of them when empty): the same cells, seeds and named contrasts,
    /// which then stratify over the given environments. How a user asks a
    /// study's question on a task of their own.
    pub fn load_on(path: &Path, environments: &[String]) -> anyhow::Result<Self> {
        if environments.is_empty() {
            return Self::load(path);
        }
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read experiment file {}", path.display()))?;
        let mut file: ExperimentFile = toml::from_str(&text).with_context(|| format!("experiment file {}", path.display()))?;
        file.environments = environments.to_vec();
        if let Some(primary) = file.primary.as_mut() {
            primary.stratify_over_all();
        }
        Self::check(file).with_context(|| format!("experiment file {} on --env {}", path.display(), environments.join(", ")))
    }

    /// Every check that can run before a single process starts.
    pub fn check(mut file: ExperimentFile) -> anyhow::Result<Self> {
        // `[train.controller]` is the deprecated name of `[train.base]`:
        // studies recorded with it are the same studies.
        lcrl_learner::config::migrate_legacy_tables(&mut file.train);
        if file.name.is_empty() || !file.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') || file.name.len() > 40 {
            bail!("`name` \"{}\" must be 1–40 letters, digits or '-' (it names Kubernetes objects)", file.name);
        }
        if file.environments.is_empty() || file.algorithms.is_empty() || file.connections.is_empty() {
            bail!("`environments`, `algorithms` and `connections` must each list at least one entry");
        }
        let study_seeds = file.seeds.checked("seeds")?;
        let mut seeds = study_seeds.clone();
        let connections = file.connections.iter().map(|c| ConnectionSpec::parse(c)).collect::<anyhow::Result<Vec<_>>>()?;
        let labels: Vec<String> = connections.iter().map(ConnectionSpec::label).collect();
        if labels.iter().collect::<std::collections::BTreeSet<_>>().len() != labels.len() {
            bail!("`connections` lists a connection twice: {labels:?}");
        }
        let mut seeds_of = BTreeMap::new();
        for (connection, own) in &file.seeds_of {
            let label = ConnectionSpec::parse(connection).with_context(|| format!("`seeds_of.\"{connection}\"`"))?.label();
            if !labels.contains(&label) {
                bail!("`seeds_of.\"{connection}\"`: {connection} is not one of `connections` ({})", labels.join(", "));
            }
            let own = own.checked(&format!("seeds_of.\"{connection}\""))?;
            seeds.extend(own.iter().filter(|s| !seeds.contains(s)).copied().collect::<Vec<_>>());
            if seeds_of.insert(label.clone(), own).is_some() {
                bail!("`seeds_of` gives {label} its seeds twice (\"{connection}\" names it again)");
            }
        }
        if file.eval_episodes == 0 {
            bail!("`eval_episodes` must be at least 1");
        }
        let names = super::hypotheses::Names { environments: &file.environments, algorithms: &file.algorithms, connections: &file.connections };
        if let Some(primary) = &file.primary {
            primary.check(&names)?;
        }
        super::hypotheses::check_designs(&names, &file.equivalence, &file.factorial)?;
        let algos: Vec<&str> = file.algorithms.iter().map(|a| algo_name(*a)).collect();
        check_episodes(&file, &algos)?;
        let mut slugs = BTreeMap::new();
        for env in &file.environments {
            lcrl_sim::make_env(env).with_context(|| format!("environment \"{env}\""))?;
            if let Some(other) = slugs.insert(env_slug(env), env) {
                bail!("environments \"{other}\" and \"{env}\" would share the folder {}", env_slug(env));
            }
        }
        check_reward_thresholds(&file, &algos)?;
        if file.graph.samples == 0 {
            bail!("`graph.samples` must be at least 1");
        }
        let b = &file.best_constant;
        if b.enabled && (b.evaluations == 0 || b.episodes == 0 || b.eval_episodes == 0) {
            bail!("`best_constant`: evaluations, episodes and eval_episodes must each be at least 1 (or set enabled = false)");
        }
        check_train_table(&file)?;
        check_given_graphs(&file, &connections)?;
        let experiment = Experiment { file, connections, seeds, study_seeds, seeds_of };
        // Random rows: every draw is trained (run seed s trains draw s mod N).
        for connection in &experiment.connections {
            if let ConnectionSpec::RandomRows { draws, .. } = connection {
                let seeds = experiment.seeds_for(connection);
                if let Some(missing) = (0..*draws).find(|d| !seeds.iter().any(|s| s % draws == *d)) {
                    bail!("connection \"{}\": no seed trains draw {missing} (run seed s trains draw s mod {draws}); give it consecutive seeds, e.g. [seeds_of] \"{}\" = [100, …, {}]", connection.label(), connection.label(), 100 + 2 * draws - 1);
                }
            }
        }
        for env in &experiment.file.environments {
            experiment.train_config(env)?;
        }
        Ok(experiment)
    }

    /// The training settings of every run on `env`: the environment's
    /// defaults with `[train]` laid over them, and the experiment's
    /// evaluation: every run is evaluated on the starts the best constant
    /// and a = 0 are (`lcrl tune`'s evaluation seeds), so the report
    /// compares them start for start.
    pub fn train_config(&self, env: &str) -> anyhow::Result<TrainConfig> {
        let mut config = TrainConfig::for_env_with(env, &self.file.train).map_err(|e| anyhow::anyhow!("`train`: {e}"))?;
        config.run.eval_episodes = self.file.eval_episodes;
        config.run.eval_seed = Some(lcrl_sim::tune::TuneOptions::default().eval_seed);
        config.run.threads = 1;
        config.validate().map_err(|e| anyhow::anyhow!("`train`: {e}"))?;
        Ok(config)
    }

    /// The seeds of a connection's cells: its own (`[seeds_of]`) or the
    /// study's `seeds`.
    pub fn seeds_for(&self, connection: &ConnectionSpec) -> Vec<u64> {
        self.seeds_of.get(&connection.label()).unwrap_or(&self.study_seeds).clone()
    }

    pub fn episodes(&self, algo: Algo) -> usize {
        self.file.episodes.get(algo_name(algo)).copied().unwrap_or(1)
    }

    pub fn reward_threshold(&self, env: &str, algo: Algo) -> Option<f64> {
        self.file.reward_threshold.get(env)?.get(algo_name(algo)).copied()
    }
}

/// Every algorithm has an episode budget of at least 1, and every budget
/// is an algorithm's.
fn check_episodes(file: &ExperimentFile, algos: &[&str]) -> anyhow::Result<()> {
    for algo in algos {
        match file.episodes.get(*algo) {
            Some(0) => bail!("`episodes.{algo}` must be at least 1"),
            Some(_) => {}
            None => bail!("`episodes` gives no budget for {algo}; add e.g. `episodes = {{ {algo} = 200 }}`"),
        }
    }
    for key in file.episodes.keys() {
        if !algos.contains(&key.as_str()) {
            bail!("`episodes.{key}`: {key} is not one of `algorithms` ({})", algos.join(", "));
        }
    }
    Ok(())
}

/// Every reward threshold is a finite number, for a listed environment
/// and algorithm.
fn check_reward_thresholds(file: &ExperimentFile, algos: &[&str]) -> anyhow::Result<()> {
    for (env, per_algo) in &file.reward_threshold {
        if !file.environments.contains(env) {
            bail!("`reward_threshold.{env}`: {env} is not one of `environments`");
        }
        for (algo, value) in per_algo {
            if !algos.contains(&algo.as_str()) {
                bail!("`reward_threshold.{env}.{algo}`: {algo} is not one of `algorithms`");
            }
            if !value.is_finite() {
                bail!("`reward_threshold.{env}.{algo}` must be a finite number");
            }
        }
    }
    Ok(())
}

/// The `[train]` table: every key one `lcrl train` knows, none one the
/// experiment sets itself.
fn check_train_table(file: &ExperimentFile) -> anyhow::Result<()> {
    // Every key of `[train]` is one `lcrl train` knows: a typo, or an
    // option since removed (docs/peg.md), fails here, before any run.
    TrainConfig::deserialize(toml::Value::Table(file.train.clone())).context("`[train]`")?;
    if let Some(run) = file.train.get("run").and_then(|r| r.as_table()) {
        for (key, instead) in [
            ("episodes", "`episodes`"),
            ("seed", "`seeds`"),
            ("eval_episodes", "`eval_episodes`"),
            ("eval_seed", "the best constant's evaluation starts"),
            ("threads", "one thread per run"),
        ] {
            if run.contains_key(key) {
                bail!("`train.run.{key}` is set by the experiment ({instead}); remove it");
            }
        }
    }
    Ok(())
}

/// Given graphs fit every environment before a run starts.
fn check_given_graphs(file: &ExperimentFile, connections: &[ConnectionSpec]) -> anyhow::Result<()> {
    for env in &file.environments {
        let made = lcrl_sim::make_env(env)?;
        for connection in connections {
            // A matched global needs the graph of the actor it matches.
            let graph_of = match connection {
                ConnectionSpec::MatchedGlobal { to } => to.as_ref(),
                ConnectionSpec::RandomRows { of, .. } => of.as_ref(),
                other => other,
            };
            graph_of.given_graph(made.spec(), file.graph.seed).with_context(|| format!("connection \"{}\" on {env}", connection.label()))?;
            if let ConnectionSpec::Local { rows, .. } = graph_of {
                if let Some(rule) = rows.iter().find(|r| !made.spec().action_names.contains(&r.action)) {
                    bail!("connection \"{}\": {env} has no action {} (its actions: {})", connection.label(), rule.action, made.spec().action_names.join(", "));
                }
            }
        }
    }
    Ok(())
}

/// A folder name for an environment: a registered name as is, a file path
/// by its stem.
pub fn env_slug(env: &str) -> String {
    // A served environment is named by its address, not a file stem.
    let stem = match lcrl_sim::remote::address(env) {
        Some(address) => format!("grpc-{address}"),
        None => Path::new(env).file_stem().map_or(env.to_string(), |s| s.to_string_lossy().into_owned()),
    };
    stem.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every study file under experiments/ (and experiments/research/) and every config under configs/
    /// loads and passes its checks: nothing shipped names a removed key.
    #[test]
    fn every_shipped_study_and_config_loads() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let toml_files = |dir: &str| {
            let mut files: Vec<_> = std::fs::read_dir(root.join(dir)).unwrap().flatten().map(|e| e.path()).filter(|p| p.extension().is_some_and(|e| e == "toml")).collect();
            files.sort();
            files
        };
        // The studies users start from, and the research ones beside them.
        let studies = [toml_files("experiments"), toml_files("experiments/research")].concat();
        let top = toml_files("experiments").len();
        assert!(top <= 10, "experiments/ holds {top} studies at its top: research studies go to experiments/research/");
        for path in &studies {
            let text = std::fs::read_to_string(path).unwrap();
            if text.contains("grpc://") {
                // Its checks would connect to the environment server: the
                // file and its training keys only.
                let file: ExperimentFile = toml::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                TrainConfig::deserialize(toml::Value::Table(file.train)).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            } else {
                Experiment::load(path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
            }
        }
        let configs = toml_files("configs");
        for path in &configs {
            let text = std::fs::read_to_string(path).unwrap();
            if text.contains("[job]") {
                crate::preset::Preset::load(path).map(|_| ()).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
            } else {
                // A training config lays over an environment's settings
                // (configs/peg-group2.toml over the peg defaults): its keys.
                toml::from_str::<TrainConfig>(&text).map(|_| ()).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            }
        }
        assert!(studies.len() >= 20 && configs.len() >= 10, "{} studies, {} configs", studies.len(), configs.len());
        let removed = "name = \"x\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ddpg\"]\nconnections = [\"global\"]\nseeds = [0]\nepisodes = { ddpg = 10 }\n[train.ddpg]\nwarmup_actions = \"policy\"\n";
        let err = format!("{:#}", Experiment::parse(removed).unwrap_err());
        assert!(err.contains("warmup_actions"), "{err}");
    }

    #[test]
    fn env_slugs_are_folder_names() {
        assert_eq!(env_slug("grpc://127.0.0.1:50070"), "grpc-127_0_0_1_50070");
        assert_eq!(env_slug("envs/my-system.toml"), "my-system");
        assert_eq!(env_slug("peg-group1"), "peg-group1");
    }

    const MINIMAL: &str = "name = \"t\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"local@0.1\", \"local@0.25\", \"global\"]\nseeds = 3\nepisodes = { ppo = 10 }\n";

    #[test]
    fn parses_connections_seeds_and_overlays_training_settings() {
        let text = format!("{MINIMAL}[train.ppo]\nactor_lr = 0.005\n");
        let e = Experiment::parse(&text).unwrap();
        assert_eq!(e.seeds, vec![0, 1, 2]);
        assert_eq!(e.connections.iter().map(ConnectionSpec::label).collect::<Vec<_>>(), ["local@0.1", "local@0.25", "global"]);
        let cfg = e.train_config("lti-paper").unwrap();
        assert_eq!(cfg.ppo.actor_lr, 0.005);
        // Everything else keeps lti-paper's own settings (configs/lti-fast.toml).
        let (defaults, _) = TrainConfig::for_env("lti-paper");
        assert_eq!(cfg.ppo.rollout_steps, defaults.ppo.rollout_steps);
        assert_eq!((cfg.run.eval_episodes, cfg.run.threads), (100, 1));
        // Runs are evaluated on the best constant's starts.
        assert_eq!(cfg.run.eval_seed, Some(lcrl_sim::tune::TuneOptions::default().eval_seed));
    }

    #[test]
    fn bad_files_are_refused_by_name() {
        let err = |text: &str| Experiment::parse(text).err().map(|e| format!("{e:#}")).unwrap_or_else(|| panic!("accepted {text}"));
        assert!(err(&MINIMAL.replace("\"global\"", "\"globl\"")).contains("unknown connection \"globl\""));
        assert!(err(&MINIMAL.replace("seeds = 3", "seeds = 0")).contains("`seeds` is zero"));
        assert!(err(&MINIMAL.replace("seeds = 3", "seeds = []")).contains("`seeds` is zero"));
        assert!(err(&format!("{MINIMAL}colour = 1\n")).contains("colour"));
        assert!(err(&format!("{MINIMAL}[train.ppo]\nactor_rate = 1\n")).contains("actor_rate"));
        assert!(err(&format!("{MINIMAL}[train.run]\nseed = 4\n")).contains("train.run.seed"));
        assert!(err(&format!("{MINIMAL}[train.run]\neval_seed = 4\n")).contains("train.run.eval_seed"));
        assert!(err(&MINIMAL.replace("{ ppo = 10 }", "{ ddpg = 10 }")).contains("no budget for ppo"));
        assert!(err(&MINIMAL.replace("lti-paper", "peg-group9")).contains("peg-group9"));
        assert!(err(&format!("{MINIMAL}[reward_threshold.peg-group1]\nppo = -3.0\n")).contains("reward_threshold.peg-group1"));
        assert!(err(&MINIMAL.replace("local@0.25", "local@x")).contains("\"x\" is not a number"));
        // Given graphs are checked against each environment at load.
        assert!(err(&MINIMAL.replace("local@0.25", "random@2")).contains("between 3 and 9"));
        assert!(err(&MINIMAL.replace("local@0.25", "graph:no/such.json")).contains("no/such.json"));
        // So is the graph a matched global matches, in the cells or not.
        assert!(err(&MINIMAL.replace("local@0.25", "global+match=graph:no/such.json")).contains("no/such.json"));
        assert!(err(&MINIMAL.replace("local@0.25", "global+match=random@2")).contains("between 3 and 9"));
        assert!(err(&MINIMAL.replace("local@0.25", "global+match=local@1+u9=0.1")).contains("has no action u9"));
        // A connection's own seeds: one entry each, for a listed connection.
        let own = |entries: &str| format!("{MINIMAL}[seeds_of]\n{entries}");
        assert!(err(&own("\"local@0.25\" = 5\n\"local@0.250\" = 6\n")).contains("gives local@0.25 its seeds twice"));
        assert!(err(&own("\"local@0.5\" = 5\n")).contains("local@0.5 is not one of `connections`"));
        assert!(err(&own("\"local@0.25\" = []\n")).contains("`seeds_of.\"local@0.25\"` is zero"));
        let e = Experiment::parse(&own("\"local@0.25\" = [1, 4]\n")).unwrap();
        assert_eq!((e.seeds.clone(), e.seeds_for(&e.connections[1]), e.seeds_for(&e.connections[0])), (vec![0, 1, 2, 4], vec![1, 4], vec![0, 1, 2]));
    }

    #[test]
    fn given_graphs_are_cells_with_their_own_graph_task() {
        let e = Experiment::parse(&MINIMAL.replace("local@0.25", "random@4")).unwrap();
        let tasks = super::super::plan::tasks(&e);
        let random = tasks.iter().find(|t| t.id().starts_with("graph-lti-paper-random@4")).expect("a draw task");
        let args = random.args(&e, std::path::Path::new("out")).join(" ");
        assert!(args.contains("--random 4") && args.contains("--seed 0"), "{args}");
        let train = tasks.iter().find(|t| t.id().contains("-random@4-seed1")).unwrap();
        assert_eq!(train.dependency().as_ref(), Some(random));
        let args = train.args(&e, std::path::Path::new("out")).join(" ");
        assert!(args.contains("--connection local") && args.contains("--graph out/graphs/lti-paper/random@4/graph.json"), "{args}");
    }
}
