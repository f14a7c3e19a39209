#!/bin/bash
# idle re-measurements for issue 15, run after the SSAC seeds (nothing else on the machine)
cd "$(git rev-parse --show-toplevel)"   # the repository root
while pgrep -f run_seeds.sh > /dev/null; do sleep 10; done
log=runs/idle/schedule.log
step() { echo "$1 start $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)" >> $log; shift; /usr/bin/time -f "wall %e s" "$@"; echo "  end $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg) rc $?" >> $log; }
echo "commit $(git rev-parse --short HEAD)" >> $log
step balance_map_drake .venv/bin/hybridctl balance-map acrobot --controller ssac:models/policies/ssac-acrobot --grid 41 --workers 2 --out runs/idle/balance_map_drake > runs/idle/balance_map_drake.log 2>&1
step balance_map_torch .venv/bin/hybridctl balance-map acrobot --controller ssac:models/policies/ssac-acrobot --grid 41 --engine torch --out runs/idle/balance_map_torch > runs/idle/balance_map_torch.log 2>&1
step dynamics .venv/bin/python benchmarks/dynamics.py --out runs/idle/dynamics.json > runs/idle/dynamics.log 2>&1
step mujoco .venv/bin/python benchmarks/mujoco_rollout.py --repeats 3 --out runs/idle/mujoco_rollout.json > runs/idle/mujoco_rollout.log 2>&1
step training .venv/bin/python benchmarks/training.py --out runs/idle/training.json > runs/idle/training.log 2>&1
echo "all done $(date -u +%FT%TZ)" >> $log
