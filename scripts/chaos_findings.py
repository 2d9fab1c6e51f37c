"""The chaos faults for issue 71's smaller findings and the parts of its
first finding the older rows left out: a learner with nothing to do, numbers
on the command line beyond their range, a learner that answers no policy yet,
and huge-but-finite values of every kind with the checkpoints on disk
scanned afterwards; and issue 82's peers that made one call and then only
ping. Run through scripts/chaos.sh (`--only idle-cpu`, ...);
rows in docs/reliability.md.
"""

import json
import math
import os
import pathlib
import socket
import struct
import subprocess
import sys
import time
from concurrent import futures

import grpc
import numpy as np

from chaoslib import free_port, status, vm, wait
import lcrl_pb2
import lcrl_pb2_grpc

from chaos_hostile import _finite_action, _health_seconds, _health_words, _send, _step, _stored_of, _training


def _cpu_seconds(pid):
    """User plus system CPU seconds of a process, all its threads."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def idle_cpu(c, seconds=10.0):
    """A learner with no actor: the share of one core it takes."""
    port = free_port()
    learner = c.learner(c.work / "idle", port)
    time.sleep(3)  # past start-up (graph, networks, first checkpoint)
    t0, cpu0 = time.monotonic(), _cpu_seconds(learner.pid)
    time.sleep(seconds)
    share = (_cpu_seconds(learner.pid) - cpu0) / (time.monotonic() - t0)
    return {"fault": f"a learner with no actor for {seconds:.0f} s", "did": f"{100 * share:.1f}% of one core",
            "lost": "-", "core_share": share}


def out_of_range_options(c):
    """Numbers beyond their range on the learner's command line."""
    rows = {}
    for flag, value in [("--publish-every", "18446744073709551615"), ("--replay-ratio", "1e300"), ("--replay-slack", "1e300"),
                        ("--serving-share", "0"), ("--max-connections-per-peer", "0")]:
        cmd = [str(c.bins / "lcrl-learner"), "--env", "lti-paper", "--algo", "ddpg", "--run-dir", str(c.work / "bounds"),
               "--listen", f"127.0.0.1:{free_port()}", flag, value]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=20)
        except subprocess.TimeoutExpired:  # accepted: the learner started and ran
            rows[f"{flag} {value}"] = {"exit": None, "panicked": False, "said": "accepted (still running after 20 s)"}
            continue
        said = next((line for line in done.stderr.splitlines() if line.startswith("error")), done.stderr.strip()[:160])
        rows[f"{flag} {value}"] = {"exit": done.returncode, "panicked": "panicked" in done.stderr, "said": said[:160]}
    refused = sum(1 for r in rows.values() if r["exit"] != 0 and not r["panicked"])
    return {"fault": "numbers beyond their range: " + ", ".join(rows),
            "did": f"{refused} of {len(rows)} refused at start without a panic; e.g. {next(iter(rows.values()))['said']!r}",
            "lost": "-", "options": rows}


class _NoPolicyYet(grpc.GenericRpcHandler):
    """A learner still loading: every call answered UNAVAILABLE."""

    def __init__(self):
        self.calls = 0

    def service(self, details):
        def unavailable(request, context):
            self.calls += 1
            context.abort(grpc.StatusCode.UNAVAILABLE, "loading its checkpoint")
        return grpc.unary_unary_rpc_method_handler(unavailable, request_deserializer=lambda b: b, response_serializer=lambda b: b)


def first_policy_retry(c, unavailable_s=5.0):
    """The actor's first GetPolicy answered UNAVAILABLE for a few seconds
    (a learner still loading its checkpoint), then the real learner takes
    the port."""
    port = free_port()
    handler = _NoPolicyYet()
    stand_in = grpc.server(futures.ThreadPoolExecutor(max_workers=2), handlers=[handler])
    stand_in.add_insecure_port(f"127.0.0.1:{port}")
    stand_in.start()
    actor = c.actor(port, "--actor-id", "early")  # --connect-deadline 60
    time.sleep(unavailable_s)
    stand_in.stop(grace=None).wait()
    refusals = handler.calls
    exited_early = actor.poll() is not None
    started = time.monotonic()
    c.learner(c.work / "late", port)
    try:
        wait("the actor's transitions", lambda: status(port).env_steps > 0, limit=60)
        joined = f"its transitions stored {time.monotonic() - started:.1f} s after the learner started"
    except RuntimeError:
        joined = "none of its transitions stored within 60 s"
    return {"fault": f"the actor's GetPolicy answered UNAVAILABLE for {unavailable_s:.0f} s, then the learner starts on that port",
            "did": f"{refusals} refused calls; the actor " + ("had exited" if exited_early else "kept asking") + f"; {joined}",
            "lost": "nothing" if not exited_early and "none" not in joined else "the actor", "refusals": refusals, "exited": exited_early}


