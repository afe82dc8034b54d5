"""The paper's Table 2 over every real rig: one table per rig and one pooled.

``make_table2(run_dirs, data_paths)`` runs each model's forward pass (no
fine-tuning) and the Average and Geometric rows on every real set given (a
folder stands for its ``*.h5`` files), and scores them per rig and pooled
over all rigs, in both NMAE conventions, with the paper's Table 2 beside the
pooled table. ``cpl_keras.report.write_table`` writes it: Markdown, CSV,
JSON, the FOV-threshold curves and a plot of predicted against true
horizontal field of view per rig for every method, atomically.

Undefined values are never invented:

* a sample whose ``disparity_valid`` label is 0 (KITTI frames without
  ground-truth disparity) has no truth for disparity, X, Y, Z: those columns
  use the other samples, and are ``n/a`` when none is left;
* on a rectified rig (metadata ``rectified``, or pitch = yaw = roll = 0 for
  every sample) the Geometric row's fundamental-matrix focal length is
  degenerate (Bougnoux's formula is 0/0 when the optical axes are coplanar):
  its fx, fy cells say ``degenerate`` and those samples are left out of the
  pooled fx, fy and of the FOV curves and plot;
* a zero mean (pitch, tx, tz of a rectified rig) leaves NMAE undefined
  (``n/a``; ``cpl_keras.metrics``).

The pooled table scores each row on every pair where it has the column
defined, as the per-rig tables do: the networks and the Average row on every
pair with ground truth, the Geometric row on the pairs it ran on (and not
fx, fy on a rectified rig), and pitch only on rigs that are not rectified (a
rectified rig's relative pitch is 0 by construction). Where the rows' pairs
differ, the pooled table's ``shared`` holds the same rows on the same pairs:
each column pools, rig by rig, only the pairs on which every row has it.
"""

from __future__ import annotations

import dataclasses
import glob
import os

import numpy as np

from cpl_keras import metrics
from cpl_keras.baselines import geometric as geo
from cpl_keras.camera import TARGETS, fov_from_focal
from cpl_keras.evaluation.forward_pass import forget_model, published, run_predictions
from cpl_keras.evaluation.pairs import (
    EvaluationError, evaluation_indices, load_table_runs, open_dataset, truth_targets,
)
from cpl_keras.evaluation.table1 import (
    PAPER_CONVENTION, ROWS, average_rows, geometric_predictions, read_paper_table,
)
from cpl_keras.evaluation.tables import Table2
from cpl_keras.metrics import jsonable
from cpl_keras.runs import RELEASED
from cpl_keras.table_rows import Rig, Row


#: Targets that need the ground-truth disparity.
DISPARITY_TARGETS = ("disparity", "X", "Y", "Z")


#: Geometric columns that are degenerate on a rectified rig.
DEGENERATE_ON_RECTIFIED = ("fx", "fy")


def expand_data_paths(paths):
    """Files as given; a folder stands for its ``*.h5`` files (sorted)."""
    out = []
    for path in paths:
        if os.path.isdir(path):
            found = sorted(glob.glob(os.path.join(path, "*.h5")))
            if not found:
                raise EvaluationError(f"no *.h5 files in {path}")
            out += found
        elif not os.path.exists(path):
            raise EvaluationError(f"dataset not found: {path}")
        else:
            out.append(path)
    return out


def rig_name(metadata, path):
    return str(metadata.get("rig") or os.path.splitext(os.path.basename(path))[0])


def is_rectified(metadata, labels):
    if "rectified" in metadata:
        return bool(metadata["rectified"])
    return all(np.all(labels[k] == 0) for k in ("pitch", "yaw", "roll") if k in labels)


def _defined(labels, indices, n):
    valid = np.ones(n, bool)
    if "disparity_valid" in labels:
        valid = np.asarray(labels["disparity_valid"])[indices] != 0
    return {name: (valid if name in DISPARITY_TARGETS else np.ones(n, bool)) for name in TARGETS}


def score_masked(truth, pred, defined, width):
    """``score`` on the samples where each target is defined."""
    targets = {}
    for name in TARGETS:
        ok = np.asarray(defined[name], bool)
        targets[name] = metrics.parameter_metrics(
            {name: np.asarray(truth[name])[ok]}, {name: np.asarray(pred[name])[ok]},
            names=(name,))[name]
        targets[name]["num_defined"] = int(ok.sum())
    ok = np.asarray(defined["fx"], bool)
    curve = metrics.fov_threshold_curve(np.asarray(truth["fx"])[ok], np.asarray(pred["fx"])[ok],
                                        width)
    both = ok & np.asarray(defined["fy"], bool)
    # (the real sets are square: fy spans as many pixels as fx)
    field = metrics.focal_metrics(np.asarray(truth["fx"])[both], np.asarray(pred["fx"])[both],
                                  np.asarray(truth["fy"])[both], np.asarray(pred["fy"])[both],
                                  width, width)
    return {"targets": targets, "fov_within_deg": {
        str(k): float(p) for k, p in zip(metrics.FOV_THRESHOLDS_DEG, curve)}, "field": field}


