"""Which of two table rows is lower, column by column, under two rules.

A column's verdict between rows A and B (two variants, each trained on the
same seeds) is decided only where both rules give it:

* the seed-spread rule of the reports (``seeds.beyond_spread``):
  the difference of the two means over the seeds exceeds the sum of their
  sample standard deviations (``evaluation.seeds``);
* a paired bootstrap per seed: the seed's test pairs are resampled (the same
  resampled pairs for A and B), NMAE(A) - NMAE(B) (NMAE = MAE / mean|y| over
  the resampled pairs, as in the tables) is computed per resample, and its
  95 % percentile interval says "A lower" when entirely below 0, "B lower"
  when entirely above, else "undecided". The rule gives a side only when
  every seed gives it.

A row's data is ``{seed: raw}``, ``raw`` a dict of a row's arrays
(``indices``, ``truth``, ``pred``, ``defined``: the last three map a
target name to a per-pair array), from a predictions file's row
(``prediction_files.load``) or ``forward_pass.paired_outputs``. ``same_quantities`` says which columns are
the same quantity in the test labels. numpy only.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cpl_keras import metrics
from cpl_keras.camera import PARAMETERS
from cpl_keras.evaluation.pairs import EvaluationError
from cpl_keras.evaluation.seeds import mean_and_spread, beyond_spread

#: The paper table's columns, in its order, and the target each one is.
COLUMNS = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "pitch")
COLUMN_PARAMETER = dict(zip(COLUMNS, PARAMETERS))
#: The answers of a rule and of the combined verdict.
A_LOWER, B_LOWER, UNDECIDED = "A lower", "B lower", "undecided"
#: Bootstrap defaults: resamples, interval level, the Generator's seed.
RESAMPLES = 2000
LEVEL = 0.95
BOOTSTRAP_SEED = 0
#: Two label columns closer than this everywhere are the same quantity.
TOLERANCE = 1e-9
#: ``differences_beyond_spread``'s cells and the answers they stand for.
_SPREAD_CELLS = {"<": A_LOWER, ">": B_LOWER, "=": UNDECIDED, "n/a": UNDECIDED}


@dataclasses.dataclass(frozen=True)
class SeedInterval:
    """One seed's paired bootstrap of NMAE(A) - NMAE(B) on one column."""

    seed: int             # the seed (its test split and initial weights)
    num_pairs: int        # test pairs resampled (defined for both rows)
    nmae_a: float         # NMAE of A on the seed's test pairs
    nmae_b: float         # NMAE of B on the same pairs
    low: float            # lower end of the percentile interval of the difference
    high: float           # upper end
    answer: str           # A_LOWER (high < 0), B_LOWER (low > 0) or UNDECIDED


@dataclasses.dataclass(frozen=True)
class ColumnVerdict:
    """Both rules' answers for one column of rows A and B, and the verdict."""

    column: str           # the paper table's column name (``COLUMNS``)
    parameter: str        # the target it is (``camera.PARAMETERS``)
    mean_a: float         # A's NMAE, mean over the seeds
    spread_a: float       # A's sample SD over the seeds
    mean_b: float         # B's NMAE, mean over the seeds
    spread_b: float       # B's sample SD over the seeds
    spread_rule: str      # the seed-spread rule's answer
    bootstrap_rule: str   # the per-seed bootstrap's answer (a side only if every seed gives it)
    verdict: str          # the two rules' answer where they agree, else UNDECIDED
    per_seed: tuple       # SeedInterval per seed, in seed order
    # For context, not the verdict: Welch's t-test of the seeds' NMAEs (its
    # two-sided p; nan where both rows have one value each), and the rig
    # bootstrap (``rig_intervals``: whole camera configurations resampled,
    # a side when every seed gives it).
    welch_p: float = float("nan")
    rig_bootstrap: str = UNDECIDED


def _check_pairing(seed, a, b):
    """A one-line EvaluationError unless A and B of ``seed`` were scored on
    the same test pairs against the same labels."""
    ia, ib = np.asarray(a["indices"]), np.asarray(b["indices"])
    if ia.shape != ib.shape or not np.array_equal(ia, ib):
        raise EvaluationError(f"seed {seed}: the two rows were scored on different test pairs "
                              f"({len(ia)} and {len(ib)} indices, not the same)")
    for name in PARAMETERS:
        if not np.array_equal(a["truth"][name], b["truth"][name]):
            raise EvaluationError(f"seed {seed}: the two rows score '{name}' against "
                                  "different labels")


