//! Bring-your-own environments: Gymnasium environments served by real
//! `python -m lcrl_env serve` processes, used through `grpc://` URLs.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use lcrl_sim::{make_env, Env, Step};

use super::common::{assert_clean_failure, lcrl, stderr, stdout};

/// A linear system written as a Gymnasium environment (docs/method.md eq. 10,
/// s' = E s + F a), one that cannot fork (it holds a lock, which deepcopy
/// refuses), and a script that replays a trajectory in plain Python.
const TEST_ENVS: &str = r#"
import json, sys, threading
import gymnasium as gym
import numpy as np

E = np.array([[-1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
F = np.eye(3)


class Linear(gym.Env):
    lcrl_state_names = ["s1", "s2", "s3"]
    lcrl_action_names = ["a1", "a2", "a3"]

    def __init__(self, steps=50):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float64)
        self.steps = steps

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.s = self.np_random.uniform(-1.0, 1.0, 3)
        self.t = 0
        return self.s.copy(), {}

    def step(self, action):
        a = np.asarray(action, dtype=np.float64)
        reward = -(self.s @ self.s + 0.1 * a @ a)
        self.s = E @ self.s + F @ a
        self.t += 1
        return self.s.copy(), float(reward), False, self.t >= self.steps, {}


class Wild(Linear):
    """A served environment gone wrong: every third step a state of 1e300."""

    def step(self, action):
        s, r, term, trunc, info = super().step(action)
        if self.t % 3 == 0:
            s = np.full(3, 1e300)
        return s, r, term, trunc, info


class Unforkable(Linear):
    def __init__(self, steps=50):
        super().__init__(steps)
        self.lock = threading.Lock()


def replay(env_id, seed, actions):
    """The trajectory in plain Python, as f64 bit patterns (exact in JSON)."""
    env = gym.make(env_id)
    bits = lambda x: np.asarray(x, dtype=np.float64).ravel().view(np.uint64).tolist()
    obs, _ = env.reset(seed=seed)
    out = {"states": [bits(obs)], "rewards": [], "ends": []}
    for a in actions:
        obs, r, term, trunc, _ = env.step(np.asarray(a, dtype=env.action_space.dtype))
        out["states"].append(bits(obs))
        out["rewards"].append(bits([r])[0])
        out["ends"].append([bool(term), bool(trunc)])
    return out


if __name__ == "__main__":
    request = json.load(sys.stdin)
    print(json.dumps(replay(request["env"], request["seed"], request["actions"])))
"#;

fn python() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python")
}

/// A module name of its own per test, so leftover processes can be found.
fn unique_module(tag: &str) -> String {
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
    format!("served_{tag}_{}_{nanos}", std::process::id())
}

/// Writes the test environments as `module`.py in `dir`.
fn write_envs(dir: &Path, module: &str) {
    std::fs::write(dir.join(format!("{module}.py")), TEST_ENVS).unwrap();
}

/// A running `python -m lcrl_env serve`, stopped when dropped. Its log goes
/// to a file: a pipe nobody reads would fill up (MuJoCo warns on every new
/// instance) and block the server.
struct Served {
    child: Child,
    url: String,
    _log: tempfile::NamedTempFile,
}

impl Served {
    fn start(args: &[&str], pythonpath: Option<&Path>) -> Served {
        let log = tempfile::NamedTempFile::new().unwrap();
        let mut cmd = Command::new(python());
        cmd.args(["-m", "lcrl_env", "serve", "--listen", "127.0.0.1:0"]).args(args).stdout(Stdio::piped()).stderr(log.reopen().unwrap());
        if let Some(dir) = pythonpath {
            cmd.env("PYTHONPATH", dir);
        }
        let mut child = cmd.spawn().expect("run .venv/bin/python (scripts/setup.sh makes it)");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        let Some(address) = line.trim().strip_prefix("listening on ") else {
            let _ = child.wait();
            panic!("the server did not start: {}", std::fs::read_to_string(log.path()).unwrap_or_default());
        };
        Served { url: format!("grpc://{address}"), child, _log: log }
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = Command::new("kill").args(["-TERM", &self.child.id().to_string()]).status();
        let _ = self.child.wait();
    }
}

/// Actions on a 1/8 grid inside [-1, 1] (exact in f32, the action dtype of
/// Gymnasium's built-in environments).
fn grid_actions(steps: usize, n: usize, salt: usize) -> Vec<Vec<f64>> {
    (0..steps).map(|k| (0..n).map(|i| ((k * 7 + i * 3 + salt) % 17) as f64 / 8.0 - 1.0).collect()).collect()
}

fn bits(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn same_step(a: &Step, b: &Step) -> bool {
    bits(&a.state) == bits(&b.state) && a.reward.to_bits() == b.reward.to_bits() && (a.terminated, a.truncated) == (b.terminated, b.truncated)
}

#[test]
fn served_gymnasium_trajectories_are_those_of_python_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let module = unique_module("replay");
    write_envs(dir.path(), &module);
    for (env_id, steps, scale) in [("Pendulum-v1", 60, 2.0), ("HalfCheetah-v5", 60, 1.0)] {
        let served = Served::start(&["--env", env_id], None);
        let mut env = make_env(&served.url).unwrap();
        let n = env.spec().action_dim();
        let actions: Vec<Vec<f64>> = grid_actions(steps, n, 0).into_iter().map(|a| a.iter().map(|x| x * scale).collect()).collect();
        let mut remote = vec![bits(&env.reset(7).unwrap())];
        let mut rewards = Vec::new();
        let mut ends = Vec::new();
        for a in &actions {
            let step = env.step(a).unwrap();
            remote.push(bits(&step.state));
            rewards.push(step.reward.to_bits());
            ends.push(serde_json::json!([step.terminated, step.truncated]));
        }
        let mut replay = Command::new(python()).arg(dir.path().join(format!("{module}.py"))).stdin(Stdio::piped()).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
        let request = serde_json::json!({"env": env_id, "seed": 7, "actions": actions});
        std::io::Write::write_all(&mut replay.stdin.take().unwrap(), request.to_string().as_bytes()).unwrap();
        let out = replay.wait_with_output().unwrap();
        assert!(out.status.success(), "{}", stderr(&out));
        let python: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
        let python_states: Vec<Vec<u64>> = serde_json::from_value(python["states"].clone()).unwrap();
        assert_eq!(remote.len(), steps + 1);
        assert_eq!(remote, python_states, "{env_id}: states differ");
        assert_eq!(serde_json::to_value(&rewards).unwrap(), python["rewards"], "{env_id}: rewards differ");
        assert_eq!(serde_json::Value::Array(ends), python["ends"], "{env_id}: end flags differ");
    }
}

#[test]
fn forks_are_exact_and_independent_and_batched_steps_equal_single_ones() {
    for env_id in ["HalfCheetah-v5", "Pendulum-v1"] {
        let served = Served::start(&["--env", env_id, "--instances", "2"], None);
        let mut env = make_env(&served.url).unwrap();
        let n = env.spec().action_dim();
        env.reset(3).unwrap();
        for a in grid_actions(10, n, 1) {
            env.step(&a).unwrap();
        }
        let mut fork = env.snapshot().unwrap();
        let mut fork_of_fork = fork.snapshot().unwrap();
        assert_eq!(bits(fork.state()), bits(env.state()));
        for (k, a) in grid_actions(150, n, 2).iter().enumerate() {
            let (s, f, ff) = (env.step(a).unwrap(), fork.step(a).unwrap(), fork_of_fork.step(a).unwrap());
            assert!(same_step(&s, &f) && same_step(&s, &ff), "{env_id}: forks diverged at step {k}");
            if s.truncated {
                break;
            }
        }
        // A fork stepped differently leaves the original alone.
        let mut twin = env.snapshot().unwrap();
        let mut other = env.snapshot().unwrap();
        other.step(&vec![0.5; n]).unwrap();
        let a = vec![-0.25; n];
        assert!(same_step(&env.step(&a).unwrap(), &twin.step(&a).unwrap()), "{env_id}: a fork's steps reached the original");

        // K sessions stepped in one call give what K single steps give.
        let mut batch: Vec<Box<dyn Env>> = (0..4).map(|_| make_env(&served.url).unwrap()).collect();
        let mut single: Vec<Box<dyn Env>> = (0..4).map(|_| make_env(&served.url).unwrap()).collect();
        for (k, (b, s)) in batch.iter_mut().zip(single.iter_mut()).enumerate() {
            assert_eq!(bits(&b.reset(100 + k as u64).unwrap()), bits(&s.reset(100 + k as u64).unwrap()));
        }
        for t in 0..20 {
            let actions: Vec<Vec<f64>> = (0..4).map(|k| grid_actions(1, n, t * 5 + k).remove(0)).collect();
            let batched = lcrl_sim::step_all(&mut batch, &actions).unwrap();
            for (k, s) in single.iter_mut().enumerate() {
                assert!(same_step(&batched[k], &s.step(&actions[k]).unwrap()), "{env_id}: batched step {t} of env {k} differs");
            }
        }
    }
}

#[test]
fn graph_of_a_served_linear_system_is_the_lemma1_graph() {
    let dir = tempfile::tempdir().unwrap();
    let module = unique_module("graph");
    write_envs(dir.path(), &module);
    let served = Served::start(&["--entry-point", &format!("{module}:Linear")], Some(dir.path()));
    let json = dir.path().join("g.json");
    let out = lcrl().args(["graph", "--exact", "--samples", "16", "--env", &served.url, "--out"]).arg(&json).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let g: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(g["g"], serde_json::json!([[1, 0, 0], [1, 1, 0], [0, 0, 1]]));
    assert_eq!(g["state_names"], serde_json::json!(["s1", "s2", "s3"]));
    assert_eq!(g["action_names"], serde_json::json!(["a1", "a2", "a3"]));
    // The server names them as told (--state-names, --action-names), over
    // the class's own names; lcrl's graph carries them.
    let named = Served::start(&["--entry-point", &format!("{module}:Linear"), "--state-names", "x,v,w", "--action-names", "push,pull,turn"], Some(dir.path()));
    let out = lcrl().args(["graph", "--exact", "--samples", "16", "--env", &named.url, "--out"]).arg(&json).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let g: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!((g["state_names"].clone(), g["action_names"].clone()), (serde_json::json!(["x", "v", "w"]), serde_json::json!(["push", "pull", "turn"])));
}

/// Returns of the episodes in a learner's metrics.csv.
fn returns(metrics: &Path) -> Vec<f64> {
    std::fs::read_to_string(metrics).unwrap().lines().skip(1).filter_map(|l| l.split(',').nth(1)?.parse().ok()).collect()
}

#[test]
fn lcrl_run_serves_a_gymnasium_environment_trains_and_leaves_no_python_behind() {
    let dir = tempfile::tempdir().unwrap();
    let module = unique_module("run");
    write_envs(dir.path(), &module);
    let preset = dir.path().join("served.toml");
    let lti = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/lti-paper.toml")).unwrap();
    // The main job's PPO settings, on the same system served from Python.
    let training = &lti[lti.find("[network]").unwrap()..];
    let text = format!(
        "[job]\nenv = \"grpc://127.0.0.1:0\"\nalgo = \"ppo\"\nconnection = \"local\"\nepisodes = 300\nactors = 1\nenvs_per_actor = 2\n\n\
         [env_server]\nentry_point = \"{module}:Linear\"\npythonpath = \".\"\n\n{}",
        training.replace("eval_episodes = 100", "eval_episodes = 20")
    );
    std::fs::write(&preset, text).unwrap();
    let run = dir.path().join("run");
    let out = lcrl().args(["run", "--config"]).arg(&preset).arg("--run-dir").arg(&run).output().unwrap();
    assert!(out.status.success(), "{}\n{}", stdout(&out), stderr(&out));
    assert!(stderr(&out).contains("environment server at grpc://127.0.0.1:"), "{}", stderr(&out));
    let graph: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("graph.json")).unwrap()).unwrap();
    assert_eq!(graph["g"], serde_json::json!([[1, 0, 0], [1, 1, 0], [0, 0, 1]]));
    let r = returns(&run.join("learner/metrics.csv"));
    assert!(r.len() >= 300, "{} episodes", r.len());
    let mean = |s: &[f64]| s.iter().sum::<f64>() / s.len() as f64;
    let (first, last) = (mean(&r[..50]), mean(&r[r.len() - 50..]));
    assert!(last > first + 0.5 * first.abs(), "the return did not improve: first 50 episodes {first:.2}, last 50 {last:.2}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("summary.json")).unwrap()).unwrap();
    assert!(summary["eval_return"].as_f64().unwrap() > first, "{summary}");
    assert!(run.join("logs/env-server.log").is_file());
    assert_eq!(super::run_cli::processes_mentioning(&module), Vec::<String>::new(), "Python processes left behind");
}

