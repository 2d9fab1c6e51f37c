"""What the chaos runs share (scripts/chaos.py, scripts/chaos_hostile.py):
the processes of a run, gRPC stubs, waiting, memory and /metrics readings."""

import pathlib
import resource
import socket
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "clients/python/lcrl_stubs"))
import grpc  # noqa: E402
import lcrl_pb2  # noqa: E402
import lcrl_pb2_grpc  # noqa: E402

SMALL = """[network]
global_hidden = [32, 32]
subnet_hidden = [16, 16]
critic_hidden = [32, 32]
[ddpg]
warmup_steps = 100
batch_size = 32
[run]
graph_samples = 16
"""


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    """Processes of one chaos run, all killed at the end."""

    def __init__(self, bins, work):
        self.bins, self.work, self.procs = bins, pathlib.Path(work), []
        (self.work / "small.toml").write_text(SMALL)

    def learner(self, run_dir, port, *extra, run_id="chaos", config=None, listen_host="127.0.0.1"):
        config = config or self.work / "small.toml"
        cmd = [str(self.bins / "lcrl-learner"), "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--config", str(config),
               "--run-dir", str(run_dir), "--listen", f"{listen_host}:{port}", "--run-id", run_id, "--publish-every", "20", *extra]
        # Beyond loopback a learner without a token must be told it may
        # serve so (issue 82); these scenarios attack it on purpose.
        if listen_host not in ("127.0.0.1", "[::1]") and "--token-file" not in extra:
            cmd.append("--insecure")
        log = open(self.work / f"learner-{len(self.procs)}.log", "w")
        # The usual soft limit of open files (a shell's `ulimit -n`), as a
        # learner started by hand or by systemd has it.
        limit = lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (1024, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))  # noqa: E731
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True, preexec_fn=limit)
        line = p.stdout.readline()
        if not line.startswith("listening on"):
            raise RuntimeError(f"the learner said {line!r}; see {log.name}")
        self.procs.append(p)
        return p

    def actor(self, port, *extra, run_id="chaos", stderr=None, learner=None):
        cmd = [str(self.bins / "lcrl-actor"), "--learner", learner or f"http://127.0.0.1:{port}", "--run-id", run_id, "--envs", "2", "--batch", "25",
               "--connect-deadline", "60", *extra]
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=stderr or subprocess.DEVNULL, text=True)
        self.procs.append(p)
        return p

    def close(self):
        for p in self.procs:
            if p.poll() is None:
                p.kill()
                p.wait()


def stub(port):
    return lcrl_pb2_grpc.LearnerStub(grpc.insecure_channel(f"127.0.0.1:{port}"))


def status(port, timeout=5):
    return stub(port).GetStatus(lcrl_pb2.GetStatusRequest(), timeout=timeout)


def wait(what, ready, limit=60, every=0.05):
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        try:
            value = ready()
            if value:
                return value
        except (grpc.RpcError, OSError):
            pass
        time.sleep(every)
    raise RuntimeError(f"timed out waiting for {what}")


def vm(pid, field):
    """VmRSS or VmHWM of a process, MiB."""
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def scrape(port, path="/metrics"):
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".encode())
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.decode().partition("\r\n\r\n")
    return int(head.split()[1]), body


def sample(text, series):
    for line in text.splitlines():
        if line.startswith(series + " "):
            return float(line.split()[1])
    return None
