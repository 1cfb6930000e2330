"""What `bench/transfer.py` trains and scores: the datasets of each protocol, the oracle's
size, the sets, and the planning estimates (docs/transfer.md).

Pure Python (no torch), so that `--plan` and the tests are quick.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

BB = ("sis", "mak", "mm", "bd", "nd")  # Barzel & Barabási 2013, as Laber et al. 2026 train them
SETS = {"selection": ("gene", "kuramoto", "sis", "mm"),
        "confirmation": ("mak", "bd", "nd", "fhn", "grid", "pendulum", "mutualistic")}
SYSTEMS = (*SETS["selection"], *SETS["confirmation"])
GAMMAS = (2.1, 2.5, 3.5)
S1_SOURCE_NODES, S1_TARGETS, S1_LARGEST = 64, (1024, 4096), 8192
SMOKE_S1_TARGETS, SMOKE_S1_LARGEST = (256, 512), 1024
SPLIT = (0.7, 0.15, 0.15)  # `mpnode generate`'s default fractions
MIN_TRAIN, MIN_VAL, MIN_TEST = 1, 1, 2  # a target's splits hold at least these
SMOKE_TRAJECTORIES, SMOKE_GRAPHS, SMOKE_EPOCHS = 24, 3, 3
# Variants the benches rejected or superseded (the aggregations `pna`, `mean`, `mlp-sum`;
# `relu`, `softplus`, `node-mse`, the `periodic-*` ablations, the hand-made `hub-coverage*`
# and `*-long` budgets, and those built on since-retired options) are gone from here; their
# records, each with the options and commit it ran, stay in results/transfer.json, and
# docs/transfer.md lists what they measured.
VARIANTS = {  # `--variant`: train options beyond the CLI's defaults (source and oracle alike)
    "default": (),
    "l2s": ("--model", "l2s"),  # Learning to Simulate (Sanchez-Gonzalez et al. 2020), a peer
    # The recipe's rates annealed and its steps clipped (`--schedule cosine --clip 5`) over
    # the system's fixed epochs, and the clipping alone: candidates for train's defaults.
    "cosine-clip": ("--schedule", "cosine", "--clip", "5"),
    "clip": ("--clip", "5"),
    # The product path: the source trained by `mpnode train SOURCE --for-graphs TARGET...`
    # and no other option (the CLI makes the coverage data and applies the transfer
    # recipe); these are its oracles' options, the same transfer recipe on the target.
    "for-graphs": ("--schedule", "cosine", "--clip", "5"),
}
FOR_GRAPHS_VARIANTS = ("for-graphs",)

# Planning: seconds per epoch of each system's *source* training (one torch thread, the
# whole horizon, validation included). gene, kuramoto, pendulum, fhn, grid: the mean over
# the 3 seeds of the previous bench's full runs (train seconds ÷ epochs, 2026-11-25, the
# 2-core machine busy with 2–5 training processes: wall time). The five BB systems: epochs
# 2–3 of a 3-epoch run on 64-node S¹ graphs (γ = 2.5, 100 trajectories, 10 graphs, no
# curriculum), measured 2026-11-28 on the same machine at load ≈ 4 (wall time); their learned
# dynamics stiffen as training goes on (the solver's evaluations per epoch grew 1.5–2.4×
# over those 3 epochs), so the numbers are ×`STIFFENING`. Check of the scaling by
# node-trajectories (`epoch_seconds`) on 4096-node S¹ graphs (γ = 2.1, 2 train and 1
# validation trajectories, same day): mm 1.2–2.7 s per epoch (predicted 5.0), bd 2.7–4.7 s
# (predicted 2.5).
S_PER_EPOCH = {"gene": 0.71, "kuramoto": 1.38, "pendulum": 2.56, "fhn": 1.08, "grid": 9.97,
               "sis": 1.6, "mak": 3.1, "mm": 2.2, "bd": 1.1, "nd": 0.9,
               "mutualistic": 0.33}  # 2026-12-07, epochs 1-30 of one run, quiet core
STIFFENING = 1.5  # BB systems only (above)
CURRICULUM = {"sis", "mak", "mm", "bd", "nd"}  # measured without the horizon curriculum
CURRICULUM_EPOCHS, CURRICULUM_START, SAMPLES = 100, 5, 101
GEN_SECONDS = 3.0  # per dataset, plus `GEN_PER_NODE_TRAJECTORY` × K × N
GEN_PER_NODE_TRAJECTORY = 2e-3  # sis, 6 × 4096 nodes: 47 s wall (2026-11-28, load ≈ 4)
EVAL_SECONDS = 15.0  # one scoring: a process start, a rollout of the test split
PROCESS_SECONDS = 6.0  # one `mpnode train` start (imports, data, the epoch-0 validation)
SOURCE_EPOCHS = {"gene": 100, "kuramoto": 150, "pendulum": 150, "fhn": 100, "grid": 100,
                 "mutualistic": 150, **{s: 300 for s in BB}}


@dataclass(frozen=True)
class Data:
    """One dataset: what `mpnode generate` (or bench/power_grid.py) is asked for.

    Attributes:
        system: an mpnode system, "fhn" (examples/fitzhugh_nagumo.py) or "grid".
        counts: trajectories in train, validation and test; None: `SPLIT` of `k`.
        params: `-p NAME=VALUE` pairs (S¹: gamma).
    """

    system: str
    nodes: int
    topology: str
    k: int
    graphs: int = 1
    graph_seed: int = 0
    seed: int = 0
    params: tuple[tuple[str, float], ...] = ()
    counts: tuple[int, int, int] | None = None
    hubs: int = 0
    multiplicity: int = 1

    @property
    def name(self) -> str:
        extra = "".join(f"-{k}{v:g}" for k, v in self.params)
        hubs = f"-h{self.hubs}w{self.multiplicity}" if self.hubs else ""
        return (f"{self.system}-{self.topology}-n{self.nodes}{extra}{hubs}-k{self.k}"
                f"-G{self.graphs}-gs{self.graph_seed}-s{self.seed}")

    def split(self) -> tuple[int, int, int]:
        return self.counts or split_counts(self.k, SPLIT)

    def fractions(self) -> str | None:
        """`--split` for `counts` (None: the default fractions)."""
        if self.counts is None:
            return None
        return ",".join(repr(c / self.k) for c in self.counts)


@dataclass(frozen=True)
class Bench:
    """One source model's data and targets, for one training seed.

    Attributes:
        protocol: "size" (×2, ×4 and another topology) or "s1" (Laber et al. 2026).
        key: the folder of its records under `--runs`.
        targets: label ("x2", "x4", "other", "n1024", ...) → target dataset.
    """

    system: str
    protocol: str
    key: str
    source: Data
    targets: dict[str, Data]
    epochs: int
    gamma: float | None = None


def split_counts(k: int, fractions: tuple[float, float, float]) -> tuple[int, int, int]:
    """`mpnode_cli.data.splits.split_counts` (train and validation rounded, test the
    rest), here without importing torch; tests check that the two agree."""
    n_train = round(k * fractions[0])
    n_val = min(round(k * fractions[1]), k - n_train)
    return n_train, n_val, k - n_train - n_val


def oracle_counts(source: tuple[int, int, int], n_source: int,
                  n_target: int) -> tuple[int, int, int]:
    """A target's train, validation and test trajectories: each split holds at least as
    many node-trajectories as the source's (⌈K·N_source/N_target⌉), at least `MIN_*`."""
    need = [math.ceil(c * n_source / n_target) for c in source]
    return max(need[0], MIN_TRAIN), max(need[1], MIN_VAL), max(need[2], MIN_TEST)


