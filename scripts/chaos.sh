#!/usr/bin/env bash
# Chaos runs (docs/reliability.md): short real runs with one fault each,
# and the table of what the service did and what was lost. A benchmark,
# not a test. Arguments go to scripts/chaos.py (--only FAULT, --bin-dir).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --workspace --bins
# The slow-senders fault speaks HTTP/2 itself, flow control included.
.venv/bin/python -c 'import h2' 2>/dev/null || .venv/bin/python -m pip install --quiet --disable-pip-version-check h2
exec .venv/bin/python scripts/chaos.py "$@"