def _non_finite_in_safetensors(path):
    """(tensors, non-finite numbers) of a safetensors file's float tensors."""
    data = path.read_bytes()
    (size,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + size])
    body = data[8 + size:]
    kinds = {"F32": np.float32, "F64": np.float64, "F16": np.float16}
    tensors = bad = 0
    for name, info in header.items():
        if name == "__metadata__" or info["dtype"] not in kinds:
            continue
        start, end = info["data_offsets"]
        values = np.frombuffer(body[start:end], dtype=kinds[info["dtype"]])
        tensors += 1
        bad += int(np.count_nonzero(~np.isfinite(values)))
    return tensors, bad


def huge_values_everywhere(c):
    """Huge but finite numbers of every kind beside an honest actor (states
    of 3e38 and 1e12, sampled and applied actions of 1e12, a reward of 3e38,
    a return of 1e308), then every
    checkpoint on disk scanned for a non-finite number."""
    port = free_port()
    run = c.work / "huge-all"
    c.learner(run, port, "--checkpoint-secs", "1")
    c.actor(port, "--actor-id", "honest")
    wait("updates", lambda: status(port).updates > 50)
    attacks = {
        "states 3e38": [_step([3e38, 3e38, 3e38])] * 25,
        "states 1e12": [_step([1e12, -1e12, 1e12])] * 25,
        "sampled actions 1e12": [lcrl_pb2.Transition(state=[0.1, 0.1, 0.1], action=[1.0, 1.0, 1.0], sampled_action=[1e12, 1e12, 1e12], reward=-1.0,
                                                     next_state=[0.1, 0.1, 0.1])] * 25,
        # An applied action is the environment's, clipped into its box as
        # the environment clips it: stored, at the box's edge.
        "applied actions 1e12 (clipped)": [lcrl_pb2.Transition(state=[0.1, 0.1, 0.1], action=[1e12, 1e12, 1e12], reward=-1.0, next_state=[0.1, 0.1, 0.1])] * 25,
        "reward 3e38": [_step([0.1, 0.1, 0.1], reward=3e38)] * 25,
    }
    codes = {}
    for k, (what, transitions) in enumerate(attacks.items()):
        codes[what] = _send(port, [lcrl_pb2.TransitionBatch(run_id="chaos", actor_id=f"evil-{k}", sequence=1, transitions=transitions)])
    codes["return 1e308"] = _send(port, [lcrl_pb2.TransitionBatch(run_id="chaos", actor_id="evil-return", sequence=1,
                                                                   transitions=[_step([0.1, 0.1, 0.1], end=True)],
                                                                   episodes=[lcrl_pb2.EpisodeSummary(episode_return=1e308, length=1)])])
    later = _training(port, 5.0)
    finite = _finite_action(port)
    time.sleep(2)  # at least one checkpoint after the attacks
    scanned = tensors = bad = 0
    for path in sorted(run.rglob("*.safetensors")):
        try:
            n, b = _non_finite_in_safetensors(path)
        except (OSError, ValueError, struct.error):  # pruned or being written (a checkpoint a second)
            continue
        scanned, tensors, bad = scanned + 1, tensors + n, bad + b
    st = status(port)
    return {"fault": "batches of states 3e38 and 1e12, sampled and applied actions 1e12, rewards 3e38 and an episode return of 1e308 beside an honest actor",
            "did": f"batches {codes}; refused as {dict(st.rejected)}; {later} updates in the next 5 s; Policy.Act finite: {finite}; "
                   f"{scanned} safetensors files on disk ({tensors} tensors): {bad} non-finite numbers",
            "lost": "nothing" if finite and bad == 0 else "finite weights", "codes": codes, "non_finite_on_disk": bad, "files": scanned,
            "updates_after": later, "recent_return": st.recent_return if math.isfinite(st.recent_return) else str(st.recent_return)}


