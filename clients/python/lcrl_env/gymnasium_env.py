"""lcrl's own environments (peg-group1/2, the noisy presets, lti-*) as
Gymnasium environments, for any Python RL library.

    import lcrl_env
    env = lcrl_env.make("peg-group1")            # starts `lcrl serve-env` itself
    env = lcrl_env.make("peg-group1", url="127.0.0.1:50070", token_file="token")
    envs = lcrl_env.make_vec("peg-group1", num_envs=8)   # one round trip a step for all 8

    import gymnasium, lcrl_env
    env = gymnasium.make("lcrl/peg-group1")

Each instance is a session of an `lcrl.v1.Environment` server (`lcrl
serve-env`, proto/lcrl.proto); numbers travel as float64, so a trajectory
is bit-identical to one inside lcrl. `info` carries what the episode
achieved so far (success, peak force and moment, the return split into
the reward's terms). See docs/environments.md.
"""

from __future__ import annotations

import atexit
import os
import pathlib
import secrets
import shutil
import subprocess
import tempfile
import threading

import grpc
import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from . import lcrl_pb2, lcrl_pb2_grpc

#: Built-in environments registered as "lcrl/NAME".
BUILT_IN = (
    "peg-group1", "peg-group2", "peg-experiment", "peg-group1-rand", "peg-group2-rand", "peg-group1-noisy", "peg-group2-noisy",
    "lti-paper", "lti-blocks-4", "lti-blocks-8", "lti-blocks-16", "lti-blocks-32",
)

_REPO = pathlib.Path(__file__).resolve().parents[3]


def _lcrl_binary() -> str:
    """$LCRL_BIN, else this checkout's target/debug/lcrl, else `lcrl` on PATH."""
    for candidate in (os.environ.get("LCRL_BIN"), str(_REPO / "target" / "debug" / "lcrl"), shutil.which("lcrl")):
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    raise FileNotFoundError("cannot find the lcrl binary: build it (`cargo build --bin lcrl`), put it on PATH, or set $LCRL_BIN")


