#!/usr/bin/env bash
# The README.md and docs/usage.md blocks too slow for the suite (or needing
# a tool set-up does not install), run as printed in a scratch directory:
# each block marked `<!-- readme-test: apart, ... -->` (scripts/readme_blocks.py
# says how blocks are marked and what is substituted). Blocks that need a
# tool not on PATH are listed as skipped; a service (docker compose up) is
# left to be run by hand. Hours: the study block trains experiments/paper.toml.
#   bash scripts/readme-apart.sh            # run them
#   bash scripts/readme-apart.sh --dry-run  # list them
#   bash scripts/readme-apart.sh --only README.md:344   # one block (readme_blocks.py list)
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --workspace --bins
exec python3 scripts/readme_blocks.py apart "$@"
