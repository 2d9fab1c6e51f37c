//! What a `--connection` or a study's `connections` entry names: the kind
//! of actor (local, global, full-subnets) and, for a local actor, where its
//! graph G comes from (docs/lcrl-value.md):
//!
//! - `local`, `local@T`: measured by CS3 with eq. 7's threshold T;
//! - `graph:PATH`: a graph file, e.g. references/peg-eq21/graph.json;
//! - `random@K`: K edges drawn at random (`lcrl graph --random K`), the
//!   control for "does the structure matter, or only the input count?";
//! - `global`, `full-subnets`: no graph.

use std::path::PathBuf;

use anyhow::{bail, Context};
use lcrl_learner::Connection;

/// The publication's threshold T of eq. 7, used by a plain `local`.
pub const DEFAULT_THRESHOLD: f64 = lcrl_graph_builder::PAPER_THRESHOLD;

/// One parsed connection.
#[derive(Debug, Clone, PartialEq)]
pub enum ConnectionSpec {
    Local { threshold: f64 },
    Graph { path: PathBuf },
    Random { edges: usize },
    Global,
    FullSubnets,
}

impl ConnectionSpec {
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let unknown = || {
            format!(
                "unknown connection \"{text}\"; use local (T = {DEFAULT_THRESHOLD}), local@T such as local@0.25, \
                 graph:PATH (a graph.json), random@K (K random edges), global or full-subnets"
            )
        };
        match text {
            "local" => return Ok(ConnectionSpec::Local { threshold: DEFAULT_THRESHOLD }),
            "global" => return Ok(ConnectionSpec::Global),
            "full-subnets" => return Ok(ConnectionSpec::FullSubnets),
            _ => {}
        }
        if let Some(path) = text.strip_prefix("graph:") {
            if path.is_empty() {
                bail!("connection \"{text}\": give the graph file after graph:, e.g. graph:references/peg-eq21/graph.json");
            }
            return Ok(ConnectionSpec::Graph { path: PathBuf::from(path) });
        }
        if let Some(k) = text.strip_prefix("random@") {
            let edges: usize = k.parse().map_err(|_| anyhow::anyhow!("connection \"{text}\": \"{k}\" is not an edge count"))?;
            if edges == 0 {
                bail!("connection \"{text}\": K must be at least the number of actions");
            }
            return Ok(ConnectionSpec::Random { edges });
        }
        let t = text.strip_prefix("local@").with_context(unknown)?;
        let threshold: f64 = t.parse().map_err(|_| anyhow::anyhow!("{}: \"{t}\" is not a number", unknown()))?;
        if !(threshold.is_finite() && threshold >= 0.0) {
            bail!("connection \"{text}\": the threshold T must be a finite number ≥ 0");
        }
        Ok(ConnectionSpec::Local { threshold })
    }

    /// The name in tables, folders and plots: local@0.1, graph:…, random@23.
    pub fn label(&self) -> String {
        match self {
            ConnectionSpec::Local { threshold } => format!("local@{threshold}"),
            ConnectionSpec::Graph { path } => format!("graph:{}", path.display()),
            ConnectionSpec::Random { edges } => format!("random@{edges}"),
            ConnectionSpec::Global => "global".into(),
            ConnectionSpec::FullSubnets => "full-subnets".into(),
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
            other => other.label(),
        }
    }

    /// The actor this connection trains.
    pub fn connection(&self) -> Connection {
        match self {
            ConnectionSpec::Local { .. } | ConnectionSpec::Graph { .. } | ConnectionSpec::Random { .. } => Connection::Local,
            ConnectionSpec::Global => Connection::Global,
            ConnectionSpec::FullSubnets => Connection::FullSubnets,
        }
    }

    /// T, for graphs measured by CS3.
    pub fn threshold(&self) -> Option<f64> {
        match self {
            ConnectionSpec::Local { threshold } => Some(*threshold),
            _ => None,
        }
    }

    /// Whether the actor has a graph (every local kind).
    pub fn has_graph(&self) -> bool {
        self.connection() == Connection::Local
    }

    /// The given (not measured) graph for an environment: the file of
    /// `graph:PATH`, checked against it, or the draw of `random@K` with
    /// `draw_seed`. None for CS3 graphs and graph-less actors.
    pub fn given_graph(&self, spec: &lcrl_sim::EnvSpec, draw_seed: u64) -> anyhow::Result<Option<lcrl_graph_builder::GraphReport>> {
        Ok(match self {
            ConnectionSpec::Graph { path } => Some(lcrl_graph_builder::given::load_for(path, spec)?),
            ConnectionSpec::Random { edges } => Some(lcrl_graph_builder::given::random(spec, *edges, draw_seed)?),
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
        for text in ["local@0.1", "local@0.5", "global", "full-subnets", "random@23", "graph:references/peg-eq21/graph.json"] {
            let spec = ConnectionSpec::parse(text).unwrap();
            assert_eq!(spec.label(), text);
            assert_eq!(ConnectionSpec::parse(&spec.label()).unwrap(), spec);
        }
        assert_eq!(ConnectionSpec::parse("local").unwrap(), ConnectionSpec::Local { threshold: 0.1 });
        assert_eq!(ConnectionSpec::parse("random@23").unwrap().connection(), Connection::Local);
        assert_eq!(ConnectionSpec::parse("graph:g.json").unwrap().threshold(), None);
        assert_eq!(ConnectionSpec::parse("graph:references/peg-eq21/graph.json").unwrap().slug(), "graph-references-peg-eq21-graph");
    }

    #[test]
    fn bad_forms_say_what_is_wrong() {
        let err = |t: &str| ConnectionSpec::parse(t).unwrap_err().to_string();
        assert!(err("loco").contains("graph:PATH") && err("loco").contains("random@K"));
        assert!(err("random@x").contains("\"x\" is not an edge count"));
        assert!(err("random@0").contains("at least"));
        assert!(err("graph:").contains("give the graph file"));
        assert!(err("local@-1").contains("≥ 0"));
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
