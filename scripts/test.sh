#!/usr/bin/env bash
# The full test suite, from a fresh clone: set-up (libtorch), build, tests.
# Extra arguments go to the test runner (e.g. a test-name filter).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# The end-to-end tests start every workspace binary (lcrl-graph-builder, ...),
# and cargo builds only the tested package's own binaries: build them all.
cargo build --workspace --bins
if cargo nextest --version >/dev/null 2>&1; then
  cargo nextest run --workspace --no-fail-fast "$@"
else
  # One test at a time: tests share this process, and with it their
  # shared-memory namespace (tests/e2e/common.rs, shm_namespace).
  RUST_TEST_THREADS=1 cargo test --workspace --no-fail-fast "$@"
fi
