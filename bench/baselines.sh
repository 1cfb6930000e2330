#!/usr/bin/env bash
# MP-NODE and its three baselines on gene-ba-4x4, at a scale a CI machine (2 CPU cores) can
# run in a few minutes: the paper-scale dataset (200 trajectories over 5 BA graphs), 40
# epochs each, and an L2S reduced to latent/hidden 32 and 5 message-passing steps (the full
# 128-wide, 10-step L2S takes minutes per epoch here). Writes bench/results/baselines.md.
set -euo pipefail
cd "$(dirname "$0")/.."
MPNODE=${MPNODE:-.venv/bin/mpnode}
EPOCHS=${EPOCHS:-40}
OUT=runs/baselines
DATA=datasets/gene-ba-4x4.h5
rm -rf "$OUT" && mkdir -p "$OUT"
$MPNODE generate --preset gene-ba-4x4 --out "$DATA" --force
common=(--epochs "$EPOCHS" --seed 0 --no-plots)
$MPNODE train "$DATA" --model mpnode "${common[@]}" --run-dir "$OUT/mpnode"
$MPNODE train "$DATA" --model gnode "${common[@]}" --run-dir "$OUT/gnode"
$MPNODE train "$DATA" --model node "${common[@]}" --run-dir "$OUT/node"
$MPNODE train "$DATA" --model l2s --latent 32 --hidden 32 --steps 5 "${common[@]}" \
  --run-dir "$OUT/l2s"
{
  echo "# Baselines on gene-ba-4x4 (CI scale)"
  echo
  echo "Command: \`bash bench/baselines.sh\` (EPOCHS=$EPOCHS). Dataset: preset gene-ba-4x4"
  echo "(200 trajectories, 5 BA graphs, 16 nodes, 51 samples; split 140/30/30). All models"
  echo "get the same data, normalization, batch 128, Adam 1e-3, seed 0; MP-NODE, GNN-ODE and"
  echo "NODE train on whole-horizon rollouts (Huber), L2S one step ahead (MSE on normalized"
  echo "differences, random-walk input noise 3e-3) and is validated and tested by"
  echo "autoregressive rollout. L2S is reduced (latent/hidden 32, 5 steps) to fit CI time."
  echo "val loss = Huber of the whole-horizon rollout; test MSE in normalized units."
  echo
  echo '```'
  COLUMNS=150 $MPNODE compare "$OUT/mpnode" "$OUT/gnode" "$OUT/node" "$OUT/l2s"
  echo '```'
} > bench/results/baselines.md
cat bench/results/baselines.md
