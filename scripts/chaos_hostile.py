"""The chaos faults of issue 71: hostile but well-formed peers. Each is a
short real run of lcrl-learner (lti-paper, DDPG, small networks) with an
honest actor, and one attack; the row says what the service did and
what was lost. Run through scripts/chaos.sh (`--only huge-values`, ...).
"""

import json
import math
import sys
import socket
import subprocess
import threading
import time

import grpc

from chaoslib import free_port, sample, scrape, status, stub, vm, wait
import lcrl_pb2
import lcrl_pb2_grpc


def _send(port, batches):
    try:
        for _ in stub(port).StreamTransitions(iter(batches), timeout=30):
            pass
        return "ok"
    except grpc.RpcError as e:
        return e.code().name


def _step(state, reward=-1.0, end=False):
    return lcrl_pb2.Transition(state=state, action=[0.0, 0.0, 0.0], reward=reward, next_state=state, terminated=end)


def _finite_action(port):
    action = lcrl_pb2_grpc.PolicyStub(grpc.insecure_channel(f"127.0.0.1:{port}")).Act(lcrl_pb2.ActRequest(state=[0.1, 0.2, 0.3]), timeout=10).action
    return all(math.isfinite(a) for a in action)


def _training(port, seconds=3.0):
    """Updates the learner made over `seconds`."""
    before = status(port).updates
    time.sleep(seconds)
    return status(port).updates - before


def huge_values(c):
    """One batch of 25 transitions with states of 3e38 beside an honest actor."""
    port = free_port()
    c.learner(c.work / "huge", port)
    c.actor(port, "--actor-id", "honest")
    wait("updates", lambda: status(port).updates > 50)
    code = _send(port, [lcrl_pb2.TransitionBatch(run_id="chaos", actor_id="evil", sequence=1, transitions=[_step([3e38, 3e38, 3e38])] * 25)])
    later = _training(port, 5.0)
    try:
        finite = _finite_action(port)
    except grpc.RpcError as e:
        finite = f"no ({e.code().name}: {e.details()})"
    st = status(port)
    return {"fault": "one batch of 25 transitions with states of 3e38 beside an honest actor",
            "did": f"batch {code}, refused as {dict(st.rejected)}; {later} updates in the next 5 s; Policy.Act finite: {finite}",
            "lost": "nothing of the honest actor" if finite is True else "the run: every weight NaN", "updates_after": later, "finite": finite}


def forged_returns(c):
    """1,000 one-step episodes claiming a return of 1e30, against a
    1,000-episode budget."""
    port = free_port()
    c.learner(c.work / "forged", port, "--episodes", "1000")
    c.actor(port, "--actor-id", "honest")
    wait("episodes", lambda: status(port).episodes > 5)
    batch = lcrl_pb2.TransitionBatch(run_id="chaos", actor_id="evil", sequence=1, transitions=[_step([0.1, 0.1, 0.1], end=True)] * 1000,
                                     episodes=[lcrl_pb2.EpisodeSummary(episode_return=1e30, length=1)] * 1000)
    code = _send(port, [batch])
    time.sleep(3)
    st = status(port)
    return {"fault": "1,000 one-step episodes claiming return 1e30, 1,000-episode budget",
            "did": f"batch {code}; 3 s later: {st.episodes} of 1,000 episodes counted, training finished: {st.finished}, recent return {st.recent_return:.3g}; refused as {dict(st.rejected)}",
            "lost": "the run (ended by the forged episodes)" if st.finished else "nothing", "episodes": st.episodes, "finished": st.finished}


def sequence_hijack(c):
    """A batch under the honest actor's id with sequence 2^64 - 1."""
    port = free_port()
    c.learner(c.work / "hijack", port)
    c.actor(port, "--actor-id", "honest")
    wait("steps", lambda: status(port).env_steps > 500)
    code = _send(port, [lcrl_pb2.TransitionBatch(run_id="chaos", actor_id="honest", sequence=2**64 - 1, transitions=[_step([0.1, 0.1, 0.1])])])
    before = status(port)
    time.sleep(5)
    after = status(port)
    stored = after.env_steps - before.env_steps
    return {"fault": "one batch under the honest actor's id with sequence 2^64 - 1",
            "did": f"batch {code}; the honest actor's transitions stored in the next 5 s: {stored}; refused as {dict(after.rejected)}",
            "lost": "nothing" if stored > 0 else "every later batch of the honest actor", "stored_after": stored}


