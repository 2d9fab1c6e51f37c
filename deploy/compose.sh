#!/usr/bin/env bash
# docker compose for deploy/compose.yaml, after the set-up it needs:
#   bash deploy/compose.sh up --scale actor=2
#   bash deploy/compose.sh port learner 50052      # 127.0.0.1:PORT
#   bash deploy/compose.sh -f deploy/compose.secure.yaml up   # mutual TLS too
#   bash deploy/compose.sh down
# Every argument goes to docker-compose (or `docker compose`) after
# `-f deploy/compose.yaml`.
#
# The set-up (idempotent, before every command):
# - the run's token: $LCRL_SECRETS_DIR/token (default runs/compose-secrets/),
#   32 random bytes in hex, readable by its owner only, made once and kept;
#   compose.yaml mounts it read-only in every container. Clients on this
#   host pass it: lcrl status http://ADDR --token-file runs/compose-secrets/token
# - the run directory $LCRL_RUN_DIR (default runs/compose/);
# - the user the containers run as, LCRL_UID/LCRL_GID: yours, so the run
#   directory and the token stay yours; when you are root, 10001, and the
#   two folders (and $LCRL_TLS_DIR, for compose.secure.yaml) are handed to
#   it. Never 0.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
export LCRL_RUN_DIR="${LCRL_RUN_DIR:-$repo/runs/compose}"
export LCRL_SECRETS_DIR="${LCRL_SECRETS_DIR:-$repo/runs/compose-secrets}"
if [ -z "${LCRL_UID:-}" ]; then
  LCRL_UID="$(id -u)"
  LCRL_GID="${LCRL_GID:-$(id -g)}"
  if [ "$LCRL_UID" = 0 ]; then
    LCRL_UID=10001 LCRL_GID=10001
  fi
fi
export LCRL_UID LCRL_GID="${LCRL_GID:-$LCRL_UID}"
if [ "$LCRL_UID" = 0 ] || [ "$LCRL_GID" = 0 ]; then
  echo "compose: LCRL_UID/LCRL_GID 0: the containers do not run as root; unset them or name another user" >&2
  exit 1
fi

mkdir -p "$LCRL_RUN_DIR"
(umask 077 && mkdir -p "$LCRL_SECRETS_DIR")
token="$LCRL_SECRETS_DIR/token"
if [ ! -s "$token" ]; then
  if ! (umask 077 && { od -An -tx1 -N32 /dev/urandom | tr -d ' \n'; echo; } > "$token.new" && mv "$token.new" "$token"); then
    echo "compose: cannot write $token (a folder docker made as root? remove it, or set LCRL_SECRETS_DIR)" >&2
    exit 1
  fi
  echo "compose: generated the run's token: $token" >&2
fi
if [ "$(id -u)" = 0 ]; then
  chown -R "$LCRL_UID:$LCRL_GID" "$LCRL_RUN_DIR" "$LCRL_SECRETS_DIR"
  if [ -n "${LCRL_TLS_DIR:-}" ] && [ -d "$LCRL_TLS_DIR" ]; then
    chown -R "$LCRL_UID:$LCRL_GID" "$LCRL_TLS_DIR"
  fi
fi

if command -v docker-compose >/dev/null; then
  compose=(docker-compose)
else
  compose=(docker compose)
fi
exec "${compose[@]}" -f "$repo/deploy/compose.yaml" "$@"
