#!/usr/bin/env python3
"""Query the policy of a running lcrl learner, as any gRPC user would.

Checks the standard gRPC health service, then asks `lcrl.v1.Policy/Act` for
the deterministic action of one state. The lcrl.v1 stubs are generated from
proto/lcrl.proto into clients/python/lcrl_stubs/ by scripts/setup.sh
(grpcio-tools), so they always match the contract.

    .venv/bin/python clients/python/lcrl_client.py --target 127.0.0.1:50052 --state 0.1 0.2 0.3

Across hosts, with the files `lcrl certs` writes (TLS, mutual TLS, token):

    .venv/bin/python clients/python/lcrl_client.py --target learner:50052 --tls-ca certs/ca.pem \
        --tls-client-cert certs/client.pem --tls-client-key certs/client.key --token-file certs/token --state ...
"""

import argparse
import os
import pathlib
import sys

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent / "lcrl_stubs"))
import lcrl_pb2  # noqa: E402  (generated)
import lcrl_pb2_grpc  # noqa: E402  (generated)


def open_channel(args) -> grpc.Channel:
    """Plain text, or TLS (mutual with a client certificate) with --tls-ca."""
    if not args.tls_ca:
        return grpc.insecure_channel(args.target)
    read = lambda path: pathlib.Path(path).read_bytes() if path else None  # noqa: E731
    credentials = grpc.ssl_channel_credentials(
        root_certificates=read(args.tls_ca),
        private_key=read(args.tls_client_key),
        certificate_chain=read(args.tls_client_cert),
    )
    options = [("grpc.ssl_target_name_override", args.tls_server_name)] if args.tls_server_name else []
    return grpc.secure_channel(args.target, credentials, options=options)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", default="127.0.0.1:50052", help="learner address host:port")
    parser.add_argument("--state", type=float, nargs="+", required=True, help="raw environment state")
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds per call")
    parser.add_argument("--tls-ca", help="trust this CA (PEM) and speak TLS")
    parser.add_argument("--tls-client-cert", help="mutual TLS: this client's certificate (PEM)")
    parser.add_argument("--tls-client-key", help="mutual TLS: its private key (PEM)")
    parser.add_argument("--tls-server-name", help="the name in the server's certificate, if not the target's host")
    parser.add_argument("--token-file", default=os.environ.get("LCRL_TOKEN_FILE"),
                        help="send `authorization: Bearer <token>` from this file (default: $LCRL_TOKEN_FILE)")
    args = parser.parse_args()

    metadata = []
    if args.token_file:
        token = pathlib.Path(args.token_file).read_text().strip()
        metadata.append(("authorization", f"Bearer {token}"))

    with open_channel(args) as channel:
        try:
            health = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service="lcrl.v1.Policy"), timeout=args.timeout
            )
            status = health_pb2.HealthCheckResponse.ServingStatus.Name(health.status)
            print(f"health lcrl.v1.Policy: {status}")
            if health.status != health_pb2.HealthCheckResponse.SERVING:
                return 1
            reply = lcrl_pb2_grpc.PolicyStub(channel).Act(
                lcrl_pb2.ActRequest(state=args.state), timeout=args.timeout, metadata=metadata
            )
        except grpc.RpcError as error:
            print(f"error: {error.code().name}: {error.details()}", file=sys.stderr)
            return 2
    print(f"policy version {reply.policy_version}")
    print("action " + " ".join(f"{a:.6f}" for a in reply.action))
    return 0


if __name__ == "__main__":
    sys.exit(main())
