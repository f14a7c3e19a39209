#!/usr/bin/env bash
# Thesis Table 4.1 at a reduced scale that fits a 2-core machine (see notebooks/03 section 7):
#   ARS V2-t, thesis alpha 0.02 and sigma 0.025, but N = 8 directions and b = 4 kept (thesis 50 / 20;
#   Mania et al. 2018 Table 9 use 8 / 4 for Hopper), reward shift 1 for Hopper (Mania et al.; on Walker2d it taught seed 0 to fall at once, so none there),
#   P identity epochs, then C more epochs from that checkpoint with identity, mesh-lower and mesh-upper
#   (thesis: 750 + 250). One process per lane, serial backend.
# usage: notebooks/data/ch4/run_table41.sh ENV SEED [P] [C]      (writes runs/ch4/ENV-sSEED/...)
set -euo pipefail
env_id=$1; seed=$2; P=${3:-100}; C=${4:-40}
case $env_id in Hopper-v5) shift_=1 ;; *) shift_=0 ;; esac
root=runs/ch4/$env_id-s$seed
common=(--seed "$seed" --backend serial --quiet --set n_directions=8 --set top_directions=4 --set reward_shift=$shift_)
hc=${HYBRIDCTL:-.venv/bin/hybridctl}
if [ ! -f "$root/pretrain/eval.json" ]; then
  $hc train ars "$env_id" "${common[@]}" --epochs "$P" --out "$root/pretrain" --resume
fi
for pp in identity mesh-lower mesh-upper; do
  if [ ! -f "$root/$pp/eval.json" ]; then
    if ls "$root/$pp"/checkpoint* >/dev/null 2>&1; then
      $hc train ars "$env_id" "${common[@]}" --epochs $((P + C)) --postprocess $pp --out "$root/$pp" --resume
    else
      $hc train ars "$env_id" "${common[@]}" --epochs $((P + C)) --postprocess $pp --init "$root/pretrain/final" --out "$root/$pp"
    fi
  fi
done
