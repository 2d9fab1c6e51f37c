#!/usr/bin/env bash
# Coverage-guided fuzzing (cargo fuzz, libFuzzer) of the decoders a peer or a
# file controls: fuzz/fuzz_targets/*.rs, seeds in fuzz/seeds/TARGET/.
#
#   bash scripts/fuzz.sh TARGET SECONDS   fuzz one target for SECONDS
#   bash scripts/fuzz.sh all SECONDS      each target in turn
#   bash scripts/fuzz.sh list             the targets
#
# SECONDS = 0 replays the seeds and fuzz/regressions/TARGET/ (every input a
# past run crashed on) once, without mutating: a regression check.
# New inputs that reach new code go to fuzz/target/corpus/TARGET (not
# committed); a crash is written to fuzz/artifacts/TARGET/ and stops the run
# with a non-zero exit: fix it, then keep the input in fuzz/regressions/TARGET/
# and as a unit test beside the code it crashed.
#
# Needs the nightly toolchain (libFuzzer's instrumentation) and cargo-fuzz,
# which this script installs from crates.io when it is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
targets=$(sed -n 's/^name = "\(.*\)"$/\1/p' fuzz/Cargo.toml | grep -v '^lcrl-fuzz$')
usage() { echo "usage: bash scripts/fuzz.sh TARGET|all|list SECONDS (targets: $(echo $targets))" >&2; exit 2; }
[[ $# -ge 1 ]] || usage
if [[ $1 == list ]]; then echo "$targets"; exit 0; fi
[[ $# -eq 2 && $2 =~ ^[0-9]+$ ]] || usage
if [[ $1 == all ]]; then chosen=$targets; elif grep -qx "$1" <<<"$targets"; then chosen=$1; else
  echo "fuzz.sh: no target '$1'" >&2; usage; fi
if ! rustup toolchain list | grep -q '^nightly'; then
  echo "fuzz.sh: cargo fuzz needs the nightly toolchain (rustup toolchain install nightly)" >&2; exit 1
fi
bash scripts/setup.sh >/dev/null
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked
# libtorch for the targets that reach the learner (tch links it dynamically).
export LD_LIBRARY_PATH="$PWD/.venv/libtorch/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export LIBTORCH="$PWD/.venv/libtorch"
for target in $chosen; do
  corpus=fuzz/target/corpus/$target
  mkdir -p "$corpus" "fuzz/regressions/$target"
  if [[ $2 -eq 0 ]]; then
    flags=(-runs=0)
  else
    flags=(-max_total_time="$2" -print_final_stats=1)
  fi
  echo "== $target (${2}s)"
  # Leak checking is off: libtorch keeps its global allocations to exit.
  cargo +nightly fuzz run "$target" "$corpus" "fuzz/seeds/$target" "fuzz/regressions/$target" -- \
    -detect_leaks=0 -rss_limit_mb=4096 "${flags[@]}" 2>&1 | tee "fuzz/target/$target.log" | grep -E '^(#[0-9]+[[:space:]]+(INITED|DONE)|Done|stat::|==[0-9]+==|SUMMARY|thread .* panicked)' || true
  status=${PIPESTATUS[0]}
  if [[ $status -ne 0 ]]; then
    echo "fuzz.sh: $target failed (exit $status); the input is under fuzz/artifacts/$target/, the log in fuzz/target/$target.log" >&2
    exit "$status"
  fi
done
