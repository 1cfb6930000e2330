#!/usr/bin/env bash
# `make demo`: a small end-to-end run on a fresh clone. It grows as the verbs land.
set -euo pipefail
cd "$(dirname "$0")/.."
MPNODE=.venv/bin/mpnode
PY=.venv/bin/python

echo "== mpnode --version"; $MPNODE --version
echo "== mpnode --help";    $MPNODE --help
echo "== the batched Tsit5 solver against scipy"; $PY examples/solver_demo.py
