//! Presets (configs/*.toml): a training config plus a `[job]` section, and
//! the one place that turns a preset into the command lines of the graph
//! builder, the learner and the actors. `lcrl run` (one machine) and
//! `lcrl launch` (one role per container or pod) both start processes from
//! here, so a preset means the same run everywhere.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use lcrl_learner::{Algo, Connection, TrainConfig};
use serde::Deserialize;

/// The [job] section of a preset.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Job {
    /// Environment: a registered name, a .toml path, or grpc://HOST:PORT
    /// (a served environment; with [env_server], where `lcrl run` serves it).
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    /// Episode budget of the whole run (`lcrl run`).
    pub episodes: u64,
    #[serde(default = "one")]
    pub actors: usize,
    #[serde(default = "one")]
    pub envs_per_actor: usize,
    /// DDPG replay ratio (samples per insert) or "unlimited"; default
    /// Algorithm 2's, one update of ddpg.batch_size per environment step.
    #[serde(default)]
    pub replay_ratio: Option<String>,
    /// DDPG: the learner publishes a new policy every this many updates
    /// (`lcrl-learner --publish-every`; default its own).
    #[serde(default)]
    pub publish_every: Option<u64>,
    /// DDPG: how far, in inserted transitions, the actors may run ahead of
    /// the replay ratio (`lcrl-learner --replay-slack`; default its own).
    #[serde(default)]
    pub replay_slack: Option<u64>,
    /// Batches that may wait in the learner's queue
    /// (`lcrl-learner --queued-batches`; default its own).
    #[serde(default)]
    pub queued_batches: Option<u64>,
    /// Transitions per batch an actor sends (`lcrl-actor --batch`; default
    /// its own). A batch's steps all wait for the learner together.
    #[serde(default)]
    pub actor_batch: Option<u64>,
    /// PPO: how many policy versions behind the newest a batch may be and
    /// still be trained on (`lcrl-learner --max-staleness`; default
    /// [`PPO_MAX_STALENESS`], asynchronous; 0 is on-policy, as `lcrl
    /// train`). Above 0 the actors' steps acted by an older policy are
    /// kept, PPO's clipped ratio taken against the behaviour policy's
    /// probabilities they carry (docs/method.md, "Asynchronous PPO").
    #[serde(default)]
    pub max_staleness: Option<u64>,
    /// T of eq. 7 for the graph builder: a number, or "auto" for T_rule
    /// (the above-average rule, docs/method.md "Choosing T"); unset is
    /// T_rule too, by experiments/default-graph.toml's decision.
    #[serde(default = "t_rule", deserialize_with = "lcrl_graph_builder::choose_t::deserialize_threshold")]
    pub graph_threshold: f64,
    /// A given graph instead of the graph builder's (connection local):
    /// "graph:PATH" (a graph.json, relative to the preset's folder) or
    /// "random@K" (K random edges, draw seed 0, as `lcrl train`'s default
    /// --graph-seed). `lcrl run` writes it as the run's graph.json and
    /// starts no graph builder.
    #[serde(default)]
    pub graph: Option<String>,
    /// The headroom reference `lcrl run` evaluates beside the trained
    /// policy: a best_policy.json of `lcrl tune --policy` (relative to the
    /// preset's folder; resolved on load, read by `Preset::headroom`).
    #[serde(default)]
    pub headroom: Option<PathBuf>,
}

/// `[env_server]`: a Gymnasium environment that `lcrl run` serves itself
/// (`python -m lcrl_env serve`) at `job.env`, a `grpc://HOST:PORT` address
/// (port 0: any free port), for the whole run (docs/environments.md).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnvServer {
    /// A registered Gymnasium id, e.g. "HalfCheetah-v5".
    #[serde(default)]
    pub gym: Option<String>,
    /// Or your own class, "module:Class" (the module on `pythonpath`).
    #[serde(default)]
    pub entry_point: Option<String>,
    /// Keyword arguments for gymnasium.make or the class.
    #[serde(default)]
    pub kwargs: toml::Table,
    /// Truncate episodes after this many steps.
    #[serde(default)]
    pub max_episode_steps: Option<u32>,
    /// Folder added to PYTHONPATH, relative to the preset's folder.
    #[serde(default)]
    pub pythonpath: Option<PathBuf>,
    /// The Python with lcrl_env installed (default: $LCRL_PYTHON, else this
    /// project's .venv, as scripts/setup.sh makes it).
    #[serde(default)]
    pub python: Option<PathBuf>,
}

