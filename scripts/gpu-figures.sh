#!/usr/bin/env bash
# The GPU and many-core figures of docs/scaling.md, in one run on a machine
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
# timed; a failing section is reported and the next one runs. About 6
# minutes on a 16-core machine with an H100-class GPU.
set -uo pipefail
bin=$1
out=$2
baseline=${3:-}
tests=${4:-}
work=${WORK:-$(mktemp -d)}
mkdir -p "$out" "$work"
exec > >(tee "$out/figures.log") 2>&1
failed=0
section() {
  local title=$1
  shift
  echo
  echo "=== $title ($(date +%T))"
  local started=$SECONDS
  "$@" || { echo "!!! $title failed (exit $?)"; failed=$((failed + 1)); }
  echo "--- $title: $((SECONDS - started)) s"
}

section "machine" bash -c 'nproc; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; python3 -c "import torch; print(\"python torch\", torch.__version__)"'
section "lcrl doctor" "$bin/lcrl" doctor

if [ -n "$tests" ]; then
  # The unit-test binary's GPU tests, then the end-to-end GPU run.
  section "learner GPU tests" "$tests/learner-tests" --exact tests::cuda_updates_equal_cpu_updates device::tests::cuda_resolves_exactly_when_a_device_is_there replay::mirror_tests::the_mirror_samples_what_the_buffer_samples flat::tests::variables_become_views_of_the_buffer_and_keep_their_values --nocapture
  section "e2e GPU test" "$tests/e2e" --exact e2e::doctor::a_cuda_run_reaches_the_cpu_runs_bar e2e::doctor::cuda_is_loaded_reported_and_refused_cleanly_without_a_gpu --test-threads 1 --nocapture
fi

if [ -n "$baseline" ]; then
  section "DDPG/PPO update on the GPU, baseline build" "$baseline/lcrl" bench learner --device cuda --threads 1 --updates 500 --python none
fi
section "DDPG/PPO update on the GPU, this build (and PyTorch eager)" "$bin/lcrl" bench learner --device cuda --threads 1 --updates 500 --python python3
section "DDPG/PPO update on the CPU by threads (and PyTorch eager)" "$bin/lcrl" bench learner --device cpu --threads 1,4,16 --updates 200 --python python3

scale() {
  local name=$1
  shift
  "$bin/lcrl" scale "$@" --seconds 10 --warmup 4 --out "$work/$name" && cp "$work/$name/scale.csv" "$out/$name.csv"
}
section "lcrl scale, DDPG on the GPU" scale scale-gpu --config configs/peg-group1-ddpg-local.toml --actors 1,4,8,14 --device cuda
section "lcrl scale, DDPG on the CPU" scale scale-cpu --config configs/peg-group1-ddpg-local.toml --actors 1,8,14
section "lcrl scale, DDPG on the GPU, replay ratio unlimited" scale scale-gpu-unlimited --config configs/peg-group1-ddpg-local.toml --actors 14 --device cuda --replay-ratio unlimited

section "CS3 on every core" "$bin/lcrl" bench graph --repeats 3
section "simulator and evaluation on every core" "$bin/lcrl" bench sim --episodes 100
section "tune on every core" "$bin/lcrl" bench tune
echo
echo "gpu-figures: $failed section(s) failed"
