"""The `lcrl.v1.Environment` service (proto/lcrl.proto) over one Gymnasium
environment: sessions of instances, batched Reset and Step, exact Fork.

`Sessions` holds the logic and raises `EnvServiceError`; `Servicer` only
translates gRPC messages and status codes, so tests can drive `Sessions`
without a network. `Security` secures the server like lcrl's own (TLS,
mutual TLS, a bearer token on every call but health checks, refusals
counted), and server reflection describes it to grpcurl and friends.
"""

from __future__ import annotations

import hmac
import itertools
import logging
import threading
import time
from concurrent import futures

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from . import lcrl_pb2, lcrl_pb2_grpc
from .adapter import EnvSpec


class EnvServiceError(Exception):
    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(message)
        self.code = code


class _Session:
    __slots__ = ("env", "lock", "reset_done", "ended", "last_used")

    def __init__(self, env):
        self.env = env
        self.lock = threading.Lock()
        self.reset_done = False
        self.ended = False
        self.last_used = time.monotonic()


class Sessions:
    """Instances of one environment, each in a session with a numeric id."""

    def __init__(self, factory, spec: EnvSpec, fork, *, instances: int, max_sessions: int, idle_timeout_s: float):
        self.factory = factory
        self.spec = spec
        self.fork = fork
        self.max_sessions = max_sessions
        self.idle_timeout_s = idle_timeout_s
        self._sessions: dict[int, _Session] = {}
        self._ready = [factory() for _ in range(instances)]  # made before serving: Open is then instant
        self._ids = itertools.count(1)
        self._lock = threading.Lock()

    # -- bookkeeping --------------------------------------------------------

    def open_count(self) -> int:
        return len(self._sessions)

    def _add(self, env) -> int:
        with self._lock:
            self._evict_idle()
            if len(self._sessions) >= self.max_sessions:
                raise EnvServiceError(
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                    f"{len(self._sessions)} sessions are open, the server's limit (--max-sessions {self.max_sessions}); close some",
                )
            sid = next(self._ids)
            self._sessions[sid] = _Session(env)
            return sid

    def _evict_idle(self):
        now = time.monotonic()
        for sid in [s for s, v in self._sessions.items() if now - v.last_used > self.idle_timeout_s]:
            self._sessions.pop(sid).env.close()

    def _get(self, sid: int) -> _Session:
        session = self._sessions.get(sid)
        if session is None:
            raise EnvServiceError(grpc.StatusCode.NOT_FOUND, f"no session {sid} on this server (closed, or idle for over {self.idle_timeout_s:.0f} s)")
        session.last_used = time.monotonic()
        return session

    # -- the RPCs' logic ----------------------------------------------------

    def open(self, count: int) -> list[int]:
        if count < 1:
            raise EnvServiceError(grpc.StatusCode.INVALID_ARGUMENT, "Open needs count >= 1")
        ids = []
        for _ in range(count):
            with self._lock:
                env = self._ready.pop() if self._ready else None
            ids.append(self._add(env if env is not None else self.factory()))
        return ids

    def close(self, ids) -> None:
        with self._lock:
            closed = [self._sessions.pop(sid) for sid in ids if sid in self._sessions]
        for session in closed:
            session.env.close()

    def reset(self, sid: int, seed: int) -> np.ndarray:
        session = self._get(sid)
        with session.lock:
            obs, _info = session.env.reset(seed=int(seed))
            session.reset_done, session.ended = True, False
        return obs

    def step(self, sid: int, action) -> tuple:
        session = self._get(sid)
        spec = self.spec
        a = np.asarray(action, dtype=np.float64)
        if a.shape != spec.action_low.shape:
            raise EnvServiceError(grpc.StatusCode.INVALID_ARGUMENT, f"session {sid}: the action has {a.size} components, the environment expects {spec.action_low.size}")
        if not np.all(np.isfinite(a)):
            bad = int(np.flatnonzero(~np.isfinite(a))[0])
            raise EnvServiceError(grpc.StatusCode.INVALID_ARGUMENT, f"session {sid}: action component {bad} is {a[bad]}; actions must be finite")
        a = np.clip(a, spec.action_low, spec.action_high).astype(spec.action_dtype, copy=False)
        with session.lock:
            if not session.reset_done:
                raise EnvServiceError(grpc.StatusCode.FAILED_PRECONDITION, f"session {sid} has not been reset; call Reset before Step")
            if session.ended:
                raise EnvServiceError(grpc.StatusCode.FAILED_PRECONDITION, f"session {sid}: the episode has ended; call Reset before stepping again")
            obs, reward, terminated, truncated, _info = session.env.step(a)
            session.ended = bool(terminated or truncated)
        return obs, float(reward), bool(terminated), bool(truncated)

    def fork_session(self, sid: int) -> int:
        if self.fork is None:
            raise EnvServiceError(grpc.StatusCode.FAILED_PRECONDITION, f"this environment cannot fork: {self.spec.fork_unavailable}")
        session = self._get(sid)
        with session.lock:
            copy = self.fork(session.env)
            reset_done, ended = session.reset_done, session.ended
        new = self._add(copy)
        self._sessions[new].reset_done, self._sessions[new].ended = reset_done, ended
        return new


