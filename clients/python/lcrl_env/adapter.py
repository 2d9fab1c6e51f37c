"""One Gymnasium environment as lcrl sees it: a flat f64 state, a Box of
actions, names for both, and exact forks.

Everything here is plain Python over Gymnasium; the gRPC server
(`server.py`) only moves numbers in and out of it, so tests can call it
without a network.
"""

from __future__ import annotations

import copy
import importlib
import math
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np


class SpecError(ValueError):
    """The environment cannot be served: the message says why and what to do."""


@dataclass
class EnvSpec:
    env_id: str
    state_names: list[str]
    action_names: list[str]
    state_low: np.ndarray
    state_high: np.ndarray
    action_low: np.ndarray
    action_high: np.ndarray
    action_dtype: np.dtype
    fork_method: str = ""
    fork_unavailable: str = ""
    max_episode_steps: int = 0
    dt: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def can_fork(self) -> bool:
        return self.fork_method != ""


def make_factory(env_id: str | None, entry_point: str | None, kwargs: dict, max_episode_steps: int | None):
    """A function that makes one new instance, checked once here.

    `env_id`: a registered Gymnasium id (``"HalfCheetah-v5"``, or
    ``"module:Id"`` to import the module that registers it first).
    `entry_point`: ``"module:Class"``, a user's own ``gymnasium.Env``.
    """
    if (env_id is None) == (entry_point is None):
        raise SpecError("give exactly one of --env ID and --entry-point module:Class")
    if entry_point is not None:
        module_name, _, class_name = entry_point.partition(":")
        if not module_name or not class_name:
            raise SpecError(f"--entry-point {entry_point!r} must look like module:Class")
        try:
            module = importlib.import_module(module_name)
        except ImportError as e:
            raise SpecError(f"--entry-point {entry_point!r}: cannot import {module_name!r} ({e}); is it on PYTHONPATH?") from e
        cls = getattr(module, class_name, None)
        if cls is None:
            raise SpecError(f"--entry-point {entry_point!r}: module {module_name!r} has no {class_name!r}")

        def factory():
            env = cls(**kwargs)
            if max_episode_steps:
                env = gym.wrappers.TimeLimit(env, max_episode_steps=max_episode_steps)
            return env

        return factory, entry_point
    try:
        gym.spec(env_id)
    except gym.error.Error as e:
        raise SpecError(f"unknown Gymnasium environment {env_id!r} ({e}); `python -c 'import gymnasium; gymnasium.pprint_registry()'` lists them") from e

    def factory():
        extra = {"max_episode_steps": max_episode_steps} if max_episode_steps else {}
        return gym.make(env_id, **kwargs, **extra)

    return factory, env_id


def _box_or_refuse(space, what: str, flag: str) -> gym.spaces.Box:
    if isinstance(space, gym.spaces.Box):
        return space
    kind = type(space).__name__
    raise SpecError(
        f"the {what} space is {kind} ({space}); lcrl serves environments whose {what} space is a Box "
        f"(continuous: LCRL gives every action component its own network with a real-valued output, "
        f"and CS3 measures real state differences). {flag}"
    )


def describe(env: gym.Env, env_id: str, state_names=None, action_names=None) -> EnvSpec:
    """The spec of `env` (a fresh instance), or SpecError for what lcrl cannot serve.

    The components' names, in order of precedence: `state_names` and
    `action_names` (serve's --state-names, --action-names), the class's
    `lcrl_state_names` and `lcrl_action_names`, MuJoCo's joint names, s0… a0….
    """
    obs_space = _box_or_refuse(env.observation_space, "observation", "Flatten the observation (gymnasium.wrappers.FlattenObservation) in your entry point.")
    act_space = _box_or_refuse(env.action_space, "action", "Discrete actions need another method.")
    if len(act_space.shape) != 1:
        raise SpecError(f"the action space has shape {act_space.shape}; lcrl needs a 1-D Box of action components")
    a_low = np.asarray(act_space.low, dtype=np.float64).ravel()
    a_high = np.asarray(act_space.high, dtype=np.float64).ravel()
    if not (np.all(np.isfinite(a_low)) and np.all(np.isfinite(a_high))):
        raise SpecError(f"the action space's bounds must be finite (low {a_low}, high {a_high}): lcrl maps its policy's [-1, 1] onto them")
    m = int(np.prod(obs_space.shape))
    n = a_low.size
    u = env.unwrapped
    state_names = list(state_names or getattr(u, "lcrl_state_names", None) or _mujoco_state_names(env, m) or [f"s{j}" for j in range(m)])
    action_names = list(action_names or getattr(u, "lcrl_action_names", None) or _mujoco_action_names(u, n) or [f"a{i}" for i in range(n)])
    if len(state_names) != m or len(action_names) != n:
        raise SpecError(f"the state and action names (--state-names/--action-names or lcrl_state_names/lcrl_action_names) are {len(state_names)} and {len(action_names)} for {m} states and {n} actions")
    if len(set(state_names)) != m or len(set(action_names)) != n:
        raise SpecError("state and action names must each be different from one another")
    spec = env.spec
    dt = float(getattr(u, "dt", 0.0) or 0.0)
    return EnvSpec(
        env_id=env_id,
        state_names=state_names,
        action_names=action_names,
        state_low=np.asarray(obs_space.low, dtype=np.float64).ravel(),
        state_high=np.asarray(obs_space.high, dtype=np.float64).ravel(),
        action_low=a_low,
        action_high=a_high,
        action_dtype=act_space.dtype,
        max_episode_steps=int(spec.max_episode_steps or 0) if spec is not None else 0,
        dt=dt if math.isfinite(dt) else 0.0,
    )


