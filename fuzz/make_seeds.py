"""Writes the fuzz targets' seed corpus (fuzz/seeds/TARGET/) from real
artefacts: a graph and a checkpoint that lcrl itself writes for lti-paper,
protobuf messages encoded by the project's own Python stubs, the shipped
TOML files, and a shared-memory frame laid out as learner/src/service/shm.rs
lays it. Run once after `bash scripts/setup.sh` and a build:

    .venv/bin/python fuzz/make_seeds.py

The seeds are committed; rerun only when a format changes.
"""
import pathlib
import shutil
import struct
import subprocess
import sys
import tempfile

root = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(root / "clients/python/lcrl_stubs"))
import lcrl_pb2 as pb  # noqa: E402

seeds = root / "fuzz/seeds"
lcrl = root / "target/debug/lcrl"


def put(target, name, data):
    folder = seeds / target
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_bytes(data if isinstance(data, bytes) else data.encode())


# lti-paper: 3 states, 3 actions (docs/method.md eq. 10).
M, N = 3, 3


def transition(k, sampled=True):
    t = pb.Transition(state=[0.1 * k, -0.2, 0.3], action=[0.5, -1.0, 1.0], reward=-1.0 - k,
                      next_state=[0.2, -0.1, 0.0], terminated=False, truncated=(k == 2), policy_version=3)
    if sampled:
        t.sampled_action.extend([0.25, -0.5, 0.75])
        t.log_prob = -1.5
    return t


batch = pb.TransitionBatch(run_id="run", actor_id="actor-0", sequence=7, episode_id=1, policy_version=3,
                           transitions=[transition(k) for k in range(3)],
                           episodes=[pb.EpisodeSummary(episode_return=-6.0, length=3, success=True)])
put("ingest_batch", "three-transitions-one-episode", batch.SerializeToString())
plain = pb.TransitionBatch(run_id="run", actor_id="a", sequence=1, policy_version=1,
                           transitions=[transition(0, sampled=False)])
put("ingest_batch", "applied-action-only", plain.SerializeToString())

reply = pb.StepResponse(results=[pb.StepResult(state=[0.1, 0.2, 0.3], reward=-0.5, terminated=False, truncated=False),
                                 pb.StepResult(state=[0.0, 0.0, 0.0], reward=-0.1, terminated=True)])
put("step_reply", "two-sessions", reply.SerializeToString())

# The frame's header (shm.rs TransitionSample, #[repr(C)]): actor id,
# sequence, episode id, policy version, count, state/action dims, episodes;
# then states, next states, actions, ... (the target zero-fills the rest).
header = b"actor-0".ljust(64, b"\0") + struct.pack("<QQQIIII", 7, 1, 3, 2, M, N, 1)
states = struct.pack(f"<{2 * M}f", 0.1, -0.2, 0.3, 0.2, -0.1, 0.0)
put("shm_frame", "two-transitions-header", header + states)
put("shm_frame", "empty", b"")

with tempfile.TemporaryDirectory() as tmp:
    tmp = pathlib.Path(tmp)
    subprocess.run([lcrl, "graph", "--env", "lti-paper", "--samples", "16", "--out", tmp / "graph.json"], check=True,
                   stdout=subprocess.DEVNULL)
    put("graph_json", "lti-paper-cs3", (tmp / "graph.json").read_bytes())
    subprocess.run([lcrl, "graph", "--env", "lti-paper", "--random", "4", "--out", tmp / "random.json"], check=True,
                   stdout=subprocess.DEVNULL)
    put("graph_json", "lti-paper-random4", (tmp / "random.json").read_bytes())
    for algo in ["ddpg", "ppo"]:
        run = tmp / algo
        subprocess.run([lcrl, "train", "--env", "lti-paper", "--algo", algo, "--connection", "local", "--episodes", "2",
                        "--run-dir", run], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        checkpoint = sorted((run / "checkpoints").iterdir())[-1]
        meta = (checkpoint / "checkpoint.json").read_bytes()
        # The target's split: a 2-byte little-endian length, checkpoint.json, actor.safetensors.
        put("checkpoint", f"lti-paper-{algo}-local", struct.pack("<H", len(meta)) + meta + (checkpoint / "actor.safetensors").read_bytes())

for path in sorted((root / "configs").glob("*.toml")):
    put("toml_config", path.name, path.read_bytes())
put("toml_config", "env-lti.toml", 'kind = "lti"\ne = [[0.5, 0.0], [1.0, 0.5]]\nf = [[1.0], [0.0]]\nnoise_std = 0.1\n')
put("toml_config", "env-peg.toml", 'kind = "peg"\npreset = "peg-group2"\n[contact]\nfriction = 0.6\n')
print(f"seeds written under {seeds.relative_to(root)}")
