# Two commands do all set-up on a fresh clone: `make demo` and `make test`.
PY      := .venv/bin/python
STAMP   := .venv/.installed
TORCH   := torch==2.13.0

.PHONY: setup demo test lint bench bench-quality clean

setup: $(STAMP)

# torch is pinned and installed first: a CPU build of this version is available locally,
# while an unpinned torch would pull gigabytes of CUDA packages.
$(STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q --no-compile $(TORCH)
	$(PY) -m pip install -q --no-compile -e '.[dev]'
	@# pip byte-compiles every file it installs (torch alone: ~50 s of a 2-core machine's
	@# set-up); --no-compile skips that, and importing what mpnode uses compiles only those
	@# modules (~15 s), even where PYTHONDONTWRITEBYTECODE is set.
	env -u PYTHONDONTWRITEBYTECODE $(PY) -c "import torch, torch._dynamo, torch.distributed, \
	  numpy, h5py, matplotlib.pyplot, networkx, rich, typer, pydantic, mpnode_cli.cli.app"
	touch $(STAMP)

demo: $(STAMP)
	bash examples/demo.sh

# Two test processes (pytest-xdist), one per core, each on one torch thread (tests/conftest.py);
# a file's tests stay together so its module-scoped fixtures (datasets, trained runs) are built
# once. `make test TEST_WORKERS=0` runs them in this process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

lint: $(STAMP)
	$(PY) -m ruff check mpnode_cli tests bench examples

# Benchmarks print tables and write bench/results/*.md (minutes; run on a quiet machine).
# The baselines comparison is separate: `bash bench/baselines.sh` (about 10 minutes).
bench: $(STAMP)
	$(PY) -m pip install -q -e '.[dev,bench]'
	$(PY) bench/solver.py
	$(PY) bench/generate.py
	$(PY) bench/train.py
	$(PY) bench/l2s_step.py

# The paper's experiments at fixed epoch budgets beside naive baselines; writes
# bench/results/quality.md (about an hour on 2 cores: `$(PY) bench/quality.py --plan`).
bench-quality: $(STAMP)
	$(PY) -m pip install -q -e '.[dev,bench]'
	$(PY) bench/quality.py

clean:
	rm -rf .venv build *.egg-info .pytest_cache .ruff_cache
