"""lcrl_env: Gymnasium and lcrl, both ways, over `lcrl.v1.Environment`.

lcrl's own environments as Gymnasium environments (they start `lcrl
serve-env` themselves; docs/environments.md):

    env = lcrl_env.make("peg-group1")          # or gymnasium.make("lcrl/peg-group1")
    envs = lcrl_env.make_vec("peg-group1", num_envs=8)

Any Gymnasium environment as a gRPC service lcrl trains on:

    python -m lcrl_env serve --env HalfCheetah-v5 --listen 127.0.0.1:50070
    python -m lcrl_env serve --entry-point my_module:MyEnv --listen 127.0.0.1:50070

Then `lcrl graph --env grpc://127.0.0.1:50070` (and `lcrl train`, `lcrl run`,
...) use it like a built-in environment. See docs/environments.md.
"""

import pathlib
import sys

# The lcrl.v1 stubs are generated from proto/lcrl.proto by scripts/setup.sh
# into clients/python/lcrl_stubs, beside this package; the generated
# lcrl_pb2_grpc imports lcrl_pb2 as a top-level module.
_STUBS = pathlib.Path(__file__).resolve().parent.parent / "lcrl_stubs"
if str(_STUBS) not in sys.path:
    sys.path.insert(0, str(_STUBS))

import lcrl_pb2  # noqa: E402
import lcrl_pb2_grpc  # noqa: E402

from .gymnasium_env import LcrlEnv, LcrlVectorEnv, make, make_vec, register  # noqa: E402

register()

__all__ = ["lcrl_pb2", "lcrl_pb2_grpc", "LcrlEnv", "LcrlVectorEnv", "make", "make_vec", "register"]