#[test]
fn errors_are_clear_unreachable_unknown_discrete_and_unforkable() {
    // No server there.
    let out = lcrl().args(["graph", "--env", "grpc://127.0.0.1:1"]).output().unwrap();
    assert_clean_failure(&out, "cannot connect");
    let out = lcrl().args(["train", "--algo", "ppo", "--connection", "global", "--episodes", "2", "--env", "grpc://127.0.0.1:1"]).output().unwrap();
    assert_clean_failure(&out, "python -m lcrl_env serve");
    let out = lcrl().args(["graph", "--env", "grpc://no-port"]).output().unwrap();
    assert_clean_failure(&out, "grpc://HOST:PORT");

    // The server refuses what it cannot serve, with exit status 2.
    for (args, needle) in [(vec!["--env", "NoSuchEnv-v0"], "unknown Gymnasium environment 'NoSuchEnv-v0'"), (vec!["--env", "CartPole-v1"], "action space is Discrete")] {
        let out = Command::new(python()).args(["-m", "lcrl_env", "serve", "--listen", "127.0.0.1:0"]).args(&args).output().unwrap();
        assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
        assert!(stdout(&out).is_empty(), "it must not claim to listen: {}", stdout(&out));
        assert_clean_failure(&out, needle);
    }

    // CS3 on an environment that cannot fork fails at once and says why.
    let dir = tempfile::tempdir().unwrap();
    let module = unique_module("errors");
    write_envs(dir.path(), &module);
    let served = Served::start(&["--entry-point", &format!("{module}:Unforkable")], Some(dir.path()));
    let out = lcrl().args(["graph", "--env", &served.url]).output().unwrap();
    assert_clean_failure(&out, "cannot fork");
    assert!(stderr(&out).contains("cannot pickle"), "the reason is missing: {}", stderr(&out));
    // It still trains: only CS3 needs forks.
    let out = lcrl().args(["train", "--connection", "global", "--algo", "ppo", "--episodes", "2", "--env", &served.url, "--run-dir"]).arg(dir.path().join("t")).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));

    // A preset whose server cannot start: the log's reason, non-zero exit.
    let preset = dir.path().join("bad.toml");
    std::fs::write(&preset, "[job]\nenv = \"grpc://127.0.0.1:0\"\nalgo = \"ppo\"\nconnection = \"global\"\nepisodes = 5\n[env_server]\nentry_point = \"no_such_module:Env\"\n").unwrap();
    let out = lcrl().args(["run", "--config"]).arg(&preset).arg("--run-dir").arg(dir.path().join("r")).output().unwrap();
    assert_clean_failure(&out, "cannot import 'no_such_module'");
    std::fs::write(&preset, "[job]\nenv = \"lti-paper\"\nalgo = \"ppo\"\nconnection = \"global\"\nepisodes = 5\n[env_server]\ngym = \"Pendulum-v1\"\n").unwrap();
    assert_clean_failure(&lcrl().args(["run", "--check", "--config"]).arg(&preset).output().unwrap(), "grpc://HOST:PORT");
}