def _flat(obs) -> list[float]:
    return np.asarray(obs, dtype=np.float64).ravel().tolist()


class Servicer(lcrl_pb2_grpc.EnvironmentServicer):
    """Thin: messages in, `Sessions` calls, messages out."""

    def __init__(self, sessions: Sessions):
        self.sessions = sessions

    def _run(self, context, fn):
        try:
            return fn()
        except EnvServiceError as e:
            context.abort(e.code, str(e))
        except Exception as e:  # noqa: BLE001 - the environment itself raised
            context.abort(grpc.StatusCode.INTERNAL, f"the environment raised {type(e).__name__}: {e}")

    def GetSpec(self, request, context):
        s = self.sessions.spec
        return lcrl_pb2.EnvironmentSpec(
            env_id=s.env_id,
            state_names=s.state_names,
            action_names=s.action_names,
            state_low=s.state_low.tolist(),
            state_high=s.state_high.tolist(),
            action_low=s.action_low.tolist(),
            action_high=s.action_high.tolist(),
            can_fork=s.can_fork,
            fork_method=s.fork_method,
            fork_unavailable=s.fork_unavailable,
            max_episode_steps=s.max_episode_steps,
            dt=s.dt,
            max_sessions=self.sessions.max_sessions,
            open_sessions=self.sessions.open_count(),
        )

    def Open(self, request, context):
        return self._run(context, lambda: lcrl_pb2.OpenResponse(sessions=self.sessions.open(request.count)))

    def Close(self, request, context):
        self.sessions.close(list(request.sessions))
        return lcrl_pb2.CloseResponse()

    def Reset(self, request, context):
        def reset_all():
            if not request.resets:
                raise EnvServiceError(grpc.StatusCode.INVALID_ARGUMENT, "Reset needs at least one session")
            states = [lcrl_pb2.EnvironmentState(state=_flat(self.sessions.reset(r.session, r.seed))) for r in request.resets]
            return lcrl_pb2.ResetResponse(states=states)

        return self._run(context, reset_all)

    def Step(self, request, context):
        def step_all():
            if not request.steps:
                raise EnvServiceError(grpc.StatusCode.INVALID_ARGUMENT, "Step needs at least one session")
            results = []
            for s in request.steps:
                obs, reward, terminated, truncated = self.sessions.step(s.session, s.action)
                results.append(lcrl_pb2.StepResult(state=_flat(obs), reward=reward, terminated=terminated, truncated=truncated))
            return lcrl_pb2.StepResponse(results=results)

        return self._run(context, step_all)

    def Fork(self, request, context):
        return self._run(context, lambda: lcrl_pb2.ForkResponse(session=self.sessions.fork_session(request.session)))


