"""Claims judged on results: whether each holds, on one model or on an ensemble's members,
and the verdict as the reports write it.

A claim (`spec.Claim`) compares two numbers of the steps' results, `LEFT OP RIGHT`
(`spec.parse_claim`). Run with `--seeds S`, every training is an ensemble and a claim is
judged member by member and on the members' means (`members.decide_pairs`). A verdict also
says what it rests on: training runs that did not learn (their test error not below the
time-mean predictor's) or barely learned, and an MP-NODE that is not the paper's model.
"""

from __future__ import annotations

from typing import Any

from mpnode_cli.experiments import members
from mpnode_cli.experiments.claim_grammar import parse_claim
from mpnode_cli.experiments.spec import TRAINING, Experiment


def with_derived(result: Any) -> Any:
    """A step's results with two ratios added where a training run's are:

    - `table2_per_mean`: the Table-2 figure with the best checkpoint's validation MSE
      divided by the time-mean predictor's (best epoch × val MSE ÷ time-mean MSE);
    - `test_per_mean`: the test MSE ÷ the time-mean predictor's on the test split.

    Both MSEs are in the run's own normalization, so the ratios are not: a finetune keeps
    its parent's normalization, and two models normalize the same data differently where
    one embeds angles, so their MSEs are in other units while these ratios compare."""
    if not isinstance(result, dict) or "best_epoch" not in result:
        return result
    derived = {}
    for split, key, factor in (("val", "table2_per_mean", result["best_epoch"]),
                               ("test", "test_per_mean", 1)):
        part = result.get(split) or {}
        mse, mean = part.get("mse"), part.get("time_mean")
        if isinstance(mse, int | float) and isinstance(mean, int | float) and mean > 0:
            derived[key] = factor * mse / mean
    return {**result, **derived} if derived else result


# A training run less than this many times below the time-mean predictor has barely
# learned: a claim comparing it says little, though it "beats" the time mean (by 1.006×).
# 3×: a baseline that a reviewer accepts beats the time mean at least that far.
BARELY_LEARNED = 3.0
# The paper averages the incoming messages (§3.2, eq. (3)); mpnode's recipe may not.
PAPER_AGGREGATE = "mean"
_AGGREGATE_NAMES = {"pna": "PNA", "sum": "sum"}


def learning(text: str, results: dict[str, dict[str, Any]]) -> dict[str, float]:
    """The training runs a claim reads that have not learned, or barely: run → its test
    MSE's time-mean predictor's MSE over its own (≤ 1: not below the time mean; below
    `BARELY_LEARNED`: barely below it). The time mean predicts the train split's mean state
    at each sample time. Evaluate and zero-shot steps are not listed: a model with its
    messages zeroed is meant to be bad."""
    out: dict[str, float] = {}
    for _, ref in parse_claim(text)[::2]:
        step = (ref or "").partition(".")[0]
        result = results.get(step)
        if not isinstance(result, dict) or "best_epoch" not in result or step in out:
            continue
        test = result.get("test") or {}
        mse, mean = test.get("mse"), test.get("time_mean")
        if not (isinstance(mse, int | float) and isinstance(mean, int | float)) or mse <= 0:
            continue  # a number missing, or a perfect fit
        if mean < BARELY_LEARNED * mse:
            out[step] = mean / mse
    return out


def member_learning(text: str, results: dict[str, dict[str, Any]]
                    ) -> dict[str, dict[int | None, float]]:
    """`learning` member by member: run → {member k → its ratio} for the members that have
    not learned or barely (the member is None for a single model's results)."""
    out: dict[str, dict[int | None, float]] = {}
    named = _named(text, results)
    for k in range(members.count(named)):
        for step, ratio in learning(text, members.view(named, k)).items():
            out.setdefault(step, {})[k if _ensemble(named) else None] = ratio
    return out


def _named(text: str, results: dict[str, Any]) -> dict[str, Any]:
    """The results of the steps a claim names."""
    steps = [(ref or "").partition(".")[0] for _, ref in parse_claim(text)[::2]]
    return {step: results[step] for step in steps if step in results}


def _ensemble(results: dict[str, Any]) -> bool:
    return any(isinstance(r, dict) and r.get(members.MEMBERS) for r in results.values())