#[tokio::test]
async fn the_service_refuses_bad_calls_with_the_right_codes() {
    use lcrl_proto::v1::environment_client::EnvironmentClient;
    use lcrl_proto::v1::{ForkRequest, OpenRequest, ResetRequest, SessionReset, SessionStep, StepRequest};
    let served = Served::start(&["--env", "Pendulum-v1", "--max-sessions", "3"], None);
    let mut client = EnvironmentClient::connect(served.url.replace("grpc://", "http://")).await.unwrap();
    let sessions = client.open(OpenRequest { count: 2 }).await.unwrap().into_inner().sessions;
    let step = |session: u64, action: Vec<f64>| StepRequest { steps: vec![SessionStep { session, action }] };
    let code = |r: Result<tonic::Response<_>, tonic::Status>| r.map(|_: tonic::Response<lcrl_proto::v1::StepResponse>| ()).unwrap_err().code();
    assert_eq!(code(client.step(step(sessions[0], vec![0.1])).await), tonic::Code::FailedPrecondition, "step before reset");
    client.reset(ResetRequest { resets: vec![SessionReset { session: sessions[0], seed: 1 }] }).await.unwrap();
    assert_eq!(code(client.step(step(sessions[0], vec![f64::NAN])).await), tonic::Code::InvalidArgument, "NaN action");
    assert_eq!(code(client.step(step(sessions[0], vec![0.1, 0.2])).await), tonic::Code::InvalidArgument, "wrong length");
    assert_eq!(code(client.step(step(999, vec![0.1])).await), tonic::Code::NotFound, "unknown session");
    assert_eq!(code(client.step(StepRequest { steps: vec![] }).await), tonic::Code::InvalidArgument, "empty request");
    client.fork(ForkRequest { session: sessions[0] }).await.unwrap();
    let full = client.fork(ForkRequest { session: sessions[0] }).await.unwrap_err();
    assert_eq!(full.code(), tonic::Code::ResourceExhausted, "{full:?}");
    // An out-of-bounds action is clipped, as Gymnasium's own bounds say.
    let clipped = client.step(step(sessions[0], vec![1e9])).await.unwrap().into_inner();
    assert_eq!(clipped.results.len(), 1);
}