FAULTS = {"idle-cpu": idle_cpu, "out-of-range-options": out_of_range_options, "first-policy-retry": first_policy_retry,
          "huge-values-everywhere": huge_values_everywhere}


def _slow_sender(host, port, streams=32, claim=1_000_000, send=900_000, path="/lcrl.v1.Learner/StreamTransitions"):
    """One HTTP/2 connection (flow control kept, by the `h2` package) that
    opens `streams` streams of `path` and sends each a message
    prefix claiming `claim` bytes, then `send` of them, and never the rest.
    Returns (socket, streams refused with RESOURCE_EXHAUSTED)."""
    import h2.config
    import h2.connection
    import h2.events
    s = socket.create_connection((host, port), timeout=10)
    conn = h2.connection.H2Connection(h2.config.H2Configuration(client_side=True, header_encoding="utf-8"))
    conn.initiate_connection()
    s.sendall(conn.data_to_send())
    pending, refused = {}, 0
    for _ in range(streams):
        sid = conn.get_next_available_stream_id()
        conn.send_headers(sid, [(":method", "POST"), (":scheme", "http"), (":path", path), (":authority", "x"),
                                ("content-type", "application/grpc"), ("te", "trailers")])
        pending[sid] = b"\x00" + claim.to_bytes(4, "big") + bytes(send)
    s.sendall(conn.data_to_send())
    deadline = time.monotonic() + 60
    s.settimeout(1)
    while pending and time.monotonic() < deadline:
        sent = True
        while sent:  # as much as the windows allow
            sent = False
            for sid, data in list(pending.items()):
                n = min(len(data), conn.local_flow_control_window(sid), conn.max_outbound_frame_size)
                if n > 0:
                    conn.send_data(sid, data[:n])
                    pending[sid], sent = data[n:], True
                    if not pending[sid]:
                        del pending[sid]
            s.sendall(conn.data_to_send())
        if not pending:
            break
        try:
            chunk = s.recv(65536)
        except socket.timeout:
            continue
        if not chunk:
            break
        for event in conn.receive_data(chunk):
            if isinstance(event, (h2.events.TrailersReceived, h2.events.ResponseReceived)):
                if dict(event.headers).get("grpc-status") == "8":
                    refused += 1
                    pending.pop(event.stream_id, None)
            elif isinstance(event, h2.events.StreamReset):
                pending.pop(event.stream_id, None)
        s.sendall(conn.data_to_send())
    return s, refused


def slow_senders(c):
    """The attack below twice: with the request budget at its largest (1 TiB:
    no bound, as before the budget) and at its default."""
    unbounded = _slow_senders_once(c, "--request-budget-mib", str(1 << 20))
    c.close()  # nothing of the first run left beside the second
    bounded = _slow_senders_once(c)
    return {**bounded, "fault": bounded["fault"], "did": f"budget {bounded['did']}; at 1 TiB (unbounded, as before): {unbounded['did']}", "unbounded": unbounded}


