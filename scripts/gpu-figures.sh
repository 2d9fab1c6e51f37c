#!/usr/bin/env bash
# The GPU and many-core figures of docs/scaling.md (the record:
# docs/research/2026-11-26-gpu-learner-h200.md and
# docs/research/2026-11-26-cuda-graphs-h100.md), in one run on a machine
# with a GPU (run from the project root):
#
#   scripts/gpu-figures.sh BIN_DIR OUT_DIR [BASELINE_BIN_DIR] [TEST_BIN_DIR]
#
# BIN_DIR holds the lcrl binaries to measure; BASELINE_BIN_DIR, optional, an
# older build whose GPU update is timed beside them (same run, same card);
# TEST_BIN_DIR, optional, the learner's unit-test binary (`learner-tests`)
# and the end-to-end one (`e2e`), whose GPU tests run first. Writes
# OUT_DIR/figures.log and the scale tables (scale-*.csv); the scale runs'
# own folders go under WORK (default: a temporary folder). Each section is
# timed, and stopped after LIMIT seconds (default 240); a failing section is
# reported and the next one runs. ONLY, a space-separated list of section
# groups (tests gpu cpu scale cores), runs those alone (default: all). About
# 8 minutes in all on a 16-core machine with an H100-class GPU.
set -uo pipefail
bin=$1
out=$2
baseline=${3:-}
tests=${4:-}
work=${WORK:-$(mktemp -d)}
mkdir -p "$out" "$work"
exec > >(tee "$out/figures.log") 2>&1
failed=0
only=" ${ONLY:-tests gpu cpu scale cores} "
wanted() { [[ $only == *" $1 "* ]]; }
section() {
  local title=$1
  shift
  echo
  echo "=== $title ($(date +%T))"
  local started=$SECONDS
  # (A function, scale below, applies the limit itself.)
  if declare -F "$1" >/dev/null; then "$@"; else timeout "${LIMIT:-240}" "$@"; fi || { echo "!!! $title failed (exit $?)"; failed=$((failed + 1)); }
  echo "--- $title: $((SECONDS - started)) s"
}

section "machine" bash -c 'nproc; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; python3 -c "import torch; print(\"python torch\", torch.__version__)"'
section "lcrl doctor" "$bin/lcrl" doctor

if [ -n "$tests" ] && wanted tests; then
  # The unit-test binary's GPU tests, then the end-to-end GPU run.
  section "learner GPU tests" "$tests/learner-tests" --exact tests::cuda_graph_updates_equal_eager_updates tests::cuda_updates_equal_cpu_updates cuda_graph::tests::the_shim_loads_where_the_build_carries_it device::tests::cuda_resolves_exactly_when_a_device_is_there replay::mirror_tests::the_mirror_samples_what_the_buffer_samples flat::tests::variables_become_views_of_the_buffer_and_keep_their_values --test-threads 1 --nocapture
  [ -x "$tests/e2e" ] && section "e2e GPU test" "$tests/e2e" --exact e2e::doctor::a_cuda_run_reaches_the_cpu_runs_bar e2e::doctor::cuda_is_loaded_reported_and_refused_cleanly_without_a_gpu --test-threads 1 --nocapture
fi

if wanted gpu; then
  if [ -n "$baseline" ]; then
    section "DDPG/PPO update on the GPU, baseline build" "$baseline/lcrl" bench learner --device cuda --threads 1 --updates 500 --python none
  fi
  # Eager and CUDA-graph rows per actor, then PyTorch eager.
  # Table I's settings: what the baseline build times and PyTorch eager repeats.
  section "DDPG/PPO update on the GPU, this build (and PyTorch eager)" "$bin/lcrl" bench learner --device cuda --threads 1 --updates 500 --settings table1 --python "${PYTHON_EAGER:-python3}"
fi
if wanted cpu; then
  section "DDPG/PPO update on the CPU by threads (and PyTorch eager)" "$bin/lcrl" bench learner --device cpu --threads 1,4,16 --updates 200 --settings table1 --python python3
  section "DDPG/PPO update on the CPU by threads, the presets' settings" "$bin/lcrl" bench learner --device cpu --threads 1,2,4,16 --updates 200 --rounds 5
fi

scale() {
  local name=$1
  shift
  timeout "${LIMIT:-240}" "$bin/lcrl" scale "$@" --seconds 10 --warmup 4 --out "$work/$name" && cp "$work/$name/scale.csv" "$out/$name.csv"
}
if wanted scale; then
  # The preset with eager updates on the GPU (run.cuda_graphs = false),
  # beside it so its relative paths hold; removed afterwards.
  eager=configs/peg-group1-ddpg-local-eager.toml
  sed 's/^\[run\]$/[run]\ncuda_graphs = false/' configs/peg-group1-ddpg-local.toml >"$eager"
  section "lcrl scale, DDPG on the GPU, CUDA graphs" scale scale-gpu --config configs/peg-group1-ddpg-local.toml --actors 1,4,14 --device cuda
  section "lcrl scale, DDPG on the GPU, eager" scale scale-gpu-eager --config "$eager" --actors 1,4,14 --device cuda
  rm -f "$eager"
  if wanted cpu; then
    section "lcrl scale, DDPG on the CPU" scale scale-cpu --config configs/peg-group1-ddpg-local.toml --actors 1,8,14
  fi
  section "lcrl scale, DDPG on the GPU, replay ratio unlimited" scale scale-gpu-unlimited --config configs/peg-group1-ddpg-local.toml --actors 14 --device cuda --replay-ratio unlimited
fi

if wanted cores; then
  section "CS3 on every core" "$bin/lcrl" bench graph --repeats 3
  section "simulator and evaluation on every core" "$bin/lcrl" bench sim --episodes 100
  section "tune on every core" "$bin/lcrl" bench tune
fi
echo
echo "gpu-figures: $failed section(s) failed"
