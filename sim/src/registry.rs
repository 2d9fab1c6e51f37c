//! Environments by name (`lti-paper`) or by TOML file (`kind = "lti"`).

use std::path::Path;

use crate::env::{Env, EnvError};
use crate::lti::{LtiConfig, LtiEnv};

/// The registered environment names, for help texts and error messages.
pub fn known_env_names() -> Vec<&'static str> {
    vec!["lti-paper"]
}

/// Makes an environment from a registered name or a path to a `.toml` file.
pub fn make_env(name_or_path: &str) -> Result<Box<dyn Env>, EnvError> {
    match name_or_path {
        "lti-paper" => Ok(Box::new(LtiEnv::new("lti-paper", &LtiConfig::paper_example())?)),
        path if path.ends_with(".toml") || Path::new(path).is_file() => load_file(path),
        name => Err(EnvError::Unknown { name: name.to_string(), known: known_env_names().join(", ") }),
    }
}

fn load_file(path: &str) -> Result<Box<dyn Env>, EnvError> {
    let text = std::fs::read_to_string(path)
        .map_err(|source| EnvError::Read { path: path.to_string(), source })?;
    let parse_err = |e: toml::de::Error| EnvError::Parse { path: path.to_string(), message: e.to_string() };
    let table: toml::Table = toml::from_str(&text).map_err(parse_err)?;
    match table.get("kind").and_then(|k| k.as_str()) {
        Some("lti") => {
            let cfg: LtiConfig = toml::from_str(&text).map_err(parse_err)?;
            Ok(Box::new(LtiEnv::new(path, &cfg)?))
        }
        Some(other) => Err(EnvError::invalid("kind", format!("unknown environment kind \"{other}\"; known: \"lti\""))),
        None => Err(EnvError::invalid("kind", "missing; say which environment the file describes, e.g. kind = \"lti\"")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn write(text: &str) -> tempfile::NamedTempFile {
        let mut file = tempfile::Builder::new().suffix(".toml").tempfile().unwrap();
        file.write_all(text.as_bytes()).unwrap();
        file
    }

    #[test]
    fn loads_an_lti_file() {
        let file = write("kind = \"lti\"\ne = [[0.5, 0.0], [1.0, 0.5]]\nf = [[1.0], [0.0]]\nnoise_std = 0.1\n");
        let env = make_env(file.path().to_str().unwrap()).unwrap();
        assert_eq!(env.spec().state_dim(), 2);
        assert_eq!(env.spec().action_dim(), 1);
        assert!(env.is_stochastic());
    }

    #[test]
    fn errors_name_what_is_wrong() {
        let err = make_env("no-such-env").err().unwrap().to_string();
        assert!(err.contains("unknown environment 'no-such-env'") && err.contains("lti-paper"), "{err}");
        let file = write("kind = \"lti\"\ne = [[0.5, 0.0], [1.0]]\nf = [[1.0], [0.0]]\n");
        let err = make_env(file.path().to_str().unwrap()).err().unwrap().to_string();
        assert!(err.contains("`e`") && err.contains("row 2"), "{err}");
        let file = write("kind = \"lti\"\ne = [[0.5]]\nf = [[1.0]]\nnoise = 1.0\n");
        let err = make_env(file.path().to_str().unwrap()).err().unwrap().to_string();
        assert!(err.contains("noise"), "{err}");
        let file = write("kind = \"lti\"\ne = [[nan]]\nf = [[1.0]]\n");
        let err = make_env(file.path().to_str().unwrap()).err().unwrap().to_string();
        assert!(err.contains("`e`") && err.contains("finite"), "{err}");
        let err = make_env("/nonexistent/x.toml").err().unwrap().to_string();
        assert!(err.contains("cannot read"), "{err}");
    }
}