class Server:
    """An `lcrl serve-env` process of this Python process, on loopback with
    a fresh token; stopped by `close` or at exit."""

    def __init__(self, env: str, max_sessions: int = 256):
        folder = tempfile.mkdtemp(prefix="lcrl-env-")
        self.token_file = os.path.join(folder, "token")
        with open(os.open(self.token_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "w") as f:
            f.write(secrets.token_hex(32) + "\n")
        command = [_lcrl_binary(), "serve-env", "--env", env, "--listen", "127.0.0.1:0", "--max-sessions", str(max_sessions), "--token-file", self.token_file]
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.process.stdout.readline()
        if not line.startswith("listening on "):
            self.process.kill()
            error = self.process.stderr.read().strip()
            raise RuntimeError(f"`lcrl serve-env --env {env}` did not start: {error or 'no output'}")
        self.address = line.split()[-1]
        # Its log goes on being read, so a full pipe never stops it.
        threading.Thread(target=self.process.stderr.read, daemon=True).start()
        atexit.register(self.close)

    def close(self):
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
        shutil.rmtree(os.path.dirname(self.token_file), ignore_errors=True)


class Client:
    """A connection to an environment server: its spec and batched calls."""

    def __init__(self, env: str = "peg-group1", url: str | None = None, token_file: str | None = None, tls_ca: str | None = None, sessions: int = 1):
        self.server = None
        if url is None:
            self.server = Server(env, max_sessions=max(256, sessions + 1))
            url, token_file = self.server.address, self.server.token_file
        token_file = token_file or os.environ.get("LCRL_TOKEN_FILE")
        self.metadata = ()
        if token_file:
            with open(token_file) as f:
                self.metadata = (("authorization", "Bearer " + f.read().strip()),)
        options = [("grpc.max_receive_message_length", 16 << 20)]
        if tls_ca:
            with open(tls_ca, "rb") as f:
                self.channel = grpc.secure_channel(url, grpc.ssl_channel_credentials(f.read()), options)
        else:
            self.channel = grpc.insecure_channel(url, options)
        self.stub = lcrl_pb2_grpc.EnvironmentStub(self.channel)
        self.spec = self.call(self.stub.GetSpec, lcrl_pb2.GetSpecRequest())
        self.sessions = list(self.call(self.stub.Open, lcrl_pb2.OpenRequest(count=sessions)).sessions)

    def call(self, method, request):
        try:
            return method(request, metadata=self.metadata, timeout=120)
        except grpc.RpcError as e:
            raise RuntimeError(f"environment server: {e.code().name}: {e.details()}") from None

    def reset(self, seeds) -> list[np.ndarray]:
        resets = [lcrl_pb2.SessionReset(session=s, seed=int(seed)) for s, seed in zip(self.sessions, seeds) if seed is not None]
        return [np.asarray(r.state, dtype=np.float64) for r in self.call(self.stub.Reset, lcrl_pb2.ResetRequest(resets=resets)).states]

    def step(self, actions) -> list:
        steps = [lcrl_pb2.SessionStep(session=s, action=np.asarray(a, dtype=np.float64).ravel().tolist()) for s, a in actions]
        return list(self.call(self.stub.Step, lcrl_pb2.StepRequest(steps=steps)).results)

    def close(self):
        try:
            self.call(self.stub.Close, lcrl_pb2.CloseRequest(sessions=self.sessions))
        except RuntimeError:
            pass
        self.channel.close()
        if self.server is not None:
            self.server.close()


def _spaces(spec):
    m = len(spec.state_names)
    observation = spaces.Box(low=-np.inf, high=np.inf, shape=(m,), dtype=np.float64)
    action = spaces.Box(low=np.asarray(spec.action_low, dtype=np.float64), high=np.asarray(spec.action_high, dtype=np.float64), dtype=np.float64)
    return observation, action


def _info(result) -> dict:
    """What the episode achieved so far, as Gymnasium's `info`."""
    info = {}
    if not result.HasField("so_far"):
        return info
    so_far = result.so_far
    for name in ("success", "peak_force_n", "peak_moment_nm", "max_penetration_mm"):
        if so_far.HasField(name):
            info[name] = getattr(so_far, name)
    if so_far.HasField("return_terms"):
        terms = so_far.return_terms
        info.update({f"return_{k}": getattr(terms, k) for k in ("depth", "force", "moment", "bonus", "failure")})
    return info


class LcrlEnv(gymnasium.Env):
    """One of lcrl's environments as a `gymnasium.Env` (one session)."""

    metadata = {"render_modes": []}

    def __init__(self, env: str = "peg-group1", url: str | None = None, token_file: str | None = None, tls_ca: str | None = None):
        self.client = Client(env, url, token_file, tls_ca)
        self.spec_message = self.client.spec
        self.observation_space, self.action_space = _spaces(self.spec_message)
        self.state_names = list(self.spec_message.state_names)
        self.action_names = list(self.spec_message.action_names)

    def reset(self, *, seed: int | None = None, options=None):
        super().reset(seed=seed)
        # Equal seeds give equal starts; without one, the next start comes
        # from this environment's own generator (seeded by the last seed).
        episode_seed = seed if seed is not None else int(self.np_random.integers(2**63))
        return self.client.reset([episode_seed])[0], {}

    def step(self, action):
        (result,) = self.client.step([(self.client.sessions[0], action)])
        return np.asarray(result.state, dtype=np.float64), float(result.reward), result.terminated, result.truncated, _info(result)

    def close(self):
        self.client.close()


class LcrlVectorEnv(VectorEnv):
    """`num_envs` sessions of one server stepped in one call a step
    (Gymnasium's next-step autoreset: the step after an episode's end
    resets that environment)."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, env: str = "peg-group1", num_envs: int = 8, url: str | None = None, token_file: str | None = None, tls_ca: str | None = None):
        if num_envs < 1:
            raise ValueError("num_envs must be at least 1")
        self.client = Client(env, url, token_file, tls_ca, sessions=num_envs)
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = _spaces(self.client.spec)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, num_envs)
        self._ended = np.zeros(num_envs, dtype=bool)
        self._rng = np.random.default_rng()

    def _seeds(self, n: int) -> list[int]:
        return [int(s) for s in self._rng.integers(2**63, size=n)]

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        seeds = seed if isinstance(seed, (list, tuple)) else self._seeds(self.num_envs)
        self._ended[:] = False
        return np.stack(self.client.reset(seeds)), {}

    def step(self, actions):
        actions = np.asarray(actions, dtype=np.float64).reshape(self.num_envs, -1)
        obs = np.zeros((self.num_envs, self.single_observation_space.shape[0]))
        rewards = np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        ended = np.flatnonzero(self._ended)
        if ended.size:
            starts = self.client.reset([s if k in ended else None for k, s in enumerate(self._seeds(self.num_envs))])
            obs[ended] = np.stack(starts)
        running = np.flatnonzero(~self._ended)
        infos = [{} for _ in range(self.num_envs)]
        if running.size:
            results = self.client.step([(self.client.sessions[k], actions[k]) for k in running])
            for k, r in zip(running, results):
                obs[k], rewards[k], terminated[k], truncated[k], infos[k] = r.state, r.reward, r.terminated, r.truncated, _info(r)
        self._ended = terminated | truncated
        return obs, rewards, terminated, truncated, {"per_env": infos}

    def close_extras(self, **kwargs):
        self.client.close()


def make(env: str = "peg-group1", url: str | None = None, **kwargs) -> LcrlEnv:
    """One environment; without `url`, a server of this process serves it."""
    return LcrlEnv(env, url=url, **kwargs)


def make_vec(env: str = "peg-group1", num_envs: int = 8, url: str | None = None, **kwargs) -> LcrlVectorEnv:
    """`num_envs` environments stepped together, one round trip a step."""
    return LcrlVectorEnv(env, num_envs=num_envs, url=url, **kwargs)


def register() -> None:
    """Registers "lcrl/NAME" for every built-in environment."""
    for name in BUILT_IN:
        if f"lcrl/{name}" not in gymnasium.registry:
            gymnasium.register(f"lcrl/{name}", entry_point="lcrl_env.gymnasium_env:LcrlEnv", kwargs={"env": name})