def not_learned(text: str, results: dict[str, dict[str, Any]]) -> list[str]:
    """The training runs a claim reads with a member whose test MSE is not below the
    time-mean predictor's: it has not learned, so the claim says little whichever way it
    goes."""
    return [step for step, ratios in member_learning(text, results).items()
            if any(ratio <= 1 for ratio in ratios.values())]


def barely_learned(text: str, results: dict[str, dict[str, Any]]) -> list[str]:
    """The training runs a claim reads with a member below the time-mean predictor, but by
    less than `BARELY_LEARNED`×."""
    return [step for step, ratios in member_learning(text, results).items()
            if any(ratio > 1 for ratio in ratios.values())]


def nothing_learned(text: str, results: dict[str, dict[str, Any]]) -> bool:
    """Whether every training run a claim compares, every member of it, is not below the
    time-mean predictor: then the claim is not tested, whichever way its numbers fall."""
    named = _named(text, results)
    first = members.view(named, 0) if named else {}
    runs = [step for step, r in first.items() if isinstance(r, dict) and "best_epoch" in r]
    found = member_learning(text, results)
    size = members.count(named)
    return bool(runs) and all(
        len(found.get(step, {})) == size and all(r <= 1 for r in found[step].values())
        for step in runs)


def beaten_unlearned(text: str, results: dict[str, dict[str, Any]]) -> list[str]:
    """The training run on the side a claim says it beats (the right of `<` and `<=`, the
    left of `>` and `>=`) when every member of it is not below the time-mean predictor: a
    claim that holds against it rests on a run that never learned."""
    left, op, right = parse_claim(text)
    step = ((right if op in ("<", "<=") else left)[1] or "").partition(".")[0]
    named = _named(text, results)
    if "best_epoch" not in (members.view(named, 0).get(step) or {}):
        return []
    found = member_learning(text, results).get(step, {})
    unlearned = len(found) == members.count(named) and all(r <= 1 for r in found.values())
    return [step] if unlearned else []


def learning_notes(text: str, results: dict[str, dict[str, Any]]) -> dict[str, str]:
    """What `member_learning` finds, a phrase per run: `not below the time mean` or
    `barely learned, 1.3× below the time mean`; for an ensemble `member 1 not below the
    time mean, member 2 barely learned (1.3× below the time mean)`."""
    def said(k: int | None, ratio: float) -> str:
        if ratio <= 1:
            return "not below the time mean" if k is None else \
                f"member {k} not below the time mean"
        below = f"{ratio:.3g}× below the time mean"
        return f"barely learned, {below}" if k is None else \
            f"member {k} barely learned ({below})"

    return {step: ", ".join(said(k, ratio) for k, ratio in ratios.items())
            for step, ratios in member_learning(text, results).items()}


def table2_notes(text: str, results: dict[str, dict[str, Any]]) -> dict[str, str]:
    """For a claim on Table-2 figures (`table2`, `table2_per_mean`), the runs it names
    whose figure is degenerate or capped, a phrase each: a best epoch of 0 makes the
    figure 0 whatever the loss, and a best epoch at the budget's last says the run was
    still improving, so its figure measures the budget."""
    if "table2" not in text:
        return {}
    out = {}
    for step, result in _named(text, results).items():
        phrases = []
        for k in range(members.count({step: result})):
            r = members.of(result, k)
            best, last = r.get("best_epoch"), r.get("epochs")
            who = f"member {k}'s" if result.get(members.MEMBERS) else "its"
            if best == 0:
                phrases.append(f"{who} best epoch is 0 (figure 0)")
            elif best is not None and best == last:
                phrases.append(f"{who} best epoch is the budget's last ({last}): "
                               "not converged")
        if phrases:
            out[step] = ", ".join(phrases)
    return out


def run_notes(text: str, results: dict[str, dict[str, Any]]) -> dict[str, str]:
    """`learning_notes` and `table2_notes` together, a phrase per run."""
    notes = learning_notes(text, results)
    for step, note in table2_notes(text, results).items():
        notes[step] = f"{notes[step]}; {note}" if step in notes else note
    return notes


