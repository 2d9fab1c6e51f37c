#!/usr/bin/env python3
"""Call lcrl.v1.Policy/Act knowing nothing but the server's address.

No generated stubs: the service list and every message descriptor come from
the server's reflection service, through grpcio's own `grpcio-reflection`
client (which speaks grpc.reflection.v1alpha), as generic tooling does.

    .venv/bin/python clients/python/reflect_act.py --target 127.0.0.1:50052 --token-file RUN/token --state 0.1 0.2 0.3

It takes the same connection flags as lcrl_client.py (lcrl_connect.py).
"""

import argparse
import pathlib
import sys

import grpc
from google.protobuf import descriptor_pool, message_factory
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from lcrl_connect import add_connection_args, open_channel  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_connection_args(parser)
    parser.add_argument("--state", type=float, nargs="+", required=True, help="raw environment state, all of its numbers")
    args = parser.parse_args()

    with open_channel(args) as channel:
        try:
            database = ProtoReflectionDescriptorDatabase(channel)
            services = sorted(database.get_services())
            print("services " + " ".join(services))
            pool = descriptor_pool.DescriptorPool(database)
            method = pool.FindServiceByName("lcrl.v1.Policy").FindMethodByName("Act")
            request_class = message_factory.GetMessageClass(method.input_type)
            reply_class = message_factory.GetMessageClass(method.output_type)
            act = channel.unary_unary(
                "/lcrl.v1.Policy/Act",
                request_serializer=request_class.SerializeToString,
                response_deserializer=reply_class.FromString,
            )
            reply = act(request_class(state=args.state), timeout=args.timeout)
        except grpc.RpcError as error:
            print(f"error: {error.code().name}: {error.details()}", file=sys.stderr)
            return 2
    print(f"policy version {reply.policy_version}")
    print("action " + " ".join(f"{a:.6f}" for a in reply.action))
    return 0


if __name__ == "__main__":
    sys.exit(main())
