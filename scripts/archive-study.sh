#!/usr/bin/env bash
# Copy a study's results (not its checkpoints, policies or logs) from an
# `lcrl experiment` output folder into a folder that can be committed:
# experiment.toml/json, the cell configs, graphs, best constants, headroom
# references, each run's config.toml, summary.json and metrics.csv, and the
# report. A run with summary.json counts as finished, so
#   cp -r DEST runs/NAME && lcrl experiment run FILE --out runs/NAME
# resumes the study where the archive left it.
#
#   bash scripts/archive-study.sh runs/peg-bars results/peg-bars
set -euo pipefail
if [ $# -ne 2 ]; then
  echo "usage: bash scripts/archive-study.sh STUDY_OUT DEST" >&2
  exit 2
fi
src=$1 dest=$2
if [ ! -f "$src/experiment.json" ]; then
  echo "archive-study: $src has no experiment.json; give the --out folder of 'lcrl experiment run'" >&2
  exit 1
fi
mkdir -p "$dest"
dest=$(cd "$dest" && pwd)
cd "$src"
find . -type f \( -name summary.json -o -name metrics.csv -o -name 'report.md' -o -name 'report.json' \
  -o -name curves.png -o -name 'graph.json' -o -name 'graph.png' -o -name best_constant.json \
  -o -name best_policy.json -o -name '*.toml' -o -name experiment.json \) \
  -not -path '*/checkpoints/*' -not -path '*/selected/*' -print0 |
  xargs -0 --no-run-if-empty cp --parents -t "$dest"
echo "archive-study: $(find "$dest" -name summary.json | wc -l) finished runs in $dest"
