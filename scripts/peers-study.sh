#!/usr/bin/env bash
# The peer study of docs/peers.md (design: docs/research/2026-11-28-peers-design.md):
# Stable-Baselines3's SAC, TD3 and PPO on peg-group1/2 through lcrl_env's
# Gymnasium face, 5 seeds a cell, the publication's budgets, each policy
# evaluated on the best constant's 100 starts; then lcrl's PPO cells
# (experiments/research/peers-ppo.toml). Resumable: finished runs are skipped.
#
#   bash scripts/peers-study.sh [OUT] [JOBS]      # default runs/peers, 2 at a time
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-runs/peers}
jobs=${2:-2}
bash scripts/setup.sh >/dev/null
cargo build --bins -q
tasks=()
for env in peg-group1 peg-group2; do
  for seed in 200 201 202 203 204; do
    tasks+=("$env sac $seed 200" "$env td3 $seed 200" "$env ppo $seed 900")
  done
done
printf '%s\n' "${tasks[@]}" | xargs -P "$jobs" -L 1 bash -c \
  '.venv/bin/python scripts/sb3_peers.py --env "$0" --algo "$1" --seed "$2" --episodes "$3" --out "'"$out"'/sb3/$0/$1/seed$2"'
target/debug/lcrl experiment run experiments/research/peers-ppo.toml --out "$out/lcrl-ppo" --jobs "$jobs"
