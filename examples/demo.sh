#!/usr/bin/env bash
# `make demo`: a small end-to-end run on a fresh clone (about 3 minutes on 2 cores).
set -euo pipefail
cd "$(dirname "$0")/.."
MPNODE=.venv/bin/mpnode
PY=.venv/bin/python
DATA=datasets/demo
RUN=runs/demo-lorenz3

echo "== mpnode --version"; $MPNODE --version
echo "== mpnode --help";    $MPNODE --help
echo "== the batched Tsit5 solver against scipy"; $PY examples/solver_demo.py

# Short horizons (0.5 s) keep the demo to minutes; the paper's sets are `--preset lorenz3`.
echo "== generate: coupled Lorenz on 3 nodes (training) and on 5 and 7 nodes (zero-shot)"
$MPNODE generate lorenz --nodes 3 --trajectories 400 --t-end 0.5 --out $DATA/lorenz3.h5 --force
$MPNODE generate lorenz --nodes 5 --trajectories 100 --t-end 0.5 --seed 1 \
    --out $DATA/lorenz5.h5 --force
$MPNODE generate lorenz --nodes 7 --trajectories 100 --t-end 0.5 --seed 2 \
    --out $DATA/lorenz7.h5 --force

echo "== train MP-NODE on lorenz3 (200 epochs; the paper trains 4000)"
rm -rf $RUN
$MPNODE train $DATA/lorenz3.h5 --epochs 200 --lr 1e-2 --batch-size 32 --patience 50 \
    --run-dir $RUN

echo "== evaluate the best checkpoint on the test split (plots in $RUN/plots)"
$MPNODE evaluate $RUN/checkpoints/best.pt $DATA/lorenz3.h5 --plot

echo "== zero-shot: the same node network on 5 and 7 coupled systems, no training"
$MPNODE zeroshot $RUN/checkpoints/best.pt $DATA/lorenz3.h5 $DATA/lorenz5.h5 $DATA/lorenz7.h5

echo "== compare runs"
$MPNODE compare $RUN
