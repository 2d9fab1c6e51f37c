//! One action's row of G under its own rule: the controls of the claim
//! study (docs/lcrl-value.md) ask whether a result comes from fewer inputs
//! per action or from one action left without inputs (a learned constant).
//! A row rule rebuilds one row of G from the same phi, at another T of
//! eq. 7 or with no inputs at all; the other rows stay as measured.

use serde::{Deserialize, Serialize};

use crate::{GraphError, GraphReport};

/// `ACTION=T` (the row at eq. 7's threshold T) or `ACTION=none` (no inputs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RowRule {
    pub action: String,
    /// T of eq. 7 for this row; None: the row is empty.
    pub threshold: Option<f64>,
}

impl RowRule {
    /// Parses `dz=0.1` or `dz=none`.
    pub fn parse(text: &str) -> Result<Self, GraphError> {
        let bad = |why: &str| GraphError::Row(format!("row rule \"{text}\": {why}; write ACTION=T (e.g. dz=0.1) or ACTION=none"));
        let (action, value) = text.split_once('=').ok_or_else(|| bad("no '='"))?;
        if action.is_empty() {
            return Err(bad("no action name"));
        }
        let threshold = match value {
            "none" => None,
            t => {
                let t: f64 = t.parse().map_err(|_| bad(&format!("\"{t}\" is not a number")))?;
                if !(t.is_finite() && t > 0.0) {
                    return Err(bad("T must be a finite number above 0"));
                }
                Some(t)
            }
        };
        Ok(RowRule { action: action.to_string(), threshold })
    }

    /// As [`RowRule::parse`] reads it.
    pub fn text(&self) -> String {
        match self.threshold {
            Some(t) => format!("{}={t}", self.action),
            None => format!("{}=none", self.action),
        }
    }
}

impl GraphReport {
    /// G with each rule's row rebuilt from this report's phi (eq. 7 at the
    /// rule's T, or empty). The row's bootstrap stability was measured for
    /// the report's own T, so it becomes NaN (not measured), and its margin
    /// is the one under the rule's T (0 for an empty row). Only for graphs
    /// measured with eq. 7: a given or exact graph has no T to depart from.
    pub fn with_rows(mut self, rules: &[RowRule]) -> Result<Self, GraphError> {
        if rules.is_empty() {
            return Ok(self);
        }
        if self.threshold.is_none() || self.origin.is_some() {
            return Err(GraphError::Row("row rules apply to graphs measured with eq. 7's threshold, not to given or exact graphs".into()));
        }
        for rule in rules {
            let Some(i) = self.action_names.iter().position(|a| *a == rule.action) else {
                return Err(GraphError::Row(format!("row rule \"{}\": no action {} (actions: {})", rule.text(), rule.action, self.action_names.join(", "))));
            };
            if self.rows.iter().chain(rules.iter().take_while(|r| !std::ptr::eq(*r, rule))).any(|r| r.action == rule.action) {
                return Err(GraphError::Row(format!("row rule \"{}\": action {} has a rule already", rule.text(), rule.action)));
            }
            let states = self.states();
            match rule.threshold {
                Some(t) => {
                    self.g[i] = crate::graph::connection_graph(&self.phi, crate::Rule::Threshold(t)).g[i].clone();
                    if let Some(row) = self.margin.get_mut(i) {
                        *row = crate::graph::margins(&self.phi, t)[i].clone();
                    }
                }
                None => {
                    self.g[i] = vec![0; states];
                    if let Some(row) = self.margin.get_mut(i) {
                        *row = vec![0.0; states];
                    }
                }
            }
            if let Some(row) = self.stability.get_mut(i) {
                *row = vec![f64::NAN; states];
            }
        }
        self.rows.extend(rules.iter().cloned());
        // A rule may leave a state column with no action at all.
        self.unmoved_states = (0..self.states()).filter(|&j| self.g.iter().all(|row| row[j] == 0)).collect();
        Ok(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(threshold: f64) -> GraphReport {
        // Two actions, three states; phi chosen so T = 0.1 keeps every entry
        // and T = 1 keeps only the larger of each column.
        let phi = vec![vec![4.0, 1.0, 3.0], vec![1.0, 4.0, 3.0]];
        let graph = crate::graph::connection_graph(&phi, crate::Rule::Threshold(threshold));
        GraphReport {
            env: "test".into(),
            state_names: vec!["a".into(), "b".into(), "c".into()],
            action_names: vec!["u".into(), "v".into()],
            samples: 1,
            threshold: Some(threshold),
            exact: false,
            tolerance: None,
            seed: 0,
            threads: 1,
            bootstrap_resamples: 1,
            phi_normalized: crate::graph::normalized(&phi),
            margin: crate::graph::margins(&phi, threshold),
            phi,
            g: graph.g,
            stability: vec![vec![1.0; 3]; 2],
            unmoved_states: graph.unmoved_states,
            start: None,
            sweep: Vec::new(),
            elapsed_s: 0.0,
            origin: None,
            rows: Vec::new(),
        }
    }

    #[test]
    fn a_row_rule_rebuilds_that_row_from_the_same_phi() {
        let sparse = report(1.0);
        assert_eq!(sparse.g, vec![vec![1, 0, 1], vec![0, 1, 1]]);
        let dense_v = sparse.clone().with_rows(&[RowRule::parse("v=0.1").unwrap()]).unwrap();
        // v's row is the T = 0.1 graph's row; u's row is untouched.
        assert_eq!(dense_v.g, vec![vec![1, 0, 1], report(0.1).g[1].clone()]);
        assert_eq!(dense_v.margin[1], report(0.1).margin[1]);
        assert!(dense_v.stability[1].iter().all(|s| s.is_nan()) && dense_v.stability[0] == vec![1.0; 3]);
        assert_eq!(dense_v.rows, vec![RowRule { action: "v".into(), threshold: Some(0.1) }]);
        // An empty row: column b is then moved by no action.
        let no_v = sparse.with_rows(&[RowRule::parse("v=none").unwrap()]).unwrap();
        assert_eq!(no_v.g, vec![vec![1, 0, 1], vec![0, 0, 0]]);
        assert_eq!(no_v.unmoved_states, vec![1]);
    }

    #[test]
    fn row_rules_round_trip_and_bad_ones_say_why() {
        for text in ["dz=0.1", "dz=none", "dalpha=2.5"] {
            assert_eq!(RowRule::parse(text).unwrap().text(), text);
        }
        let err = |t: &str| RowRule::parse(t).unwrap_err().to_string();
        assert!(err("dz").contains("no '='"), "{}", err("dz"));
        assert!(err("dz=x").contains("\"x\" is not a number"));
        assert!(err("dz=-1").contains("above 0"));
        assert!(err("=0.1").contains("no action name"));
        let unknown = report(1.0).with_rows(&[RowRule::parse("w=0.1").unwrap()]).unwrap_err().to_string();
        assert!(unknown.contains("no action w") && unknown.contains("u, v"), "{unknown}");
        let twice = report(1.0).with_rows(&[RowRule::parse("u=0.1").unwrap(), RowRule::parse("u=none").unwrap()]).unwrap_err().to_string();
        assert!(twice.contains("has a rule already"), "{twice}");
        let mut given = report(1.0);
        given.origin = Some("random@3, draw seed 0".into());
        assert!(given.with_rows(&[RowRule::parse("u=none").unwrap()]).unwrap_err().to_string().contains("not to given"));
    }
}