def trained_runs(text: str, experiment: Experiment) -> list[str]:
    """The training steps a claim reads: those it names, and the checkpoints of the
    evaluate and zero-shot steps it names."""
    by_id = {step.id: step for step in experiment.steps}
    out: list[str] = []
    for _, ref in parse_claim(text)[::2]:
        step = by_id.get((ref or "").partition(".")[0])
        if step is not None and step.verb not in TRAINING:
            step = by_id.get(getattr(step, "checkpoint", None) or "")
        if step is not None and step.verb in TRAINING and step.id not in out:
            out.append(step.id)
    return out


def departures(text: str, results: dict[str, dict[str, Any]],
               experiment: Experiment | None) -> list[str]:
    """How the MP-NODE runs a claim reads differ from the paper's model: an aggregation
    other than the paper's mean (mpnode's recipe sums over the neighbours)."""
    if experiment is None:
        return []
    found = []
    for step in trained_runs(text, experiment):
        result = results.get(step) or {}
        aggregate = (result.get("model_options") or {}).get("aggregate")
        if result.get("model") == "mpnode" and aggregate not in (None, PAPER_AGGREGATE):
            found.append(_AGGREGATE_NAMES.get(aggregate, aggregate))
    return [f"{name} aggregation, not the paper's mean" for name in dict.fromkeys(found)]


def verdict(text: str, results: dict[str, dict[str, Any]],
            experiment: Experiment | None = None) -> tuple[bool | None, str, str]:
    """Whether a claim holds (None: undecided, or a number missing), the numbers shown, and
    the verdict as the reports write it: yes, **no**, undecided, not tested (no training run
    it compares beat the time mean, `nothing_learned`, or it holds against one that did
    not, `beaten_unlearned`) or — (a number missing),
    followed by what it rests on: for an ensemble, how many members it holds for and
    whether the means differ by more than their combined std (`members.decide_pairs`); the
    runs (members) that did not beat the time mean or barely did, and Table-2 figures
    that are 0 or still improving at the budget's end (`run_notes`); and a model that is not
    the paper's (with `experiment`, to find the runs behind an evaluation). A claim with a
    number missing (a step not run) is — alone: it compared nothing.

    One model's results show their two numbers (`0.025 < 0.62`), an ensemble's their means
    ± std over the members."""
    decision = decide_claim(text, results)
    holds = {"holds": True, "fails": False}.get(decision.outcome or "")
    said = {"holds": "yes", "fails": "**no**", "undecided": "undecided"}.get(
        decision.outcome or "", "—")
    if decision.outcome and nothing_learned(text, results):
        holds, said = None, "not tested (no run it compares learned)"
    elif decision.outcome == "holds" and (beaten := beaten_unlearned(text, results)):
        holds, said = None, f"not tested ({beaten[0]}, the side it beats, did not learn)"
    if decision.outcome is None:  # a number missing: nothing was compared, nothing to note
        return holds, decision.shown(), said
    notes = [decision.reason()] if _ensemble(_named(text, results)) else []
    notes += [f"{step}: {note}" for step, note in run_notes(text, results).items()]
    notes += departures(text, results, experiment)
    if notes:
        said += f" ({'; '.join(notes)})"
    return holds, decision.shown(), said


def decide_claim(text: str, results: dict[str, dict[str, Any]]) -> members.Decision:
    """A claim judged on each member alone (member k of every step it names) and on the
    members' means (`members.decide_pairs`); results without members are one member."""
    named = _named(text, results)
    return members.decide_pairs([_sides(text, members.view(named, k))
                                 for k in range(members.count(named))], parse_claim(text)[1])


def judge(text: str, results: dict[str, dict[str, Any]]) -> tuple[bool | None, str]:
    """Whether a claim holds on `results` (step id → its results; one model's, or one
    member's), and the numbers shown.

    Returns:
        (True/False, or None when a number is missing; e.g. "0.025 < 0.62").
    """
    values = _sides(text, results)
    op = parse_claim(text)[1]
    shown = f" {op} ".join("—" if v is None else f"{v:.4g}" for v in values)
    if None in values:
        return None, shown
    return members.OPS[op](float(values[0]), float(values[1])), shown