def _check_never_trained_on(loaded, rig, data_path):
    """Leave one rig out: EvaluationError when a run's training pairs
    include pairs of ``rig`` (a real or mixed training set records its rigs)."""
    for run in loaded:
        if rig in run.config.data.training_rigs:
            raise EvaluationError(
                f"{run.run_dir} was trained on pairs of the rig '{rig}' ({data_path}); "
                f"Table 2 scores a model only on rigs it never saw in training")


def _rig_rows(loaded, data_path, geometric, geometric_max, progress):
    """The ``Rig`` of one real set: truth, predictions and definedness of every row."""
    reference = loaded[0]
    with open_dataset(data_path) as data:
        _check_never_trained_on(loaded, rig_name(data.metadata, data_path), data_path)
        indices, description = evaluation_indices(reference, data_path, data.num_pairs)
        labels, metadata = data.labels, data.metadata
        width, n = data.image_shape[1], len(indices)
        rectified = is_rectified(metadata, labels)
        defined = _defined(labels, indices, n)
        rows = {name: dataclasses.replace(row, defined=defined)
                for name, row in average_rows(reference, labels, indices).items()}
        for run in loaded:
            if progress:
                progress(f"forward pass on {rig_name(metadata, data_path)}: "
                         f"{run.config.variant} ({run.run_dir})")
            rows[run.row] = Row(
                source=run.run_dir, as_released=run.as_released, indices=indices,
                truth=truth_targets(labels, indices, run.as_released),
                pred=published(run_predictions(run, data, indices)), defined=defined)
        if geometric and data.as_released_only and progress:
            progress(f"no Geometric row on {rig_name(metadata, data_path)}: it predicts the "
                     "project's quantities, and this file has the release's labels only")
        if geometric and not data.as_released_only:
            subset = indices if geometric_max is None else indices[: int(geometric_max)]
            if progress:
                progress(f"geometric baseline on {len(subset)} pairs of {rig_name(metadata, data_path)}")
            priors, pred, statuses = geometric_predictions(reference, data, subset)
            geo_defined = _defined(labels, subset, len(subset))
            if rectified:
                geo_defined = dict(geo_defined, **{k: np.zeros(len(subset), bool)
                                                   for k in DEGENERATE_ON_RECTIFIED})
            rows["Geometric"] = Row(
                source="cpl_keras.baselines.geometric", as_released=False, indices=subset,
                truth=truth_targets(labels, subset, False), pred=published(pred),
                defined=geo_defined, priors=priors, statuses=statuses,
                degenerate=list(DEGENERATE_ON_RECTIFIED) if rectified else [])
    return Rig(rig=rig_name(metadata, data_path), data=os.path.abspath(data_path),
               data_description=description, rectified=rectified, width=int(width),
               data_source=metadata.get("source", metadata.get("protocol")),
               num_pairs=int(n), rows=rows)


def _table(raw_rows, *, number_of_pairs, width, data, description, source, runs, paper):
    rows = {}
    for name, r in raw_rows.items():
        entry = {"source": r.source, "as_released": r.as_released,
                 "num_pairs": int(r.num_pairs),
                 **score_masked(r.truth, r.pred, r.defined, width)}
        if name == "Geometric":
            entry.update(priors=r.priors, failures=geo.failure_report(r.statuses),
                         degenerate=r.degenerate)
        rows[name] = entry
    return jsonable({
        "table": 2, "data": data, "data_description": description, "data_source": source,
        "num_pairs": int(number_of_pairs), "image_width": int(width), "runs": runs,
        "rows": {row: rows[row] for base in ROWS for row in (base, base + RELEASED) if row in rows},
        "paper": paper, "paper_convention": PAPER_CONVENTION[2],
    })  # (the fields of a Table2: table2_from_rigs makes the records)


def _fov_points(r, width):
    ok = np.asarray(r.defined["fx"], bool)
    true = np.degrees(fov_from_focal(np.asarray(r.truth["fx"])[ok], width))
    pred = np.degrees(fov_from_focal(np.asarray(r.pred["fx"])[ok], width))
    return {"true_deg": true.tolist(), "pred_deg": pred.tolist()}


def table2_rigs(run_dirs, data_paths, geometric=True, geometric_max=None, progress=None):
    """The rows of Table 2 on every real set: ``(runs, rigs)``, the run
    directories and one ``cpl_keras.table_rows.Rig`` per real set (its rows:
    name -> ``Row``, each with ``defined``; Geometric's with ``priors``,
    ``statuses``, ``degenerate``), everything ``table2_from_rigs`` scores."""
    if run_dirs and not data_paths:
        raise EvaluationError("table 2 needs --data REAL.h5 (or a folder of real sets)")
    loaded = load_table_runs(run_dirs)
    paths = expand_data_paths(data_paths)
    try:
        rigs = [_rig_rows(loaded, path, geometric, geometric_max, progress) for path in paths]
    finally:
        for run in loaded:
            forget_model(run)
    return [r.run_dir for r in loaded], rigs


