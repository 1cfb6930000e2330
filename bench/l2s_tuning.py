"""L2S tuned until it learns: configurations of the L2S baseline on the quadrotor swarms.

L2S (Sanchez-Gonzalez et al., ICML 2020; `mpnode_cli/models/l2s.py`) is the paper's GNN
baseline. Trained one step ahead and rolled out over a whole flight (50 steps of dt 0.2 at
the quadrotor presets), a poorly regularized L2S drifts off the data: with the experiments'
first small configuration (latent and hidden 32, 5 message-passing steps, input noise 3e-3
in normalized units, mpnode's recipe) no member beat the time-mean predictor on quad3 or
quad6. A comparison that MP-NODE wins against such a baseline says nothing, so this bench
searches the knobs that L2S itself has, each config trained with 3 seeds (an ensemble of 3
members; `mpnode train --seeds 3`) on each swarm:

- `step_noise`: the random-walk noise on the one-step inputs, which teaches the model to
  correct its own drift (Sanchez-Gonzalez et al.'s remedy for rollout error, their
  "Training noise");
- the horizon curriculum: mpnode's recipe trains on prefixes of the horizon that grow over
  the epochs, so a one-step model sees the late part of a flight only at the end; without
  it every transition is trained from the first epoch;
- the batch size: mpnode's recipe takes 32 flights a batch, 4 optimizer steps an epoch on
  105 training flights, where L2S was trained for millions of small steps;
- `unroll`: training rollouts of several steps from noisy data states, backpropagated
  through the model's own predictions (`L2S.unrolled_loss`; multi-step training, not in
  L2S as published), which trains the model against the drift its errors cause.

A config **learns** when every member's test MSE is below the time-mean predictor's (the
train split's mean at each time, on the same test flights). The table gives, per config
and swarm, the members' test MSE (mean ± std) and its ratio to the time mean, hold x(0)'s
ratio, the best epoch and the wall time. Runs are cached in `--runs` (a finished run is
not rerun) and their numbers are kept in `--records`, from which `--table-only` rebuilds
the table.

Usage:
    .venv/bin/python bench/l2s_tuning.py --configs base,unroll-5 --swarms quad3
    .venv/bin/python bench/l2s_tuning.py --table-only
Writes `bench/results/l2s-tuning.md` and `bench/results/l2s-tuning.json`.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from mpnode_cli.data.atomic import atomic_text

HERE = Path(__file__).resolve().parent
EPOCHS = 120      # the finetune-quad experiment's small budget for its quad6 runs
TRAJECTORIES = 150
SEEDS = 3
SMALL = ["--latent", "32", "--hidden", "32", "--steps", "5"]

# name → (what it changes, the flags after the common ones)
CONFIGS: dict[str, tuple[str, list[str]]] = {
    "base": ("the experiments' small L2S (noise 3e-3, curriculum on)", SMALL),
    "noise-0.03": ("step noise 0.03", [*SMALL, "--step-noise", "0.03"]),
    "no-curriculum": ("whole horizon from epoch 1", [*SMALL, "--no-horizon-curriculum"]),
    "batch-4": ("batches of 4 flights (27 optimizer steps an epoch, not 4)",
                [*SMALL, "--batch-size", "4"]),
    "unroll-5": ("5-step training rollouts", [*SMALL, "--unroll", "5"]),
}
SWARMS = ("quad3", "quad6")


def mpnode(*args: str) -> list[str]:
    return [sys.executable, "-m", "mpnode_cli", *args]


def dataset(data: Path, swarm: str) -> Path:
    path = data / f"{swarm}.h5"
    if not path.exists():
        data.mkdir(parents=True, exist_ok=True)
        subprocess.run(mpnode("generate", "--preset", swarm, "--trajectories",
                              str(TRAJECTORIES), "--out", str(path)), check=True,
                       stdout=subprocess.DEVNULL)
    return path


def record_of(summary: dict, swarm: str, config: str, seconds: float) -> dict:
    test = summary["test"]
    members = [m["mse"] for m in test["members"]]
    return {"swarm": swarm, "config": config, "flags": CONFIGS[config][1],
            "epochs": summary["epochs"], "best_epochs": [m["best_epoch"] for m in
                                                          summary["members"]],
            "member_mse": members, "ensemble_mse": test["mse"],
            "time_mean": summary["baselines"]["time_mean"],  # on the test split
            "hold_x0": summary["baselines"]["hold_x0"],
            "wall_seconds": seconds, "parameters": summary["parameters"]}


def run_one(data: Path, runs: Path, swarm: str, config: str) -> dict:
    folder = runs / f"{swarm}-{config}"
    summary_path = folder / "summary.json"
    if summary_path.exists() and json.loads(summary_path.read_text()).get("finished"):
        summary = json.loads(summary_path.read_text())
        return record_of(summary, swarm, config, summary["wall_seconds"])
    if folder.exists():  # cut off: runs are minutes, so start again
        shutil.rmtree(folder)
    start = time.monotonic()
    subprocess.run(mpnode("train", str(dataset(data, swarm)), "--no-plots", "--model", "l2s",
                          "--epochs", str(EPOCHS), "--seeds", str(SEEDS), "--recipe",
                          "mpnode", "--threads", "1", "--run-dir", str(folder),
                          *CONFIGS[config][1]),
                   check=True, stdout=subprocess.DEVNULL)
    summary = json.loads(summary_path.read_text())
    return record_of(summary, swarm, config, time.monotonic() - start)


def table(records: list[dict]) -> str:
    lines = [
        "# L2S on the quadrotor swarms: configurations until every member learns",
        "",
        "Written by `bench/l2s_tuning.py` from its records (`l2s-tuning.json`). Each row: one",
        f"config on one swarm ({TRAJECTORIES} flights, the preset's split), {EPOCHS} epochs of",
        f"mpnode's recipe, {SEEDS} members (seeds); test MSE in the run's normalized units,",
        "members' mean ± std; **÷ time mean**: each member's test MSE over the time-mean",
        "predictor's (the train split's mean at each time) on the same flights, worst member in",
        "brackets; **learns**: every member below the time mean. Wall s: the run's, one torch",
        "thread, with one other training job on the 2-core machine beside it (the runs of",
        "2026-11-28).",
        "",
        "| swarm | config | what changes | members' test MSE | ÷ time mean [worst] | "
        "hold x(0) ÷ time mean | ensemble MSE | learns | best epochs | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    order = list(CONFIGS)
    for r in sorted(records, key=lambda r: (r["swarm"], order.index(r["config"])
                                            if r["config"] in order else len(order))):
        m = np.asarray(r["member_mse"])
        ratio = m / r["time_mean"]
        learns = "**yes**" if bool((ratio < 1).all()) else f"no ({int((ratio >= 1).sum())}"\
            f" of {m.size} not below)"
        what = CONFIGS.get(r["config"], ("",))[0]
        lines.append(
            f"| {r['swarm']} | {r['config']} | {what} | {m.mean():.3g} ± {m.std():.2g} | "
            f"{ratio.mean():.2f} [{ratio.max():.2f}] | {r['hold_x0'] / r['time_mean']:.2f} | "
            f"{r['ensemble_mse']:.3g} | {learns} | "
            f"{', '.join(str(e) for e in r['best_epochs'])} | {r['wall_seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--configs", default=",".join(CONFIGS),
                   help=f"comma-separated, of {','.join(CONFIGS)}")
    p.add_argument("--swarms", default=",".join(SWARMS))
    p.add_argument("--data", type=Path, default=HERE / ".data" / "l2s")
    p.add_argument("--runs", type=Path, default=HERE / ".runs" / "l2s")
    p.add_argument("--out", type=Path, default=HERE / "results" / "l2s-tuning.md")
    p.add_argument("--records", type=Path, default=HERE / "results" / "l2s-tuning.json")
    p.add_argument("--table-only", action="store_true")
    args = p.parse_args(argv)
    configs = [c for c in args.configs.split(",") if c]
    swarms = [s for s in args.swarms.split(",") if s]
    bad = [c for c in configs if c not in CONFIGS] + [s for s in swarms if s not in SWARMS]
    if bad:
        print(f"error: unknown config or swarm: {', '.join(bad)}", file=sys.stderr)
        return 2
    records = json.loads(args.records.read_text()) if args.records.exists() else []
    if not args.table_only:
        for swarm in swarms:
            for config in configs:
                rec = run_one(args.data, args.runs, swarm, config)
                records = [r for r in records
                           if (r["swarm"], r["config"]) != (swarm, config)] + [rec]
                atomic_text(args.records, json.dumps(records, indent=1) + "\n")
                atomic_text(args.out, table(records))
                print(f"{swarm} {config}: members {rec['member_mse']} "
                      f"time mean {rec['time_mean']:.3g}", flush=True)
    atomic_text(args.out, table(records))
    print(table(records))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
