//! What a study file commits to before its runs, beyond its cells: the
//! primary contrasts and the family-wise rule over them, equivalence
//! margins, and 2 × 2 factorial designs (docs/experiment.md, "What a study
//! names before its runs"). Checked on load like the rest of the file; the
//! tests themselves are in crate::experiment::inference, ::primary and
//! ::named.

use anyhow::bail;
use lcrl_learner::Algo;
use serde::{Deserialize, Serialize};

use crate::connection::ConnectionSpec;
use crate::preset::algo_name;

/// What the checks need of a study file: its environments, algorithms
/// and connections as written.
pub struct Names<'a> {
    pub environments: &'a [String],
    pub algorithms: &'a [Algo],
    pub connections: &'a [String],
}


/// `[primary]`: one contrast (`metric`, `a`, `b`, `algorithm`), or a
/// family of them under a stated rule:
/// `family = "holm"`, `alpha = 0.05`, `[[primary.contrasts]]` ….
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Primary {
    Family(PrimaryFamily),
    One(PrimaryContrast),
}

/// Several primary contrasts tested together: Holm's step-down rule (or
/// Bonferroni) keeps the chance of any false claim among them at `alpha`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrimaryFamily {
    /// `holm` or `bonferroni`.
    pub family: String,
    #[serde(default = "default_alpha")]
    pub alpha: f64,
    /// What the study decides from these contrasts (e.g. which shipped
    /// default changes), in words: committed with the contrasts, before
    /// any run, and printed beside them in the report.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decision: Option<String>,
    pub contrasts: Vec<PrimaryContrast>,
}

/// The family-wise rules a file may state.
pub const FAMILY_RULES: [&str; 2] = ["holm", "bonferroni"];

fn default_alpha() -> f64 {
    0.05
}

impl Primary {
    /// Its contrasts, in the file's order.
    pub fn contrasts(&self) -> Vec<&PrimaryContrast> {
        match self {
            Primary::One(c) => vec![c],
            Primary::Family(f) => f.contrasts.iter().collect(),
        }
    }

    /// Every contrast stratified over all the study's environments (its
    /// `environments` lists dropped): for a study moved to other tasks.
    pub fn stratify_over_all(&mut self) {
        match self {
            Primary::One(c) => c.environments.clear(),
            Primary::Family(f) => f.contrasts.iter_mut().for_each(|c| c.environments.clear()),
        }
    }

    /// The decision rule the file states, if any.
    pub fn decision(&self) -> Option<&str> {
        match self {
            Primary::One(_) => None,
            Primary::Family(f) => f.decision.as_deref(),
        }
    }

    /// The rule and level (a single contrast: none needed, α = 0.05).
    pub fn rule(&self) -> (&str, f64) {
        match self {
            Primary::One(_) => ("none", 0.05),
            Primary::Family(f) => (f.family.as_str(), f.alpha),
        }
    }

    pub fn check(&self, file: &Names) -> anyhow::Result<()> {
        if let Primary::Family(f) = self {
            if !FAMILY_RULES.contains(&f.family.as_str()) {
                bail!("`primary.family` \"{}\" must be one of {}", f.family, FAMILY_RULES.join(", "));
            }
            if !(f.alpha > 0.0 && f.alpha < 0.5) {
                bail!("`primary.alpha` must lie between 0 and 0.5, got {}", f.alpha);
            }
            if f.contrasts.is_empty() {
                bail!("`primary.contrasts` is empty: list at least one `[[primary.contrasts]]`");
            }
        }
        for (k, c) in self.contrasts().into_iter().enumerate() {
            c.check(file).map_err(|e| anyhow::anyhow!("primary contrast {}: {e:#}", k + 1))?;
        }
        Ok(())
    }
}

/// A study's primary contrast: the one comparison its file names before
/// any run, so that the result it reports first was not picked after
/// seeing the data (tested by crate::experiment::primary).
/// Written as `[primary]`, e.g.
/// `metric = "eval_return"`, `a = "local@1"`, `b = "global"`,
/// `algorithm = "ddpg"` (strata: every environment, or `environments`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrimaryContrast {
    /// One of [`METRICS`].
    pub metric: String,
    /// The connections compared, a − b, as `connections` writes them.
    pub a: String,
    pub b: String,
    pub algorithm: Algo,
    /// The strata; every environment of the study when left out.
    #[serde(default)]
    pub environments: Vec<String>,
}

