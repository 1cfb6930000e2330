#!/bin/bash
# Training under a memory budget, end to end (docs/solver.md, "Checkpointed backprop"):
# (a) a 1024-node S¹ SIS dataset trained with 1000 fixed steps over the whole horizon at
#     batch 8, which plain backprop would need ~34 GiB for, under --memory-budget 4GiB;
# (b) a run that stores ~7 GiB with plain backprop, against the same run under
#     --memory-budget 1.5GiB: peak RSS and per-epoch losses side by side.
# Peak memory: /usr/bin/time -v's maximum resident set size. One torch thread per run.
# Usage: bash bench/memory_training.sh [WORK]   (about 15 minutes of one core)
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"  # this checkout's package, on its interpreter
M() { PYTHONPATH="$ROOT" "${PYTHON:-$ROOT/.venv/bin/python}" -m mpnode_cli "$@"; }
W="${1:-bench/.runs/memory-training}"
mkdir -p "$W" && cd "$W"
[ -f sis1024.h5 ] || M generate sis --topology s1 --nodes 1024 -p gamma=2.5 \
  --trajectories 12 --t-end 10 --dt 0.1 --seed 3 --graph-seed 3 -o sis1024.h5 -y --threads 1
run() {  # NAME OPTIONS...: train 2 epochs at batch 8 over the whole horizon, seed 0
  local name=$1; shift
  rm -rf "$name"
  /usr/bin/time -v env PYTHONPATH="$ROOT" "${PYTHON:-$ROOT/.venv/bin/python}" -m mpnode_cli \
    train sis1024.h5 --epochs 2 --batch-size 8 --no-horizon-curriculum \
    --run-dir "$name" --no-plots --threads 1 --seed 0 "$@" > "$name.log" 2>&1
  python3 - "$name" <<'PY'
import json, re, sys
name = sys.argv[1]
log = open(f"{name}.log").read()
peak = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", log)[1]) / 2**20
rows = [json.loads(line) for line in open(f"{name}/metrics.jsonl")]
print(f"| {name} | {peak:.2f} | " + " | ".join(
    f"{r['train_loss']!r} / {r['val_loss']!r}" for r in rows if r["epoch"] > 0) + " |")
PY
}
echo "| run | peak GiB | epoch 1: train / validation loss | epoch 2: train / validation loss |"
echo "|---|---:|---|---|"
run a-1000-steps-4GiB --fixed-dt 0.01 --memory-budget 4GiB
run b-200-steps-plain --fixed-dt 0.08
run b-200-steps-1.5GiB --fixed-dt 0.08 --memory-budget 1.5GiB