/// `lcrl sim` against a served environment, with `vars` set (and the
/// token and TLS variables of this test process cleared first).
fn sim_against(url: &str, vars: &[(&str, &Path)]) -> std::process::Output {
    let mut cmd = lcrl();
    cmd.args(["sim", "--env", url, "--episodes", "1", "--seed", "0"]);
    for name in ["LCRL_TOKEN_FILE", lcrl_sim::remote::TLS_CA_ENV, lcrl_sim::remote::TLS_CLIENT_CERT_ENV, lcrl_sim::remote::TLS_CLIENT_KEY_ENV] {
        cmd.env_remove(name);
    }
    for (name, value) in vars {
        cmd.env(name, value);
    }
    cmd.output().unwrap()
}

/// The environment service is secured like lcrl's own servers: with a
/// token it refuses every call without it (and counts the refusals),
/// serves with it, and answers health checks without one; under mutual
/// TLS (`grpcs://`) a client needs the CA and its own certificate.
#[test]
fn the_environment_service_takes_tls_and_a_token() {
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "s3cret-env-token\n").unwrap();
    let served = Served::start(&["--env", "Pendulum-v1", "--token-file", token.to_str().unwrap()], None);
    assert_clean_failure(&sim_against(&served.url, &[]), "refused this client");
    let out = sim_against(&served.url, &[("LCRL_TOKEN_FILE", &token)]);
    assert!(out.status.success(), "with the token: {}", stderr(&out));
    let health_url = served.url.replace("grpc://", "http://");
    let out = lcrl().args(["health", &health_url]).env_remove("LCRL_TOKEN_FILE").output().unwrap();
    assert!(stdout(&out).contains("SERVING"), "health needs no token: {}", stderr(&out));
    let log = std::fs::read_to_string(served._log.path()).unwrap();
    assert!(log.contains("1 refusal(s) so far"), "refusals are counted: {log}");
    // Server reflection lists the service (behind the token).
    let list = "import grpc, sys\n\
        from grpc_reflection.v1alpha import reflection_pb2 as pb, reflection_pb2_grpc as rpc\n\
        stub = rpc.ServerReflectionStub(grpc.insecure_channel(sys.argv[1]))\n\
        auth = [('authorization', 'Bearer ' + open(sys.argv[2]).read().strip())]\n\
        reply = next(stub.ServerReflectionInfo(iter([pb.ServerReflectionRequest(list_services='')]), metadata=auth))\n\
        print(' '.join(s.name for s in reply.list_services_response.service))\n";
    let out = Command::new(python()).args(["-c", list, served.url.trim_start_matches("grpc://")]).arg(&token).output().unwrap();
    assert!(stdout(&out).contains("lcrl.v1.Environment"), "reflection: {}{}", stdout(&out), stderr(&out));

    let certs = dir.path().join("certs");
    let out = lcrl().args(["certs", "--out"]).arg(&certs).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let file = |name: &str| certs.join(name).to_str().unwrap().to_string();
    let (cert, key, ca) = (file("server.pem"), file("server.key"), file("ca.pem"));
    let tls = Served::start(&["--env", "Pendulum-v1", "--token-file", token.to_str().unwrap(), "--tls-cert", &cert, "--tls-key", &key, "--tls-client-ca", &ca], None);
    let url = tls.url.replace("grpc://", "grpcs://");
    let (ca_path, client_cert, client_key) = (certs.join("ca.pem"), certs.join("client.pem"), certs.join("client.key"));
    let trusted = [("LCRL_TOKEN_FILE", token.as_path()), (lcrl_sim::remote::TLS_CA_ENV, ca_path.as_path())];
    let out = sim_against(&url, &[trusted[0], trusted[1], (lcrl_sim::remote::TLS_CLIENT_CERT_ENV, &client_cert), (lcrl_sim::remote::TLS_CLIENT_KEY_ENV, &client_key)]);
    assert!(out.status.success(), "mutual TLS with the token: {}", stderr(&out));
    assert!(!sim_against(&url, &trusted).status.success(), "no client certificate: refused by mutual TLS");
    assert_clean_failure(&sim_against(&url, &[trusted[0]]), lcrl_sim::remote::TLS_CA_ENV);
    assert!(!sim_against(&tls.url, &trusted).status.success(), "plain text to a TLS server fails");
}