impl PrimaryContrast {
    /// Checked with the file, before a single run.
    pub fn check(&self, file: &Names) -> anyhow::Result<()> {
        if !METRICS.contains(&self.metric.as_str()) {
            bail!("`primary.metric` \"{}\" must be one of {}", self.metric, METRICS.join(", "));
        }
        let labels: Vec<String> = file.connections.iter().filter_map(|c| ConnectionSpec::parse(c).ok()).map(|c| c.label()).collect();
        for (key, connection) in [("a", &self.a), ("b", &self.b)] {
            let label = ConnectionSpec::parse(connection)?.label();
            if !labels.contains(&label) {
                bail!("`primary.{key}` \"{connection}\" is not one of `connections` ({})", labels.join(", "));
            }
        }
        let rows = |c: &str| matches!(ConnectionSpec::parse(c), Ok(ConnectionSpec::RandomRows { .. }));
        if self.metric == "episodes_to_best_constant" && (rows(&self.a) || rows(&self.b)) {
            bail!("`primary`: a random-rows cell's unit is the draw, which has no one time to the best constant; compare it on a mean (eval_return, final_return, auc_100)");
        }
        if ConnectionSpec::parse(&self.a)?.label() == ConnectionSpec::parse(&self.b)?.label() {
            bail!("`primary.a` and `primary.b` are the same connection");
        }
        if !file.algorithms.contains(&self.algorithm) {
            bail!("`primary.algorithm` {} is not one of `algorithms`", algo_name(self.algorithm));
        }
        if let Some(env) = self.environments.iter().find(|e| !file.environments.contains(e)) {
            bail!("`primary.environments`: {env} is not one of `environments`");
        }
        Ok(())
    }

    /// In words, as a report's heading gives it.
    pub fn describe(&self, environments: &[String]) -> String {
        format!("{}, {} − {}, {}, stratified by environment over {}", self.metric, self.a, self.b, algo_name(self.algorithm).to_uppercase(), environments.join(", "))
    }
}

/// `[[equivalence]]`: a − b is called equivalent when the 90% interval of
/// the (stratified) difference lies inside ±`margin` (two one-sided tests
/// at 5%); the margin is named before the runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Equivalence {
    pub metric: String,
    pub a: String,
    pub b: String,
    pub algorithm: Algo,
    pub margin: f64,
    /// The strata; every environment of the study when left out.
    #[serde(default)]
    pub environments: Vec<String>,
}

impl Equivalence {
    pub fn check(&self, file: &Names) -> anyhow::Result<()> {
        PrimaryContrast { metric: self.metric.clone(), a: self.a.clone(), b: self.b.clone(), algorithm: self.algorithm, environments: self.environments.clone() }
            .check(file)?;
        if !WELCH_METRICS.contains(&self.metric.as_str()) {
            bail!("an equivalence test needs a mean difference: metric one of {}", WELCH_METRICS.join(", "));
        }
        if !(self.margin.is_finite() && self.margin > 0.0) {
            bail!("`margin` must be a finite number above 0, got {}", self.margin);
        }
        Ok(())
    }
}

/// `[[factorial]]`: a 2 × 2 design, each cell `ENV/CONNECTION` of one
/// algorithm. `cells[r][c]` is level r of the first factor and level c of
/// the second; the report gives both main effects (level 2 − level 1,
/// averaged over the other factor) and the interaction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Factorial {
    pub name: String,
    pub metric: String,
    pub algorithm: Algo,
    /// The two factors' names, e.g. ["preset", "connection"].
    pub factors: [String; 2],
    pub cells: [[String; 2]; 2],
}

impl Factorial {
    pub fn check(&self, file: &Names) -> anyhow::Result<()> {
        if !WELCH_METRICS.contains(&self.metric.as_str()) {
            bail!("factorial \"{}\": metric must be one of {}", self.name, WELCH_METRICS.join(", "));
        }
        if !file.algorithms.contains(&self.algorithm) {
            bail!("factorial \"{}\": algorithm {} is not one of `algorithms`", self.name, algo_name(self.algorithm));
        }
        let labels: Vec<String> = file.connections.iter().filter_map(|c| ConnectionSpec::parse(c).ok()).map(|c| c.label()).collect();
        let mut seen = Vec::new();
        for cell in self.cells.iter().flatten() {
            let (env, connection) = split_cell(cell)?;
            if !file.environments.iter().any(|e| e == env) {
                bail!("factorial \"{}\": cell \"{cell}\": {env} is not one of `environments`", self.name);
            }
            let label = ConnectionSpec::parse(connection)?.label();
            if !labels.contains(&label) {
                bail!("factorial \"{}\": cell \"{cell}\": {connection} is not one of `connections`", self.name);
            }
            if seen.contains(&(env, label.clone())) {
                bail!("factorial \"{}\": cell \"{cell}\" appears twice", self.name);
            }
            seen.push((env, label));
        }
        Ok(())
    }
}

