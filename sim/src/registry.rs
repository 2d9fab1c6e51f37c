//! Environments by name (`lti-paper`), by TOML file (`kind = "lti"`) or
//! served by another process (`grpc://HOST:PORT`, [`crate::remote`]).

use std::path::Path;

use crate::env::{Env, EnvError};
use crate::lti::{LtiConfig, LtiEnv};
use crate::peg::{PegConfig, PegEnv};

/// The registered environment names, for help texts and error messages.
pub fn known_env_names() -> Vec<&'static str> {
    std::iter::once("lti-paper")
        .chain(["lti-blocks-4", "lti-blocks-8", "lti-blocks-16", "lti-blocks-32"])
        .chain(crate::peg::PegConfig::NAMES)
        .collect()
}

/// Makes an environment from a registered name, a path to a `.toml` file,
/// or a server's URL (`grpc://HOST:PORT`).
pub fn make_env(name_or_path: &str) -> Result<Box<dyn Env>, EnvError> {
    if crate::remote::is_served(name_or_path) {
        return Ok(Box::new(crate::remote::RemoteEnv::connect(name_or_path)?));
    }
    if let Some(cfg) = PegConfig::preset(name_or_path) {
        return Ok(Box::new(PegEnv::new(name_or_path, cfg)?));
    }
    if let Some(n) = LtiConfig::blocks_size(name_or_path) {
        let cfg = LtiConfig::blocks(n).ok_or_else(|| EnvError::invalid("lti-blocks-N", format!("N = {n}: N must be even, from 2 to {} (registered: 4, 8, 16, 32)", LtiConfig::MAX_BLOCKS)))?;
        return Ok(Box::new(LtiEnv::new(name_or_path, &cfg)?));
    }
    match name_or_path {
        "lti-paper" => Ok(Box::new(LtiEnv::new("lti-paper", &LtiConfig::paper_example())?)),
        path if path.ends_with(".toml") || Path::new(path).is_file() => load_file(path),
        name => Err(EnvError::Unknown { name: name.to_string(), known: known_env_names().join(", ") }),
    }
}

fn load_file(path: &str) -> Result<Box<dyn Env>, EnvError> {
    let text = std::fs::read_to_string(path)
        .map_err(|source| EnvError::Read { path: path.to_string(), source })?;
    env_from_toml(&text, path)
}

/// The environment an environment file's text describes (`kind = "lti"` or
/// `"peg"`), named `path` in the environment and in errors. Everything a
/// file controls passes here (fuzzed by fuzz/fuzz_targets/toml_config.rs).
pub fn env_from_toml(text: &str, path: &str) -> Result<Box<dyn Env>, EnvError> {
    let parse_err = |e: toml::de::Error| EnvError::Parse { path: path.to_string(), message: e.to_string() };
    let table: toml::Table = toml::from_str(text).map_err(parse_err)?;
    match table.get("kind").and_then(|k| k.as_str()) {
        Some("lti") => {
            let cfg: LtiConfig = toml::from_str(text).map_err(parse_err)?;
            Ok(Box::new(LtiEnv::new(path, &cfg)?))
        }
        Some("peg") => {
            // A peg file starts from a preset and overrides sections of it.
            let mut overrides = table;
            overrides.remove("kind");
            let preset = match overrides.remove("preset") {
                Some(toml::Value::String(name)) => name,
                Some(_) => return Err(EnvError::invalid("preset", "must be a string such as \"peg-group1\"")),
                None => "peg-group1".to_string(),
            };
            let base = PegConfig::preset(&preset).ok_or_else(|| {
                EnvError::invalid("preset", format!("unknown preset \"{preset}\"; use one of {}", PegConfig::NAMES.join(", ")))
            })?;
            Ok(Box::new(PegEnv::new(path, base.with_overrides(&overrides, path)?)?))
        }
        Some(other) => Err(EnvError::invalid("kind", format!("unknown environment kind \"{other}\"; known: \"lti\", \"peg\""))),
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
    fn loads_peg_presets_and_override_files() {
        for name in ["peg-group1", "peg-group2", "peg-experiment"] {
            let env = make_env(name).unwrap();
            assert_eq!((env.spec().state_dim(), env.spec().action_dim()), (12, 6));
            assert_eq!(env.spec().action_high, vec![2.0, 2.0, 2.0, 4.0, 4.0, 4.0]);
        }
        let file = write("kind = \"peg\"\npreset = \"peg-group2\"\n[contact]\nfriction = 0.6\n");
        assert_eq!(make_env(file.path().to_str().unwrap()).unwrap().spec().state_dim(), 12);
        let file = write("kind = \"peg\"\n[geometry]\npeg_side_mm = 12.0\n");
        let err = make_env(file.path().to_str().unwrap()).err().unwrap().to_string();
        assert!(err.contains("geometry.peg_side_mm"), "{err}");
        let file = write("kind = \"peg\"\npreset = \"peg-group9\"\n");
        assert!(make_env(file.path().to_str().unwrap()).err().unwrap().to_string().contains("peg-group9"));
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

    /// `lti-blocks-N` is a name anyone can type: a huge N is refused with
    /// the accepted range instead of allocating a 2N × 2N matrix (which
    /// aborted the process).
    #[test]
    fn lti_blocks_n_is_bounded() {
        assert!(LtiConfig::blocks(LtiConfig::MAX_BLOCKS).is_some());
        assert!(LtiConfig::blocks(LtiConfig::MAX_BLOCKS + 2).is_none());
        for n in [LtiConfig::MAX_BLOCKS + 2, 1 << 40] {
            let err = make_env(&format!("lti-blocks-{n}")).err().expect("a huge N is refused").to_string();
            assert!(err.contains("lti-blocks-N") && err.contains(&LtiConfig::MAX_BLOCKS.to_string()), "{err}");
        }
        assert_eq!(make_env("lti-blocks-8").unwrap().spec().action_dim(), 8);
    }
}