/// `lcrl run --tls-dir --token-file` secures the environment server it
/// starts like the run's other servers (mutual TLS + token, `grpcs://`),
/// and the learner, the actors and the final evaluation reach it.
#[test]
fn lcrl_run_secures_the_environment_server_it_starts() {
    let dir = tempfile::tempdir().unwrap();
    let module = unique_module("secured");
    write_envs(dir.path(), &module);
    let certs = dir.path().join("certs");
    let out = lcrl().args(["certs", "--out"]).arg(&certs).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let token = dir.path().join("token");
    std::fs::write(&token, "a-run-token-of-24-chars\n").unwrap();
    let preset = dir.path().join("secured.toml");
    let text = format!(
        "[job]\nenv = \"grpc://127.0.0.1:0\"\nalgo = \"ppo\"\nconnection = \"global\"\nepisodes = 20\nactors = 1\n\n\
         [env_server]\nentry_point = \"{module}:Linear\"\npythonpath = \".\"\n\n[ppo]\nrollout_steps = 200\nminibatch_size = 50\n[run]\neval_episodes = 3\n"
    );
    std::fs::write(&preset, text).unwrap();
    let run = dir.path().join("run");
    let out = lcrl()
        .args(["run", "--config"])
        .arg(&preset)
        .arg("--run-dir")
        .arg(&run)
        .arg("--tls-dir")
        .arg(&certs)
        .arg("--token-file")
        .arg(&token)
        .env_remove("LCRL_TOKEN_FILE")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}\n{}", stdout(&out), stderr(&out));
    assert!(stderr(&out).contains("environment server at grpcs://127.0.0.1:"), "{}", stderr(&out));
    let log = std::fs::read_to_string(run.join("logs/env-server.log")).unwrap();
    assert!(log.contains("(TLS + token)"), "{log}");
    assert!(run.join("summary.json").is_file());
    assert_eq!(super::run_cli::processes_mentioning(&module), Vec::<String>::new(), "Python processes left behind");
}