impl EnvServer {
    /// One of `gym` and `entry_point`, and an `env` where it listens.
    pub fn check(&self, env: &str) -> anyhow::Result<()> {
        if self.gym.is_some() == self.entry_point.is_some() {
            bail!("[env_server] needs exactly one of gym = \"ID\" (a Gymnasium id) and entry_point = \"module:Class\"");
        }
        if !lcrl_sim::remote::is_served(env) {
            bail!("with [env_server], the environment (job.env, or lcrl train's --env) is where it listens: grpc://HOST:PORT (e.g. grpc://127.0.0.1:0 for any free port), not {env:?}");
        }
        Ok(())
    }

    /// The server's command line, listening on `listen` (HOST:PORT);
    /// relative paths are taken from `preset_dir`.
    pub fn command(&self, listen: &str, instances: usize, preset_dir: &Path) -> anyhow::Result<std::process::Command> {
        let python = match &self.python {
            Some(p) => preset_dir.join(p),
            None => crate::binaries::lcrl_python()?,
        };
        if !python.is_file() {
            bail!("[env_server] python = {} is missing", python.display());
        }
        let mut cmd = std::process::Command::new(python);
        cmd.args(["-m", "lcrl_env", "serve", "--listen", listen, "--instances", &instances.to_string()]);
        match (&self.gym, &self.entry_point) {
            (Some(id), _) => cmd.args(["--env", id]),
            (None, Some(entry)) => cmd.args(["--entry-point", entry]),
            (None, None) => bail!("[env_server] needs gym or entry_point"),
        };
        if !self.kwargs.is_empty() {
            cmd.args(["--kwargs", &serde_json::to_string(&self.kwargs)?]);
        }
        if let Some(steps) = self.max_episode_steps {
            cmd.args(["--max-episode-steps", &steps.to_string()]);
        }
        if let Some(extra) = &self.pythonpath {
            let mut paths = vec![preset_dir.join(extra)];
            paths.extend(std::env::var_os("PYTHONPATH").iter().flat_map(std::env::split_paths));
            cmd.env("PYTHONPATH", std::env::join_paths(paths)?);
        }
        Ok(cmd)
    }
}

fn one() -> usize {
    1
}

/// A bare `connection = "local"` trains T_rule (experiments/default-graph.toml).
fn t_rule() -> f64 {
    lcrl_graph_builder::choose_t::RULE_THRESHOLD
}

/// The most actor processes a preset (or `lcrl run --actors`) may ask for.
pub const MAX_ACTORS: usize = 256;
/// The most environments per actor (`lcrl-actor --envs` takes as many).
pub const MAX_ENVS_PER_ACTOR: usize = 1024;

/// A loaded, checked preset.
#[derive(Debug, Clone)]
pub struct Preset {
    pub job: Job,
    pub env_server: Option<EnvServer>,
    pub train: TrainConfig,
    /// The file as written, kept in the run directory as config.toml.
    pub text: String,
}

/// `lcrl run`'s lag bound for PPO when a preset names none: asynchronous
/// PPO, one version. The parity study named before its runs
/// (docs/research/2026-12-05-async-ppo-design.md) found no cell of the
/// main job's presets at 1, 2 and 4 actors more than 0.30 behind `lcrl
/// train` (every paired lower bound above −0.30;
/// docs/research/2026-12-05-async-ppo.md), which by its rule makes this
/// the default. Other PPO presets inherit it untested.
pub const PPO_MAX_STALENESS: u64 = 1;

impl Preset {
    /// The learner's lag bound for this job: the preset's, else
    /// [`PPO_MAX_STALENESS`] for PPO (DDPG keeps none).
    pub fn max_staleness(&self) -> Option<u64> {
        self.job.max_staleness.or((self.job.algo == lcrl_learner::Algo::Ppo).then_some(PPO_MAX_STALENESS))
    }

