"""One way for lcrl's Python clients to reach a server: plain text or TLS
(mutual with a client certificate), and the bearer token on every call.

The flags are those `lcrl run` prints beside its learner's address
(`--token-file RUN/token`, and `--tls-ca`, `--tls-client-cert`,
`--tls-client-key` for a TLS run), so a printed command can be pasted.
"""

import argparse
import os
import pathlib

import grpc


def add_connection_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--target", default="127.0.0.1:50052", help="server address host:port")
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds per call")
    parser.add_argument("--tls-ca", help="trust this CA (PEM) and speak TLS")
    parser.add_argument("--tls-client-cert", help="mutual TLS: this client's certificate (PEM)")
    parser.add_argument("--tls-client-key", help="mutual TLS: its private key (PEM)")
    parser.add_argument("--tls-server-name", help="the name in the server's certificate, if not the target's host")
    parser.add_argument("--token-file", default=os.environ.get("LCRL_TOKEN_FILE"),
                        help="send `authorization: Bearer <token>` from this file on every call (default: $LCRL_TOKEN_FILE)")


class _Bearer(grpc.UnaryUnaryClientInterceptor, grpc.UnaryStreamClientInterceptor,
              grpc.StreamUnaryClientInterceptor, grpc.StreamStreamClientInterceptor):
    """Adds the token to every call, reflection's streams included."""

    def __init__(self, token: str):
        self._header = ("authorization", f"Bearer {token}")

    def _with_token(self, details):
        metadata = list(details.metadata or []) + [self._header]
        return details._replace(metadata=metadata) if hasattr(details, "_replace") else _Details(details, metadata)

    def intercept_unary_unary(self, continuation, details, request):
        return continuation(self._with_token(details), request)

    def intercept_unary_stream(self, continuation, details, request):
        return continuation(self._with_token(details), request)

    def intercept_stream_unary(self, continuation, details, requests):
        return continuation(self._with_token(details), requests)

    def intercept_stream_stream(self, continuation, details, requests):
        return continuation(self._with_token(details), requests)


class _Details(grpc.ClientCallDetails):
    def __init__(self, details, metadata):
        self.method = details.method
        self.timeout = details.timeout
        self.metadata = metadata
        self.credentials = details.credentials
        self.wait_for_ready = getattr(details, "wait_for_ready", None)
        self.compression = getattr(details, "compression", None)


def open_channel(args) -> grpc.Channel:
    """The channel the flags describe, carrying the token if one is given."""
    if args.tls_ca:
        read = lambda path: pathlib.Path(path).read_bytes() if path else None  # noqa: E731
        credentials = grpc.ssl_channel_credentials(
            root_certificates=read(args.tls_ca),
            private_key=read(args.tls_client_key),
            certificate_chain=read(args.tls_client_cert),
        )
        options = [("grpc.ssl_target_name_override", args.tls_server_name)] if args.tls_server_name else []
        channel = grpc.secure_channel(args.target, credentials, options=options)
    else:
        channel = grpc.insecure_channel(args.target)
    if args.token_file:
        token = pathlib.Path(args.token_file).read_text().strip()
        channel = grpc.intercept_channel(channel, _Bearer(token))
    return channel