def _health_seconds(c, port, tries=5):
    """The slowest of `tries` health checks, each on a new connection: the
    learner's answer (a gRPC health Check from this process) and a whole
    `lcrl health` process (which also loads the lcrl binary and libtorch).
    Returns (answer_s, process_s); None where a check failed."""
    from grpc_health.v1 import health_pb2, health_pb2_grpc
    answer, process = 0.0, 0.0
    for _ in range(tries):
        t0 = time.monotonic()
        try:
            with grpc.insecure_channel(f"127.0.0.1:{port}", options=[("grpc.use_local_subchannel_pool", 1)]) as channel:
                health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=""), timeout=30)
            answer = max(answer, time.monotonic() - t0) if answer is not None else None
        except grpc.RpcError:
            answer = None
        t0 = time.monotonic()
        ok = subprocess.run([str(c.bins / "lcrl"), "health", f"http://127.0.0.1:{port}"], capture_output=True).returncode == 0
        process = max(process, time.monotonic() - t0) if ok and process is not None else None
        time.sleep(1)
    return answer, process


def _health_words(health):
    answer, process = health
    said = lambda t: "FAILED" if t is None else "%.2f s" % t  # noqa: E731
    return f"health answered in {said(answer)} at worst (a whole `lcrl health` process: {said(process)})"


def ping_flood(c):
    """520 connections that only answer and send HTTP/2 pings (every 2 s)."""
    port = free_port()
    c.learner(c.work / "pings", port)
    c.actor(port, "--actor-id", "honest")
    wait("updates", lambda: status(port).updates > 10)
    options = [("grpc.keepalive_time_ms", 2000), ("grpc.keepalive_permit_without_calls", 1), ("grpc.http2.max_pings_without_data", 0), ("grpc.use_local_subchannel_pool", 1)]
    channels = [grpc.insecure_channel(f"127.0.0.1:{port}", options=options) for _ in range(520)]
    for ch in channels:
        ch.subscribe(lambda _: None, try_to_connect=True)
    time.sleep(15)
    health = _health_seconds(c, port)
    try:
        training = f"{_training(port, 3.0)} updates in 3 s; connections closed {dict(status(port).connections_refused)}"
    except grpc.RpcError as e:
        training = f"GetStatus failed ({e.code().name})"
    for ch in channels:
        ch.close()
    return {"fault": "520 connections answering and sending HTTP/2 pings every 2 s, no calls",
            "did": f"5 checks 15 s in: {_health_words(health)}; {training}",
            "lost": "nothing" if None not in health else "health and status while it lasts", "health_answer_worst_s": health[0], "health_process_worst_s": health[1]}


def slowloris_metrics(c):
    """1,100 unfinished GETs on /metrics."""
    port, metrics = free_port(), free_port()
    c.learner(c.work / "slowloris", port, "--metrics-listen", f"127.0.0.1:{metrics}", "--checkpoint-secs", "1")
    c.actor(port, "--actor-id", "honest")
    wait("updates", lambda: status(port).updates > 10)
    socks = []
    for _ in range(1100):
        try:
            s = socket.create_connection(("127.0.0.1", metrics), timeout=2)
            s.sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\n")
            socks.append(s)
        except OSError:
            break
    health = _health_seconds(c, port)
    for s in socks:
        s.close()
    time.sleep(1)
    _, text = scrape(metrics)
    failures = sample(text, "lcrl_learner_checkpoint_failures_total") or 0
    return {"fault": "1,100 unfinished GETs on /metrics (its connections held open)",
            "did": f"5 checks: {_health_words(health)}; checkpoint failures {failures:.0f}; {len(socks)} sockets opened",
            "lost": "nothing" if not failures else f"{failures:.0f} checkpoints", "health_answer_worst_s": health[0], "health_process_worst_s": health[1],
            "checkpoint_failures": failures}


