//! lcrl's own environments for Python: `lcrl serve-env` driven by the
//! Python package's Gymnasium face (clients/python/lcrl_env/gymnasium_env.py),
//! real processes over real gRPC.

use std::path::{Path, PathBuf};
use std::process::Command;

use lcrl_sim::make_env;

use super::common::{assert_clean_failure, lcrl, spawn_listening, stdout};

fn python() -> Command {
    let mut cmd = Command::new(Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python"));
    // The Gymnasium face starts this build's `lcrl serve-env`.
    cmd.env("LCRL_BIN", env!("CARGO_BIN_EXE_lcrl"));
    cmd
}

fn run_python(script: &str, args: &[&str]) -> String {
    let out = python().arg("-c").arg(script).args(args).output().unwrap();
    assert!(out.status.success(), "python failed: {}", String::from_utf8_lossy(&out.stderr));
    stdout(&out)
}

/// Steps a served environment from Python with the given actions; prints
/// the states and rewards as f64 bit patterns, one JSON object.
const REPLAY: &str = r#"
import json, sys
import numpy as np
import lcrl_env
url, token, seed, actions = sys.argv[1], sys.argv[2], int(sys.argv[3]), json.loads(sys.argv[4])
env = lcrl_env.make("ignored", url=url, token_file=token)
bits = lambda x: np.asarray(x, dtype=np.float64).ravel().view(np.uint64).tolist()
obs, _ = env.reset(seed=seed)
out = {"states": [bits(obs)], "rewards": [], "ends": [], "terms": None}
for a in actions:
    obs, r, term, trunc, info = env.step(np.asarray(a))
    out["states"].append(bits(obs)); out["rewards"].append(bits([r])[0]); out["ends"].append([term, trunc])
    out["terms"] = sum(v for k, v in info.items() if k.startswith("return_"))
    if term or trunc:
        break
env.close()
print(json.dumps(out))
"#;

/// A trajectory of the peg task through `lcrl serve-env` and the Python
/// face is the in-process one, bit for bit, and `info`'s reward terms add
/// up to the return.
#[test]
fn served_peg_steps_are_bit_identical_to_in_process_ones() {
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "0123456789abcdef0123456789abcdef\n").unwrap();
    let (mut server, addr) = spawn_listening(lcrl().args(["serve-env", "--env", "peg-group1", "--listen", "127.0.0.1:0", "--token-file"]).arg(&token));
    let mut env = make_env("peg-group1").unwrap();
    let n = env.spec().action_dim();
    let actions: Vec<Vec<f64>> = (0..40).map(|t| (0..n).map(|i| (((t * 7 + i * 3) % 11) as f64 / 5.0 - 1.0) * 0.8).collect()).collect();
    let served: serde_json::Value = serde_json::from_str(&run_python(REPLAY, &[&addr, &token.to_string_lossy(), "17", &serde_json::to_string(&actions).unwrap()])).unwrap();
    let _ = server.kill();
    let _ = server.wait();
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
    let as_bits = |v: &serde_json::Value| v.as_array().unwrap().iter().map(|b| b.as_u64().unwrap()).collect::<Vec<u64>>();
    let states = served["states"].as_array().unwrap();
    assert_eq!(as_bits(&states[0]), bits(&env.reset(17).unwrap()));
    let mut total = 0.0;
    for (t, action) in actions.iter().enumerate().take(states.len() - 1) {
        let step = env.step(action).unwrap();
        total += step.reward;
        assert_eq!(as_bits(&states[t + 1]), bits(&step.state), "state after step {t}");
        assert_eq!(served["rewards"][t].as_u64().unwrap(), step.reward.to_bits(), "reward of step {t}");
        assert_eq!(served["ends"][t], serde_json::json!([step.terminated, step.truncated]));
    }
    let terms = served["terms"].as_f64().expect("the peg task's info has its reward terms");
    assert!((terms - total).abs() < 1e-9 * total.abs().max(1.0), "terms {terms} against the return {total}");
}