def target(source: Data, nodes: int, topology: str, graphs: int, graph_seed: int,
           seed: int) -> Data:
    """A target of the source's system and parameters, sized by `oracle_counts`."""
    counts = oracle_counts(source.split(), source.nodes, nodes)
    k = sum(counts)
    return replace(source, nodes=nodes, topology=topology, k=k, graphs=min(graphs, k),
                   graph_seed=graph_seed, seed=seed, counts=counts)


def _size_sources() -> dict[str, tuple[Data, dict[str, tuple]]]:
    """Each system's size bench: source, then label → (N, topology, graphs, graph seed,
    seed). kuramoto keeps graph seed 0 everywhere: its natural frequencies are drawn per
    graph seed, and only shared ones can carry over."""
    bb = {s: (Data(s, 16, "ba", 100, graphs=10),
              {"x2": (32, "ba", 5, 100, 1), "x4": (64, "ba", 5, 200, 2)}) for s in BB}
    ba = {"x2": (20, "ba", 4, 100, 1), "x4": (40, "ba", 4, 200, 2)}
    return {
        "gene": (Data("gene", 9, "ba", 300, graphs=10),
                 {"x2": (18, "ba", 5, 100, 1), "x4": (36, "ba", 5, 200, 2),
                  "other": (18, "ws", 5, 300, 3)}),
        "kuramoto": (Data("kuramoto", 10, "ba", 500),
                     {"x2": (20, "ba", 1, 0, 1), "x4": (40, "ba", 1, 0, 2),
                      "other": (20, "er", 1, 0, 3)}),
        "pendulum": (Data("pendulum", 3, "chain", 500),
                     {"x2": (6, "chain", 1, 0, 1), "x4": (12, "chain", 1, 0, 2)}),
        "fhn": (Data("fhn", 10, "ba", 400, graphs=8), ba),
        # A Barzel–Barabási-form plug-in that nothing here was tuned on: BA 20 → BA 160
        # (in-degree up to 12 → 45), its hubs' states above the source's range.
        "mutualistic": (Data("mutualistic", 20, "ba", 60, graphs=5),
                        {"x8": (160, "ba", 2, 400, 4)}),
        "grid": (Data("grid", 10, "ba", 400, graphs=8), ba),
        **bb}


