#!/usr/bin/env python3
"""Rare handover failures: do a policy's near-limit starts on its
confirmation predict the starts it fails later?
(docs/research/2026-11-27-peg-rare-handover-failures.md).

    python3 scripts/force-tail.py STUDY_DIR [--fresh 2000] [--lcrl PATH]

For every training run under STUDY_DIR/runs and every policy the run kept
for its confirmation (RUN/candidates/episode-*, RUN/selected/), it runs
`lcrl sim` twice:

- on the run's own 300 confirmation starts (seeds 2^43 + r*2^20 + k, the
  ones learner/src/run/selection.rs scored it on; the mean return is checked
  against selection.json, to the last digit), and
- on --fresh further starts from seed 100000 (no run trains, validates or
  is evaluated there),

keeps each episodes.csv under STUDY_DIR/force-tail/, and prints per policy:
confirmation mean return, failed starts, starts that came near a limit
(peak force above 0.9 x 50 N or peak moment above 0.9 x 1.5 N*m), highest
peak force; and on the fresh starts the failures and mean return. Then it
compares today's confirmation rule (best mean return) with one that first
sets aside candidates that came near a limit on their confirmation starts.

Written before the data (2026-11-27), the hypothesis and the rule:
a policy that fails at least one of the fresh starts came near a limit on
at least one of its confirmation starts more often than one that fails
none. The near-limit rule becomes the confirmation's default only if, on
this study's runs, it hands over policies that fail fewer fresh starts
than today's rule in total, at a fresh-start mean return no more than
0.05 below today's (paired by run); even then ten runs are a first look,
to be confirmed on seeds the rule was not read on.
"""

import argparse
import json
import os
import sys
from dataclasses import dataclass

from studylib import FRESH_SEED, finished_runs, paired_ci, run_seed, sim

FORCE_LIMIT_N = 50.0
MOMENT_LIMIT_NM = 1.5
NEAR = 0.9
CONFIRMATION_BASE = 1 << 43
PER_RUN = 1 << 20


@dataclass(eq=False)
class Candidate:
    """One kept policy: its confirmation profile, and its fresh one once run."""

    episode: int
    path: str
    out: str
    confirmation_mean: float
    confirmation: dict
    fresh_mean: float | None = None
    fresh: dict | None = None


def near_limit(row):
    return float(row["peak_force_n"]) > NEAR * FORCE_LIMIT_N or float(row["peak_moment_nm"]) > NEAR * MOMENT_LIMIT_NM


def profile(rows):
    return {
        "failed": sum(r["failed"] == "true" for r in rows),
        "near": sum(near_limit(r) for r in rows),
        "max_force": max(float(r["peak_force_n"]) for r in rows),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("study")
    ap.add_argument("--fresh", type=int, default=2000)
    ap.add_argument("--fresh-all", action="store_true", help="run the fresh starts for every candidate, not only the two rules' picks")
    ap.add_argument("--only", type=int, help="the run of this seed alone")
    ap.add_argument("--lcrl", default=os.environ.get("LCRL", "target/debug/lcrl"))
    args = ap.parse_args()
    runs = finished_runs(args.study)
    if not runs:
        sys.exit(f"no finished runs under {args.study}/runs")
    picks = {"today's rule": [], "near-limit rule": []}
    for run in runs:
        r = run_seed(run)
        if args.only is not None and r != args.only:
            continue
        with open(os.path.join(run, "selected", "selection.json")) as f:
            selection = json.load(f)
        confirmation = selection.get("confirmation") or {"candidates": []}
        candidates = []
        for cand in confirmation["candidates"]:
            episode = cand["episode"]
            path = os.path.join(run, "candidates", f"episode-{episode:07d}")
            out = os.path.join(args.study, "force-tail", f"seed{r}", f"episode-{episode:07d}")
            rows, mean = sim(args.lcrl, path, CONFIRMATION_BASE + r * PER_RUN, 300, os.path.join(out, "confirmation"))
            if mean != cand["mean_return"]:
                sys.exit(f"seed {r} episode {episode}: confirmation {mean} does not repeat selection.json's {cand['mean_return']}")
            candidates.append(Candidate(episode, path, out, mean, profile(rows)))
        if not candidates:
            print(f"seed {r}: no confirmation (one distinct policy), skipped")
            continue
        # Today's rule: the first of the best confirmation means (max keeps
        # the first of equals; candidates come best-validated first).
        today = max(candidates, key=lambda c: c.confirmation_mean)
        calm = [c for c in candidates if c.confirmation["near"] == 0] or candidates
        near_rule = max(calm, key=lambda c: c.confirmation_mean)
        # The fresh starts are the expensive part: the two rules' picks
        # always run them, the other candidates with --fresh-all.
        for c in candidates:
            fresh_out = os.path.join(c.out, f"fresh{args.fresh}")
            if args.fresh_all or os.path.exists(os.path.join(fresh_out, "episodes.csv")) or c in (today, near_rule):
                rows, c.fresh_mean = sim(args.lcrl, c.path, FRESH_SEED, args.fresh, fresh_out)
                c.fresh = profile(rows)
            chosen = "*" if c.episode == selection["episode"] else " "
            conf, fresh = c.confirmation, c.fresh
            fresh_text = f"fresh {c.fresh_mean:8.3f} failed {fresh['failed']} near {fresh['near']:3d} max {fresh['max_force']:5.1f} N" if fresh else "fresh not run"
            print(f"seed {r:3d} {chosen} episode {c.episode:4d}: confirmation {c.confirmation_mean:8.3f} failed {conf['failed']} near {conf['near']:3d} max {conf['max_force']:5.1f} N | {fresh_text}")
        picks["today's rule"].append(today)
        picks["near-limit rule"].append(near_rule)
        print(f"seed {r:3d}: today's rule hands over episode {today.episode}, the near-limit rule episode {near_rule.episode}")
    n = len(picks["today's rule"])
    if n == 0:
        sys.exit("no run confirmed between several policies: nothing to compare")
    for rule, chosen in picks.items():
        print(f"{rule}: {sum(c.fresh['failed'] for c in chosen)} failed fresh starts, mean fresh return {sum(c.fresh_mean for c in chosen) / n:.3f}")
    mean, low, high = paired_ci([near.fresh_mean - today.fresh_mean for today, near in zip(picks["today's rule"], picks["near-limit rule"])])
    print(f"near-limit minus today, paired: {mean:+.3f} [{low:+.3f}, {high:+.3f}] over {n} runs")

if __name__ == "__main__":
    main()