/// Every built-in environment passes Gymnasium's own checker through
/// `gymnasium.make("lcrl/NAME")` (which starts its server), the vector
/// form steps with next-step autoreset, and the steps per second of a
/// Python loop are printed beside the vector form's.
#[test]
fn check_env_passes_on_the_built_in_environments() {
    const CHECK: &str = r#"
import sys, time, warnings
import gymnasium, numpy as np
import lcrl_env
from gymnasium.utils.env_checker import check_env
for name in sys.argv[1:]:
    env = gymnasium.make(f"lcrl/{name}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # float64 spaces and unbounded states are allowed, and warned of
        check_env(env.unwrapped, skip_render_check=True)
    env.close()
    print("checked", name)
env = lcrl_env.make("peg-group1")
env.reset(seed=0)
steps, t0 = 0, time.perf_counter()
while steps < 300:
    _, _, term, trunc, _ = env.step(env.action_space.sample())
    steps += 1
    if term or trunc:
        env.reset()
single = steps / (time.perf_counter() - t0)
env.close()
envs = lcrl_env.make_vec("peg-group1", num_envs=8)
obs, _ = envs.reset(seed=3)
assert obs.shape == (8, 12), obs.shape
ends, t0 = 0, time.perf_counter()
for _ in range(150):
    obs, rewards, term, trunc, _ = envs.step(envs.action_space.sample())
    assert np.all(np.isfinite(obs)) and np.all(np.isfinite(rewards))
    ends += int(np.sum(term | trunc))
vector = 8 * 150 / (time.perf_counter() - t0)
envs.close()
print(f"steps/s: single {single:.0f}, vector of 8 {vector:.0f}; episodes ended {ends}")
"#;
    // Every registered name, so a preset added later is checked too.
    let names = lcrl_sim::known_env_names();
    let out = run_python(CHECK, &names);
    for name in names {
        assert!(out.contains(&format!("checked {name}\n")), "{out}");
    }
    let figures = out.lines().find(|l| l.starts_with("steps/s")).expect("the steps/s line");
    eprintln!("{figures}");
    let ends: u64 = figures.rsplit(' ').next().unwrap().parse().unwrap();
    assert!(ends > 0, "150 vector steps of 8 peg episodes end some (autoreset): {figures}");
}

#[test]
fn serve_env_refuses_bad_settings_clearly() {
    let out = lcrl().args(["serve-env", "--env", "no-such-env", "--listen", "127.0.0.1:0"]).output().unwrap();
    assert_clean_failure(&out, "unknown environment 'no-such-env'");
    let out = lcrl().args(["serve-env", "--env", "lti-paper", "--listen", "127.0.0.1:0", "--max-sessions", "0"]).output().unwrap();
    assert_clean_failure(&out, "max_sessions");
    let out = lcrl().args(["serve-env", "--env", "grpc://127.0.0.1:1", "--listen", "127.0.0.1:0"]).output().unwrap();
    assert_clean_failure(&out, "already served");
    let missing: PathBuf = std::env::temp_dir().join("lcrl-no-such-token-file");
    let out = lcrl().args(["serve-env", "--env", "lti-paper", "--listen", "127.0.0.1:0", "--token-file"]).arg(&missing).output().unwrap();
    assert_clean_failure(&out, "token file");
}

/// Stable-Baselines3's SAC trains on the peg task through the Gymnasium
/// face (a short loop: the path works, not what it learns), and its policy
/// is evaluated on the same server.
#[test]
fn stable_baselines3_sac_trains_on_peg_group1() {
    const SAC: &str = r#"
import gymnasium, numpy as np
import lcrl_env
from stable_baselines3 import SAC
env = gymnasium.make("lcrl/peg-group1")
model = SAC("MlpPolicy", env, learning_starts=100, batch_size=64, seed=0, device="cpu")
model.learn(total_timesteps=300)
obs, _ = env.reset(seed=5)
total, done, steps = 0.0, False, 0
while not done:
    action, _ = model.predict(obs, deterministic=True)
    obs, reward, term, trunc, info = env.step(action)
    total, done, steps = total + reward, term or trunc, steps + 1
env.close()
print(f"timesteps {model.num_timesteps} updates {model._n_updates} episode {steps} steps return {total:.3f}")
"#;
    let out = run_python(SAC, &[]);
    let line = out.lines().find(|l| l.starts_with("timesteps")).unwrap_or_else(|| panic!("{out}"));
    eprintln!("{line}");
    let words: Vec<&str> = line.split(' ').collect();
    assert_eq!(words[1], "300", "{line}");
    assert!(words[3].parse::<u64>().unwrap() >= 150, "SAC updated after its 100 warm-up steps: {line}");
    assert!(words[8].parse::<f64>().unwrap().is_finite(), "{line}");
}

/// `lcrl serve-env` is secured like every lcrl service and forks: under
/// mutual TLS and a token (`grpcs://`), CS3 run against the served
/// lti-paper (paired rollouts from forks of one state) measures the graph
/// it measures in process, and a client without its certificate or the
/// token is refused.
#[test]
fn serve_env_takes_mutual_tls_and_a_token_and_forks_for_cs3() {
    use lcrl_sim::remote::{TLS_CA_ENV, TLS_CLIENT_CERT_ENV, TLS_CLIENT_KEY_ENV};
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "0123456789abcdef0123456789abcdef\n").unwrap();
    let certs = dir.path().join("certs");
    let out = lcrl().args(["certs", "--out"]).arg(&certs).output().unwrap();
    assert!(out.status.success(), "{}", super::common::stderr(&out));
    let (mut server, addr) = spawn_listening(
        lcrl()
            .args(["serve-env", "--env", "lti-paper", "--listen", "127.0.0.1:0", "--token-file"])
            .arg(&token)
            .arg("--tls-cert")
            .arg(certs.join("server.pem"))
            .arg("--tls-key")
            .arg(certs.join("server.key"))
            .arg("--tls-client-ca")
            .arg(certs.join("ca.pem")),
    );
    let graph = |env: &str, vars: &[(&str, PathBuf)]| {
        let json = dir.path().join(format!("g{}.json", vars.len()));
        let mut cmd = lcrl();
        cmd.args(["graph", "--samples", "16", "--seed", "3", "--env", env, "--out"]).arg(&json);
        for name in ["LCRL_TOKEN_FILE", TLS_CA_ENV, TLS_CLIENT_CERT_ENV, TLS_CLIENT_KEY_ENV] {
            cmd.env_remove(name);
        }
        cmd.envs(vars.iter().cloned());
        let out = cmd.output().unwrap();
        (out.status.success().then(|| serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(&json).unwrap()).unwrap()), out)
    };
    let url = format!("grpcs://{addr}");
    let trusted = vec![("LCRL_TOKEN_FILE", token.clone()), (TLS_CA_ENV, certs.join("ca.pem")), (TLS_CLIENT_CERT_ENV, certs.join("client.pem")), (TLS_CLIENT_KEY_ENV, certs.join("client.key"))];
    let (served, out) = graph(&url, &trusted);
    let served = served.unwrap_or_else(|| panic!("CS3 against the served environment: {}", super::common::stderr(&out)));
    let (local, _) = graph("lti-paper", &[]);
    let local = local.expect("CS3 in process");
    assert_eq!(served["g"], local["g"], "the served graph is the in-process one");
    assert_eq!(served["phi"], local["phi"], "the same CS3 values, bit for bit through f64 JSON");
    let (no_cert, _) = graph(&url, &trusted[..2]);
    assert!(no_cert.is_none(), "no client certificate: refused by mutual TLS");
    let (no_token, out) = graph(&url, &trusted[1..]);
    assert!(no_token.is_none(), "no token: refused");
    assert!(super::common::stderr(&out).to_lowercase().contains("token"), "{}", super::common::stderr(&out));
    let _ = server.kill();
    let _ = server.wait();
}
