#!/usr/bin/env bash
# Chaos runs (docs/reliability.md): short real runs with one fault each,
# and the table of what the service did and what was lost. A benchmark,
# not a test. Arguments go to scripts/chaos.py (--only FAULT, --bin-dir).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --workspace --bins
exec .venv/bin/python scripts/chaos.py "$@"
