#!/usr/bin/env bash
# The main job, from a fresh clone: set-up (libtorch), build, then an LCRL
# run on the publication's linear example (METHOD.md eq. 10):
#   1. build its connection graph G with CS3 and print it;
#   2. train the locally connected actor with PPO (single process, ~10 s)
#      and compare it with the LQR optimum.
# Results go to runs/lti-paper/. Extra arguments go to `lcrl train`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --workspace --bins
out=runs/lti-paper
mkdir -p "$out"
target/debug/lcrl graph --env lti-paper --samples 256 --out "$out/graph.json" --plot "$out/graph.png"
echo
rm -rf "$out/train"
target/debug/lcrl train --env lti-paper --algo ppo --connection local \
  --graph "$out/graph.json" --config configs/lti-fast.toml --episodes 1000 \
  --run-dir "$out/train" "$@"
echo
echo "results: $out/graph.json, $out/graph.png, $out/train/ (metrics.csv, summary.json, reward_curve.png, checkpoints/)"