def _storm_clients(port, seconds):
    """4 Act and 4 ActBatch(4,096) clients for `seconds`; the answers by code."""
    policy = lcrl_pb2_grpc.PolicyStub(grpc.insecure_channel(f"127.0.0.1:{port}"))
    stop, codes = threading.Event(), {}

    def client(batch):
        while not stop.is_set():
            try:
                if batch:
                    policy.ActBatch(lcrl_pb2.ActBatchRequest(count=4096, states=[0.1] * (4096 * 3)), timeout=60)
                else:
                    policy.Act(lcrl_pb2.ActRequest(state=[0.1, 0.2, 0.3]), timeout=60)
                codes["OK"] = codes.get("OK", 0) + 1
            except grpc.RpcError as e:
                codes[e.code().name] = codes.get(e.code().name, 0) + 1

    workers = [threading.Thread(target=client, args=(k >= 4,)) for k in range(8)]
    for w in workers:
        w.start()
    time.sleep(seconds)
    stop.set()
    for w in workers:
        w.join()
    return codes


def _storm(port, niceness):
    """Updates per second while the storm's clients run in their own
    process at `niceness`."""
    clients = subprocess.Popen(["nice", "-n", str(niceness), sys.executable, __file__, "--storm-clients", str(port), "14"], stdout=subprocess.PIPE, text=True)
    time.sleep(2)
    rate = _training(port, 10.0) / 10.0
    out = clients.communicate(timeout=120)[0]
    codes = json.loads(out) if out.strip() else {"clients failed": clients.returncode}
    return rate, codes


def query_storm(c):
    """4 Act and 4 ActBatch(4,096) clients: updates per second against a
    quiet stretch of the same run, with the clients at normal priority
    (their own CPU taken from the learner on a small machine) and at the
    lowest (as clients on other machines would be)."""
    port = free_port()
    c.learner(c.work / "storm", port)
    c.actor(port, "--actor-id", "honest")
    wait("updates", lambda: status(port).updates > 200)
    # A quiet stretch right before each storm: the rate drifts over a run.
    quiet = _training(port, 10.0) / 10.0
    beside, beside_codes = _storm(port, 0)
    time.sleep(3)
    quiet_niced = _training(port, 10.0) / 10.0
    niced, niced_codes = _storm(port, 19)
    ratio = lambda r, q: r / q if q else float("nan")  # noqa: E731
    return {"fault": "4 Act and 4 ActBatch(4,096) clients for 10 s",
            "did": f"clients beside the learner at normal priority: {beside:.0f} updates/s against {quiet:.0f} quiet just before ({ratio(beside, quiet):.2f}), "
                   f"queries {beside_codes}; clients at nice 19: {niced:.0f} against {quiet_niced:.0f} ({ratio(niced, quiet_niced):.2f}), queries {niced_codes}",
            "lost": "nothing", "updates_ratio": ratio(beside, quiet), "updates_ratio_clients_niced": ratio(niced, quiet_niced)}


def _hpack(name, value):
    """One header as an HPACK literal without indexing (no Huffman)."""
    def length(n):
        if n < 127:
            return bytes([n])
        out, n = bytearray([127]), n - 127
        while n >= 128:
            out.append(n % 128 + 128)
            n //= 128
        return bytes(out + bytearray([n]))
    return b"\x00" + length(len(name)) + name + length(len(value)) + value


def _frame(kind, flags, stream, payload=b""):
    return len(payload).to_bytes(3, "big") + bytes([kind, flags]) + stream.to_bytes(4, "big") + payload


def _slow_watcher(port):
    """A raw HTTP/2 connection that opens one WatchPolicy stream, takes the
    first 64 KiB window's worth, and never reads or widens it again."""
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    headers = b"".join(_hpack(n, v) for n, v in [(b":method", b"POST"), (b":scheme", b"http"), (b":path", b"/lcrl.v1.Learner/WatchPolicy"),
                                                  (b":authority", b"x"), (b"content-type", b"application/grpc"), (b"te", b"trailers")])
    s.sendall(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + _frame(4, 0, 0) + _frame(1, 4, 1, headers) + _frame(0, 1, 1, b"\x00" + bytes(4)))
    s.recv(4096)  # the server's settings
    s.sendall(_frame(4, 1, 0))  # acknowledged; nothing is read from here on
    return s


