#!/usr/bin/env bash
# Evaluates every finished run of an `lcrl experiment` study on the starts
# of the bar (`lcrl sim --episodes 100 --seed 0`, the ones `lcrl tune`
# evaluates the best constant on), beside a = 0 and the best constant, and
# prints one markdown table: per cell the mean over seeds, each seed, the
# success rate and the number of runs below a = 0 (diverged). A run whose
# policy was chosen by validation (RUN/selected/) is evaluated twice: its
# policy (the selected one) and, on a row of its own, its last checkpoint.
# Studies run since runs are evaluated on the best constant's starts
# (summary.json's eval_seed = 0) already have the selected policy's figure
# in their report; this script still adds the last policies and serves
# older studies.
# Usage: bash scripts/eval-study.sh STUDY_DIR
set -euo pipefail
cd "$(dirname "$0")/.."
study=${1:?usage: bash scripts/eval-study.sh STUDY_DIR}
lcrl=${LCRL_BIN:-target/debug/lcrl}
for summary in $(find "$study/runs" -name summary.json -path '*seed*' | sort); do
  dir=$(dirname "$summary")
  [ -f "$dir/eval100/summary.json" ] || $lcrl sim --checkpoint "$dir" --episodes 100 --seed 0 --out "$dir/eval100" > /dev/null 2>&1
  if [ -d "$dir/selected" ] && [ ! -f "$dir/eval100-last/summary.json" ]; then
    last=$(ls -d "$dir"/checkpoints/ep* | sort | tail -n 1)
    $lcrl sim --checkpoint "$last" --episodes 100 --seed 0 --out "$dir/eval100-last" > /dev/null 2>&1
  fi
done
for bc in $(find "$study/best_constant" -name best_constant.json 2>/dev/null); do
  env=$(basename "$(dirname "$bc")")
  d="$study/best_constant/$env"
  [ -f "$d/zero/summary.json" ] || $lcrl sim --env "$env" --episodes 100 --seed 0 --out "$d/zero" > /dev/null 2>&1
  action=$(python3 -c 'import json,sys; print(",".join(repr(a) for a in json.load(open(sys.argv[1]))["action"]))' "$bc")
  [ -f "$d/best/summary.json" ] || $lcrl sim --env "$env" --episodes 100 --seed 0 --action="$action" --out "$d/best" > /dev/null 2>&1
done
python3 - "$study" <<'PY'
import json, sys, glob, os, statistics as st
study = sys.argv[1]
def load(p): return json.load(open(p))
print("| env | algo | controller | return: mean (per seed) | success | below a = 0 |")
print("|---|---|---|---|---|---|")
for env_dir in sorted(glob.glob(f"{study}/runs/*")):
    env = os.path.basename(env_dir)
    ref = f"{study}/best_constant/{env}"
    zero = load(f"{ref}/zero/summary.json")["mean_return"] if os.path.exists(f"{ref}/zero/summary.json") else None
    for label, d in [("a = 0", f"{ref}/zero"), ("best constant", f"{ref}/best")]:
        if os.path.exists(f"{d}/summary.json"):
            x = load(f"{d}/summary.json")
            print(f"| {env} | — | {label} | {x['mean_return']:.2f} | {100*x['success_rate']:.0f}% | — |")
    for algo_dir in sorted(glob.glob(f"{env_dir}/*")):
        for conn_dir in sorted(glob.glob(f"{algo_dir}/*")):
            for folder, note in [("eval100", ""), ("eval100-last", " (last policy)")]:
                xs = [load(p) for p in sorted(glob.glob(f"{conn_dir}/seed*/{folder}/summary.json"))]
                if not xs: continue
                r = [x["mean_return"] for x in xs]
                succ = st.mean(x["success_rate"] for x in xs)
                below = sum(1 for v in r if zero is not None and v < zero)
                print(f"| {env} | {os.path.basename(algo_dir)} | {os.path.basename(conn_dir)}{note} | {st.mean(r):.2f} ({', '.join(f'{v:.2f}' for v in r)}) | {100*succ:.0f}% | {below} of {len(r)} |")
PY
