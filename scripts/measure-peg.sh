#!/usr/bin/env bash
# The peg-in-hole measurement behind
# docs/research/2026-11-22-peg-table1-results.md: for each peg preset, the
# constant controllers (a = 0 and the tuned best constant) and DDPG local
# and global (200 episodes, seeds 0–2, Table I's settings: configs/table1-ddpg.toml), all evaluated on the same 100
# starts (`lcrl sim --episodes 100 --seed 0`). Two runs at a time.
# Usage: bash scripts/measure-peg.sh [OUT_DIR] [PRESETS...]
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-runs/measure-peg}
shift || true
presets=("${@:-peg-group1 peg-group2 peg-experiment}")
read -r -a presets <<< "${presets[*]}"
lcrl=${LCRL_BIN:-target/debug/lcrl}
mkdir -p "$out"
jobs=()
for env in "${presets[@]}"; do
  [ -f "$out/$env-tune/best_constant.json" ] || $lcrl tune --env "$env" --out "$out/$env-tune" > "$out/$env-tune.log" 2>&1
  $lcrl sim --env "$env" --episodes 100 --seed 0 --out "$out/$env-zero" > "$out/$env-zero.log" 2>&1
  action=$(python3 -c 'import json,sys; print(",".join(repr(a) for a in json.load(open(sys.argv[1]))["action"]))' "$out/$env-tune/best_constant.json")
  $lcrl sim --env "$env" --episodes 100 --seed 0 --action="$action" --out "$out/$env-best" > "$out/$env-best.log" 2>&1
  for seed in 0 1 2; do
    for conn in local global; do
      jobs+=("$env $conn $seed")
    done
  done
done
run_one() {
  read -r env conn seed <<< "$1"
  dir="$out/$env-ddpg-$conn-s$seed"
  if [ ! -f "$dir/summary.json" ]; then
    rm -rf "$dir"
    # Table I's local is the publication's T = 0.1 (a plain `local` is T_rule).
    spec=$conn; [ "$conn" = local ] && spec=local@0.1
    $lcrl train --env "$env" --algo ddpg --connection "$spec" --seed "$seed" --episodes 200 --config configs/table1-ddpg.toml --run-dir "$dir" > "$dir.log" 2>&1
  fi
  $lcrl sim --checkpoint "$dir" --episodes 100 --seed 0 --out "$dir/eval100" > "$dir.eval.log" 2>&1
}
export -f run_one
export out lcrl
printf '%s\n' "${jobs[@]}" | xargs -P 2 -I{} bash -c 'run_one "{}"'
python3 - "$out" "${presets[@]}" <<'PY'
import json, sys, statistics as st
out, presets = sys.argv[1], sys.argv[2:]
def s(path): return json.load(open(path))
print("| preset | controller | return (mean over seeds; per seed) | success | peak force N |")
print("|---|---|---|---|---|")
for env in presets:
    for label, d in [("a = 0", f"{out}/{env}-zero"), ("best constant", f"{out}/{env}-best")]:
        x = s(f"{d}/summary.json")
        print(f"| {env} | {label} | {x['mean_return']:.2f} | {100*x['success_rate']:.0f}% | {x['mean_peak_force_n']:.2f} |")
    for conn in ["local", "global"]:
        xs = [s(f"{out}/{env}-ddpg-{conn}-s{k}/eval100/summary.json") for k in range(3)]
        r = [x['mean_return'] for x in xs]
        print(f"| {env} | DDPG {conn}, 200 ep | {st.mean(r):.2f} ({', '.join(f'{v:.2f}' for v in r)}) | "
              f"{100*st.mean(x['success_rate'] for x in xs):.0f}% | {st.mean(x['mean_peak_force_n'] for x in xs):.2f} |")
PY