/// `ENV/CONNECTION` → (ENV, CONNECTION); the connection may hold '/'
/// (graph:PATH), the environment may not.
pub fn split_cell(cell: &str) -> anyhow::Result<(&str, &str)> {
    match cell.split_once('/') {
        Some((env, connection)) if !env.is_empty() && !connection.is_empty() => Ok((env, connection)),
        _ => bail!("cell \"{cell}\" must read ENV/CONNECTION, e.g. peg-group1/local@0.5"),
    }
}

/// Metrics with one number per run, compared by mean difference (Welch).
pub const WELCH_METRICS: [&str; 3] = ["eval_return", "final_return", "auc_100"];

/// Every metric a contrast may name: the mean-difference ones and
/// `episodes_to_best_constant`, a time to an event censored at the budget
/// (compared by the log-rank test).
pub const METRICS: [&str; 4] = ["eval_return", "final_return", "auc_100", "episodes_to_best_constant"];

/// Checks `[[equivalence]]` and `[[factorial]]` entries of a file.
pub fn check_designs(file: &Names, equivalence: &[Equivalence], factorial: &[Factorial]) -> anyhow::Result<()> {
    for (k, e) in equivalence.iter().enumerate() {
        e.check(file).map_err(|err| anyhow::anyhow!("equivalence {}: {err:#}", k + 1))?;
    }
    for f in factorial {
        f.check(file)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::config::Experiment;

    const BASE: &str = "name = \"t\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"local@0.1\", \"global\", \"full-subnets\"]\nseeds = 3\nepisodes = { ppo = 10 }\n";

    #[test]
    fn a_primary_family_parses_and_is_checked() {
        let family = format!(
            "{BASE}[primary]\nfamily = \"holm\"\n[[primary.contrasts]]\nmetric = \"eval_return\"\na = \"local@0.1\"\nb = \"global\"\nalgorithm = \"ppo\"\n\
             [[primary.contrasts]]\nmetric = \"episodes_to_best_constant\"\na = \"local@0.1\"\nb = \"global\"\nalgorithm = \"ppo\"\n"
        );
        let e = Experiment::parse(&family).unwrap();
        let primary = e.file.primary.as_ref().unwrap();
        assert_eq!(primary.contrasts().len(), 2);
        assert_eq!(primary.rule(), ("holm", 0.05));
        let err = |text: String| format!("{:#}", Experiment::parse(&text).unwrap_err());
        assert!(err(family.replace("\"holm\"", "\"hope\"")).contains("must be one of holm, bonferroni"));
        assert!(err(family.replace("episodes_to_best_constant", "speed")).contains("primary contrast 2"));
        // The single form still reads as it did.
        let one = format!("{BASE}[primary]\nmetric = \"auc_100\"\na = \"local@0.1\"\nb = \"global\"\nalgorithm = \"ppo\"\n");
        assert_eq!(Experiment::parse(&one).unwrap().file.primary.unwrap().rule().0, "none");
    }

    #[test]
    fn equivalence_and_factorials_are_checked_by_name() {
        let eq = format!("{BASE}[[equivalence]]\nmetric = \"eval_return\"\na = \"full-subnets\"\nb = \"global\"\nalgorithm = \"ppo\"\nmargin = 0.3\n");
        assert_eq!(Experiment::parse(&eq).unwrap().file.equivalence[0].margin, 0.3);
        let err = |text: String| format!("{:#}", Experiment::parse(&text).unwrap_err());
        assert!(err(eq.replace("0.3", "-1")).contains("`margin` must be a finite number above 0"));
        assert!(err(eq.replace("\"eval_return\"", "\"episodes_to_best_constant\"")).contains("needs a mean difference"));
        let fac = format!(
            "{BASE}[[factorial]]\nname = \"mask × split\"\nmetric = \"eval_return\"\nalgorithm = \"ppo\"\nfactors = [\"split\", \"mask\"]\n\
             cells = [[\"lti-paper/global\", \"lti-paper/global\"], [\"lti-paper/full-subnets\", \"lti-paper/local\"]]\n"
        );
        assert!(err(fac.clone()).contains("appears twice"));
        let fac = fac.replacen("\"lti-paper/global\", \"lti-paper/global\"", "\"lti-paper/global\", \"lti-paper/local@0.2\"", 1);
        assert!(err(fac.clone()).contains("local@0.2 is not one of `connections`"));
        assert!(err(fac.replace("lti-paper/local@0.2", "local@0.2")).contains("must read ENV/CONNECTION"));
    }
}
