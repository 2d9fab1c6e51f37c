//! What a `--connection` or a study's `connections` entry names: the kind
//! of actor (local, global, full-subnets) and, for a local actor, where its
//! graph G comes from (docs/lcrl-value.md):
//!
//! - `local`, `local@T`: measured by CS3 with eq. 7's threshold T;
//! - `graph:PATH`: a graph file, e.g. references/peg-eq21/graph.json;
//! - `random@K`: K edges drawn at random (`lcrl graph --random K`), the
//!   control for "does the structure matter, or only the input count?";
//! - `random-rows@CONNECTION` (studies): for each of 10 draws (or N with
//!   `+draws=N`), every action keeps the number of inputs CONNECTION's
//!   measured graph gives it, the states drawn at random; run seed s trains
//!   on draw s mod N, and each draw's seed comes from the environment and
//!   the draw index, never from the run (docs/experiment.md);
//! - `global`, `full-subnets`: no graph;
//! - `global+match=CONNECTION` (studies): a global actor with as many
//!   parameters as the local actor of CONNECTION on the same environment
//!   (its hidden widths chosen by `lcrl train --match-params`), so a local
//!   actor's lead cannot be its size.
//!
//! In a study, a measured or random graph takes modifiers after `+`:
//! - `+per-seed`: each run gets its own graph (CS3 with the run's seed, or
//!   the run's own draw), so no result rests on one measured graph;
//! - `+ACTION=T`, `+ACTION=none` (local@T only): that action's row of G
//!   under its own rule, from the same CS3 values (`lcrl graph --row`),
//!   e.g. `local@1+dz=0.1` or `local@0.1+dz=none` (the dz control).

use std::path::PathBuf;

use anyhow::{bail, Context};
use lcrl_graph_builder::RowRule;
use lcrl_learner::Connection;

/// T of eq. 7 for a plain `local`: T_rule, the above-average rule
/// (docs/method.md, "Choosing T"), as `connection = "local"` in a config
/// (experiments/default-graph.toml's decision); `local@0.1` is the
/// publication's.
pub const DEFAULT_THRESHOLD: f64 = lcrl_graph_builder::choose_t::RULE_THRESHOLD;

/// One parsed connection.
#[derive(Debug, Clone, PartialEq)]
pub enum ConnectionSpec {
    Local { threshold: f64, rows: Vec<RowRule>, per_seed: bool },
    Graph { path: PathBuf },
    Random { edges: usize, per_seed: bool },
    /// Degree-matched random rows of a measured graph (`local@T`, row
    /// rules allowed, no +per-seed), in `draws` draws.
    RandomRows { of: Box<ConnectionSpec>, draws: u64 },
    Global,
    FullSubnets,
    /// A global actor sized to the local actor of `to` (`global+match=…`).
    MatchedGlobal { to: Box<ConnectionSpec> },
}

/// A graph a study makes before its runs (crate::experiment::plan):
/// measured by CS3 at T with any row rules, or drawn at random.
#[derive(Debug, Clone, PartialEq)]
pub enum MadeGraph {
    Measured { threshold: f64, rows: Vec<RowRule> },
    Drawn { edges: usize },
    /// Degree-matched rows drawn from the graph measured at T with `rows`
    /// (one graph per draw index).
    RowsDrawn { threshold: f64, rows: Vec<RowRule> },
}

impl MadeGraph {
    /// Its folder under graphs/ENV/: T1, T1+dz=0.1, random@23.
    pub fn folder(&self) -> String {
        match self {
            MadeGraph::Measured { threshold, rows } => format!("T{threshold}{}", rows.iter().map(|r| format!("+{}", r.text())).collect::<String>()),
            MadeGraph::Drawn { edges } => format!("random@{edges}"),
            MadeGraph::RowsDrawn { .. } => format!("random-rows@{}", self.source().map(|m| m.folder()).unwrap_or_default()),
        }
    }

    /// The folder of one instance: a run's own graph (seedK), or a draw (drawK).
    pub fn instance(&self, k: u64) -> String {
        match self {
            MadeGraph::RowsDrawn { .. } => format!("draw{k}"),
            _ => format!("seed{k}"),
        }
    }

    /// The measured graph a drawn one is made from (random rows).
    pub fn source(&self) -> Option<MadeGraph> {
        match self {
            MadeGraph::RowsDrawn { threshold, rows } => Some(MadeGraph::Measured { threshold: *threshold, rows: rows.clone() }),
            _ => None,
        }
    }
}

/// Draws of a `random-rows@…` connection without `+draws=N`.
pub const DEFAULT_DRAWS: u64 = 10;
/// The most draws `+draws=N` takes (each is a graph task and needs seeds).
pub const MAX_DRAWS: u64 = 1000;

