#!/usr/bin/env bash
# One-time, idempotent set-up for building lcrl on a fresh machine.
#
# - libtorch: PyPI's torch==2.13.0 (the version tch 0.26 is built against)
#   installed into a project-local venv (.venv). `.venv/libtorch` is a stable
#   link to the wheel's torch/ folder; .cargo/config.toml points LIBTORCH at
#   it, and the crates that link tch add an rpath to it (build.rs), so built
#   binaries find libtorch without LD_LIBRARY_PATH.
# - protoc: not needed; proto/build.rs uses the protoc shipped in the
#   protoc-bin-vendored crate.
#
# A second run with everything in place takes about a second.
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH_VERSION=2.13.0
VENV=.venv
PY=${PYTHON:-python3}

if ! command -v "$PY" >/dev/null; then
  echo "setup: python3 is needed to install libtorch (PyPI torch==$TORCH_VERSION); install it and retry" >&2
  exit 1
fi
if ! command -v cargo >/dev/null; then
  echo "setup: cargo is needed (install Rust with rustup) " >&2
  exit 1
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV"
  "$PY" -m venv "$VENV"
fi

have=$("$VENV/bin/python" -c 'import importlib.metadata as m; print(m.version("torch"))' 2>/dev/null || true)
if [ "$have" != "$TORCH_VERSION" ]; then
  echo "setup: installing torch==$TORCH_VERSION into $VENV (about 5 GB, a minute or two)"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "torch==$TORCH_VERSION"
fi

# find_spec locates the package without importing it (fast, no warnings).
torch_dir=$("$VENV/bin/python" -c 'import importlib.util as u; print(u.find_spec("torch").submodule_search_locations[0])')
if [ "$(readlink "$VENV/libtorch" 2>/dev/null || true)" != "$torch_dir" ]; then
  ln -sfn "$torch_dir" "$VENV/libtorch"
fi
if [ ! -f "$VENV/libtorch/lib/libtorch_cpu.so" ]; then
  echo "setup: $VENV/libtorch/lib/libtorch_cpu.so is missing; remove $VENV and rerun" >&2
  exit 1
fi
echo "setup: libtorch $TORCH_VERSION at $VENV/libtorch"

# The Python gRPC client (clients/python): grpcio, and stubs generated from
# the contract itself, so they can never drift from proto/lcrl.proto.
# grpcio-reflection: clients that know no stubs (clients/python/reflect_act.py).
if ! "$VENV/bin/python" -c 'import grpc, grpc_tools, grpc_health, grpc_reflection' 2>/dev/null; then
  echo "setup: installing grpcio, grpcio-tools, grpcio-health-checking, grpcio-reflection into $VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check grpcio grpcio-tools grpcio-health-checking grpcio-reflection
fi
# `lcrl export --format onnx` (docs/export.md): PyTorch's ONNX exporter
# (clients/python/lcrl_export_onnx.py) needs onnx; the export's check, the
# test that compares the exported files with the served policy, and
# controllers without libtorch run the file with ONNX Runtime.
ONNX_VERSION=1.23.2
ONNXRUNTIME_VERSION=1.32.0
if ! "$VENV/bin/python" -c "import importlib.metadata as m, sys; sys.exit(m.version('onnx') != '$ONNX_VERSION' or m.version('onnxruntime') != '$ONNXRUNTIME_VERSION')" 2>/dev/null; then
  echo "setup: installing onnx==$ONNX_VERSION and onnxruntime==$ONNXRUNTIME_VERSION into $VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "onnx==$ONNX_VERSION" "onnxruntime==$ONNXRUNTIME_VERSION"
fi
# Bring-your-own environments (clients/python/lcrl_env, docs/environments.md):
# Gymnasium with MuJoCo (HalfCheetah-v5, the example), and lcrl_env itself,
# editable so it runs from clients/python beside the generated stubs.
GYMNASIUM_VERSION=1.4.0
MUJOCO_VERSION=4.0.0
if ! "$VENV/bin/python" -c "import importlib.metadata as m, sys; sys.exit(m.version('gymnasium') != '$GYMNASIUM_VERSION' or m.version('mujoco') != '$MUJOCO_VERSION')" 2>/dev/null; then
  echo "setup: installing gymnasium[mujoco]==$GYMNASIUM_VERSION (mujoco==$MUJOCO_VERSION) into $VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "gymnasium[mujoco]==$GYMNASIUM_VERSION" "mujoco==$MUJOCO_VERSION"
fi
if ! "$VENV/bin/python" -c 'import importlib.metadata as m; m.version("lcrl-env")' 2>/dev/null; then
  echo "setup: installing lcrl_env (clients/python) into $VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-build-isolation --no-deps -e clients/python
fi
# Stable-Baselines3: the peer learners of docs/peers.md, and the test that
# trains SB3's SAC on the peg task through lcrl_env's Gymnasium face.
SB3_VERSION=2.9.2
if ! "$VENV/bin/python" -c "import importlib.metadata as m, sys; sys.exit(m.version('stable-baselines3') != '$SB3_VERSION')" 2>/dev/null; then
  echo "setup: installing stable-baselines3==$SB3_VERSION into $VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "stable-baselines3==$SB3_VERSION"
fi
stubs=clients/python/lcrl_stubs
if [ ! -f "$stubs/lcrl_pb2.py" ] || [ proto/lcrl.proto -nt "$stubs/lcrl_pb2.py" ]; then
  mkdir -p "$stubs"
  "$VENV/bin/python" -m grpc_tools.protoc -I proto --python_out="$stubs" --grpc_python_out="$stubs" proto/lcrl.proto
  echo "setup: generated Python stubs in $stubs"
fi