def slow_watchers(c):
    """8 rounds of 64 slow WatchPolicy readers against a 4.2 MB policy: the
    learner's memory while they hold on and after they leave."""
    port = free_port()
    big = c.work / "big.toml"
    big.write_text(c.work.joinpath("small.toml").read_text().replace("global_hidden = [32, 32]", "global_hidden = [1024, 1024]"))
    learner = c.learner(c.work / "watchers", port, config=big)
    c.actor(port, "--actor-id", "honest")
    wait("updates", lambda: status(port).updates > 10, limit=120)
    start, held, after, worst = vm(learner.pid, "VmRSS"), [], [], (0.0, 0.0)
    for _ in range(8):
        socks = []
        for _ in range(64):
            socks.append(_slow_watcher(port))
        time.sleep(3)
        held.append(vm(learner.pid, "VmRSS"))
        health = _health_seconds(c, port, tries=1)
        worst = tuple(None if w is None or h is None else max(w, h) for w, h in zip(worst, health))
        for s in socks:
            s.close()
        time.sleep(3)
        after.append(vm(learner.pid, "VmRSS"))
    rejected = dict(status(port).rejected)
    training = _training(port, 3.0)
    return {"fault": "8 rounds of 64 WatchPolicy streams that stop reading, 4.2 MB policy",
            "did": f"learner RSS {start:.0f} MiB at the start, {max(held):.0f} MiB at most while held, {after[-1]:.0f} MiB after the 8th round "
                   f"(after each: {', '.join('%.0f' % a for a in after)}); {_health_words(worst)}; "
                   f"{training} updates in 3 s after; rejected {rejected}",
            "lost": "nothing" if training > 0 else "training",
            "rss_start_mib": start, "rss_held_max_mib": max(held), "rss_after_mib": after[-1], "health_answer_worst_s": worst[0], "health_process_worst_s": worst[1]}


def _stored_of(port, seconds):
    """Transitions the learner stored over `seconds`."""
    before = status(port).env_steps
    time.sleep(seconds)
    return status(port).env_steps - before


def id_hijack(c):
    """Batches under a live honest actor's id, from another stream, with
    the sequences it is about to send."""
    port = free_port()
    c.learner(c.work / "bound", port)
    c.actor(port, "--actor-id", "honest")
    wait("steps", lambda: status(port).env_steps > 500)
    # The honest actor's next sequences (actors number batches from the
    # clock in µs): a hijacker that got them first would make the honest
    # batches "duplicates".
    codes = {}
    for k in range(20):
        seq = int(time.time() * 1e6) + 2_000_000 + k * 100_000
        code = _send(port, [lcrl_pb2.TransitionBatch(run_id="chaos", actor_id="honest", sequence=seq, transitions=[_step([0.1, 0.1, 0.1])] * 25)])
        codes[code] = codes.get(code, 0) + 1
    stored = _stored_of(port, 5.0)
    st = status(port)
    return {"fault": "20 batches under a live honest actor's id, from another stream, with its coming sequences",
            "did": f"batches {codes}; refused as {dict(st.rejected)}; the honest actor's transitions stored in the next 5 s: {stored}",
            "lost": "nothing" if stored > 0 and "ok" not in codes else "the honest actor's batches", "codes": codes, "stored_after": stored}


class _FreezableProxy:
    """A TCP relay to the learner. `freeze()` stops moving bytes on the
    connections open now, and never closes them (a pulled cable: neither
    end is told); connections opened later are relayed."""

    def __init__(self, target):
        self.target, self.generation, self.accepted_after_freeze = target, 0, []
        self.listener = socket.socket()
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(64)
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            client, _ = self.listener.accept()
            if self.generation:
                self.accepted_after_freeze.append(time.monotonic())
            upstream = socket.create_connection(("127.0.0.1", self.target))
            for src, dst in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(src, dst, self.generation), daemon=True).start()

    def _pipe(self, src, dst, generation):
        while True:
            try:
                data = src.recv(65536)
            except OSError:
                return
            if generation != self.generation:
                if not data:
                    return  # an end that gives up is not passed on
                continue  # frozen: bytes are lost
            if not data:
                dst.close()
                return
            dst.sendall(data)

    def freeze(self):
        self.generation += 1


