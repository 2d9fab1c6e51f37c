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
import pathlib
import sys

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent / "lcrl_stubs"))
from lcrl_connect import add_connection_args, open_channel  # noqa: E402
import lcrl_pb2  # noqa: E402  (generated)
import lcrl_pb2_grpc  # noqa: E402  (generated)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_connection_args(parser)
    parser.add_argument("--state", type=float, nargs="+", required=True,
                        help="raw environment state, all of its numbers (12 on the peg tasks)")
    args = parser.parse_args()

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
                lcrl_pb2.ActRequest(state=args.state), timeout=args.timeout
            )
        except grpc.RpcError as error:
            print(f"error: {error.code().name}: {error.details()}", file=sys.stderr)
            return 2
    print(f"policy version {reply.policy_version}")
    print("action " + " ".join(f"{a:.6f}" for a in reply.action))
    return 0


if __name__ == "__main__":
    sys.exit(main())
