#!/usr/bin/env bash
# How much room is there on a randomized preset for a controller that
# knew the episode's draw? Runs the given constant on each evaluation
# start alone (`lcrl sim --seed k --episodes 1`, the same starts as
# `lcrl sim --seed 0 --episodes N`), lists the starts it fails, and
# searches a constant for each failed start on that start alone
# (`lcrl tune --episodes 1 --seed k --eval-seed k`). A start no constant
# inserts is one that adapting by a constant cannot win; the count of
# those a per-start constant does insert bounds what a draw-aware choice
# of constant could gain (docs/research/2026-11-23-peg-rand-adapt.md).
# Usage: bash scripts/per-draw-constants.sh ENV BEST_CONSTANT_JSON OUT [N] [EVALUATIONS]
set -euo pipefail
cd "$(dirname "$0")/.."
usage="usage: bash scripts/per-draw-constants.sh ENV BEST_CONSTANT_JSON OUT [N] [EVALUATIONS]"
env=${1:?$usage}
bc=${2:?$usage}
out=${3:?$usage}
n=${4:-100}
evaluations=${5:-300}
lcrl=${LCRL_BIN:-target/debug/lcrl}
action=$(python3 -c 'import json,sys; print(",".join(repr(a) for a in json.load(open(sys.argv[1]))["action"]))' "$bc")
for k in $(seq 0 $((n - 1))); do
  [ -f "$out/start/$k/summary.json" ] || $lcrl sim --env "$env" --action="$action" --episodes 1 --seed "$k" --out "$out/start/$k" > /dev/null
done
failed=$(python3 -c '
import json, sys
out, n = sys.argv[1], int(sys.argv[2])
print(" ".join(str(k) for k in range(n) if json.load(open(f"{out}/start/{k}/summary.json"))["success_rate"] < 1))
' "$out" "$n")
for k in $failed; do
  [ -f "$out/oracle/$k/best_constant.json" ] || $lcrl tune --env "$env" --episodes 1 --seed "$k" --eval-episodes 1 --eval-seed "$k" \
    --evaluations "$evaluations" --out "$out/oracle/$k" > /dev/null
done
python3 - "$out" "$n" "$failed" <<'PY'
import json, sys
out, n, failed = sys.argv[1], int(sys.argv[2]), [int(k) for k in sys.argv[3].split()]
def load(p): return json.load(open(p))
given = [load(f"{out}/start/{k}/summary.json")["mean_return"] for k in range(n)]
print("| start | given constant | per-start constant | success | peak force | action |")
print("|---|---|---|---|---|---|")
best = list(given)
inserted = 0
for k in failed:
    o = load(f"{out}/oracle/{k}/best_constant.json")
    best[k] = max(given[k], o["mean_return"])
    inserted += o["success_rate"] >= 1
    action = ", ".join(f"{a:.2f}" for a in o["action"])
    print(f"| {k} | {given[k]:.2f} | {o['mean_return']:.2f} | {100 * o['success_rate']:.0f}% | {o['mean_peak_force_n']:.1f} N | [{action}] |")
print()
print(f"the given constant fails {len(failed)} of {n} starts; a per-start constant inserts {inserted} of them")
print(f"mean return: given constant {sum(given) / n:.2f}; with the per-start constant on its failed starts {sum(best) / n:.2f}")
PY
