"""Command line: `python -m lcrl_env serve ...` and `python -m lcrl_env bench ...`."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time

import numpy as np

from .adapter import SpecError, choose_fork, describe, make_factory


def _add_env_args(p: argparse.ArgumentParser) -> None:
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--env", metavar="ID", help="a registered Gymnasium id, e.g. HalfCheetah-v5 or Pendulum-v1 (module:Id imports module first)")
    which.add_argument("--entry-point", metavar="MODULE:CLASS", help="your own gymnasium.Env class (MODULE must be importable: PYTHONPATH)")
    p.add_argument("--kwargs", default="{}", metavar="JSON", help="keyword arguments for gymnasium.make or the class, as a JSON object")
    p.add_argument("--max-episode-steps", type=int, default=None, metavar="N", help="truncate episodes after N steps (default: the registered limit; none for an entry point)")


def _factory(args):
    try:
        kwargs = json.loads(args.kwargs)
    except json.JSONDecodeError as e:
        raise SpecError(f"--kwargs is not JSON: {e}") from e
    if not isinstance(kwargs, dict):
        raise SpecError("--kwargs must be a JSON object, e.g. '{\"ctrl_cost_weight\": 0.1}'")
    return make_factory(args.env, args.entry_point, kwargs, args.max_episode_steps)


def serve_command(args) -> int:
    from .server import Security, Sessions, serve

    security = Security(args.tls_cert, args.tls_key, args.tls_client_ca, args.token_file or os.environ.get("LCRL_TOKEN_FILE") or None)

    factory, env_id = _factory(args)
    probe = factory()
    names = lambda text: [n.strip() for n in text.split(",")] if text else None  # noqa: E731
    spec = describe(probe, env_id, names(args.state_names), names(args.action_names))
    method, fork = choose_fork(probe)
    probe.close()
    if method:
        spec.fork_method = method
    else:
        spec.fork_unavailable, fork = fork, None
        logging.warning("Fork unavailable (CS3 will refuse this environment): %s", spec.fork_unavailable)
    if args.instances < 0 or args.max_sessions < max(1, args.instances):
        raise SpecError("--instances must be >= 0 and --max-sessions at least 1 and at least --instances")
    sessions = Sessions(factory, spec, fork, instances=args.instances, max_sessions=args.max_sessions, idle_timeout_s=args.idle_timeout)
    server, address = serve(sessions, args.listen, args.workers, security)
    logging.info(
        "serving %s (%s): %d states, %d actions, fork %s, %d instance(s) ready",
        env_id, security.describe(), len(spec.state_names), len(spec.action_names), spec.fork_method or "unavailable", args.instances,
    )
    # The first stdout line is the address (lcrl run reads it, as it does
    # for its own servers); logs go to stderr.
    print(f"listening on {address}", flush=True)
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    # A timed wait: the kernel may deliver SIGTERM to one of gRPC's threads,
    # and Python runs the handler only when the main thread runs bytecode;
    # an untimed wait would then sleep through it forever.
    while not stop.wait(0.2):
        pass
    server.stop(grace=2).wait()
    logging.info("stopped (refused calls: %s)", security.refusals)
    return 0


def bench_command(args) -> int:
    """One environment stepped in plain Python: the floor under any service."""
    factory, env_id = _factory(args)
    env = factory()
    describe(env, env_id)
    rng = np.random.default_rng(0)
    low, high = env.action_space.low, env.action_space.high
    actions = rng.uniform(low, high, size=(args.steps, low.size)).astype(env.action_space.dtype)
    env.reset(seed=0)
    start = time.perf_counter()
    for k in range(args.steps):
        _, _, terminated, truncated, _ = env.step(actions[k])
        if terminated or truncated:
            env.reset()
    seconds = time.perf_counter() - start
    print(json.dumps({"env": env_id, "steps": args.steps, "us_per_step": seconds / args.steps * 1e6, "steps_per_s": args.steps / seconds}))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lcrl_env", description="Gymnasium environments for lcrl over gRPC (lcrl.v1.Environment).")
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser("serve", help="serve one Gymnasium environment (many instances)")
    _add_env_args(s)
    s.add_argument("--listen", default="127.0.0.1:50070", metavar="HOST:PORT", help="address to serve on (port 0: any free port; the first stdout line says which)")
    s.add_argument("--instances", type=int, default=1, metavar="K", help="instances made before serving, so the first K sessions open at once (default 1)")
    s.add_argument("--max-sessions", type=int, default=1024, help="most sessions open at once, forks included (default 1024)")
    s.add_argument("--idle-timeout", type=float, default=3600.0, metavar="S", help="close sessions unused for S seconds (clients that died without closing)")
    s.add_argument("--workers", type=int, default=8, help="gRPC worker threads (default 8)")
    s.add_argument("--state-names", metavar="A,B,...", help="names of the state components, in order (default: the class's lcrl_state_names, MuJoCo's joints, else s0, s1, ...); lcrl graph and every report use them")
    s.add_argument("--action-names", metavar="A,B,...", help="names of the action components, in order (default: lcrl_action_names, MuJoCo's actuators, else a0, a1, ...)")
    s.add_argument("--tls-cert", metavar="PEM", help="serve TLS with this certificate (with --tls-key; `lcrl certs` writes server.pem)")
    s.add_argument("--tls-key", metavar="PEM", help="the certificate's private key (server.key)")
    s.add_argument("--tls-client-ca", metavar="PEM", help="accept only clients with a certificate of this CA (mutual TLS; ca.pem)")
    s.add_argument("--token-file", metavar="FILE", help="require `authorization: Bearer <token>` from this file on every call but health checks [default: the file $LCRL_TOKEN_FILE names, if set]")
    b = sub.add_parser("bench", help="time env.step in plain Python (no service)")
    _add_env_args(b)
    b.add_argument("--steps", type=int, default=5000)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s lcrl_env %(levelname)s %(message)s", stream=sys.stderr)
    try:
        return serve_command(args) if args.command == "serve" else bench_command(args)
    except (SpecError, ValueError, OSError) as e:
        print(f"lcrl_env: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