def table2_from_rigs(run_list, rigs):
    """Table 2 per rig and pooled from the ``Rig`` records of ``table2_rigs``
    (or of published predictions files): a pooled ``Table2``, with ``rigs`` (a
    ``Table2`` per rig) and ``fov_points`` (true and predicted horizontal
    FOV per rig and row)."""
    names = [r.rig for r in rigs]
    rigs = [dataclasses.replace(rig, rig=f"{rig.rig} ({os.path.basename(rig.data)})")
            if names.count(rig.rig) > 1 else rig      # two files of one rig: tell apart
            for rig in rigs]
    widths = {r.width for r in rigs}
    if len(widths) > 1:
        raise EvaluationError(f"real sets differ in image width ({sorted(widths)}); build them "
                              f"with one --image-size")
    width = widths.pop()
    run_list = list(run_list)
    tables = {}
    for rig in rigs:
        tables[rig.rig] = Table2(**_table(
            rig.rows, number_of_pairs=rig.num_pairs, width=width, data=rig.data,
            description=rig.data_description, source=rig.data_source, runs=run_list,
            paper={}), rectified=bool(rig.rectified))
    total = sum(r.num_pairs for r in rigs)
    single = len(rigs) == 1
    context = dict(number_of_pairs=total, width=width,
                   data=rigs[0].data if single else ", ".join(r.data for r in rigs),
                   description=rigs[0].data_description if single else (
                       f"{total} pairs pooled over {len(rigs)} rigs: " + ", ".join(
                           f"{r.rig} {r.num_pairs}" for r in rigs)),
                   source=rigs[0].data_source if single else "pooled real rigs", runs=run_list)
    own = _pooled_rows(rigs, [dict.fromkeys(TARGETS) for _ in rigs])   # every row's own pairs
    common = _pooled_rows(rigs, [_shared_pairs(rig) for rig in rigs])
    shared = None
    if any(not np.array_equal(own[row].defined[k], common[row].defined[k])
           for row in own for k in TARGETS):
        shared = Table2(**_table(common, **context, paper={}))
    fov_points = {rig.rig: {row: _fov_points(r, width) for row, r in rig.rows.items()}
                  for rig in rigs}
    return Table2(**_table(own, **context, paper=read_paper_table(2)), rigs=tables,
                  shared=shared, fov_points=jsonable(fov_points))


def _pooled_rows(rigs, pairs):
    """Every row's truth, predictions and definedness concatenated over the
    rigs, each target defined only on the pairs ``pairs`` gives per rig
    (None: all the row's own; or ``_shared_pairs``; ``_on_pairs``)."""
    pooled_rows = {}
    for row in rigs[0].rows:
        parts = [_on_pairs(rig.rows[row], chosen, rig.rectified)
                 for rig, chosen in zip(rigs, pairs) if row in rig.rows]
        defined = {k: np.concatenate([p.defined[k] for p in parts]) for k in TARGETS}
        geometric = {} if row != "Geometric" else dict(
            statuses=[s for p in parts for s in p.statuses],
            degenerate=[k for k in DEGENERATE_ON_RECTIFIED if not defined[k].any()])
        pooled_rows[row] = dataclasses.replace(
            parts[0], indices=np.concatenate([p.indices for p in parts]),
            truth={k: np.concatenate([p.truth[k] for p in parts]) for k in TARGETS},
            pred={k: np.concatenate([np.asarray(p.pred[k]) for p in parts]) for k in TARGETS},
            defined=defined, **geometric)
    return pooled_rows


def _shared_pairs(rig):
    """``{target: set of pair indices}`` where every row of the rig has the
    target defined: the pairs a pooled column compares all rows on."""
    common = {}
    for name in TARGETS:
        sets = [set(np.asarray(r.indices)[np.asarray(r.defined[name], bool)].tolist())
                for r in rig.rows.values()]
        common[name] = set.intersection(*sets) if sets else set()
    return common


def _on_pairs(raw, chosen, rectified):
    """A row of one rig for pooling: each target defined only on its
    ``chosen`` pairs (a set of pair indices, or None for all the row's), and
    pitch not at all on a rectified rig (its true relative pitch is 0 by
    construction: nothing to measure)."""
    indices = np.asarray(raw.indices)
    defined = {}
    for name in TARGETS:
        mask = np.asarray(raw.defined[name], bool)
        if chosen[name] is not None:
            mask = mask & np.isin(indices, list(chosen[name]))
        if rectified and name in UNDEFINED_ON_RECTIFIED:
            mask = np.zeros_like(mask)
        defined[name] = mask
    return dataclasses.replace(raw, defined=defined)


#: Targets that a rectified rig does not define (its rotation is 0 by construction).
UNDEFINED_ON_RECTIFIED = ("pitch",)


def make_table2(run_dirs, data_paths, geometric=True, geometric_max=None, progress=None):
    """Table 2 per rig and pooled (see the module doc): a pooled ``Table2``,
    with ``rigs`` (a ``Table2`` per rig) and ``fov_points`` (true and
    predicted horizontal FOV per rig and row)."""
    return table2_from_rigs(*table2_rigs(run_dirs, data_paths, geometric, geometric_max,
                                         progress))