    /// Reads and checks a preset, its environment included.
    pub fn load(path: &Path) -> anyhow::Result<Preset> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        Self::parse(text, path)
    }

    /// [`Preset::load`] on a file's text; `path` names it in errors, and
    /// the files it names (headroom, graph) are read beside it. Fuzzed by
    /// fuzz/fuzz_targets/toml_config.rs.
    pub fn parse(text: String, path: &Path) -> anyhow::Result<Preset> {
        let mut table: toml::Table = toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        let job_value = table.remove("job").with_context(|| format!("{} has no [job] section (env, algo, connection, episodes)", path.display()))?;
        let mut job: Job = job_value.try_into().with_context(|| format!("{}: [job]", path.display()))?;
        if let Some(headroom) = &job.headroom {
            job.headroom = Some(path.parent().unwrap_or(Path::new(".")).join(headroom));
        }
        if let Some(file) = job.graph.as_deref().and_then(|g| g.strip_prefix("graph:")) {
            job.graph = Some(format!("graph:{}", path.parent().unwrap_or(Path::new(".")).join(file).display()));
        }
        let env_server: Option<EnvServer> = match table.remove("env_server") {
            Some(value) => Some(value.try_into().with_context(|| format!("{}: [env_server]", path.display()))?),
            None => None,
        };
        // Keys a preset leaves out keep the environment's own settings
        // (configs/peg.toml on the peg presets), as `lcrl train` does.
        let train = TrainConfig::for_env_with(&job.env, &table).with_context(|| format!("{}: training sections", path.display()))?;
        let preset = Preset { job, env_server, train, text };
        preset.check()?;
        Ok(preset)
    }

    /// Checks what the sections cannot check alone (after overrides too).
    pub fn check(&self) -> anyhow::Result<()> {
        let job = &self.job;
        if job.actors == 0 || job.envs_per_actor == 0 || job.episodes == 0 {
            bail!("job.actors, job.envs_per_actor and job.episodes must be at least 1");
        }
        // Each actor is a process on this machine (`lcrl run`) and each
        // environment an instance in it: a typo must not fork thousands.
        for (key, value, most) in [("actors (--actors)", job.actors, MAX_ACTORS), ("envs_per_actor", job.envs_per_actor, MAX_ENVS_PER_ACTOR)] {
            if value > most {
                bail!("job.{key} must be from 1 to {most}, not {value}");
            }
        }
        // The learner and the actors would refuse these too, but only once
        // the run has started; a preset check should say so first.
        if let Some(lag) = job.max_staleness.filter(|l| *l > 1_000_000) {
            bail!("job.max_staleness must be at most 1000000, not {lag}");
        }
        for (key, value, most) in [("publish_every", job.publish_every, 1_000_000), ("queued_batches", job.queued_batches, 1024), ("actor_batch", job.actor_batch, 4096)] {
            match value {
                Some(0) => bail!("job.{key} must be at least 1, not 0"),
                Some(v) if v > most => bail!("job.{key} must be at most {most}, not {v}"),
                _ => {}
            }
        }
        if let Some(slack) = job.replay_slack.filter(|s| *s > 1_000_000) {
            bail!("job.replay_slack must be at most 1000000, not {slack}");
        }
        match job.replay_ratio.as_deref() {
            None | Some("unlimited") => {}
            Some(text) => {
                let most = lcrl_learner::algo::rate_limiter::MAX_SAMPLES_PER_INSERT;
                match text.parse::<f64>() {
                    Ok(v) if v > 0.0 && v <= most => {}
                    _ => bail!("job.replay_ratio must be `unlimited` or a number of samples per insert above 0 and at most {most:e}, not {text:?}"),
                }
            }
        }
        if !(job.graph_threshold.is_finite() && job.graph_threshold > 0.0) {
            bail!("job.graph_threshold must be a positive number (T of eq. 7), not {}", job.graph_threshold);
        }
        match &self.env_server {
            // Served by the run itself: there is nothing to reach yet.
            Some(_) if job.graph.is_some() => bail!("job.graph needs the environment's names before the run starts; with [env_server] let the graph builder measure G"),
            Some(server) => server.check(&job.env)?,
            None => {
                let env = lcrl_sim::make_env(&job.env)?;
                // A given graph must fit before anything starts.
                self.given_graph(env.spec())?;
            }
        }
        Ok(())
    }

    /// `job.graph` as a graph for the environment `spec` describes: the
    /// file checked against it, or the draw. None when the graph builder
    /// measures it (or the actor has no graph).
    pub fn given_graph(&self, spec: &lcrl_sim::EnvSpec) -> anyhow::Result<Option<lcrl_graph_builder::GraphReport>> {
        let Some(text) = &self.job.graph else { return Ok(None) };
        let spec_of = crate::connection::ConnectionSpec::parse(text).context("job.graph")?;
        if !matches!(spec_of, crate::connection::ConnectionSpec::Graph { .. } | crate::connection::ConnectionSpec::Random { .. }) {
            bail!("job.graph = \"{text}\": give \"graph:PATH\" or \"random@K\" (a measured graph is the graph builder's: job.graph_threshold)");
        }
        if self.job.connection != Connection::Local {
            bail!("job.graph applies to connection = \"local\" only");
        }
        spec_of.given_graph(spec, 0).context("job.graph")
    }

    /// The preset's headroom reference (`job.headroom`), read and checked
    /// against its environment; None when the preset names none.
    pub fn headroom(&self) -> anyhow::Result<Option<lcrl_sim::tune::feedback::StoredPolicy>> {
        let Some(path) = &self.job.headroom else { return Ok(None) };
        let stored = lcrl_sim::tune::feedback::StoredPolicy::read(path).with_context(|| format!("job.headroom = {}", path.display()))?;
        if self.env_server.is_none() {
            stored.check_env(lcrl_sim::make_env(&self.job.env)?.as_ref()).with_context(|| format!("job.headroom = {}", path.display()))?;
        }
        Ok(Some(stored))
    }

    /// Writes the training sections alone (what `lcrl-learner --config`
    /// reads) to `path`.
    pub fn write_train_config(&self, path: &Path) -> anyhow::Result<()> {
        crate::output::write_atomic(path, &toml::to_string_pretty(&self.train)?)
    }

    /// `lcrl-graph-builder`'s arguments: CS3 samples and seed from [run];
    /// graph.json and graph.png into `run_dir`.
    pub fn graph_builder_args(&self, listen: &str, run_dir: &Path) -> Vec<OsString> {
        let mut args = os(&["--env", &self.job.env, "--listen", listen]);
        args.extend(os(&["--samples", &self.train.run.graph_samples.to_string(), "--seed", &self.train.run.seed.to_string()]));
        args.extend(os(&["--threshold", &self.job.graph_threshold.to_string()]));
        args.extend([OsString::from("--out"), run_dir.join("graph.json").into(), OsString::from("--plot"), run_dir.join("graph.png").into()]);
        args
    }

    /// `lcrl-learner`'s arguments; the graph (connection local) comes from
    /// `graph_builder`, a gRPC URL.
    pub fn learner_args(&self, listen: &str, run_id: &str, train_config: &Path, learner_dir: &Path, graph_builder: Option<&str>) -> anyhow::Result<Vec<OsString>> {
        let mut args = self.learner_base_args(listen, run_id, train_config, learner_dir);
        // The learner evaluates its hand-over beside the preset's headroom
        // reference, as summary.json shows it.
        if let Some(headroom) = &self.job.headroom {
            args.extend([OsString::from("--headroom"), headroom.into()]);
        }
        match (self.job.connection, graph_builder) {
            (Connection::Local, Some(url)) => args.extend(os(&["--graph-builder", url])),
            (Connection::Local, None) => bail!("connection local needs the graph builder's URL (--graph-builder)"),
            _ => {}
        }
        Ok(args)
    }

    /// `lcrl-learner`'s arguments with the graph (connection local) from a
    /// graph.json file instead of a graph builder (`lcrl scale` builds it
    /// once for all its points).
    pub fn learner_args_with_graph_file(&self, listen: &str, run_id: &str, train_config: &Path, learner_dir: &Path, graph: &Path) -> Vec<OsString> {
        let mut args = self.learner_base_args(listen, run_id, train_config, learner_dir);
        if self.job.connection == Connection::Local {
            args.extend([OsString::from("--graph"), graph.into()]);
        }
        args
    }

    /// Everything but where the graph comes from.
    fn learner_base_args(&self, listen: &str, run_id: &str, train_config: &Path, learner_dir: &Path) -> Vec<OsString> {
        let mut args = os(&["--env", &self.job.env, "--listen", listen, "--run-id", run_id, "--checkpoint-secs", "30"]);
        args.extend(os(&["--algo", algo_name(self.job.algo), "--connection", connection_name(self.job.connection)]));
        // The run's budget lives in the learner: it drives the schedules
        // and ends training (compose and Kubernetes get it the same way).
        args.extend(os(&["--episodes", &self.job.episodes.to_string()]));
        if let Some(ratio) = &self.job.replay_ratio {
            args.extend(os(&["--replay-ratio", ratio]));
        }
        for (flag, value) in [
            ("--publish-every", self.job.publish_every),
            ("--replay-slack", self.job.replay_slack),
            ("--queued-batches", self.job.queued_batches),
            ("--max-staleness", self.max_staleness()),
        ] {
            if let Some(value) = value {
                args.extend(os(&[flag, &value.to_string()]));
            }
        }
        args.extend([OsString::from("--config"), train_config.into(), OsString::from("--run-dir"), learner_dir.into()]);
        args
    }

    /// `lcrl-actor`'s arguments. `actor_id` None: the actor names itself
    /// (host name and process id), as replicas in containers must.
    pub fn actor_args(&self, learner: &str, run_id: &str, transport: &str, actor_id: Option<&str>, seed_offset: u64) -> Vec<OsString> {
        let mut args = os(&["--learner", learner, "--run-id", run_id, "--transport", transport]);
        args.extend(os(&["--envs", &self.job.envs_per_actor.to_string(), "--seed", &self.train.run.seed.wrapping_add(seed_offset).to_string()]));
        if let Some(batch) = self.job.actor_batch {
            args.extend(os(&["--batch", &batch.to_string()]));
        }
        if let Some(id) = actor_id {
            args.extend(os(&["--actor-id", id]));
        }
        args
    }
}