def _slow_senders_once(c, *extra, connections=16):
    """16 connections of 32 StreamTransitions streams each, every stream
    900 KB into a message of 1 MB and never finished (460 MB held if
    nothing bounds it), from this machine's non-loopback address where it
    has one (a remote peer, held to its quarter of the budget), beside an
    honest actor on loopback."""
    v4 = [a for a in subprocess.run(["hostname", "-I"], capture_output=True, text=True).stdout.split() if ":" not in a and not a.startswith("127.")]
    attacker_at = v4[0] if v4 else "127.0.0.1"
    port = free_port()
    learner = c.learner(c.work / f"senders{len(extra)}", port, *extra, listen_host="0.0.0.0")
    c.actor(port, "--actor-id", "honest")
    wait("steps", lambda: status(port).env_steps > 200)
    start = vm(learner.pid, "VmRSS")
    socks, refused = [], 0
    t0 = time.monotonic()
    for _ in range(connections):
        sock, r = _slow_sender(attacker_at, port)
        socks.append(sock)
        refused += r
    fill_s = time.monotonic() - t0
    time.sleep(2)
    held = vm(learner.pid, "VmRSS")
    stored = _stored_of(port, 5.0)
    health = _health_seconds(c, port, tries=2)
    for sock in socks:
        sock.close()
    time.sleep(3)
    after = vm(learner.pid, "VmRSS")
    st = status(port)
    return {"fault": f"{connections} connections × 32 StreamTransitions streams from {attacker_at}, each 900 KB into a 1 MB message and never finished",
            "did": f"learner RSS {start:.0f} MiB at the start, {held:.0f} MiB while held ({fill_s:.0f} s to send), {after:.0f} MiB after they closed; "
                   f"{refused} of {connections * 32} streams refused (RESOURCE_EXHAUSTED); the honest actor's transitions stored in 5 s meanwhile: {stored}; "
                   f"{_health_words(health)}; rejected {dict(st.rejected)}",
            "lost": "nothing" if stored > 0 else "the honest actor's batches", "rss_start_mib": start, "rss_held_mib": held, "rss_after_mib": after,
            "refused": refused, "stored_meanwhile": stored}


FAULTS["slow-senders"] = slow_senders


def called_ping_flood(c):
    """510 connections that each made one GetStatus, then only send HTTP/2
    pings (every 2 s), from one other process: before issue 82 they kept
    every place of a token-less learner."""
    port = free_port()
    c.learner(c.work / "called", port)
    c.actor(port, "--actor-id", "honest")
    wait("updates", lambda: status(port).updates > 10)
    # The flood is a process of its own, as an attacker is: this one checks.
    flood = subprocess.Popen([sys.executable, __file__, "--called-ping-flood", str(port)], stdout=subprocess.PIPE, text=True)
    c.procs.append(flood)
    called = int(flood.stdout.readline() or 0)
    time.sleep(10)
    health = _health_seconds(c, port)
    # A new actor over gRPC (another process): seconds until its stream is
    # open (each status read is a new connection from this process).
    try:
        before = status(port).connected_actors
    except grpc.RpcError:
        before = 1
    t0 = time.monotonic()
    c.actor(port, "--actor-id", "late", "--transport", "grpc")
    try:
        wait("the late actor's stream", lambda: status(port).connected_actors > before, limit=60)
        late = time.monotonic() - t0
    except RuntimeError:
        late = None
    try:
        refused = dict(status(port).connections_refused)
    except grpc.RpcError as e:
        refused = f"GetStatus failed ({e.code().name})"
    flood.kill()
    flood.wait()
    joined = "did not join within 60 s" if late is None else f"joined in {late:.1f} s"
    return {"fault": "510 connections from one process, each one GetStatus then HTTP/2 pings every 2 s",
            "did": f"{called} calls answered; {_health_words(health)}; a new actor {joined}; connections closed {refused}",
            "lost": "nothing" if None not in health and late is not None else "health or a new actor while it lasts",
            "health_answer_worst_s": health[0], "health_process_worst_s": health[1], "late_actor_s": late}


FAULTS["called-ping-flood"] = called_ping_flood


def _called_ping_flood_process(port):
    """The flood of `called_ping_flood`, in its own process: prints how many
    calls were answered, then holds the connections until killed."""
    options = [("grpc.keepalive_time_ms", 2000), ("grpc.keepalive_permit_without_calls", 1), ("grpc.http2.max_pings_without_data", 0), ("grpc.use_local_subchannel_pool", 1)]
    channels = [grpc.insecure_channel(f"127.0.0.1:{port}", options=options) for _ in range(510)]
    called = 0
    for ch in channels:
        try:
            lcrl_pb2_grpc.LearnerStub(ch).GetStatus(lcrl_pb2.GetStatusRequest(), timeout=5)
            called += 1
        except grpc.RpcError:
            pass
        # Under the per-peer rate of GetStatus (20 a second).
        time.sleep(0.055)
    print(called, flush=True)
    while True:
        time.sleep(60)


if __name__ == "__main__" and sys.argv[1:2] == ["--called-ping-flood"]:
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    _called_ping_flood_process(int(sys.argv[2]))
