#!/usr/bin/env python3
"""One Stable-Baselines3 run on one of lcrl's environments, through
lcrl_env's Gymnasium face (`lcrl serve-env`), recorded as lcrl records its
own runs: metrics.csv (one row per training episode) and summary.json
(the final policy evaluated on the best constant's 100 evaluation starts,
seeds 0-99, deterministic actions). The peer cells of
the peer study (docs/peers.md; lcrl's own cells are
experiments/research/peers-ppo.toml).

    .venv/bin/python scripts/sb3_peers.py --env peg-group1 --algo sac --seed 0 --episodes 200 --out runs/peers/peg-group1/sac/seed0

Settings: SB3's defaults for the algorithm, with the overrides of
--settings (a JSON object of keyword arguments), all written to
summary.json. Some spellings are rl-zoo3's rather than SB3's: "noise_std"
(with "noise_type": "normal") becomes a NormalActionNoise of that scale on
every action component, a list "train_freq" ([1, "episode"]) a tuple,
"learning_rate" or "clip_range" "lin_X" a schedule from X to 0 over the
episode budget, and policy_kwargs' "activation_fn" a name (tanh, relu,
elu). A finished run (summary.json present) is skipped.
"""

import argparse
import csv
import json
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "clients/python"))

import lcrl_env  # noqa: E402
import torch  # noqa: E402
from stable_baselines3 import PPO, SAC, TD3  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402

ALGOS = {"sac": SAC, "td3": TD3, "ppo": PPO}


class Episodes(BaseCallback):
    """Records each finished training episode and stops at the budget."""

    def __init__(self, budget: int, rows: list):
        super().__init__()
        self.budget, self.rows = budget, rows
        self.ret, self.length, self.started = 0.0, 0, time.monotonic()

    def _on_step(self) -> bool:
        self.ret += float(self.locals["rewards"][0])
        self.length += 1
        if self.locals["dones"][0]:
            self.rows.append({"episode": len(self.rows) + 1, "return": self.ret, "length": self.length, "wall_s": round(time.monotonic() - self.started, 3)})
            if len(self.rows) % 10 == 0:
                print(f"episode {len(self.rows)}/{self.budget}: return {self.ret:.3f}, {self.rows[-1]['wall_s']:.0f} s", file=sys.stderr, flush=True)
            self.ret, self.length = 0.0, 0
        return len(self.rows) < self.budget


def evaluate(model, env, episodes: int = 100) -> list[float]:
    """Deterministic returns on evaluation starts 0..episodes-1 (lcrl
    tune's, the best constant's)."""
    returns = []
    for seed in range(episodes):
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, term, trunc, _ = env.step(action)
            total, done = total + reward, term or trunc
        returns.append(total)
    return returns


ACTIVATIONS = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU, "elu": torch.nn.ELU}


def linear_to_zero(value: float, done) -> callable:
    """rl-zoo3's "lin_X" schedule, over this run's episode budget: X times
    the share of the budget left. SB3's own progress counts steps against
    total_timesteps, which an episode budget leaves at 10**9 (see main)."""
    return lambda _progress_remaining: value * max(0.0, 1.0 - done())


def sb3_keywords(settings: dict, env, done=lambda: 0.0) -> dict:
    """SB3's keyword arguments for `settings` (rl-zoo3's noise, train_freq,
    "lin_X" schedules and activation names spelled as SB3 takes them;
    `done` is the share of the episode budget done, for the schedules)."""
    kw = dict(settings)
    for key in ("learning_rate", "clip_range"):
        if isinstance(kw.get(key), str):
            if not kw[key].startswith("lin_"):
                raise SystemExit(f"--settings: {key} {kw[key]!r}: a number or \"lin_X\" (linear from X to 0 over the episode budget)")
            kw[key] = linear_to_zero(float(kw[key][4:]), done)
    policy_kwargs = dict(kw.get("policy_kwargs") or {})
    if isinstance(policy_kwargs.get("activation_fn"), str):
        name = policy_kwargs["activation_fn"]
        if name not in ACTIVATIONS:
            raise SystemExit(f"--settings: activation_fn {name!r} is not one of {sorted(ACTIVATIONS)}")
        policy_kwargs["activation_fn"] = ACTIVATIONS[name]
        kw["policy_kwargs"] = policy_kwargs
    noise_type, noise_std = kw.pop("noise_type", None), kw.pop("noise_std", None)
    if noise_std is not None:
        if noise_type not in (None, "normal"):
            raise SystemExit(f"--settings: noise_type {noise_type!r} is not supported (normal only)")
        from stable_baselines3.common.noise import NormalActionNoise
        n = env.action_space.shape[0]
        kw["action_noise"] = NormalActionNoise(mean=np.zeros(n), sigma=noise_std * np.ones(n))
    if isinstance(kw.get("train_freq"), list):
        kw["train_freq"] = tuple(kw["train_freq"])
    return kw


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", required=True, help="an lcrl environment (peg-group1, peg-group2, ...)")
    parser.add_argument("--algo", required=True, choices=sorted(ALGOS))
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--episodes", type=int, required=True, help="training episodes (the publication's budgets: 200 off-policy, 900 PPO)")
    parser.add_argument("--settings", default="{}", help="keyword arguments for the SB3 algorithm, as JSON")
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--out", required=True, type=pathlib.Path)
    args = parser.parse_args()
    if (args.out / "summary.json").is_file():
        print(f"{args.out}: finished before", file=sys.stderr)
        return 0
    settings = json.loads(args.settings)
    if not isinstance(settings, dict):
        parser.error("--settings must be a JSON object")
    args.out.mkdir(parents=True, exist_ok=True)
    # One libtorch thread, as lcrl's own runs (`--threads 1`): two runs side
    # by side on 2 cores with 2 threads each spend their time waiting for
    # each other.
    torch.set_num_threads(1)
    env = lcrl_env.make(args.env)
    rows: list = []
    started = time.monotonic()
    model = ALGOS[args.algo]("MlpPolicy", env, seed=args.seed, device="cpu", verbose=0, **sb3_keywords(settings, env, lambda: len(rows) / args.episodes))
    # SB3 counts steps; the budget is in episodes (at most 100 steps each
    # on the peg presets), so the step cap is never what stops it.
    model.learn(total_timesteps=10**9, callback=Episodes(args.episodes, rows))
    train_s = time.monotonic() - started
    returns = evaluate(model, env, args.eval_episodes)
    env.close()
    with open(args.out / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["episode", "return", "length", "wall_s"])
        writer.writeheader()
        writer.writerows(rows)
    summary = {
        "env": args.env, "algo": f"sb3-{args.algo}", "seed": args.seed, "episodes": len(rows), "env_steps": int(model.num_timesteps),
        "eval_return": float(np.mean(returns)), "eval_returns": returns, "eval_seed": 0,
        "train_seconds": round(train_s, 2), "total_seconds": round(time.monotonic() - started, 2),
        "settings": settings, "sb3": __import__("stable_baselines3").__version__, "torch_threads": torch.get_num_threads(),
    }
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{args.env} {args.algo} seed {args.seed}: {len(rows)} episodes, eval {summary['eval_return']:.3f}, {train_s:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