# --- MuJoCo -----------------------------------------------------------------


def _mujoco(u):
    """The mujoco module when `u` simulates with MuJoCo (has model and data)."""
    try:
        import mujoco
    except ImportError:
        return None
    if isinstance(getattr(u, "model", None), mujoco.MjModel) and isinstance(getattr(u, "data", None), mujoco.MjData):
        return mujoco
    return None


def _mujoco_action_names(u, n: int):
    mujoco = _mujoco(u)
    if mujoco is None or u.model.nu != n:
        return None
    return [mujoco.mj_id2name(u.model, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"a{i}" for i in range(n)]


def _mujoco_state_names(env: gym.Env, m: int):
    """Names for observations that are qpos[skip:] followed by qvel (HalfCheetah,
    Hopper, Walker2d, Swimmer, ...): "qpos:JOINT" and "qvel:JOINT". Checked on
    a real reset, so an observation of another layout gets generic names."""
    u = env.unwrapped
    mujoco = _mujoco(u)
    if mujoco is None:
        return None
    model = u.model
    skip = model.nq + model.nv - m
    if not 0 <= skip <= model.nq:
        return None
    obs, _ = env.reset(seed=0)
    layout = np.concatenate([u.data.qpos[skip:], u.data.qvel]).ravel()
    if not np.array_equal(np.asarray(obs, dtype=np.float64).ravel(), layout):
        return None

    def per_coordinate(address, count, kind):
        names = [f"{kind}{k}" for k in range(count)]
        for j in range(model.njnt):
            joint = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
            start = int(address[j])
            width = {0: (7 if kind == "qpos" else 6), 1: (4 if kind == "qpos" else 3)}.get(int(model.jnt_type[j]), 1)
            for k in range(width):
                names[start + k] = f"{kind}:{joint}" if width == 1 else f"{kind}:{joint}[{k}]"
        return names

    return per_coordinate(model.jnt_qposadr, model.nq, "qpos")[skip:] + per_coordinate(model.jnt_dofadr, model.nv, "qvel")


# --- Forks ------------------------------------------------------------------


def _fork_mujoco(env: gym.Env) -> gym.Env:
    """A copy whose MjData is set from the source's integration state (qpos,
    qvel, act, time, controls, warm start, ...) with the MjModel shared; every
    other attribute, the wrappers' and the RNG included, deep-copied.
    Gymnasium's MuJoCo environments pickle by constructor arguments
    (EzPickle), so a plain deepcopy would make a fresh, reset-state
    environment instead of a copy."""
    u = env.unwrapped
    mujoco = _mujoco(u)
    kind = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(u.model, kind))
    mujoco.mj_getState(u.model, u.data, state, kind)
    data = mujoco.MjData(u.model)
    mujoco.mj_setState(u.model, data, state, kind)
    copy_u = object.__new__(type(u))
    memo = {id(u.model): u.model, id(u.data): data, id(u): copy_u}
    for name, value in vars(u).items():
        setattr(copy_u, name, copy.deepcopy(value, memo))
    # The wrappers (TimeLimit's step count, ...) are copied around copy_u.
    return copy.deepcopy(env, memo)


def _fork_deepcopy(env: gym.Env) -> gym.Env:
    return copy.deepcopy(env)


def choose_fork(env: gym.Env):
    """(method name, fork function) for `env`, or ("", reason) when no exact
    copy can be made. A fork is tried on `env` (reset and one step in) and
    must step bit-identically to it."""
    u = env.unwrapped
    if _mujoco(u) is not None:
        method, fork = "mujoco-state", _fork_mujoco
    elif type(u).__getstate__ is not object.__getstate__ and hasattr(u, "_ezpickle_args"):
        return "", (f"{type(u).__name__} pickles by its constructor arguments (EzPickle), so a deepcopy would be a new "
                    "environment, not a copy; it is not a MuJoCo environment, whose state lcrl can copy")
    else:
        method, fork = "deepcopy", _fork_deepcopy
    try:
        env.reset(seed=0)
        probe_action = np.zeros(env.action_space.shape, dtype=env.action_space.dtype)
        probe_action = np.clip(probe_action, env.action_space.low, env.action_space.high)
        env.step(probe_action)
        twin = fork(env)
        a, b = env.step(probe_action), twin.step(probe_action)
    except Exception as e:  # noqa: BLE001 - any failure means: cannot fork
        return "", f"{method} failed: {type(e).__name__}: {e}"
    if not (np.array_equal(np.asarray(a[0]), np.asarray(b[0])) and a[1] == b[1]):
        return "", f"a {method} copy does not step like the original"
    return method, fork