/// Where a run's learner computes (`lcrl run`, `lcrl scale`): overrides of
/// the preset's run.device and run.threads. Actors always use the CPU.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct LearnerCompute {
    /// The learner's device (overrides run.device).
    #[arg(long, value_parser = ["cpu", "cuda"])]
    pub device: Option<String>,
    /// The learner's libtorch intra-op threads (overrides run.threads; 0:
    /// the cores this machine has left over after the actors, 1 to 4).
    #[arg(long)]
    pub threads: Option<usize>,
}

impl Preset {
    /// Applies `compute`'s overrides and checks the result.
    pub fn set_compute(&mut self, compute: &LearnerCompute) -> anyhow::Result<()> {
        if let Some(device) = &compute.device {
            self.train.run.device = device.clone();
        }
        if let Some(threads) = compute.threads {
            self.train.run.threads = threads;
        }
        self.train.validate()?;
        Ok(())
    }

    /// run.threads as a count for a learner that shares this machine with
    /// the job's actors (one core each): 0 ("auto") becomes the cores left
    /// over, so learner and actors do not fight for cores.
    pub fn pin_learner_threads(&mut self) {
        self.train.run.threads = lcrl_learner::device::torch::resolve_threads(self.train.run.threads, self.job.actors);
    }
}

fn os(args: &[&str]) -> Vec<OsString> {
    args.iter().map(OsString::from).collect()
}