impl ConnectionSpec {
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let unknown = || {
            format!(
                "unknown connection \"{text}\"; use local (T = {DEFAULT_THRESHOLD}), local@T such as local@0.25, \
                 graph:PATH (a graph.json), random@K (K random edges), random-rows@CONNECTION, global, full-subnets or global+match=CONNECTION"
            )
        };
        match text {
            "local" => return Ok(ConnectionSpec::Local { threshold: DEFAULT_THRESHOLD, rows: Vec::new(), per_seed: false }),
            "global" => return Ok(ConnectionSpec::Global),
            "full-subnets" => return Ok(ConnectionSpec::FullSubnets),
            _ => {}
        }
        if let Some(to) = text.strip_prefix("global+match=") {
            let to = Self::parse(to).with_context(|| format!("connection \"{text}\""))?;
            if !to.has_graph() || matches!(to, ConnectionSpec::RandomRows { .. }) {
                bail!("connection \"{text}\": match a local actor (local@T, graph:PATH, random@K), e.g. global+match=local@0.1");
            }
            return Ok(ConnectionSpec::MatchedGlobal { to: Box::new(to) });
        }
        if let Some(rest) = text.strip_prefix("random-rows@") {
            let (of_text, draws) = match rest.rsplit_once("+draws=") {
                Some((of, n)) => (of, n.parse::<u64>().map_err(|_| anyhow::anyhow!("connection \"{text}\": \"{n}\" is not a draw count"))?),
                None => (rest, DEFAULT_DRAWS),
            };
            if !(2..=MAX_DRAWS).contains(&draws) {
                bail!("connection \"{text}\": random rows need from 2 to {MAX_DRAWS} draws");
            }
            let of = Self::parse(of_text).with_context(|| format!("connection \"{text}\""))?;
            if !matches!(of, ConnectionSpec::Local { per_seed: false, .. }) {
                bail!("connection \"{text}\": random rows match a measured graph, local@T (with any +ACTION=T rows, without +per-seed), e.g. random-rows@local@0.5");
            }
            return Ok(ConnectionSpec::RandomRows { of: Box::new(of), draws });
        }
        if let Some(path) = text.strip_prefix("graph:") {
            if path.is_empty() {
                bail!("connection \"{text}\": give the graph file after graph:, e.g. graph:references/peg-eq21/graph.json");
            }
            return Ok(ConnectionSpec::Graph { path: PathBuf::from(path) });
        }
        let mut parts = text.split('+');
        let base = parts.next().unwrap_or_default();
        let (mut rows, mut per_seed) = (Vec::new(), false);
        for modifier in parts {
            if modifier == "per-seed" {
                per_seed = true;
            } else if modifier.contains('=') {
                let rule = RowRule::parse(modifier).with_context(|| format!("connection \"{text}\""))?;
                if rows.iter().any(|r: &RowRule| r.action == rule.action) {
                    bail!("connection \"{text}\": two rules for the row of {}", rule.action);
                }
                rows.push(rule);
            } else {
                bail!("connection \"{text}\": unknown modifier \"+{modifier}\"; use +per-seed or +ACTION=T / +ACTION=none (e.g. +dz=0.1)");
            }
        }
        if let Some(k) = base.strip_prefix("random@") {
            let edges: usize = k.parse().map_err(|_| anyhow::anyhow!("connection \"{text}\": \"{k}\" is not an edge count"))?;
            if edges == 0 {
                bail!("connection \"{text}\": K must be at least the number of actions");
            }
            if !rows.is_empty() {
                bail!("connection \"{text}\": row rules apply to measured graphs (local@T), not to random draws");
            }
            return Ok(ConnectionSpec::Random { edges, per_seed });
        }
        let t = base.strip_prefix("local@").with_context(unknown)?;
        let threshold: f64 = t.parse().map_err(|_| anyhow::anyhow!("{}: \"{t}\" is not a number", unknown()))?;
        if !(threshold.is_finite() && threshold >= 0.0) {
            bail!("connection \"{text}\": the threshold T must be a finite number ≥ 0");
        }
        Ok(ConnectionSpec::Local { threshold, rows, per_seed })
    }

    /// The name in tables, folders and plots: local@0.1, graph:…, random@23,
    /// local@1+dz=0.1, random@23+per-seed.
    pub fn label(&self) -> String {
        let modifiers = |rows: &[RowRule], per_seed: bool| {
            let mut out: String = rows.iter().map(|r| format!("+{}", r.text())).collect();
            if per_seed {
                out.push_str("+per-seed");
            }
            out
        };
        match self {
            ConnectionSpec::Local { threshold, rows, per_seed } => format!("local@{threshold}{}", modifiers(rows, *per_seed)),
            ConnectionSpec::Graph { path } => format!("graph:{}", path.display()),
            ConnectionSpec::Random { edges, per_seed } => format!("random@{edges}{}", modifiers(&[], *per_seed)),
            ConnectionSpec::RandomRows { of, draws } => {
                format!("random-rows@{}{}", of.label(), if *draws == DEFAULT_DRAWS { String::new() } else { format!("+draws={draws}") })
            }
            ConnectionSpec::Global => "global".into(),
            ConnectionSpec::FullSubnets => "full-subnets".into(),
            ConnectionSpec::MatchedGlobal { to } => format!("global+match={}", to.label()),
        }
    }

    /// A folder name for the label ('/' would nest folders).
    pub fn slug(&self) -> String {
        match self {
            ConnectionSpec::Graph { path } => {
                let stem = path.with_extension("");
                let parts: Vec<String> = stem.components().filter_map(|c| c.as_os_str().to_str()).filter(|c| *c != "." && *c != "..").map(String::from).collect();
                format!("graph-{}", parts.join("-"))
            }
            ConnectionSpec::MatchedGlobal { to } => format!("global+match={}", to.slug()),
            other => other.label(),
        }
    }

    /// The actor this connection trains.
    pub fn connection(&self) -> Connection {
        match self {
            ConnectionSpec::Local { .. } | ConnectionSpec::Graph { .. } | ConnectionSpec::Random { .. } | ConnectionSpec::RandomRows { .. } => Connection::Local,
            ConnectionSpec::Global | ConnectionSpec::MatchedGlobal { .. } => Connection::Global,
            ConnectionSpec::FullSubnets => Connection::FullSubnets,
        }
    }

    /// T, for graphs measured by CS3.
    pub fn threshold(&self) -> Option<f64> {
        match self {
            ConnectionSpec::Local { threshold, .. } => Some(*threshold),
            _ => None,
        }
    }

    /// Whether the actor has a graph (every local kind).
    pub fn has_graph(&self) -> bool {
        self.connection() == Connection::Local
    }

    /// Whether only a study can train it: modifiers its graph tasks apply
    /// (+per-seed, row rules), or a matched global (the study makes the
    /// graph it matches).
    pub fn has_modifiers(&self) -> bool {
        matches!(self, ConnectionSpec::Local { rows, per_seed, .. } if !rows.is_empty() || *per_seed)
            || matches!(self, ConnectionSpec::Random { per_seed: true, .. } | ConnectionSpec::MatchedGlobal { .. } | ConnectionSpec::RandomRows { .. })
    }

    /// The graph a study makes for this connection (none for a given file
    /// or a graph-less actor), and whether each run gets its own; for
    /// `global+match=…`, the graph of the actor it matches.
    pub fn made_graph(&self) -> Option<(MadeGraph, bool)> {
        match self {
            ConnectionSpec::Local { threshold, rows, per_seed } => Some((MadeGraph::Measured { threshold: *threshold, rows: rows.clone() }, *per_seed)),
            ConnectionSpec::Random { edges, per_seed } => Some((MadeGraph::Drawn { edges: *edges }, *per_seed)),
            ConnectionSpec::RandomRows { of, .. } => match of.made_graph()? {
                (MadeGraph::Measured { threshold, rows }, _) => Some((MadeGraph::RowsDrawn { threshold, rows }, true)),
                _ => None,
            },
            ConnectionSpec::MatchedGlobal { to } => to.made_graph(),
            _ => None,
        }
    }

    /// Random rows: the draw a run with `seed` trains on (seed mod draws).
    pub fn draw_of(&self, seed: u64) -> Option<u64> {
        match self {
            ConnectionSpec::RandomRows { draws, .. } => Some(seed % draws),
            _ => None,
        }
    }

    /// The given graph file (`graph:PATH`), also behind `global+match=`.
    pub fn graph_file(&self) -> Option<&std::path::Path> {
        match self {
            ConnectionSpec::Graph { path } => Some(path),
            ConnectionSpec::MatchedGlobal { to } => to.graph_file(),
            _ => None,
        }
    }

    /// The given (not measured) graph for an environment: the file of
    /// `graph:PATH`, checked against it, or the draw of `random@K` with
    /// `draw_seed`. None for CS3 graphs and graph-less actors.
    pub fn given_graph(&self, spec: &lcrl_sim::EnvSpec, draw_seed: u64) -> anyhow::Result<Option<lcrl_graph_builder::GraphReport>> {
        Ok(match self {
            ConnectionSpec::Graph { path } => Some(lcrl_graph_builder::given::load_for(path, spec)?),
            ConnectionSpec::Random { edges, .. } => Some(lcrl_graph_builder::given::random(spec, *edges, draw_seed)?),
            _ => None,
        })
    }
}

