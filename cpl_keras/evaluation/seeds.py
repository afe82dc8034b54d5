"""One table over several seeds: the mean and spread of every cell.

``aggregate_seeds`` turns the same table made for several seeds (each seed
its own split and initial weights) into one, for Table 1 and for Table 2
rig by rig.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cpl_keras.baselines.geometric import FAILURE_FLAGS
from cpl_keras.evaluation.pairs import EvaluationError
from cpl_keras.evaluation.table1 import ROWS
from cpl_keras.evaluation.tables import Table2
from cpl_keras.metrics import jsonable
from cpl_keras.runs import RELEASED


#: What the spread of a table over seeds is (the "± x" of its cells).
SPREAD = "sample standard deviation over the seeds (n - 1 in the denominator)"


#: The metrics of a target that get a spread.
SPREAD_METRICS = ("mae", "nmae", "nmae_signed")


def mean_and_spread(values):
    """Mean and sample standard deviation of ``values`` (None = undefined:
    an undefined value in any seed leaves both undefined)."""
    a = np.array([np.nan if v is None else v for v in values], np.float64)
    if not np.all(np.isfinite(a)):
        return None, None
    return float(np.mean(a)), float(np.std(a, ddof=1)) if len(a) > 1 else 0.0


def beyond_spread(mean_a, spread_a, mean_b, spread_b):
    """The seed-spread rule on one column: ``"<"`` where row A's mean NMAE is
    lower than B's by more than the sum of their spreads, ``">"`` where B's
    is, ``"="`` within the spreads, ``"n/a"`` where a value is undefined
    (None or not finite). The reports claim an ordering only where this
    says so."""
    values = np.array([np.nan if v is None else v for v in (mean_a, spread_a, mean_b, spread_b)],
                      np.float64)
    if not np.all(np.isfinite(values)):
        return "n/a"
    mean_a, spread_a, mean_b, spread_b = values
    if abs(mean_a - mean_b) <= spread_a + spread_b:
        return "="
    return "<" if mean_a < mean_b else ">"


def _row_order(row_sets):
    """Every row of ``row_sets`` (each a table's row names; a row may be
    missing from some), in the tables' order (``ROWS``, each followed by its
    as-released row)."""
    names = []
    for rows in row_sets:
        names += [row for row in rows if row not in names]
    order = [row for base in ROWS for row in (base, base + RELEASED)]
    return sorted(names, key=lambda r: (order.index(r) if r in order else len(order),
                                        names.index(r)))


def _aggregate_rows(tables, seeds):
    """Each row over the seeds that have it: means, its ``seeds``, its
    ``per_seed`` values and (2+ seeds) its ``spread``."""
    rows = {}
    for row in _row_order([t.rows for t in tables]):
        present = [(s, t.rows[row]) for s, t in zip(seeds, tables) if row in t.rows]
        row_seeds = [s for s, _ in present]
        parts = [p for _, p in present]
        first = parts[0]
        entry = {"source": ", ".join(p["source"] for p in parts),
                 "as_released": first["as_released"],
                 "num_pairs": int(sum(p["num_pairs"] for p in parts))}
        if "failures" in first:
            total = entry["num_pairs"]
            failures = {"num_pairs": total}
            for flag in FAILURE_FLAGS + ("all_stages_ok",):
                count = int(sum(p["failures"][flag]["count"] for p in parts))
                failures[flag] = {"count": count, "rate": count / total if total else None}
            entry["priors"] = {f"seed {s}": p["priors"] for s, p in present}
            entry["failures"] = failures
        targets, target_spread = {}, {}
        for name, first_metrics in first["targets"].items():
            targets[name], target_spread[name] = {}, {}
            for key in first_metrics:
                values = [p["targets"][name][key] for p in parts]
                if key == "num_defined":
                    targets[name][key] = int(sum(values))
                    continue
                targets[name][key], spread = mean_and_spread(values)
                if key in SPREAD_METRICS:
                    target_spread[name][key] = spread
        fov, fov_spread = {}, {}
        for k in first["fov_within_deg"]:
            fov[k], fov_spread[k] = mean_and_spread([p["fov_within_deg"][k] for p in parts])
        entry.update(targets=targets, fov_within_deg=fov)
        if all("field" in p for p in parts):  # (Table 2: the field's focal and FoV metrics)
            entry["field"] = {key: mean_and_spread([p["field"][key] for p in parts])[0]
                              for key in first["field"]}
        if "degenerate" in first:
            entry["degenerate"] = first["degenerate"]
        entry["seeds"] = row_seeds
        if len(parts) > 1:              # one seed: its values, no spread
            entry["spread"] = {"targets": target_spread, "fov_within_deg": fov_spread}
        entry["per_seed"] = {str(s): {
            "targets": {name: {key: p["targets"][name][key] for key in SPREAD_METRICS}
                        for name in p["targets"]},
            "fov_within_deg": p["fov_within_deg"]} for s, p in present}
        rows[row] = entry
    return rows


def _aggregate_table(tables, seeds):
    """The first seed's table with the seeds' rows, pairs, runs and
    descriptions (a ``Table1`` or ``Table2``; a pooled Table 2's rigs left
    to ``aggregate_seeds``)."""
    num_pairs = int(sum(t.num_pairs for t in tables))
    description = f"{num_pairs} pairs over {len(seeds)} seeds: " + "; ".join(
        f"seed {s}: {t.data_description}" for s, t in zip(seeds, tables))
    return dataclasses.replace(
        tables[0], seeds=[int(s) for s in seeds], spread=SPREAD, num_pairs=num_pairs,
        data_description=description, runs=[r for t in tables for r in t.runs],
        rows=jsonable(_aggregate_rows(tables, seeds)))


def aggregate_seeds(tables, seeds):
    """One table from the same table made for several seeds (each seed its
    own split and initial weights): every cell is the mean over the seeds
    that have the row (a run trained on the first seed only is a row of that
    seed's table alone), the row's ``seeds`` lists them, its spread
    (``SPREAD``, only over 2+ seeds) is in the row's ``spread`` and each
    seed's value in ``per_seed``; pair and failure counts are summed. Table
    2's rigs are aggregated one by one and its FOV points pooled. One seed:
    that table."""
    tables, seeds = list(tables), [int(s) for s in seeds]
    if len(tables) != len(seeds) or not tables:
        raise EvaluationError("aggregate_seeds needs one table per seed")
    if len(tables) == 1:
        return tables[0]
    table = _aggregate_table(tables, seeds)
    if not (isinstance(table, Table2) and table.pooled):
        return table
    rigs = list(tables[0].rigs)
    for seed, other in zip(seeds[1:], tables[1:]):
        if list(other.rigs) != rigs:
            raise EvaluationError(f"seed {seed} has rigs {list(other.rigs)}, seed "
                                  f"{seeds[0]} has {rigs}")
    fov_points = {
        rig: {row: {key: [x for t in tables if row in t.fov_points[rig]
                          for x in t.fov_points[rig][row][key]]
                    for key in ("true_deg", "pred_deg")}
              for row in _row_order([t.fov_points[rig] for t in tables])}
        for rig in tables[0].fov_points}
    # a seed whose rows all had the same pairs is its own table on shared pairs
    shared = [t.shared or dataclasses.replace(t, rigs=None, fov_points=None, paper={})
              for t in tables]
    return dataclasses.replace(
        table, rigs={rig: _aggregate_table([t.rigs[rig] for t in tables], seeds)
                     for rig in rigs}, fov_points=jsonable(fov_points),
        shared=_aggregate_table(shared, seeds) if any(t.shared for t in tables) else None)

