#!/usr/bin/env python3
"""Every handed-over policy of a study on fresh starts, and two arms
paired by seed (the twelfth, thirteenth and sixteenth rounds:
docs/research/2026-11-27-peg-safety-12-exploring-base-bar.md,
docs/research/2026-11-27-peg-safety-13-reach-seven-eighths.md,
docs/research/2026-11-27-peg-safety-16-temporal-smoothness.md).

    python3 scripts/fresh-starts.py STUDY_DIR [--against OTHER_STUDY_DIR] [--episodes 2000] [--lcrl PATH]

For every finished run under STUDY_DIR/runs (and OTHER_STUDY_DIR's, with
--against) it runs `lcrl sim --checkpoint RUN/selected --episodes N --seed
100000 --out RUN/freshN` (skipped when already there), and prints per seed:
the mean return, failed starts, the highest peak force, and how bang-bang
the policy acts: the mean over starts of `max_action_jump` (the largest
switch of one action component between two steps, as a share of its
range) and the share of starts with a switch of half the range or more (at reach 0.875 the most a residual can switch is 0.875). With
--against, the return difference per seed and its paired 95% interval.
"""

import argparse
import os
import sys

from studylib import FRESH_SEED, finished_runs, paired_ci, run_seed, sim

LARGE_JUMP = 0.5


def arm(study, episodes, lcrl):
    """Per seed: (mean return, failed, max force, mean jump, share of jumps ≥ 0.5)."""
    figures = {}
    for run in finished_runs(study):
        rows, mean = sim(lcrl, os.path.join(run, "selected"), FRESH_SEED, episodes, os.path.join(run, f"fresh{episodes}"))
        jumps = [float(r["max_action_jump"]) for r in rows]
        figures[run_seed(run)] = (
            mean,
            sum(r["failed"] == "true" for r in rows),
            max(float(r["peak_force_n"]) for r in rows),
            sum(jumps) / len(jumps),
            sum(j >= LARGE_JUMP for j in jumps) / len(jumps),
        )
    if not figures:
        sys.exit(f"no finished runs under {study}/runs")
    return figures


def show(name, figures):
    print(f"{name}:")
    for seed, (mean, failed, force, jump, edge) in figures.items():
        print(f"  seed {seed:3d}: return {mean:8.3f}  failed {failed}  max {force:5.1f} N  action jump: mean {jump:.3f}, ≥ {LARGE_JUMP} in {100 * edge:5.1f}% of starts")
    n = len(figures)
    values = list(figures.values())
    print(f"  all {n}: return {sum(v[0] for v in values) / n:.3f}  failed {sum(v[1] for v in values)}  max {max(v[2] for v in values):.1f} N"
          f"  action jump: mean {sum(v[3] for v in values) / n:.3f}, ≥ {LARGE_JUMP} in {100 * sum(v[4] for v in values) / n:.1f}% of starts")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("study")
    ap.add_argument("--against")
    ap.add_argument("--episodes", type=int, default=2000)
    ap.add_argument("--lcrl", default=os.environ.get("LCRL", "target/debug/lcrl"))
    args = ap.parse_args()
    mine = arm(args.study, args.episodes, args.lcrl)
    show(args.study, mine)
    if not args.against:
        return
    theirs = arm(args.against, args.episodes, args.lcrl)
    show(args.against, theirs)
    seeds = sorted(set(mine) & set(theirs))
    if len(seeds) < 2:
        sys.exit("fewer than two seeds in both arms: nothing to pair")
    diffs = [mine[s][0] - theirs[s][0] for s in seeds]
    print("paired, per seed: " + ", ".join(f"{s}: {d:+.3f}" for s, d in zip(seeds, diffs)))
    mean, low, high = paired_ci(diffs)
    print(f"{args.study} minus {args.against}: {mean:+.3f} [{low:+.3f}, {high:+.3f}] over {len(seeds)} seeds")


if __name__ == "__main__":
    main()
