"""Chaos faults of issue 82 that are processes and files rather than
hostile peers: an actor of `lcrl run` killed, a checkpoint whose recorded
environment names a server, and run token files that are not owner-only
or are links. Run through scripts/chaos.sh (`--only run-actor-kill`, ...);
rows in docs/reliability.md ("This round's faults").
"""

import json
import os
import pathlib
import socket
import stat
import subprocess
import threading
import time

from chaoslib import free_port, status, wait
import lcrl_pb2

from chaos_hostile import _send, _step

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _children(pid):
    """(pid, command name, state) of the direct children of `pid`."""
    found = []
    for proc in pathlib.Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            fields = (proc / "stat").read_text().rsplit(")", 1)
            name = fields[0].split("(", 1)[1]
            state, ppid = fields[1].split()[0], int(fields[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid:
            found.append((int(proc.name), name, state))
    return found


def run_actor_kill(c):
    """kill -9 of `lcrl run`'s only actor, mid-run."""
    run = c.work / "run"
    p = subprocess.Popen([str(c.bins / "lcrl"), "run", "--config", str(ROOT / "configs/lti-paper.toml"), "--episodes", "300", "--run-dir", str(run)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    c.procs.append(p)
    said = []
    threading.Thread(target=lambda: said.extend(p.stderr), daemon=True).start()
    actor = wait("the run's actor", lambda: [k for k in _children(p.pid) if k[1].startswith("lcrl-actor")], limit=120)[0]
    wait("the run's first episodes", lambda: (run / "learner/metrics.csv").exists() and len((run / "learner/metrics.csv").read_text().splitlines()) > 5, limit=120)
    os.kill(actor[0], 9)
    t0 = time.monotonic()
    replaced = wait("a new actor", lambda: [k for k in _children(p.pid) if k[1].startswith("lcrl-actor") and k[0] != actor[0] and k[2] != "Z"], limit=120)
    restarted = time.monotonic() - t0
    zombies = [k for k in _children(p.pid) if k[2] == "Z"]
    code = p.wait(timeout=600)
    summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").exists() else {}
    noticed = next((line.strip() for line in said if "died" in line), "nothing said")
    return {"fault": "kill -9 of `lcrl run`'s only actor (lti-paper, 300 episodes)",
            "did": f"said \"{noticed[:140]}\"; a new actor (pid {replaced[0][0]}) {restarted:.1f} s after the kill; zombies then: {len(zombies)}; "
                   f"the run exited {code} with summary.json ({summary.get('episodes', '?')} episodes, actor_restarts {summary.get('actor_restarts', '?')})",
            "lost": "the dead actor's unsent steps", "restart_s": restarted, "exit": code}


def _listener():
    """A TCP port that records whether anything connected and what it sent."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    heard = []

    def serve():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            conn.settimeout(2)
            try:
                heard.append(conn.recv(65536))
            except OSError:
                heard.append(b"")
            conn.close()
    threading.Thread(target=serve, daemon=True).start()
    return server, heard


def checkpoint_address(c):
    """A checkpoint whose recorded environment is a server (grpc://) or a
    secret local file: `lcrl sim --checkpoint` and `lcrl export` with a
    token file in the environment."""
    run = c.work / "trained"
    subprocess.run([str(c.bins / "lcrl"), "train", "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--episodes", "3", "--run-dir", str(run)],
                   capture_output=True, check=True, cwd=ROOT)
    checkpoint = sorted((run / "checkpoints").iterdir())[-1] / "checkpoint.json"
    original = checkpoint.read_text()
    token = c.work / "token"
    token.write_text("s3cret-token-of-the-user-0123456789abcdef\n")
    token.chmod(0o600)
    secret = c.work / "secret.toml"
    secret.write_text("password = hunter2-not-a-config\n")
    server, heard = _listener()
    outcomes = []
    for target in (f"grpc://127.0.0.1:{server.getsockname()[1]}", str(secret)):
        checkpoint.write_text(original.replace('"env": "lti-paper"', json.dumps({"env": target})[1:-1]))
        for cmd in (["sim", "--checkpoint", str(run), "--episodes", "2"], ["export", str(run), "--out", str(c.work / "policy.pt")]):
            out = subprocess.run([str(c.bins / "lcrl"), *cmd], capture_output=True, text=True, cwd=ROOT, env={**os.environ, "LCRL_TOKEN_FILE": str(token)})
            outcomes.append((cmd[0], "server" if target.startswith("grpc") else "file", out.returncode, "hunter2" in out.stderr + out.stdout))
    time.sleep(0.5)
    server.close()
    captured = sum(b"s3cret" in h for h in heard)
    refused = all(code != 0 for _, _, code, _ in outcomes)
    echoed = sum(e for *_, e in outcomes)
    return {"fault": "checkpoint.json's env set to a listening grpc:// address, then to a local file; `lcrl sim --checkpoint` and `lcrl export` with LCRL_TOKEN_FILE set",
            "did": f"{len(outcomes)} commands, {'all refused (non-zero exit)' if refused else 'NOT all refused'}; connections to the address: {len(heard)}, tokens captured: {captured}; "
                   f"the file's content echoed: {echoed} times",
            "lost": "nothing" if captured == 0 and echoed == 0 else "the token or the file's content", "connections": len(heard), "captured": captured}


def token_files(c):
    """RUN/token already there with mode 0644, or a symbolic link to a
    world-writable file elsewhere: `lcrl run` against each."""
    rows = []
    for kind in ("0644 file", "symlink"):
        run = c.work / kind.replace(" ", "-")
        run.mkdir()
        token = run / "token"
        outside = c.work / f"outside-{kind.replace(' ', '-')}"
        if kind == "symlink":
            outside.write_text("")
            outside.chmod(0o666)
            token.symlink_to(outside)
        else:
            token.write_text("old-token-0123456789abcdef0123456789\n")
            token.chmod(0o644)
        out = subprocess.run([str(c.bins / "lcrl"), "run", "--config", str(ROOT / "configs/lti-paper.toml"), "--episodes", "5", "--run-dir", str(run)],
                             capture_output=True, text=True, cwd=ROOT, timeout=300)
        last = (out.stderr.strip().splitlines() or ["(nothing)"])[-1]
        mode = stat.S_IMODE(os.lstat(token).st_mode) if not token.is_symlink() else None
        written = outside.read_text() if outside.exists() else ""
        rows.append(f"{kind}: exit {out.returncode}, said \"{last[:160]}\"" + (f", mode now {mode:o}" if mode is not None else f", {len(written)} bytes written outside"))
    return {"fault": "RUN/token already there as a 0644 file, or as a symlink to a 0666 file outside the run, then `lcrl run`",
            "did": "; ".join(rows), "lost": "nothing"}


def pre_claim(c):
    """An actor's id pre-claimed while it restarts: one batch under its id
    with a sequence 59 minutes ahead of the clock (µs, as actors number
    them), then the honest actor back under the same id."""
    port = free_port()
    c.learner(c.work / "claim", port)
    honest = c.actor(port, "--actor-id", "honest", "--transport", "grpc")
    wait("steps", lambda: status(port).env_steps > 500)
    honest.kill()
    honest.wait()
    ahead = int(time.time() * 1e6) + 59 * 60 * 1_000_000
    code = _send(port, [lcrl_pb2.TransitionBatch(run_id="chaos", actor_id="honest", sequence=ahead, transitions=[_step([0.1, 0.1, 0.1])])])
    stderr = open(c.work / "honest-again.log", "w")
    c.actor(port, "--actor-id", "honest", "--transport", "grpc", stderr=stderr)
    before = status(port).env_steps
    time.sleep(5)
    after = status(port)
    stored = after.env_steps - before
    return {"fault": "one batch under a restarting actor's id, sequence 59 min ahead of the clock, then the actor back under that id (gRPC)",
            "did": f"the claim: {code}; the honest actor's transitions stored in its first 5 s back: {stored}; refused as {dict(after.rejected)}",
            "lost": "nothing" if stored > 0 else "every batch of the honest actor", "stored_after": stored}


FAULTS = {"pre-claim": pre_claim, "run-actor-kill": run_actor_kill, "checkpoint-address": checkpoint_address, "token-files": token_files}


def _server(c, name, cmd):
    """A server process of this run, its address read from its first line."""
    log = open(c.work / f"{name}.log", "w")
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True, cwd=ROOT)
    c.procs.append(p)
    line = p.stdout.readline()
    if not line.startswith("listening on"):
        raise RuntimeError(f"{name} said {line!r}")
    return p, int(line.strip().rsplit(":", 1)[1])


def unbudgeted_servers(c):
    """16 connections × 32 streams, each 900 KB into a declared 1 MB
    message and never finished, from loopback, against the graph builder
    (its Graph service), `lcrl serve-env` (Environment) and the learner's
    reflection; RSS before, while held and 3 s after they closed."""
    from chaos_findings import _slow_sender
    from chaoslib import vm
    targets = [
        ("graph builder", [str(c.bins / "lcrl-graph-builder"), "--env", "lti-paper", "--samples", "8", "--listen", "127.0.0.1:0"], "/lcrl.v1.Graph/GetGraph"),
        ("serve-env", [str(c.bins / "lcrl"), "serve-env", "--env", "lti-paper", "--listen", "127.0.0.1:0"], "/lcrl.v1.Environment/Step"),
        ("learner reflection", [str(c.bins / "lcrl-learner"), "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--config", str(c.work / "small.toml"),
                                "--run-dir", str(c.work / "refl"), "--listen", "127.0.0.1:0", "--run-id", "refl"], "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo"),
    ]
    said, figures = [], {}
    for name, cmd, path in targets:
        p, port = _server(c, name.replace(" ", "-"), cmd)
        time.sleep(2)
        start = vm(p.pid, "VmRSS")
        socks, refused = [], 0
        for _ in range(16):
            sock, r = _slow_sender("127.0.0.1", port, path=path)
            socks.append(sock)
            refused += r
        time.sleep(2)
        held = vm(p.pid, "VmRSS")
        for sock in socks:
            sock.close()
        time.sleep(3)
        after = vm(p.pid, "VmRSS")
        p.kill()
        p.wait()
        said.append(f"{name}: RSS {start:.0f} → {held:.0f} MiB held → {after:.0f} MiB 3 s after they closed, {refused} of 512 streams refused")
        figures[name] = {"start": start, "held": held, "after": after, "refused": refused}
    return {"fault": "16 connections × 32 streams from loopback, each 900 KB into a declared 1 MB message and never finished, against the graph builder, serve-env and the learner's reflection",
            "did": "; ".join(said), "lost": "nothing", "figures": figures}


FAULTS["unbudgeted-servers"] = unbudgeted_servers


WILD_ENV = '''
import gymnasium as gym
import numpy as np


class Wild(gym.Env):
    """A linear system gone wrong: every third step a state of 1e300."""
    lcrl_state_names = ["s1", "s2", "s3"]
    lcrl_action_names = ["a1", "a2", "a3"]

    def __init__(self):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float64)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.s, self.t = self.np_random.uniform(-1.0, 1.0, 3), 0
        return self.s.copy(), {}

    def step(self, action):
        self.s = 0.9 * self.s + np.asarray(action, dtype=np.float64)
        self.t += 1
        s = np.full(3, 1e300) if self.t % 3 == 0 else self.s.copy()
        return s, -float(self.s @ self.s), False, self.t >= 50, {}
'''


def wild_served_env(c):
    """`lcrl train` against a served environment that returns states of
    1e300 every third step (`python -m lcrl_env serve`)."""
    (c.work / "chaos_wild_env.py").write_text(WILD_ENV)
    python = ROOT / ".venv/bin/python"
    server = subprocess.Popen([str(python), "-m", "lcrl_env", "serve", "--listen", "127.0.0.1:0", "--entry-point", "chaos_wild_env:Wild"],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=c.work, env={**os.environ, "PYTHONPATH": str(c.work)})
    c.procs.append(server)
    line = server.stdout.readline()
    if not line.startswith("listening on"):
        raise RuntimeError(f"the environment server said {line!r}")
    url = "grpc://" + line.strip().split("listening on ", 1)[1]
    run = c.work / "run"
    out = subprocess.run([str(c.bins / "lcrl"), "train", "--algo", "ddpg", "--connection", "global", "--episodes", "6", "--eval-episodes", "3", "--env", url, "--run-dir", str(run)],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)
    summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").exists() else {}
    last = (out.stderr.strip().splitlines() or ["(nothing)"])[-1]
    did = (f"exit {out.returncode}; summary.json written: diverged_env {summary.get('diverged_env')}, eval_return {summary.get('eval_return')}"
           if summary else f"exit {out.returncode}, no summary.json; said \"{last[:160]}\"")
    return {"fault": "`lcrl train` (DDPG, 6 episodes, 3 evaluation episodes) against a served environment returning states of 1e300 every third step",
            "did": did, "lost": "nothing" if summary else "the run's record", "exit": out.returncode}


FAULTS["wild-served-env"] = wild_served_env


def shm_without_token(c):
    """A process of the same user, without the token, feeding a
    token-protected learner over shared memory."""
    port = free_port()
    token = c.work / "token"
    token.write_text("chaos-shm-token-0123456789abcdef0123456789\n")
    token.chmod(0o600)
    c.learner(c.work / "guarded", port, "--token-file", str(token))
    env = {k: v for k, v in os.environ.items() if k != "LCRL_TOKEN_FILE"}
    intruder = subprocess.Popen([str(c.bins / "lcrl-actor"), "--learner", f"http://127.0.0.1:{port}", "--run-id", "chaos", "--transport", "shm", "--envs", "2",
                                 "--batch", "25", "--connect-deadline", "6"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        _, err = intruder.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        intruder.kill()
        _, err = intruder.communicate()
    said = next((line for line in err.splitlines() if "error" in line), "")
    import grpc
    import lcrl_pb2
    import lcrl_pb2_grpc
    channel = grpc.insecure_channel(f"127.0.0.1:{port}")
    stored = lcrl_pb2_grpc.LearnerStub(channel).GetStatus(lcrl_pb2.GetStatusRequest(), metadata=[("authorization", "Bearer " + token.read_text().strip())], timeout=5).env_steps
    return {"fault": "a same-user process without the token runs an actor over shared memory against a token-protected learner for its 6 s deadline",
            "did": f"the learner stored {stored} of its steps in 10 s; the actor exited {intruder.returncode}" + (f": \"{said.strip()[:200]}\"" if said else " (killed after 10 s)"),
            "lost": "nothing" if stored == 0 else "the record: steps of a peer without the token", "stored": stored}


FAULTS["shm-without-token"] = shm_without_token


def threads_busy(c):
    """The learner's thread count beside two busy processes: `lcrl bench
    busy` (one round of 8 s each way)."""
    out = subprocess.run([str(c.bins / "lcrl"), "bench", "busy", "--rounds", "1"], capture_output=True, text=True, cwd=ROOT, timeout=600)
    line = next((l for l in out.stdout.splitlines() if l.startswith("--threads 1 keeps")), f"no figure (exit {out.returncode})")
    return {"fault": "`--threads 1` against `OMP_NUM_THREADS=1` exported, peg-group1 DDPG with one actor, beside two processes busy at nice 10 (`lcrl bench busy --rounds 1`)",
            "did": line, "lost": "nothing"}


def smaller_faults(c):
    """Issue 82's smaller faults that are one command each: the largest
    u64 seed, and a finished learner's checkpoint left alone."""
    seed = subprocess.run([str(c.bins / "lcrl"), "train", "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--episodes", "1",
                           "--seed", "18446744073709551615", "--run-dir", str(c.work / "seed")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    said = (seed.stderr.strip().splitlines() or ["(nothing)"])[-1]
    port = free_port()
    run = c.work / "budget"
    c.learner(run, port, "--episodes", "10", "--checkpoint-secs", "0.5")
    c.actor(port, "--actor-id", "honest")
    wait("the budget", lambda: status(port).episodes >= 10, limit=120)
    time.sleep(1.0)
    stamp = lambda: sorted((p.name, p.stat().st_mtime_ns) for p in (run / "checkpoints").rglob("*") if p.is_file())  # noqa: E731
    before = stamp()
    time.sleep(3.0)
    rewritten = stamp() != before
    return {"fault": "`lcrl train --seed 18446744073709551615`; a learner past its 10-episode budget with --checkpoint-secs 0.5, watched for 3 s",
            "did": f"the seed: exit {seed.returncode}, \"{said[:150]}\"; the finished checkpoint {'REWRITTEN' if rewritten else 'left alone'} over 3 s",
            "lost": "nothing", "checkpoint_rewritten": rewritten}


FAULTS["threads-busy"] = threads_busy
FAULTS["smaller-faults"] = smaller_faults
