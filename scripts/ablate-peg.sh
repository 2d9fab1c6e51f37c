#!/usr/bin/env bash
# One change at a time: DDPG with configs/peg.toml and each variant that
# undoes one of its differences from Table I
# (docs/research/2026-11-23-peg-settings-that-do-not-diverge.md, "Which
# changes mattered"), on one preset and a few seeds, two runs at a time.
# Each run is `lcrl train` with the variant's overlay (validation off: it
# does not change training, and every run is judged by its last policy, on
# the run's own 100 evaluation starts). Prints one markdown table.
#   bash scripts/ablate-peg.sh [ENV] [SEEDS] [OUT] [VARIANTS]
# e.g. bash scripts/ablate-peg.sh peg-group1 "0 1 2" runs/ablate-peg-group1 "peg squared-loss"
# (VARIANTS: a subset of the names below; all by default).
set -euo pipefail
cd "$(dirname "$0")/.."
env=${1:-peg-group1}
seeds=${2:-0 1 2}
out=${3:-runs/ablate-$env}
only=${4:-}
lcrl=${LCRL_BIN:-target/debug/lcrl}
mkdir -p "$out/configs"
# name|TOML laid over configs/peg.toml (one change each)
variants=(
  "peg|"
  "squared-loss|[ddpg]\nhuber_delta = 0.0"
  "critic-lr-1e-2|[ddpg]\ncritic_lr = 1e-2"
  "no-td3|[ddpg]\ntwin_critics = false\npolicy_delay = 1\ntarget_noise = 0.0"
  "table1-noise|[ddpg]\nnoise_start = 0.3\nnoise_end = 0.05"
  "relu|[network]\nactivation = \"relu\""
  "no-anneal|[ddpg]\nanneal_lr = false"
  "no-base|[controller]\nbase = \"none\""
)
# The graph, once (every local run of the preset uses the same G).
[ -f "$out/graph.json" ] || $lcrl graph --env "$env" --samples 64 --seed 0 --out "$out/graph.json" > /dev/null
jobs=()
for v in "${variants[@]}"; do
  name=${v%%|*}
  if [ -n "$only" ] && [[ " $only " != *" $name "* ]]; then continue; fi
  printf '%b\n[run]\nvalidation_episodes = 0\n' "${v#*|}" > "$out/configs/$name.toml"
  for seed in $seeds; do
    jobs+=("$name $seed")
  done
done
printf '%s\n' "${jobs[@]}" | xargs -P 2 -L 1 bash -c '
  dir="'"$out"'/$0/seed$1"
  [ -f "$dir/summary.json" ] && exit 0
  rm -rf "$dir"; mkdir -p "$(dirname "$dir")"
  '"$lcrl"' train --env '"$env"' --algo ddpg --connection local --graph '"$out"'/graph.json --episodes 200 --seed "$1" --threads 1 \
    --config '"$out"'/configs/$0.toml --run-dir "$dir" > "$dir.log" 2>&1 && echo "finished $0 seed $1"'
python3 - "$out" <<'PY'
import json, sys, glob, os, statistics as st
out = sys.argv[1]
print("| variant | eval return: mean (per seed) | success | failed episodes in training |")
print("|---|---|---|---|")
for d in sorted(glob.glob(f"{out}/*/"), key=lambda d: (os.path.basename(d.rstrip('/')) != 'peg', d)):
    runs = sorted(glob.glob(f"{d}seed*/summary.json"))
    if not runs: continue
    xs = [json.load(open(p)) for p in runs]
    fails = []
    for p in runs:
        rows = open(os.path.join(os.path.dirname(p), "metrics.csv")).read().splitlines()[1:]
        fails.append(sum(1 for r in rows if r.split(",")[3] == "false"))
    r = [x["eval_return"] for x in xs]
    succ = st.mean(x.get("eval_success_rate") or 0 for x in xs)
    print(f"| {os.path.basename(d.rstrip('/'))} | {st.mean(r):.2f} ({', '.join(f'{v:.2f}' for v in r)}) | {100*succ:.0f}% | {', '.join(map(str, fails))} |")
PY