/// `lcrl train` with `[env_server]` in its config starts the environment
/// server itself, as `lcrl run` does, trains on it, and leaves no Python
/// process behind; without a served `--env` it says where it must listen.
#[test]
fn lcrl_train_serves_the_configured_environment_itself() {
    let dir = tempfile::tempdir().unwrap();
    let module = unique_module("train");
    write_envs(dir.path(), &module);
    let config = dir.path().join("served.toml");
    std::fs::write(&config, format!("[env_server]\nentry_point = \"{module}:Linear\"\npythonpath = \".\"\n\n[ddpg]\nwarmup_steps = 40\nbatch_size = 16\n")).unwrap();
    let run = dir.path().join("run");
    let train = |env: &str, run: &Path| {
        lcrl()
            .args(["train", "--env", env, "--algo", "ddpg", "--connection", "global", "--episodes", "3", "--eval-episodes", "2", "--config"])
            .arg(&config)
            .arg("--run-dir")
            .arg(run)
            .output()
            .unwrap()
    };
    let out = train("grpc://127.0.0.1:0", &run);
    assert!(out.status.success(), "{}\n{}", stdout(&out), stderr(&out));
    assert!(stderr(&out).contains("environment server at grpc://127.0.0.1:"), "{}", stderr(&out));
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["episodes"], 3, "{summary}");
    assert!(run.join("logs/env-server.log").is_file());
    assert_eq!(super::run_cli::processes_mentioning(&module), Vec::<String>::new(), "Python processes left behind");
    assert_clean_failure(&train("lti-paper", &dir.path().join("r2")), "is where it listens");
}

/// A served environment that returns states of 1e300 cannot end a run
/// (issue 82): training ends those episodes and goes on, the final
/// evaluation never hands such a state to the policy (its episodes end
/// there, counted), and summary.json is written.
#[test]
fn a_wild_served_environment_ends_episodes_not_the_run() {
    let dir = tempfile::tempdir().unwrap();
    let module = unique_module("wild");
    write_envs(dir.path(), &module);
    let served = Served::start(&["--entry-point", &format!("{module}:Wild")], Some(dir.path()));
    let run = dir.path().join("run");
    let out = lcrl().args(["train", "--algo", "ddpg", "--connection", "global", "--episodes", "4", "--eval-episodes", "3", "--env", &served.url, "--run-dir"]).arg(&run).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("summary.json")).unwrap()).unwrap();
    assert!(summary["diverged_env"].as_u64().unwrap_or(0) >= 4, "{summary}");
    assert!(summary["eval_return"].as_f64().is_some_and(f64::is_finite), "{summary}");
    let references = summary["references"].as_array().unwrap();
    assert!(references.iter().all(|r| r["diverged_episodes"] == 3), "{summary}");
}
