#!/usr/bin/env bash
# Parity of the distributed service with `lcrl train` (docs/scaling.md,
# "Parity"): one preset and its seeds through `lcrl train` and through `lcrl
# run` with 1, 2 and 4 actors, one run at a time, then a table of the eval
# return, the runs above the best constant, training safety (failed episodes,
# the worst 10-episode mean, the peak training force) and the wall time of
# each loop.
#
#   bash scripts/parity.sh [PRESET] [SEEDS] [ACTOR COUNTS...]
#   bash scripts/parity.sh configs/peg-group1-ppo-local.toml 3 1 2 4
#   LCRL_BIN_DIR=/tmp/lcrl-bin bash scripts/parity.sh ...   (binaries copied there)
#   SEED_FROM=5 bash scripts/parity.sh PRESET 5 2   (seeds 5-9; the table covers every seed folder there)
#   MAX_STALENESS=0 bash scripts/parity.sh PRESET 5 1 2 4   (PPO on-policy: lcrl run --max-staleness 0, not the
#                                                          preset's default of 1; runs go to runs/parity/<preset>-lag0/)
#
# Runs go to runs/parity/<preset>/<loop>/seed<k>; the table is printed and
# written to runs/parity/<preset>/parity.md. A run folder that already holds
# summary.json is kept (rerun after an interruption to finish the rest).
set -euo pipefail
cd "$(dirname "$0")/.."
preset=${1:-configs/peg-group1-ppo-local.toml}
seeds=${2:-3}
shift $(( $# < 2 ? $# : 2 ))
actor_counts=("$@")
[[ ${#actor_counts[@]} -gt 0 ]] || actor_counts=(1 2 4)
[[ -f $preset ]] || { echo "parity.sh: no preset $preset" >&2; exit 2; }
[[ $seeds =~ ^[1-9][0-9]*$ ]] || { echo "parity.sh: SEEDS must be a positive number, not '$seeds'" >&2; exit 2; }
seed_from=${SEED_FROM:-0}
[[ $seed_from =~ ^[0-9]+$ ]] || { echo "parity.sh: SEED_FROM must be a seed number, not '$seed_from'" >&2; exit 2; }
# LCRL_BIN_DIR: binaries copied elsewhere (lcrl and the lcrl-* it starts),
# so that a long comparison is not broken by rebuilding target/debug.
if [[ -n ${LCRL_BIN_DIR:-} ]]; then
  lcrl=$LCRL_BIN_DIR/lcrl
  [[ -x $lcrl ]] || { echo "parity.sh: no lcrl in LCRL_BIN_DIR=$LCRL_BIN_DIR" >&2; exit 2; }
else
  bash scripts/setup.sh >/dev/null
  cargo build --workspace --bins
  lcrl=target/debug/lcrl
fi
name=$(basename "$preset" .toml)
max_staleness=${MAX_STALENESS:-}
[[ -z $max_staleness || $max_staleness =~ ^[0-9]+$ ]] || { echo "parity.sh: MAX_STALENESS must be a number of versions, not '$max_staleness'" >&2; exit 2; }
lag_args=()
[[ -n $max_staleness ]] && lag_args=(--max-staleness "$max_staleness")
out=runs/parity/$name${max_staleness:+-lag$max_staleness}
mkdir -p "$out/presets"
read -r env algo connection episodes < <(python3 -c 'import sys, tomllib; j = tomllib.load(open(sys.argv[1], "rb"))["job"]; print(j["env"], j["algo"], j["connection"], j["episodes"])' "$preset")

# The preset with `seed = K` in its [run] table (added when it has none),
# and its training sections alone for `lcrl train --config` (the budget,
# [job] episodes, goes to `lcrl train --episodes`).
with_seed() {
  awk -v seed="$2" '
    /^\[run\][[:space:]]*$/ { print; print "seed = " seed; done = 1; next }
    /^seed[[:space:]]*=/ && in_run { next }
    /^\[/ { in_run = ($0 ~ /^\[run\]/) }
    { print }
    END { if (!done) { print "\n[run]\nseed = " seed } }' "$1"
}
training_sections() {
  awk '/^\[job\]/ { skip = 1; next } /^\[/ { skip = 0 } !skip' "$1"
}

for seed in $(seq "$seed_from" $((seed_from + seeds - 1))); do
  seeded=$out/presets/seed$seed.toml
  # Relative paths in the preset (headroom, graph) stay relative to its folder.
  with_seed "$preset" "$seed" | sed "s#\"\.\./#\"$(cd "$(dirname "$preset")/.." && pwd)/#g" > "$seeded"
  training_sections "$seeded" > "$out/presets/seed$seed-train.toml"
  dir=$out/train/seed$seed
  if [[ ! -f $dir/summary.json ]]; then
    rm -rf "$dir"
    echo "== lcrl train, seed $seed"
    "$lcrl" train --env "$env" --algo "$algo" --connection "$connection" --episodes "$episodes" --config "$out/presets/seed$seed-train.toml" --run-dir "$dir" >/dev/null
  fi
  for actors in "${actor_counts[@]}"; do
    dir=$out/run$actors/seed$seed
    if [[ ! -f $dir/summary.json ]]; then
      rm -rf "$dir"
      echo "== lcrl run --actors $actors, seed $seed"
      "$lcrl" run --config "$seeded" --actors "$actors" --run-dir "$dir" "${lag_args[@]}" >/dev/null
    fi
  done
done

python3 - "$out" "${actor_counts[@]}" <<'EOF'
import csv, json, pathlib, statistics, sys

out = pathlib.Path(sys.argv[1])
loops = ["train"] + [f"run{a}" for a in sys.argv[2:]]

def metrics(run):
    path = run / "metrics.csv" if (run / "metrics.csv").is_file() else run / "learner" / "metrics.csv"
    with open(path) as f:
        return list(csv.DictReader(f))

def interval(values):
    m = statistics.fmean(values)
    if len(values) < 2:
        return f"{m:.3f}"
    half = 1.96 * statistics.stdev(values) / len(values) ** 0.5
    return f"{m:.3f} [{m - half:.3f}, {m + half:.3f}]"

def peak_force(rows):
    # Runs from before the actors reported forces leave the column empty.
    forces = [float(r["peak_force_n"]) for r in rows if r.get("peak_force_n")]
    return max(forces) if forces else None

lines = ["| loop | seeds | eval return (mean [≈95% CI]) | above the best constant | failed training episodes | worst 10-episode mean | peak training force, N (highest) | wall s |",
         "|---|---|---|---|---|---|---|---|"]
for loop in loops:
    runs = sorted((out / loop).glob("seed*/summary.json"))
    if not runs:
        continue
    evals, above, failed, episodes, worst, peaks, wall = [], 0, 0, 0, [], [], []
    for path in runs:
        s = json.loads(path.read_text())
        evals.append(s["eval_return"])
        bar = next((r["mean_return"] for r in s.get("references", []) if r["controller"] == "best constant"), None)
        above += bar is not None and s["eval_return"] > bar
        rows = metrics(path.parent)
        returns = [float(r["return"]) for r in rows]
        failed += sum(r["success"] == "false" for r in rows)
        episodes += len(rows)
        worst.append(min(statistics.fmean(returns[k:k + 10]) for k in range(max(1, len(returns) - 9))))
        peaks.append(peak_force(rows))
        wall.append(s["total_seconds"])
    name = "lcrl train" if loop == "train" else f"lcrl run, {loop[3:]} actor(s)"
    measured = [p for p in peaks if p is not None]
    peak = f"{statistics.fmean(measured):.1f} ({max(measured):.1f})" if len(measured) == len(peaks) else "not recorded"
    lines.append(f"| {name} | {len(runs)} | {interval(evals)} | {above} of {len(runs)} | {failed} of {episodes} | {statistics.fmean(worst):.3f} (lowest {min(worst):.3f}) | {peak} | {statistics.fmean(wall):.1f} |")
table = "\n".join(lines)
(out / "parity.md").write_text(table + "\n")
print(table)
EOF