/// The CLI spelling of an algorithm (`--algo`).
pub(crate) fn algo_name(algo: Algo) -> &'static str {
    match algo {
        Algo::Ddpg => "ddpg",
        Algo::Ppo => "ppo",
    }
}

/// The CLI spelling of a connection (`--connection`).
pub(crate) fn connection_name(connection: Connection) -> &'static str {
    match connection {
        Connection::Local => "local",
        Connection::Global => "global",
        Connection::FullSubnets => "full-subnets",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// PPO runs asynchronous by default (PPO_MAX_STALENESS, by the parity
    /// study's rule); a preset's own bound wins, 0 included; DDPG has none.
    #[test]
    fn ppo_presets_lag_one_version_unless_they_say() {
        let learner_lag = |p: &Preset| {
            let args = strings(&p.learner_args("127.0.0.1:0", "r", Path::new("/t.toml"), Path::new("/l"), Some("http://g:1")).unwrap());
            value(&args, "--max-staleness").map(str::to_string)
        };
        let mut ppo = preset("");
        ppo.job.algo = lcrl_learner::Algo::Ppo;
        assert_eq!(learner_lag(&ppo), Some(PPO_MAX_STALENESS.to_string()));
        ppo.job.max_staleness = Some(0);
        assert_eq!(learner_lag(&ppo).as_deref(), Some("0"), "on-policy when the preset says so");
        assert_eq!(learner_lag(&preset("")), None, "DDPG has no lag bound");
    }

    fn preset(extra: &str) -> Preset {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.toml");
        let text = format!("[job]\nenv = \"lti-paper\"\nalgo = \"ddpg\"\nconnection = \"local\"\nepisodes = 40\nactors = 3\nenvs_per_actor = 2\n{extra}\n[run]\ngraph_samples = 32\nseed = 5\n");
        std::fs::write(&path, text).unwrap();
        Preset::load(&path).unwrap()
    }

    fn strings(args: &[OsString]) -> Vec<String> {
        args.iter().map(|a| a.to_string_lossy().into_owned()).collect()
    }

    /// The value after `flag` in `args`.
    fn value<'a>(args: &'a [String], flag: &str) -> Option<&'a str> {
        args.iter().position(|a| a == flag).and_then(|k| args.get(k + 1)).map(String::as_str)
    }

    /// Every process of a run is told the preset's settings: the graph
    /// builder its CS3 samples, seed and threshold; the learner the
    /// environment, algorithm, connection, budget, replay ratio, config and
    /// graph source; each actor its batch size, envs and its own seed.
    #[test]
    fn a_preset_becomes_each_processs_command_line() {
        let p = preset("replay_ratio = \"unlimited\"\ngraph_threshold = 0.25\npublish_every = 7\nreplay_slack = 48\nqueued_batches = 2\nactor_batch = 16\nmax_staleness = 3\n");
        let graph = strings(&p.graph_builder_args("127.0.0.1:0", Path::new("/runs/x")));
        assert_eq!(value(&graph, "--env"), Some("lti-paper"));
        assert_eq!((value(&graph, "--samples"), value(&graph, "--seed"), value(&graph, "--threshold")), (Some("32"), Some("5"), Some("0.25")));
        assert_eq!(value(&graph, "--out"), Some("/runs/x/graph.json"));

        let learner = strings(&p.learner_args("127.0.0.1:0", "run-a", Path::new("/t.toml"), Path::new("/runs/x/learner"), Some("http://g:1")).unwrap());
        for (flag, expected) in [
            ("--env", "lti-paper"),
            ("--algo", "ddpg"),
            ("--connection", "local"),
            ("--episodes", "40"),
            ("--replay-ratio", "unlimited"),
            ("--publish-every", "7"),
            ("--replay-slack", "48"),
            ("--queued-batches", "2"),
            ("--max-staleness", "3"),
            ("--run-id", "run-a"),
            ("--config", "/t.toml"),
            ("--run-dir", "/runs/x/learner"),
            ("--graph-builder", "http://g:1"),
        ] {
            assert_eq!(value(&learner, flag), Some(expected), "{flag} in {learner:?}");
        }
        // A locally connected learner cannot run without its graph.
        assert!(p.learner_args("127.0.0.1:0", "r", Path::new("/t"), Path::new("/l"), None).is_err());
        let from_file = strings(&p.learner_args_with_graph_file("127.0.0.1:0", "r", Path::new("/t"), Path::new("/l"), Path::new("/g.json")));
        assert_eq!(value(&from_file, "--graph"), Some("/g.json"));

        let first = strings(&p.actor_args("http://l:2", "run-a", "shm", None, 0));
        let third = strings(&p.actor_args("http://l:2", "run-a", "shm", Some("actor-2"), 2));
        assert_eq!((value(&first, "--learner"), value(&first, "--transport"), value(&first, "--envs")), (Some("http://l:2"), Some("shm"), Some("2")));
        assert_eq!((value(&first, "--seed"), value(&third, "--seed")), (Some("5"), Some("7")), "actors explore with distinct seeds");
        assert_eq!((value(&first, "--batch"), value(&third, "--batch")), (Some("16"), Some("16")));
        assert_eq!((value(&first, "--actor-id"), value(&third, "--actor-id")), (None, Some("actor-2")));
    }

    /// Without a replay ratio the processes get none (their own defaults:
    /// Algorithm 2's ratio); without a threshold the graph builder is given
    /// T_rule (a bare `connection = "local"`), "auto" names the same, and
    /// a named T is passed as named; a global learner gets no graph.
    #[test]
    fn unset_settings_are_left_to_each_process() {
        let p = preset("");
        let graph = strings(&p.graph_builder_args("127.0.0.1:0", Path::new("/r")));
        assert_eq!(value(&graph, "--threshold"), Some("1"));
        for (given, passed) in [("graph_threshold = \"auto\"", "1"), ("graph_threshold = 0.1", "0.1")] {
            assert_eq!(value(&strings(&preset(given).graph_builder_args("127.0.0.1:0", Path::new("/r"))), "--threshold"), Some(passed), "{given}");
        }
        let learner = strings(&p.learner_args("127.0.0.1:0", "r", Path::new("/t"), Path::new("/l"), Some("http://g:1")).unwrap());
        for flag in ["--replay-ratio", "--publish-every", "--replay-slack", "--queued-batches"] {
            assert_eq!(value(&learner, flag), None, "{flag}");
        }
        assert_eq!(value(&strings(&p.actor_args("http://l:2", "r", "shm", None, 0)), "--batch"), None);
        let mut global = p.clone();
        global.job.connection = Connection::Global;
        let learner = strings(&global.learner_args("127.0.0.1:0", "r", Path::new("/t"), Path::new("/l"), None).unwrap());
        assert!(!learner.iter().any(|a| a == "--graph-builder" || a == "--graph"), "{learner:?}");
    }

    /// Lag settings out of range fail the preset check, naming the key.
    #[test]
    fn lag_settings_out_of_range_fail_the_check() {
        preset("publish_every = 1\nqueued_batches = 1024\nactor_batch = 1\n").check().unwrap();
        let mut good = preset("");
        let edits: [(fn(&mut Preset), &str); 11] = [
            (|p| p.job.publish_every = Some(0), "job.publish_every"),
            // The learner's own bounds (issue 71), said before the run.
            (|p| p.job.publish_every = Some(u64::MAX), "job.publish_every"),
            (|p| p.job.replay_slack = Some(1_000_001), "job.replay_slack"),
            (|p| p.job.replay_ratio = Some("1e300".into()), "job.replay_ratio"),
            (|p| p.job.replay_ratio = Some("often".into()), "job.replay_ratio"),
            (|p| p.job.queued_batches = Some(0), "job.queued_batches"),
            (|p| p.job.queued_batches = Some(1025), "job.queued_batches"),
            (|p| p.job.actor_batch = Some(0), "job.actor_batch"),
            (|p| p.job.actor_batch = Some(4097), "job.actor_batch"),
            // A process each on this machine: bounded, not a fork bomb.
            (|p| p.job.actors = MAX_ACTORS + 1, "job.actors"),
            (|p| p.job.envs_per_actor = usize::MAX, "job.envs_per_actor"),
        ];
        for (edit, key) in edits {
            let mut p = good.clone();
            edit(&mut p);
            let err = p.check().unwrap_err().to_string();
            assert!(err.contains(key), "{err}");
        }
        good.job.queued_batches = Some(1024);
        good.check().unwrap();
    }

    /// `--threads 0` (automatic) leaves a run's learner the cores its
    /// actors do not use, at least one; device and thread overrides are
    /// checked.
    #[test]
    fn learner_compute_overrides_are_checked_and_threads_pinned() {
        let mut p = preset("");
        p.set_compute(&LearnerCompute { device: Some("cpu".into()), threads: Some(0) }).unwrap();
        p.pin_learner_threads();
        assert_eq!(p.train.run.threads, lcrl_learner::device::torch::available_cores().saturating_sub(3).clamp(1, lcrl_learner::device::torch::AUTO_MAX_THREADS));
        let err = p.set_compute(&LearnerCompute { device: None, threads: Some(1 << 20) }).unwrap_err().to_string();
        assert!(err.contains("run.threads"), "{err}");
    }
}
