"""Helpers shared by the study scripts (force-tail.py, fresh-starts.py):
finding a study's runs, replaying a policy with `lcrl sim`, and a paired
95% interval."""

import csv
import json
import math
import os
import subprocess
import tomllib

# Student's t, 97.5% quantile, by degrees of freedom (95% intervals).
T_975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262, 10: 2.228, 11: 2.201, 12: 2.179,
         13: 2.160, 14: 2.145, 15: 2.131, 16: 2.120, 17: 2.110, 18: 2.101, 19: 2.093, 20: 2.086, 29: 2.045}
# The fresh starts: no run trains, validates or is evaluated from seed 100000 on.
FRESH_SEED = 100000


def run_seed(run_dir):
    with open(os.path.join(run_dir, "config.toml"), "rb") as f:
        return tomllib.load(f)["run"]["seed"]


def finished_runs(study):
    """The run folders under STUDY/runs that handed over a policy, by seed."""
    runs = [root for root, dirs, files in os.walk(os.path.join(study, "runs")) if "selected" in dirs and "summary.json" in files]
    return sorted(runs, key=run_seed)


def sim(lcrl, policy, seed, episodes, out):
    """`lcrl sim` of a checkpoint on `episodes` starts from `seed` into
    `out` (skipped when `out` already holds them): episodes.csv's rows and
    the mean return."""
    if not os.path.exists(os.path.join(out, "episodes.csv")):
        subprocess.run(
            [lcrl, "sim", "--checkpoint", policy, "--seed", str(seed), "--episodes", str(episodes), "--out", out],
            check=True,
            stdout=subprocess.DEVNULL,
        )
    with open(os.path.join(out, "episodes.csv")) as f:
        rows = list(csv.DictReader(f))
    with open(os.path.join(out, "summary.json")) as f:
        mean = json.load(f)["mean_return"]
    return rows, mean


def paired_ci(diffs):
    """Mean and 95% t interval of paired differences."""
    n = len(diffs)
    mean = sum(diffs) / n
    sd = math.sqrt(sum((d - mean) ** 2 for d in diffs) / (n - 1)) if n > 1 else float("nan")
    half = T_975.get(n - 1, 1.96) * sd / math.sqrt(n)
    return mean, mean - half, mean + half