def _shrink(data: Data, smoke: bool) -> Data:
    if not smoke:
        return data
    return replace(data, k=min(data.k, SMOKE_TRAJECTORIES),
                   graphs=min(data.graphs, SMOKE_GRAPHS))


def size_bench(system: str, smoke: bool) -> Bench:
    """The ×2/×4 bench of `system` (its data do not depend on the training seed)."""
    source, spec = _size_sources()[system]
    source = _shrink(source, smoke)
    targets = {label: target(source, *args) for label, args in spec.items()}
    epochs = SMOKE_EPOCHS if smoke else SOURCE_EPOCHS[system]
    return Bench(system, "size", f"size/{system}", source, targets, epochs)


def s1_bench(system: str, gamma: float, seed: int, smoke: bool, largest: bool) -> Bench:
    """Laber et al.'s protocol for one BB system, γ and training seed: trained on 64-node
    S¹ graphs, zero-shot on larger ones. Graphs and initial states are drawn anew for each
    training seed (graph seeds 1000·seed + ..., data seed 10·seed + ...)."""
    params = (("gamma", gamma),)
    source = _shrink(Data(system, S1_SOURCE_NODES, "s1", 100, graphs=10,
                          graph_seed=1000 * seed, seed=10 * seed, params=params), smoke)
    sizes = SMOKE_S1_TARGETS if smoke else S1_TARGETS
    if largest:
        sizes = (*sizes, SMOKE_S1_LARGEST if smoke else S1_LARGEST)
    targets = {}
    for i, n in enumerate(sizes, start=1):
        t = target(source, n, "s1", 1, 1000 * seed + 100 * i, 10 * seed + i)
        targets[f"n{n}"] = replace(t, graphs=t.k)  # one graph per trajectory
    epochs = SMOKE_EPOCHS if smoke else SOURCE_EPOCHS[system]
    return Bench(system, "s1", f"s1/{system}-g{gamma:g}", source, targets, epochs, gamma)


def set_of(system: str) -> str:
    return next((name for name, members in SETS.items() if system in members), "—")


def per_degree(label: str) -> bool:
    """Whether a target gets the in-degree breakdown: every ×4 and every S¹ target."""
    return label in ("x4", "x8") or label.startswith("n")


# ------------------------------------------------------------------------------ planning


def epoch_seconds(system: str, data: Data, source: Data) -> float:
    """Planned seconds per epoch of training on `data`: the source's, scaled by the
    node-trajectories of the train and validation splits (what an epoch rolls out)."""
    def load(d: Data) -> int:
        train, val, _ = d.split()
        return (train + val) * d.nodes

    scale = STIFFENING if system in CURRICULUM else 1.0
    return S_PER_EPOCH[system] * scale * load(data) / load(source)


def curriculum_share(system: str, epochs: int) -> float:
    """The mean horizon of `epochs` epochs as a share of the whole (the curriculum grows it
    from `CURRICULUM_START` samples over `CURRICULUM_EPOCHS`); 1 where it was measured."""
    if system not in CURRICULUM or epochs <= 0:
        return 1.0
    grow = min(epochs, CURRICULUM_EPOCHS)
    mean = sum(CURRICULUM_START + (SAMPLES - CURRICULUM_START) * e / CURRICULUM_EPOCHS
               for e in range(1, grow + 1)) / grow / SAMPLES
    return (grow * mean + (epochs - grow)) / epochs


def generate_seconds(data: Data) -> float:
    return GEN_SECONDS + GEN_PER_NODE_TRAJECTORY * data.k * data.nodes