class Security:
    """TLS (a certificate and key; with a client CA, mutual TLS) and a
    bearer token, as `lcrl certs` and `--token-file` give lcrl's servers."""

    def __init__(self, cert=None, key=None, client_ca=None, token_file=None):
        read = lambda path, what: _read(path, what)  # noqa: E731
        if (cert is None) != (key is None):
            raise ValueError("--tls-cert and --tls-key go together")
        if client_ca is not None and cert is None:
            raise ValueError("--tls-client-ca needs --tls-cert and --tls-key")
        self.credentials = None
        if cert is not None:
            ca = read(client_ca, "client CA") if client_ca else None
            self.credentials = grpc.ssl_server_credentials([(read(key, "private key"), read(cert, "certificate"))], root_certificates=ca, require_client_auth=ca is not None)
        self.token = None
        if token_file is not None:
            token = read(token_file, "token").decode("utf-8", "replace").strip()
            # lcrl's own servers' rule (proto/src/security.rs).
            if len(token) < 16 or not token.isprintable() or any(c.isspace() for c in token):
                raise ValueError(f"the token file {token_file} must hold one token of at least 16 printable characters (e.g. `lcrl certs` writes one)")
            self.token = token
        self.refusals = {"missing_token": 0, "wrong_token": 0}
        self._lock = threading.Lock()

    def describe(self) -> str:
        tls = "plain text" if self.credentials is None else "TLS"
        return tls + (" + token" if self.token else "")

    def refuse(self, reason: str) -> int:
        with self._lock:
            self.refusals[reason] += 1
            return sum(self.refusals.values())


def _read(path, what: str) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as e:
        raise OSError(f"cannot read the {what} {path}: {e.strerror}") from e


class TokenCheck(grpc.ServerInterceptor):
    """Refuses every call without `authorization: Bearer <token>` but the
    health checks (which load balancers and `lcrl health` make without one),
    and counts the refusals."""

    def __init__(self, security: Security):
        self.security = security

    def intercept_service(self, continuation, details):
        if details.method.startswith("/grpc.health.v1.Health/"):
            return continuation(details)
        sent = dict(details.invocation_metadata or ()).get("authorization", "")
        expected = f"Bearer {self.security.token}"
        if hmac.compare_digest(sent.encode(), expected.encode()):
            return continuation(details)
        reason = "missing_token" if not sent else "wrong_token"
        total = self.security.refuse(reason)
        logging.warning("refused %s (%s); %d refusal(s) so far", details.method, reason.replace("_", " "), total)
        message = "missing bearer token" if not sent else "wrong bearer token"

        def deny(request, context):
            context.abort(grpc.StatusCode.UNAUTHENTICATED, message)

        return grpc.unary_unary_rpc_method_handler(deny)


def serve(sessions: Sessions, listen: str, workers: int, security: Security | None = None) -> tuple[grpc.Server, str]:
    """Starts the server; returns it and the address it listens on."""
    security = security or Security()
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=workers),
        options=[
            ("grpc.max_receive_message_length", 16 << 20),
            ("grpc.max_send_message_length", 16 << 20),
            # lcrl's clients ping every 15 s, idle or not (lcrl_proto's
            # limits.rs), and a call may take 120 s (docs/reliability.md).
            # grpc's defaults take one ping in 5 min without data; issue 82
            # saw "Too many pings" after about 45 s. Here a 50 s step and a
            # 50 s idle pause both passed with and without these options,
            # so they are a guard, not a measured fix: take a ping every
            # 10 s, with or without a call.
            ("grpc.http2.min_recv_ping_interval_without_data_ms", 10_000),
            ("grpc.keepalive_permit_without_calls", 1),
        ],
        interceptors=[TokenCheck(security)] if security.token else [],
    )
    lcrl_pb2_grpc.add_EnvironmentServicer_to_server(Servicer(sessions), server)
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    names = (lcrl_pb2.DESCRIPTOR.services_by_name["Environment"].full_name, health.SERVICE_NAME, reflection.SERVICE_NAME)
    reflection.enable_server_reflection(names, server)
    host, _, port = listen.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"--listen {listen!r} must be HOST:PORT (port 0: any free port)")
    if security.credentials is None:
        bound = server.add_insecure_port(listen)
    else:
        bound = server.add_secure_port(listen, security.credentials)
    if bound == 0:
        raise OSError(f"cannot listen on {listen} (in use, or not an address of this host)")
    server.start()
    for service in ("", "lcrl.v1.Environment"):
        health_servicer.set(service, health_pb2.HealthCheckResponse.SERVING)
    return server, f"{host}:{bound}"