def _sides(text: str, results: dict[str, dict[str, Any]]) -> tuple[float | None, float | None]:
    """A claim's two numbers on `results` (None where one is missing)."""
    results = {step: with_derived(result) for step, result in results.items()}
    left, _, right = parse_claim(text)
    values = []
    for factor, ref in (left, right):
        if ref is None:
            values.append(factor)
            continue
        step, _, path = ref.partition(".")
        value = members.lookup(results.get(step), path)
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        values.append(factor * float(value) if ok else None)
    return values[0], values[1]


# Resamples of the bootstrap over data draws and members (`interval`), and its fixed seed,
# so that a rebuilt report gives the same interval.
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0


def interval(text: str, draws: list[dict[str, dict[str, Any]]]
             ) -> tuple[float, float, float] | None:
    """A claim's margin over data draws and seeds: the ratio of its two sides' means, taken
    the claimed way (right ÷ left for `<` and `<=`, left ÷ right for `>` and `>=`, so
    above 1 is the claimed direction), and its 95% bootstrap interval.

    The bootstrap is two-stage, as the data were drawn: each resample takes the draws with
    replacement and, within each, its members (seeds) with replacement, and takes the
    ratio of the means of all the pairs taken (percentiles 2.5 and 97.5 of
    `BOOTSTRAP_RESAMPLES`, seeded).

    Args:
        draws: each data draw's results (step id → results), one draw's run each; a draw
            without the claim's numbers is left out.

    Returns:
        (ratio on all pairs, lower, upper), or None with a number missing or a side's mean
        not positive. A resample whose side claimed lower has mean 0 (a Table-2 figure
        of a best epoch 0) has an infinite ratio, so a bound may be `inf`: the data do not
        bound the margin from that side.
    """
    import numpy as np

    sides = _claimed_sides(text, draws)
    found = margin(text, draws)
    if sides is None or found is None:
        return None
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    ratios = np.empty(BOOTSTRAP_RESAMPLES)
    for b in range(BOOTSTRAP_RESAMPLES):
        taken = [sides[d][rng.integers(0, len(sides[d]), len(sides[d]))]
                 for d in rng.integers(0, len(sides), len(sides))]
        low, high = np.concatenate(taken).mean(axis=0)
        ratios[b] = high / low if low > 0 else np.inf
    # Interpolating between two infinite ratios gives NaN (∞ − ∞); the bound there is ∞.
    with np.errstate(invalid="ignore"):
        bounds = np.percentile(ratios, [2.5, 97.5])
    lower, upper = np.nan_to_num(bounds, nan=np.inf, posinf=np.inf)
    return found, float(lower), float(upper)


def over_draws(text: str, draws: list[dict[str, dict[str, Any]]]
               ) -> tuple[int, tuple[float, float, float] | None]:
    """How many of `draws` have every number the claim names, and its `interval` over
    them where two or more do (None otherwise: one draw is no spread of draws)."""
    sides = _claimed_sides(text, draws)
    counted = 0 if sides is None else len(sides)
    return counted, interval(text, draws) if counted > 1 else None


def format_bound(value: float) -> str:
    """A margin or an interval's bound: 3 significant digits, ∞ where it is unbounded."""
    return "∞" if value == float("inf") else f"{value:.3g}"


def margin(text: str, draws: list[dict[str, dict[str, Any]]]) -> float | None:
    """A claim's margin on every pair of every draw (`interval`'s ratio, without the
    bootstrap), or None with a number missing or a side's mean not positive."""
    import numpy as np

    sides = _claimed_sides(text, draws)
    if sides is None:
        return None
    low, high = np.concatenate(sides).mean(axis=0)
    return float(high / low) if low > 0 and high > 0 else None


def _claimed_sides(text: str, draws: list[dict[str, dict[str, Any]]]) -> list | None:
    """Each draw's pairs as an array `[S, 2]`: (the side claimed lower, the other), of the
    draws that have every number (a step added after a draw ran has none there); None
    where no draw has them all."""
    import numpy as np

    per_draw = [pairs for pairs in (decide_claim(text, results).pairs for results in draws)
                if pairs and None not in (v for p in pairs for v in p)]
    if not per_draw:
        return None
    flip = parse_claim(text)[1] in (">", ">=")
    return [np.array(pairs, dtype=float)[:, ::-1] if flip else np.array(pairs, dtype=float)
            for pairs in per_draw]