def frozen_connection(c):
    """The honest actor's connections stop carrying bytes without closing
    (a cable pulled): how soon are its transitions stored again, on the
    connection it opens when its keepalive gives up?"""
    port = free_port()
    c.learner(c.work / "frozen", port)
    proxy = _FreezableProxy(port)
    c.actor(port, "--actor-id", "honest", learner=f"http://127.0.0.1:{proxy.port}")
    wait("steps", lambda: status(port).env_steps > 500)
    proxy.freeze()
    frozen_at = time.monotonic()
    # Stored again: more steps than when the actor opened its new
    # connection (batches already inside the learner were stored by then).
    wait("the actor's new connection", lambda: proxy.accepted_after_freeze, limit=60, every=0.1)
    reconnect_s, steps = proxy.accepted_after_freeze[0] - frozen_at, status(port).env_steps
    wait("the honest actor stored again", lambda: status(port).env_steps > steps, limit=120, every=0.1)
    back_s = time.monotonic() - frozen_at
    st = status(port)
    refused = dict(st.rejected).get("actor_id_bound", 0)
    return {"fault": "the honest actor's connections stop carrying bytes, never closed (a pulled cable)",
            "did": f"the actor connected anew {reconnect_s:.1f} s after the freeze, its transitions stored again at {back_s:.1f} s; refused meanwhile as {dict(st.rejected)}",
            "lost": "nothing" if refused == 0 else f"{refused} transitions refused as actor_id_bound (the actor resent them)", "reconnect_s": reconnect_s, "back_s": back_s, "refused": refused}


def shm_id_hijack(c):
    """A second process on the host publishes over shared memory under a
    live honest actor's id; then the honest actor is killed (-9)."""
    port = free_port()
    c.learner(c.work / "shm", port)
    honest = c.actor(port, "--actor-id", "honest", "--transport", "shm")
    wait("steps", lambda: status(port).env_steps > 500)
    c.actor(port, "--actor-id", "honest", "--transport", "shm")
    time.sleep(2.0)
    refused_before = dict(status(port).rejected)
    stored = _stored_of(port, 5.0)
    refused = dict(status(port).rejected)
    honest.kill()
    honest.wait()
    killed_at, bound = time.monotonic(), refused.get("actor_id_bound", 0)
    # The id is free once the dead publisher is gone: the second actor's
    # batches are no longer refused, and are stored.
    def taken_without_refusals():
        bound = lambda st: dict(st.rejected).get("actor_id_bound", 0)  # noqa: E731
        first = status(port)
        time.sleep(1.0)
        last = status(port)
        return last.env_steps > first.env_steps and bound(last) == bound(first)
    wait("the id freed", taken_without_refusals, limit=60, every=0.0)
    freed_s = time.monotonic() - killed_at
    return {"fault": "a second process publishes over shared memory under a live honest actor's id; then the honest actor is killed -9",
            "did": f"refused while the honest actor lived: {refused.get('actor_id_bound', 0) - refused_before.get('actor_id_bound', 0)} transitions in 5 s ({refused}); "
                   f"the honest actor's transitions stored in those 5 s: {stored}; after the kill the id was taken by the second actor within {freed_s:.1f} s",
            "lost": "nothing" if stored > 0 and bound > 0 else "the honest actor's batches", "stored_while_hijacked": stored, "freed_s": freed_s}


def shm_fairness(c):
    """Three actors on shared memory, 30 episodes each, behind one learner
    (the bottleneck): when does each finish?"""
    port = free_port()
    c.learner(c.work / "fair", port)
    started = time.monotonic()
    actors = [c.actor(port, "--actor-id", f"a{k}", "--transport", "shm", "--episodes", "30") for k in range(3)]
    done = {}

    def all_done():
        done.update({k: round(time.monotonic() - started, 1) for k, a in enumerate(actors) if k not in done and a.poll() is not None})
        return len(done) == len(actors)
    wait("every actor done", all_done, limit=180, every=0.1)
    stored = status(port).env_steps
    spread = max(done.values()) - min(done.values())
    return {"fault": "three actors on shared memory, 30 episodes each, one learner",
            "did": f"done at {sorted(done.values())} s; {stored} transitions stored",
            "lost": "nothing" if spread < 0.25 * max(done.values()) else "turns: the actors were served one after another", "done_s": done, "stored": stored}


