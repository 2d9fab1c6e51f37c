#!/usr/bin/env bash
# The main job, from a fresh clone: set-up (libtorch), build, then a local
# LCRL training run on peg-in-hole (peg-group1, docs/peg.md):
#   1. its connection graph G by CS3 at the preset's T (T_rule = 1, the
#      above-average rule) and why, printed (the run's own samples and seed);
#   2. `lcrl run`: graph builder, learner and an actor as processes (shared
#      memory between actor and learner), PPO with the locally connected
#      actor for the preset's 900 episodes, residual on the best constant
#      compliance (configs/peg.toml); then the final policy evaluated on 100
#      starts beside a = 0, the best constant (the bar) and the headroom
#      reference (references/peg-group1/best_policy.json) on the same starts.
# About a minute on 2 cores once built. Results go to runs/peg-group1/. Extra
# arguments go to `lcrl run`. The linear example is quicker (about 10 s):
#   target/debug/lcrl run --config configs/lti-paper.toml
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --workspace --bins
# The graph at the preset's T (T_rule = 1, configs/peg-group1-ppo-local.toml),
# printed with why that T.
target/debug/lcrl graph --env peg-group1 --samples 64 --seed 0 --threshold 1
echo
rm -rf runs/peg-group1
target/debug/lcrl run --config configs/peg-group1-ppo-local.toml --run-dir runs/peg-group1 "$@"
