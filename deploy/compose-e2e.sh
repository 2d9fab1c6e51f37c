#!/usr/bin/env bash
# End-to-end check of deploy/compose.yaml on this machine's Docker engine:
# builds the image, starts graph builder + learner + 2 actors on the linear
# preset through deploy/compose.sh (which generates the token), checks the
# safe defaults (ports on 127.0.0.1 only, the token required, no container
# running as root), checks training progresses (GetStatus), kills one actor
# container and checks the learner keeps training and the restarted actor
# rejoins, then tears everything down. Skips (exit 0, with a message) when no Docker
# engine or docker-compose is available.
#   bash deploy/compose-e2e.sh
set -euo pipefail
# A command failing under set -e says where, before the logs (cleanup).
trap 'echo "compose-e2e: failed at line $LINENO: $BASH_COMMAND" >&2' ERR
cd "$(dirname "$0")/.."
started=$(date +%s)
if ! command -v docker >/dev/null || ! docker info >/dev/null 2>&1; then
  echo "compose-e2e: SKIPPED: no Docker engine reachable (docker info failed)"
  exit 0
fi
if command -v docker-compose >/dev/null; then
  compose=(docker-compose)
elif docker compose version >/dev/null 2>&1; then
  compose=(docker compose)
else
  echo "compose-e2e: SKIPPED: neither docker-compose nor the docker compose plugin is installed"
  exit 0
fi

bash deploy/build-image.sh lcrl:local
lcrl=target/debug/lcrl
project="lcrl-e2e-$$"
run_dir="$(mktemp -d /tmp/lcrl-compose-XXXXXX)"
# compose.sh generates the token here at set-up.
export LCRL_SECRETS_DIR="$run_dir/secrets"
# A budget the test never reaches: it checks that training goes on through
# a lost and a rejoined actor, so the learner must not finish meanwhile.
export LCRL_PRESET=lti-paper.toml LCRL_RUN_DIR="$run_dir/run" LCRL_RUN_ID="e2e-$$" LCRL_EPISODES=100000000
dc() { bash deploy/compose.sh -p "$project" "$@"; }
cleanup() {
  status=$?
  if [ $status -ne 0 ]; then
    echo "compose-e2e: FAILED; container logs follow" >&2
    dc logs --no-color --tail 40 >&2 || true
  fi
  dc down -v --remove-orphans >/dev/null 2>&1 || true
  rm -rf "$run_dir"
  exit $status
}
trap cleanup EXIT

fail() { echo "compose-e2e: FAILED: $*" >&2; exit 1; }
# field NAME: one number from the learner's status.
status() { "$lcrl" status "$url" --token-file "$LCRL_SECRETS_DIR/token"; }
field() { status | python3 -c "import json,sys; print(json.load(sys.stdin)['$1'])"; }
# wait_until SECONDS DESCRIPTION COMMAND...: polls until COMMAND succeeds.
wait_until() {
  local limit=$1 what=$2; shift 2
  local deadline=$(( $(date +%s) + limit ))
  until "$@"; do
    [ "$(date +%s)" -lt "$deadline" ] || fail "$what (waited ${limit} s; last status: $(status 2>&1))"
    sleep 1
  done
}

dc up -d --scale actor=2
[ -s "$LCRL_SECRETS_DIR/token" ] || fail "compose.sh generated no token"
learner_port=$(dc port learner 50052)
case "$learner_port" in 127.0.0.1:*) ;; *) fail "the learner is published on $learner_port, not on 127.0.0.1 only" ;; esac
url="http://$learner_port"
metrics="http://$(dc port learner 9090)/metrics"
echo "compose-e2e: stack up, learner at $url"
for container in $(dc ps -q); do
  user=$(docker inspect -f '{{.Config.User}}' "$container")
  case "$user" in ""|0|0:*|root|root:*) fail "container ${container:0:12} runs as root (user '$user')" ;; esac
done