impl std::str::FromStr for ConnectionSpec {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        Self::parse(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_form_parses_and_labels_round_trip() {
        for text in [
            "local@0.1", "local@0.5", "global", "full-subnets", "random@23", "graph:references/peg-eq21/graph.json",
            "local@1+per-seed", "random@23+per-seed", "local@1+dz=0.1", "local@0.1+dz=none", "local@1+dz=0.1+dx=none+per-seed",
            "global+match=local@0.1", "global+match=local@1+per-seed", "global+match=graph:g.json",
            "random-rows@local@0.5", "random-rows@local@1+dz=0.1", "random-rows@local@0.5+draws=4",
        ] {
            let spec = ConnectionSpec::parse(text).unwrap();
            assert_eq!(spec.label(), text);
            assert_eq!(ConnectionSpec::parse(&spec.label()).unwrap(), spec);
        }
        assert_eq!(ConnectionSpec::parse("local").unwrap(), ConnectionSpec::Local { threshold: 1.0, rows: Vec::new(), per_seed: false });
        assert_eq!(ConnectionSpec::parse("random@23").unwrap().connection(), Connection::Local);
        assert_eq!(ConnectionSpec::parse("graph:g.json").unwrap().threshold(), None);
        assert_eq!(ConnectionSpec::parse("graph:references/peg-eq21/graph.json").unwrap().slug(), "graph-references-peg-eq21-graph");
        // A matched global is a global actor that needs the graph it matches.
        let matched = ConnectionSpec::parse("global+match=local@1+per-seed").unwrap();
        assert_eq!(matched.connection(), Connection::Global);
        assert!(!matched.has_graph() && matched.has_modifiers());
        assert_eq!(matched.made_graph(), ConnectionSpec::parse("local@1+per-seed").unwrap().made_graph());
        assert_eq!(ConnectionSpec::parse("global+match=graph:a/g.json").unwrap().graph_file(), Some(std::path::Path::new("a/g.json")));
    }

    #[test]
    fn bad_forms_say_what_is_wrong() {
        let err = |t: &str| format!("{:#}", ConnectionSpec::parse(t).unwrap_err());
        assert!(err("loco").contains("graph:PATH") && err("loco").contains("random@K"));
        assert!(err("random@x").contains("\"x\" is not an edge count"));
        assert!(err("random@0").contains("at least"));
        assert!(err("graph:").contains("give the graph file"));
        assert!(err("local@-1").contains("≥ 0"));
        assert!(err("local@1+sometimes").contains("unknown modifier \"+sometimes\""));
        assert!(err("local@1+dz=x").contains("\"x\" is not a number"));
        assert!(err("local@1+dz=0.1+dz=none").contains("two rules for the row of dz"));
        assert!(err("random@23+dz=none").contains("not to random draws"));
        assert!(err("global+match=full-subnets").contains("match a local actor"));
        assert!(err("global+match=locl").contains("unknown connection \"locl\""));
        assert!(!ConnectionSpec::parse("local@1").unwrap().has_modifiers() && ConnectionSpec::parse("random@9+per-seed").unwrap().has_modifiers());
        assert!(err("random-rows@global").contains("match a measured graph"));
        assert!(err("random-rows@local@1+per-seed").contains("without +per-seed"));
        assert!(err("random-rows@local@1+draws=x").contains("\"x\" is not a draw count"));
        assert!(err("random-rows@local@1+draws=1").contains("from 2 to 1000 draws"));
        assert!(err("random-rows@local@1+draws=18446744073709551615").contains("from 2 to 1000 draws"));
        assert!(err("global+match=random-rows@local@1").contains("match a local actor"));
        let rows = ConnectionSpec::parse("random-rows@local@0.5+draws=4").unwrap();
        assert_eq!((rows.connection(), rows.draw_of(9), rows.threshold()), (Connection::Local, Some(1), None));
        assert_eq!(rows.made_graph(), Some((MadeGraph::RowsDrawn { threshold: 0.5, rows: Vec::new() }, true)));
        assert_eq!(rows.made_graph().unwrap().0.folder(), "random-rows@T0.5");
        assert_eq!(rows.made_graph().unwrap().0.source(), Some(MadeGraph::Measured { threshold: 0.5, rows: Vec::new() }));
    }

    #[test]
    fn random_draws_depend_on_the_draw_seed_only() {
        let env = lcrl_sim::make_env("peg-group1").unwrap();
        let spec = ConnectionSpec::parse("random@23").unwrap();
        let a = spec.given_graph(env.spec(), 7).unwrap().unwrap();
        assert_eq!(a.edges(), 23);
        assert_eq!(a, spec.given_graph(env.spec(), 7).unwrap().unwrap());
        assert_ne!(a.g, spec.given_graph(env.spec(), 8).unwrap().unwrap().g);
        let missing = ConnectionSpec::parse("graph:no/such/graph.json").unwrap().given_graph(env.spec(), 0).unwrap_err().to_string();
        assert!(missing.contains("no/such/graph.json"), "{missing}");
    }
}