def _own_addresses():
    """This machine's non-loopback IPv4 and IPv6 addresses (peers the
    learner counts). Two IPv4 addresses of one machine may reach a server
    as one (a NAT rule rewrote 172.17.0.1 into 192.0.2.2 here), so the
    attacker and the newcomer use one family each."""
    out = subprocess.run(["hostname", "-I"], capture_output=True, text=True).stdout.split()
    v4 = [a for a in out if ":" not in a and not a.startswith("127.")]
    v6 = [a for a in out if ":" in a and not a.lower().startswith("fe80")]
    return v4, v6


def id_table(c):
    """One peer address asks for 4,096 actor ids (the whole table, before
    the per-peer cap), then a new actor joins from another address."""
    v4, v6 = _own_addresses()
    if not v4 or not v6:
        return {"fault": "one peer filling the actor-id table", "did": "skipped: needs a non-loopback IPv4 and IPv6 address on this machine", "lost": "-"}
    attacker_at, newcomer_at = v4[0], f"[{v6[0]}]"
    port = free_port()
    c.learner(c.work / "table", port, listen_host="[::]")
    honest = c.actor(port, "--actor-id", "honest")
    wait("steps", lambda: status(port).env_steps > 200)
    channel = grpc.insecure_channel(f"{attacker_at}:{port}")
    attacker = lcrl_pb2_grpc.LearnerStub(channel)
    codes = {}
    t0 = time.monotonic()
    for k in range(4096):
        batch = lcrl_pb2.TransitionBatch(run_id="chaos", actor_id=f"filler-{k}", sequence=1, transitions=[_step([0.1, 0.1, 0.1])])
        try:
            for _ in attacker.StreamTransitions(iter([batch]), timeout=10):
                pass
            code = "OK"
        except grpc.RpcError as e:
            code = e.code().name
        codes[code] = codes.get(code, 0) + 1
    fill_s = time.monotonic() - t0
    channel.close()
    # Only the newcomer streams from here on: what is stored is its.
    honest.kill()
    honest.wait()
    # What the killed actor had in flight is stored, or not, by now.
    time.sleep(2)
    started = time.monotonic()
    before = status(port).env_steps
    c.actor(port, "--actor-id", "newcomer", learner=f"http://{newcomer_at}:{port}")
    try:
        wait("the newcomer's transitions", lambda: status(port).env_steps > before, limit=30)
        join = f"its transitions stored {time.monotonic() - started:.1f} s after it started"
    except RuntimeError:
        join = "none of its transitions stored within 30 s"
    st = status(port)
    return {"fault": f"4,096 actor ids asked for from one peer address ({attacker_at}), then a new actor joins from {newcomer_at}",
            "did": f"ids {codes} in {fill_s:.0f} s; refused as {dict(st.rejected)}; the new actor: {join}",
            "lost": "nothing" if "stored" in join and "none" not in join else "new actors", "codes": codes}


def forged_claims(c):
    """Issue 82, fault 6: one-step episodes that each claim 10^6 steps and a
    return of 9.9e11 (within the door's 10^6 a claimed step), against a
    300-episode budget, beside an honest actor."""
    port = free_port()
    c.learner(c.work / "claims", port, "--episodes", "300")
    c.actor(port, "--actor-id", "honest")
    wait("episodes", lambda: status(port).episodes >= 24)
    batch = lcrl_pb2.TransitionBatch(run_id="chaos", actor_id="forger", sequence=1, transitions=[_step([0.1, 0.1, 0.1], reward=-1.0, end=True)] * 276,
                                     episodes=[lcrl_pb2.EpisodeSummary(episode_return=9.9e11, length=1_000_000)] * 276)
    code = _send(port, [batch])
    time.sleep(2)
    st = status(port)
    rows = (c.work / "claims" / "metrics.csv").read_text().splitlines()[1:]
    worst = max((abs(float(r.split(",")[1])) for r in rows if r), default=0.0)
    longest = max((int(float(r.split(",")[2])) for r in rows if r), default=0)
    return {"fault": "276 one-step episodes each claiming 10^6 steps and a return of 9.9e11, 300-episode budget, after 24 honest ones",
            "did": f"batch {code}; 2 s later {st.episodes} episodes counted, training finished: {st.finished}, recent return {st.recent_return:.3g}; "
                   f"metrics.csv: largest |return| {worst:.3g}, longest episode {longest} steps",
            "lost": ("the record (claims taken)" if worst > 1e6 else "nothing of the record") + ("; the budget, ended by one-step episodes" if st.finished else ""),
            "largest_return": worst, "longest": longest, "finished": st.finished}