actors_are() { [ "$(field connected_actors)" = "$1" ]; }
steps_above() { [ "$(field env_steps)" -gt "$1" ]; }
updates_above() { [ "$(field updates)" -gt "$1" ]; }
wait_until 120 "2 actors connected" actors_are 2
steps=$(field env_steps)
wait_until 60 "env steps grow past $steps" steps_above "$steps"
wait_until 120 "the learner updates its networks" updates_above 0
python3 - "$metrics" <<'PY' || fail "learner /metrics lacks a metric"
import sys, urllib.request
text = urllib.request.urlopen(sys.argv[1], timeout=10).read().decode()
for name in ("lcrl_learner_env_steps_total", "lcrl_learner_updates_total", "lcrl_learner_policy_version", "lcrl_learner_act_latency_seconds_bucket"):
    assert name in text, name
PY
echo "compose-e2e: training: $(status)"
# The generated token guards the plain stack too.
if "$lcrl" status "$url" >/dev/null 2>&1; then fail "the learner answered a client without the token"; fi

# sed, not head: head exits after one line, and under pipefail a compose
# still writing the next one dies of SIGPIPE and fails the pipeline.
victim=$(dc ps -q actor | sed -n 1p)
[ -n "$victim" ] || fail "no actor container is listed"
docker kill "$victim" >/dev/null
echo "compose-e2e: killed actor container ${victim:0:12}"
wait_until 60 "the learner notices the lost actor" actors_are 1
steps=$(field env_steps); updates=$(field updates)
wait_until 60 "env steps grow with one actor" steps_above "$steps"
wait_until 60 "updates grow with one actor" updates_above "$updates"
[ "$(docker inspect -f '{{.State.Running}}' "$(dc ps -q learner)")" = true ] || fail "the learner container stopped"
echo "compose-e2e: learner kept training with one actor: $(status)"

docker start "$victim" >/dev/null
wait_until 120 "the restarted actor rejoins" actors_are 2
steps=$(field env_steps)
wait_until 60 "env steps grow after the rejoin" steps_above "$steps"
[ "$(docker logs "$victim" 2>&1 | grep -c "connected")" -ge 2 ] || fail "the restarted actor's log shows no second connection"
# Same container, same host name: its new batches must not pass for replays.
[ "$(status | python3 -c "import json,sys; print(json.load(sys.stdin)['rejected'].get('duplicate', 0))")" = 0 ] || fail "the restarted actor's batches were taken for duplicates"
echo "compose-e2e: restarted actor rejoined: $(status)"

# The secure stack (compose.secure.yaml): TLS between all containers, the
# token on every call; the learner refuses a client without the token.
dc down -v --remove-orphans >/dev/null 2>&1
certs="$run_dir/certs"
"$lcrl" certs --out "$certs" >/dev/null
export LCRL_TLS_DIR="$certs" LCRL_RUN_ID="e2e-tls-$$"
dc() { bash deploy/compose.sh -p "$project" -f deploy/compose.secure.yaml "$@"; }
dc up -d --scale actor=1
url="https://$(dc port learner 50052)"
tls=(--tls-ca "$certs/ca.pem" --tls-client-cert "$certs/client.pem" --tls-client-key "$certs/client.key")
status() { "$lcrl" status "$url" "${tls[@]}" --token-file "$certs/token"; }
wait_until 120 "1 actor connected over TLS" actors_are 1
steps=$(field env_steps)
wait_until 60 "env steps grow over TLS" steps_above "$steps"
if "$lcrl" status "$url" "${tls[@]}" >/dev/null 2>&1; then fail "the learner answered a client without the token"; fi
[ "$(status | python3 -c "import json,sys; print(json.load(sys.stdin)['unauthenticated']['missing_token'])")" -ge 1 ] || fail "the refusal was not counted"
echo "compose-e2e: secure stack trains over mutual TLS with a token: $(status)"

size=$(docker image inspect lcrl:local --format '{{.Size}}')
echo "compose-e2e: PASSED in $(( $(date +%s) - started )) s (image lcrl:local $(( size / 1000000 )) MB)"