def _column(a, b, name):
    """The labels and A's and B's predictions of target ``name`` over the
    pairs where both rows have the label."""
    keep = np.ones(len(a["truth"][name]), bool)
    for raw in (a, b):
        if "defined" in raw:
            keep &= np.asarray(raw["defined"][name], bool)
    return tuple(np.asarray(x[name], np.float64)[keep]
                 for x in (a["truth"], a["pred"], b["pred"]))


def _interval_answer(low, high):
    """The seed's answer from its interval of NMAE(A) - NMAE(B)."""
    if high < 0:
        return A_LOWER
    if low > 0:
        return B_LOWER
    return UNDECIDED


def seed_intervals(seed, a, b, *, resamples=RESAMPLES, level=LEVEL,
                   bootstrap_seed=BOOTSTRAP_SEED):
    """``{parameter: SeedInterval}``: the paired bootstrap of one seed's two
    runs. The resampled pairs are drawn once per seed (a Generator seeded
    with ``(bootstrap_seed, seed)``) and shared by A, B and every column."""
    _check_pairing(seed, a, b)
    n = len(np.asarray(a["indices"]))
    if n == 0:
        raise EvaluationError(f"seed {seed}: no test pairs")
    rng = np.random.default_rng([int(bootstrap_seed), int(seed)])
    draws = rng.integers(0, n, size=(int(resamples), n))
    tails = 100 * (1 - level) / 2
    out = {}
    for name in PARAMETERS:
        truth, pred_a, pred_b = _column(a, b, name)
        if len(truth) == n:
            picked = draws
        else:                                    # (labels missing for some pairs)
            picked = rng.integers(0, max(len(truth), 1), size=(int(resamples), len(truth)))
        scale, gap = np.abs(truth), np.abs(pred_a - truth) - np.abs(pred_b - truth)
        with np.errstate(divide="ignore", invalid="ignore"):
            diffs = gap[picked].mean(axis=1) / scale[picked].mean(axis=1)
            low, high = np.percentile(diffs, [tails, 100 - tails])
        defined = len(truth) > 0 and np.isfinite(low) and np.isfinite(high)
        out[name] = SeedInterval(
            seed=int(seed), num_pairs=len(truth),
            nmae_a=metrics.nmae(truth, pred_a), nmae_b=metrics.nmae(truth, pred_b),
            low=float(low), high=float(high),
            answer=_interval_answer(low, high) if defined else UNDECIDED)
    return out


def welch_p(values_a, values_b):
    """Welch's two-sided p for the seeds' NMAEs of two rows (nan when it is
    undefined: one seed a side, or no spread on either)."""
    from scipy import stats

    a, b = np.asarray(values_a, np.float64), np.asarray(values_b, np.float64)
    if len(a) < 2 or len(b) < 2 or (np.ptp(a) == 0 and np.ptp(b) == 0):
        return float("nan")
    return float(stats.ttest_ind(a, b, equal_var=False).pvalue)


def rig_keys(truth):
    """One key per test pair: its rig (camera configuration), known from the
    labels that a rig fixes (fx, fy, u0, v0, baseline, tx, ty, tz, pitch;
    the disparity is the scene's). Returns an int array (rig index)."""
    fixed = [name for name in PARAMETERS if name != "disparity"]
    table = np.stack([np.round(np.asarray(truth[name], np.float64), 6) for name in fixed], 1)
    return np.unique(table, axis=0, return_inverse=True)[1].reshape(-1)


def rig_intervals(seed, a, b, *, resamples=RESAMPLES, level=LEVEL,
                  bootstrap_seed=BOOTSTRAP_SEED):
    """``{parameter: answer}``: one seed's bootstrap of NMAE(A) - NMAE(B)
    that resamples whole rigs (``rig_keys``), not single pairs, so that the
    pairs of one rig, which share its errors, count as one draw: the
    interval of a seed whose test pairs come from few rigs is wider."""
    _check_pairing(seed, a, b)
    rigs = rig_keys(a["truth"])
    count = int(rigs.max()) + 1 if rigs.size else 0
    rng = np.random.default_rng([int(bootstrap_seed), int(seed), 1])
    draws = rng.integers(0, max(count, 1), size=(int(resamples), count))
    tails = 100 * (1 - level) / 2
    out = {}
    for name in PARAMETERS:
        keep = np.ones(len(rigs), bool)
        for raw in (a, b):
            if "defined" in raw:
                keep &= np.asarray(raw["defined"][name], bool)
        truth = np.asarray(a["truth"][name], np.float64)[keep]
        gap = (np.abs(np.asarray(a["pred"][name], np.float64)[keep] - truth)
               - np.abs(np.asarray(b["pred"][name], np.float64)[keep] - truth))
        gaps = np.bincount(rigs[keep], gap, minlength=count)
        scales = np.bincount(rigs[keep], np.abs(truth), minlength=count)
        with np.errstate(divide="ignore", invalid="ignore"):
            diffs = gaps[draws].sum(axis=1) / scales[draws].sum(axis=1)
            low, high = np.percentile(diffs, [tails, 100 - tails])
        defined = count > 1 and np.isfinite(low) and np.isfinite(high)
        out[name] = _interval_answer(low, high) if defined else UNDECIDED
    return out


