#!/usr/bin/env bash
# The settings search of docs/research/2026-12-04-peers-search-design.md: each
# candidate on peg-group1, search seeds 300-301 (resumable: finished runs are skipped).
#   bash scripts/peers-search.sh
cd "$(dirname "$0")/.."
zoo_td3='"gamma": 0.98, "buffer_size": 200000, "noise_type": "normal", "noise_std": 0.1, "gradient_steps": -1, "train_freq": [1, "episode"], "learning_rate": 0.001, "policy_kwargs": {"net_arch": [400, 300]}'
declare -A S=(
 [sac-default]='sac|{}'
 [sac-zoo]='sac|{"learning_rate": 0.001}'
 [sac-zoo-starts]='sac|{"learning_rate": 0.001, "learning_starts": 1000}'
 [td3-default]='td3|{}'
 [td3-noise]='td3|{"noise_type": "normal", "noise_std": 0.1}'
 [td3-zoo]="td3|{$zoo_td3, \"learning_starts\": 5000}"
 [td3-zoo-starts]="td3|{$zoo_td3, \"learning_starts\": 1000}"
)
# `bash scripts/peers-search.sh ppo`: SB3's PPO search instead
# (docs/research/2026-12-04-peers-ppo-search-design.md), 900 episodes;
# SEEDS="300" and SEEDS="301" split it between two workers.
zoo_ppo='"n_steps": 1024, "gae_lambda": 0.95, "gamma": 0.9, "n_epochs": 10, "ent_coef": 0.0, "learning_rate": 0.001, "clip_range": 0.2'
S[ppo-default]='ppo|{}'
S[ppo-zoo]="ppo|{$zoo_ppo, \"use_sde\": true, \"sde_sample_freq\": 4}"
S[ppo-zoo-nosde]="ppo|{$zoo_ppo}"
S[ppo-lcrl]='ppo|{"learning_rate": "lin_3e-4", "policy_kwargs": {"net_arch": {"pi": [256, 256], "vf": [256, 256]}, "activation_fn": "elu"}}'
# One SB3 run of candidate NAME: run NAME ENV SEED EPISODES OUT (skipped
# when OUT holds its summary.json; a failure is reported and the rest go on).
run() {
  local name=$1 env=$2 seed=$3 episodes=$4 out=$5 algo settings
  [ -f "$out/summary.json" ] && return 0
  IFS='|' read -r algo settings <<< "${S[$name]}"
  nice -n 19 .venv/bin/python scripts/sb3_peers.py --env "$env" --algo "$algo" --seed "$seed" --episodes "$episodes" --settings "$settings" --out "$out" || echo "FAILED $name $env $seed" >&2
}
if [ "${1:-}" = ppo ]; then
  for seed in ${SEEDS:-300 301}; do
    for name in ppo-default ppo-zoo ppo-zoo-nosde ppo-lcrl; do
      run $name peg-group1 $seed 900 runs/peers/sb3-search/peg-group1/$name/seed$seed
    done
  done
  exit 0
fi
# `bash scripts/peers-search.sh ppo-pick NAME`: the PPO search's pick on the
# table's seeds (the design's step 3; SEEDS splits it as above).
if [ "${1:-}" = ppo-pick ]; then
  name=${2:?ppo-pick needs the picked candidate}
  case $name in
    ppo-default) echo "peers-search: the pick is SB3's defaults, whose table row has run: nothing to add"; exit 0 ;;
    ppo-*) [ -n "${S[$name]:-}" ] || { echo "peers-search: no PPO candidate $name" >&2; exit 2; } ;;
    *) echo "peers-search: ppo-pick takes a PPO candidate (ppo-zoo, ppo-zoo-nosde, ppo-lcrl), not $name" >&2; exit 2 ;;
  esac
  for seed in ${SEEDS:-200 201 202 203 204}; do
    for env in peg-group1 peg-group2; do
      run $name $env $seed 900 runs/peers/sb3/$env/$name/seed$seed
    done
  done
  exit 0
fi
for seed in 300 301; do
  for name in sac-default td3-default sac-zoo td3-noise sac-zoo-starts td3-zoo td3-zoo-starts; do
    run $name peg-group1 $seed 200 runs/peers/sb3-search/peg-group1/$name/seed$seed
  done
done

# The picks on the table's seeds (the design's step 3): SAC's pick was its
# defaults (its table row); TD3's, td3-zoo-starts.
for seed in 200 201 202 203 204; do
  for env in peg-group1 peg-group2; do
    run td3-zoo-starts $env $seed 200 runs/peers/sb3/$env/td3-zoo-starts/seed$seed
  done
done
