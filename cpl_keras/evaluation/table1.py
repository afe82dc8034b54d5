"""Table 1 (and the rows every table shares): scored from runs and baselines.

``make_table`` scores the rows of the paper's tables -- Average, the
release's buggy Average, Deep-Homo, MTL-CPL-U, MTL-Baseline, MTL-CPL-A and
the Geometric baseline -- in both NMAE conventions (``cpl_keras.metrics``);
``table_rows`` gathers what it scores and ``table_from_rows`` scores it, so
a table rebuilt from published predictions goes through the same code.
``evaluate_run`` scores one run. Each returns a ``Table1``
(``cpl_keras.evaluation.tables``).

Each row is scored against the targets its method predicts: a run trained
with ``as_released`` against the release's targets
(``datasets.targets_from_labels(..., as_released=True)``), the Average rows
against the targets of the run whose statistics they use, the Geometric
baseline against the paper's targets. The truth convention of every row is
recorded in the JSON.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from cpl_keras import metrics
from cpl_keras.baselines import geometric as geo
from cpl_keras.baselines.average import average_predictions
from cpl_keras.camera import TARGETS
from cpl_keras.evaluation.forward_pass import forget_model, published, run_predictions
from cpl_keras.evaluation.pairs import (
    EvaluationError, _same_file, evaluation_indices, load_table_runs, open_dataset,
    truth_targets,
)
from cpl_keras.evaluation.tables import Table1
from cpl_keras.metrics import jsonable
from cpl_keras.models.variants import MODEL_ROWS, VARIANT_ROWS
from cpl_keras.runs import RELEASED, load_run
from cpl_keras.table_rows import Row

#: Row order of the paper's tables (plus our two extra rows).
ROWS = ("Average", "Average (release bug)") + MODEL_ROWS + ("Geometric",)
#: Which NMAE convention the paper used for each table (REPRODUCTION_NOTES.md).
PAPER_CONVENTION = {1: "nmae_signed", 2: "nmae"}
#: Where the paper's own tables are (``paper_table1.csv``, ``paper_table2.csv``):
#: package data beside this module, so that an install that is not editable
#: has them too.
PAPER_TABLES = os.path.dirname(os.path.abspath(__file__))


def score(truth, predictions, width):
    """Metrics of every target and the FOV-threshold curve."""
    per_target = metrics.parameter_metrics(truth, predictions, names=TARGETS)
    curve = metrics.fov_threshold_curve(truth["fx"], predictions["fx"], width)
    return {"targets": per_target, "fov_within_deg": {
        str(k): float(p) for k, p in zip(metrics.FOV_THRESHOLDS_DEG, curve)}}


def evaluate_run(run_dir, data_path, batch_size=32):
    """Score one run on ``data_path``: a ``Table1`` of one row (``table`` None)."""
    run = load_run(run_dir)
    with open_dataset(data_path) as data:
        indices, description = evaluation_indices(run, data_path, data.num_pairs)
        truth = truth_targets(data.labels, indices, run.as_released)
        predictions = run_predictions(run, data, indices, batch_size)
        forget_model(run)
        width = data.image_shape[1]
        metadata = data.metadata
    row = VARIANT_ROWS[run.config.variant]
    return Table1(**jsonable({
        "table": None, "data": os.path.abspath(data_path), "data_description": description,
        "data_source": metadata.get("source", metadata.get("protocol")),
        "num_pairs": int(len(indices)), "image_width": int(width), "runs": [run.run_dir],
        "rows": {row: {"source": run.run_dir, "as_released": run.as_released,
                       "num_pairs": int(len(indices)),
                       **score(truth, predictions, width)}},
        "paper": {}, "paper_convention": None,
    }))


def read_paper_table(number, directory=PAPER_TABLES):
    """The paper's Table ``number`` as {row: {column: float}} (from CSV; {}
    where ``directory`` has no such file)."""
    path = os.path.join(directory, f"paper_table{number}.csv")
    table = {}
    try:
        with open(path) as f:
            header = f.readline().strip().split(",")
            for line in f:
                cells = line.strip().split(",")
                if len(cells) == len(header):
                    table[cells[0]] = {c: float(v) for c, v in zip(header[1:], cells[1:])}
    except OSError:
        return {}
    return table


def average_rows(reference, labels, indices):
    """The two Average rows from the statistics of the run ``reference``:
    {row: ``Row``} on pairs ``indices``. The release's buggy Average
    averaged the release's labels, so it is scored against the release's
    truth (its frame, degrees, StereoBM disparity)."""
    rows = {}
    for row, kind, released in (("Average", "mean", reference.as_released),
                                ("Average (release bug)", "release", True)):
        pred = {k: np.asarray(v, np.float64)
                for k, v in average_predictions(reference.stats, len(indices), kind=kind).items()}
        rows[row] = Row(source=f"{reference.run_dir}/train_stats.json ({kind})",
                        as_released=released, indices=indices, pred=pred,
                        truth=truth_targets(labels, indices, released))
    return rows


def geometric_predictions(reference, data, subset):
    """The Geometric baseline on pairs ``subset`` of the open dataset ``data``:
    ``(priors, predictions, statuses)``; its fallbacks are the training means
    (of the run ``reference``) of the unobservable or failed quantities."""
    stats_mean = reference.stats["mean"]
    priors = {"baseline": stats_mean["baseline"], "fx": stats_mean["fx"], "fy": stats_mean["fx"]}
    pred, statuses = geo.predict_file(data, subset, priors=priors)
    return priors, pred, statuses


def table_rows(number, run_dirs, data_path=None, geometric=True, geometric_max=None,
               batch_size=32, progress=None):
    """The raw rows of the paper's Table ``number`` (1: synthetic; Table 2,
    per real rig and pooled, is ``table2_rigs``): ``(context, rows)``,
    everything ``make_table`` scores.

    ``rows`` maps a row name to its ``cpl_keras.table_rows.Row`` (the
    Geometric row's with ``priors`` and ``statuses``), gathered in any order
    (``table_from_rows`` puts them in the paper's); ``context`` holds the
    table's own fields (``table``, ``data``, ``data_description``,
    ``data_source``, ``data_metadata``, ``num_pairs``, ``image_width``,
    ``runs``). Table 1 evaluates on the runs' own dataset (their common test
    split) unless ``data_path`` is given.
    """
    if number != 1:
        raise EvaluationError(f"unknown table {number}: make_table scores Table 1 "
                              f"(Table 2 is make_table2)")
    loaded = load_table_runs(run_dirs)
    reference = loaded[0]
    data_path = _table_data(loaded, data_path)
    with open_dataset(data_path) as data:
        indices, description = _common_split(loaded, data_path, data)
        rows = {name: dataclasses.replace(row, pred=published(row.pred))
                for name, row in average_rows(reference, data.labels, indices).items()}
        rows.update(_model_rows(loaded, data, indices, batch_size, progress))
        if geometric:
            rows.update(_geometric_row(reference, data, indices, geometric_max, progress))
        metadata = data.metadata
        context = {
            "table": number, "data": os.path.abspath(data_path),
            "data_description": description,
            "data_source": metadata.get("source", metadata.get("protocol")),
            "data_metadata": {k: v for k, v in metadata.items() if k in (
                "source", "protocol", "seed", "image_size", "crops", "right", "labels",
                "split")},
            "num_pairs": int(len(indices)), "image_width": int(data.image_shape[1]),
            "runs": [r.run_dir for r in loaded],
        }
    return jsonable(context), rows


def _table_data(loaded, data_path):
    """The dataset file a table's runs are scored on: ``data_path``, or the
    one file every run of ``loaded`` was trained on."""
    if data_path is None:
        data_path = loaded[0].config.data.path
        for run in loaded[1:]:
            if not _same_file(run.config.data.path, data_path):
                raise EvaluationError(
                    f"runs use different datasets ({data_path} and {run.config.data.path}); "
                    f"pass --data to evaluate them on one file")
    if not os.path.exists(data_path):
        raise EvaluationError(f"dataset not found: {data_path}")
    return data_path


def _common_split(loaded, data_path, data):
    """``(indices, description)``: the evaluation pairs of the first run of
    ``loaded``, which every other run must share."""
    reference = loaded[0]
    indices, description = evaluation_indices(reference, data_path, data.num_pairs)
    for run in loaded[1:]:
        other, _ = evaluation_indices(run, data_path, data.num_pairs)
        if not np.array_equal(np.sort(other), np.sort(indices)):
            raise EvaluationError(
                f"{run.run_dir} has a different test split from {reference.run_dir}; "
                f"train the runs with the same --split and --seed")
    return indices, description


def _model_rows(loaded, data, indices, batch_size, progress):
    """The ``Row`` of each run of ``loaded``: its forward pass on ``indices``."""
    rows = {}
    for run in loaded:
        if progress:
            progress(f"forward pass: {run.config.variant} ({run.run_dir})")
        pred = run_predictions(run, data, indices, batch_size)
        forget_model(run)
        rows[run.row] = Row(source=run.run_dir, as_released=run.as_released, indices=indices,
                            truth=truth_targets(data.labels, indices, run.as_released),
                            pred=published(pred))
    return rows


def _geometric_row(reference, data, indices, geometric_max, progress):
    """``{"Geometric": its Row}`` on the first ``geometric_max`` of
    ``indices`` (all if None); ``{}`` for a file with the release's labels
    only (the baseline predicts the project's quantities)."""
    if data.as_released_only:
        if progress:
            progress("no Geometric row: it predicts the project's quantities, and this file "
                     "has the release's labels only")
        return {}
    subset = indices if geometric_max is None else indices[: int(geometric_max)]
    if progress:
        progress(f"geometric baseline on {len(subset)} pairs")
    priors, pred, statuses = geometric_predictions(reference, data, subset)
    return {"Geometric": Row(source="cpl_keras.baselines.geometric", as_released=False,
                             indices=subset, truth=truth_targets(data.labels, subset, False),
                             pred=published(pred), priors=priors, statuses=statuses)}


def table_from_rows(context, rows):
    """Score the ``rows`` of ``table_rows`` (name -> ``Row``; or of published
    predictions files) into the table: a ``Table1`` with every figure."""
    width = context["image_width"]
    scored = {}
    for name, row in rows.items():
        entry = {"source": row.source, "as_released": bool(row.as_released),
                 "num_pairs": int(row.num_pairs)}
        if name == "Geometric":
            entry.update(priors=row.priors, failures=geo.failure_report(row.statuses))
        scored[name] = dict(entry, **score(row.truth, row.pred, width))
    number = context["table"]
    table = dict(context)
    table["rows"] = {row: scored[row] for base in ROWS for row in (base, base + RELEASED)
                     if row in scored}
    table["paper"] = read_paper_table(number)
    table["paper_convention"] = PAPER_CONVENTION[number]
    return Table1(**jsonable(table))


def make_table(number, run_dirs, data_path=None, geometric=True, geometric_max=None,
               batch_size=32, progress=None):
    """Score the rows of the paper's Table ``number`` (1: synthetic; Table 2
    is ``make_table2``) on the runs' own dataset (their common test split)
    unless ``data_path`` is given. Returns a ``Table1`` with every figure.
    """
    return table_from_rows(*table_rows(number, run_dirs, data_path, geometric, geometric_max,
                                       batch_size, progress))