def _all_seeds(answers):
    """A side when every seed gives it, else UNDECIDED."""
    answers = set(answers)
    return answers.pop() if len(answers) == 1 and UNDECIDED not in answers else UNDECIDED


def spread_rule(nmae_a, nmae_b):
    """``{parameter: answer}`` of the seed-spread rule from each row's NMAE
    per seed (``{parameter: [value per seed]}``): the means and sample SDs
    of ``evaluation.seeds``, judged by ``seeds.beyond_spread`` (the rule the
    reports' ``differences_beyond_spread`` renders)."""
    if min(len(values) for values in list(nmae_a.values()) + list(nmae_b.values())) < 2:
        raise EvaluationError("the seed-spread rule needs 2 or more seeds")
    return {name: _SPREAD_CELLS[beyond_spread(*mean_and_spread(nmae_a[name]),
                                              *mean_and_spread(nmae_b[name]))]
            for name in PARAMETERS}


def compare(rows_a, rows_b, *, resamples=RESAMPLES, level=LEVEL,
            bootstrap_seed=BOOTSTRAP_SEED):
    """``[ColumnVerdict]`` (one per column of ``COLUMNS``) for rows A and B,
    each ``{seed: raw}`` over the same seeds (two or more)."""
    seeds = sorted(rows_a)
    if sorted(rows_b) != seeds:
        raise EvaluationError(f"rows A and B have different seeds: {seeds} and "
                              f"{sorted(rows_b)}")
    if len(seeds) < 2:
        raise EvaluationError(f"the verdicts need 2 or more seeds (the seed-spread rule): "
                              f"the rows have seed(s) {seeds}")
    intervals = {s: seed_intervals(s, rows_a[s], rows_b[s], resamples=resamples,
                                    level=level, bootstrap_seed=bootstrap_seed)
                 for s in seeds}
    per_seed = {name: tuple(intervals[s][name] for s in seeds) for name in PARAMETERS}
    nmae_a = {name: [i.nmae_a for i in per_seed[name]] for name in PARAMETERS}
    nmae_b = {name: [i.nmae_b for i in per_seed[name]] for name in PARAMETERS}
    by_spread = spread_rule(nmae_a, nmae_b)
    by_rig = {s: rig_intervals(s, rows_a[s], rows_b[s], resamples=resamples, level=level,
                               bootstrap_seed=bootstrap_seed) for s in seeds}
    verdicts = []
    for column, name in COLUMN_PARAMETER.items():
        mean_a, spread_a = mean_and_spread(nmae_a[name])
        mean_b, spread_b = mean_and_spread(nmae_b[name])
        by_bootstrap = _all_seeds(i.answer for i in per_seed[name])
        verdicts.append(ColumnVerdict(
            column=column, parameter=name, mean_a=mean_a, spread_a=spread_a,
            mean_b=mean_b, spread_b=spread_b, spread_rule=by_spread[name],
            bootstrap_rule=by_bootstrap,
            verdict=by_spread[name] if by_spread[name] == by_bootstrap else UNDECIDED,
            per_seed=per_seed[name], welch_p=welch_p(nmae_a[name], nmae_b[name]),
            rig_bootstrap=_all_seeds(by_rig[s][name] for s in seeds)))
    return verdicts



def same_quantities(truths, tolerance=TOLERANCE):
    """What the test labels say about the columns, over ``truths`` (a list
    of ``{parameter: array}``, one per seed): ``"constant"``, ``{column:
    value}`` for a column with one value on every pair, and ``"identical"``,
    the groups of other columns equal to ``tolerance`` on every pair."""
    joined = {c: np.concatenate([np.asarray(t[p], np.float64) for t in truths])
              for c, p in COLUMN_PARAMETER.items()}
    constant = {c: float(v[0]) for c, v in joined.items()
                if v.size and np.all(np.abs(v - v[0]) <= tolerance)}
    groups, placed = [], set(constant)
    for i, first in enumerate(COLUMNS):
        if first in placed:
            continue
        group = [first] + [other for other in COLUMNS[i + 1:] if other not in placed
                           and np.all(np.abs(joined[first] - joined[other]) <= tolerance)]
        if len(group) > 1:
            groups.append(group)
            placed.update(group)
    return {"identical": groups, "constant": constant}
