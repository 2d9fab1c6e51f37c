#!/usr/bin/env bash
# The main job, from a fresh clone: set-up (libtorch), build, then a local
# LCRL training run on the publication's linear example (docs/method.md eq. 10):
#   1. its connection graph G by CS3, printed;
#   2. `lcrl run`: graph builder, learner and an actor as processes (shared
#      memory between actor and learner), PPO with the locally connected
#      actor for the preset's 1000 episodes, then the final policy evaluated
#      against the best controller that sees only G's states (~10 s).
# Results go to runs/lti-paper/. Extra arguments go to `lcrl run`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --workspace --bins
target/debug/lcrl graph --env lti-paper --samples 256
echo
rm -rf runs/lti-paper
target/debug/lcrl run --config configs/lti-paper.toml --run-dir runs/lti-paper "$@"
