#!/usr/bin/env bash
# The main job, from a fresh clone: set-up (libtorch), build, then build the
# connection graph of the publication's linear example (METHOD.md eq. 10)
# with CS3, print it, and save graph.json and the heatmap under runs/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --workspace --bins
mkdir -p runs/lti-paper
target/debug/lcrl graph --env lti-paper --samples 256 \
  --out runs/lti-paper/graph.json --plot runs/lti-paper/graph.png "$@"