def same_run_id(c):
    """Issue 82, fault 7: a second learner under a live learner's run id
    (another run directory), on the same host."""
    port = free_port()
    c.learner(c.work / "first", port)
    c.actor(port, "--actor-id", "honest", "--transport", "shm")
    wait("steps", lambda: status(port).env_steps > 200)
    p = subprocess.Popen([str(c.bins / "lcrl-learner"), "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--config", str(c.work / "small.toml"),
                          "--run-dir", str(c.work / "second"), "--listen", f"127.0.0.1:{free_port()}", "--run-id", "chaos"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    c.procs.append(p)
    try:
        _, err = p.communicate(timeout=10)
        outcome = f"exited {p.returncode}: {err.strip().splitlines()[-1][:160] if err.strip() else ''}"
    except subprocess.TimeoutExpired:
        outcome = "kept running beside the first"
    before = status(port).env_steps
    time.sleep(3)
    stored = status(port).env_steps - before
    return {"fault": "a second learner under a live learner's run id, same host",
            "did": f"the second learner {outcome}; the first stored {stored} steps in the next 3 s",
            "lost": "nothing" if "exited" in outcome and stored > 0 else "the run's transitions, shared between two learners", "second": outcome, "stored_after": stored}


def _flood_status_and_metrics(port, metrics, stop):
    ch = grpc.insecure_channel(f"127.0.0.1:{port}")
    s = lcrl_pb2_grpc.LearnerStub(ch)
    while not stop.is_set():
        try:
            s.GetStatus(lcrl_pb2.GetStatusRequest(), timeout=5)
        except grpc.RpcError:
            pass
        try:
            scrape(metrics)
        except OSError:
            pass


def status_flood(c, threads=8, seconds=5.0):
    """Issue 82, fault 10: unauthenticated GetStatus and /metrics floods
    from 8 threads, against the updates of a quiet stretch of equal length."""
    port, metrics = free_port(), free_port()
    c.learner(c.work / "statusflood", port, "--metrics-listen", f"127.0.0.1:{metrics}")
    c.actor(port, "--actor-id", "honest")
    wait("updates", lambda: status(port).updates > 200)
    quiet = _training(port, seconds)
    stop = threading.Event()
    workers = [threading.Thread(target=_flood_status_and_metrics, args=(port, metrics, stop)) for _ in range(threads)]
    for w in workers:
        w.start()
    flooded = _training_tolerant(port, seconds)
    stop.set()
    for w in workers:
        w.join()
    kept = flooded / max(quiet, 1)
    return {"fault": f"GetStatus and /metrics floods from {threads} threads, {seconds:.0f} s, beside an honest actor",
            "did": f"{flooded} updates during the flood against {quiet} in as long before it: {kept:.2f} kept",
            "lost": "nothing", "kept": kept, "quiet": quiet, "flooded": flooded}


def _training_tolerant(port, seconds):
    """Updates over `seconds`, asking the status as the flood lets it."""
    before = wait("status", lambda: status(port).updates + 1) - 1
    time.sleep(seconds)
    return wait("status", lambda: status(port).updates + 1) - 1 - before

FAULTS = {"huge-values": huge_values, "forged-returns": forged_returns, "sequence-hijack": sequence_hijack, "ping-flood": ping_flood,
          "slowloris-metrics": slowloris_metrics, "query-storm": query_storm, "slow-watchers": slow_watchers, "id-hijack": id_hijack,
          "id-table": id_table, "frozen-connection": frozen_connection, "shm-id-hijack": shm_id_hijack, "shm-fairness": shm_fairness,
          "forged-claims": forged_claims, "same-run-id": same_run_id, "status-flood": status_flood}


if __name__ == "__main__" and sys.argv[1:2] == ["--storm-clients"]:
    # The storm's clients in a process of their own (query_storm).
    print(json.dumps(_storm_clients(int(sys.argv[2]), float(sys.argv[3]))))
