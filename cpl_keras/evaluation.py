"""Evaluation of trained runs and baselines: the paper's Tables 1 and 2.

* ``predict_run`` runs a model's forward pass over pairs of a dataset file.
* ``evaluate_run`` scores one run (on its test split when the data is the
  run's own dataset, else on the whole file).
* ``make_table`` scores the rows of the paper's tables -- Average, the
  release's buggy Average, Deep-Homo, MTL-CPL-U, MTL-Baseline, MTL-CPL-A and
  the Geometric baseline -- in both NMAE conventions (``cpl_keras.metrics``).

Runs are read through ``cpl_keras.runs``; the tables are rendered and
written by ``cpl_keras.report``.

Each row is scored against the targets its method predicts: a run trained
with ``as_released`` against the release's targets
(``datasets.targets_from_labels(..., as_released=True)``), the Average rows
against the targets of the run whose statistics they use, the Geometric
baseline against the paper's targets. The truth convention of every row is
recorded in the JSON.
"""

from __future__ import annotations

import os

import numpy as np

from cpl_keras import metrics, runs
from cpl_keras.baselines import geometric as geo
from cpl_keras.baselines.average import average_predictions
from cpl_keras.baselines.geometric import FAILURE_FLAGS
from cpl_keras.camera import TARGETS
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.datasets import targets_from_labels
from cpl_keras.models.variants import MODEL_ROWS, VARIANT_ROWS
from cpl_keras.report import jsonable
from cpl_keras.runs import RELEASED, as_released, row_name

#: Row order of the paper's tables (plus our two extra rows).
ROWS = ("Average", "Average (release bug)") + MODEL_ROWS + ("Geometric",)
#: Which NMAE convention the paper used for each table (REPRODUCTION_NOTES.md).
PAPER_CONVENTION = {1: "nmae_signed", 2: "nmae"}
PAPER_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                         "paper_results")


class EvaluationError(runs.RunError):
    """A run directory, dataset or argument cannot be evaluated (one line)."""


# ---------------------------------------------------------------------------
# Runs and predictions
# ---------------------------------------------------------------------------
def load_run(run_dir):
    """``runs.load_run``, raising ``EvaluationError``."""
    return runs.load_run(run_dir, error=EvaluationError)


def load_model(run):
    """``runs.load_model``, raising ``EvaluationError``."""
    return runs.load_model(run, error=EvaluationError)


def model_image_shape(model):
    """(height, width) the model takes."""
    shape = model.inputs[0].shape
    return int(shape[1]), int(shape[2])


def predict_images(model, left, right, batch_size=32):
    """Forward pass on uint8 image arrays (n, H, W, 3): dict name -> (n,) float64."""
    out = {name: [] for name in TARGETS}
    for start in range(0, len(left), batch_size):
        inputs = {"left_image": np.asarray(left[start:start + batch_size], np.float32),
                  "right_image": np.asarray(right[start:start + batch_size], np.float32)}
        pred = model.predict_on_batch(inputs)
        if not isinstance(pred, dict):
            pred = dict(zip(model.output_names, pred if isinstance(pred, (list, tuple)) else [pred]))
        for name in TARGETS:
            out[name].append(np.asarray(pred[name], np.float64).reshape(-1))
    return {name: np.concatenate(values) if values else np.zeros(0) for name, values in out.items()}


def predict_run(model, stereo_file, indices, batch_size=32):
    """Forward pass over pairs ``indices`` of an open ``StereoFile``."""
    height, width = model_image_shape(model)
    if stereo_file.image_shape[:2] != (height, width):
        raise EvaluationError(
            f"{stereo_file.path}: images are {stereo_file.image_shape[0]}x"
            f"{stereo_file.image_shape[1]}, the model takes {height}x{width}")
    parts = []
    for start in range(0, len(indices), 256):
        left, right = stereo_file.read_pairs(indices[start:start + 256])
        parts.append(predict_images(model, left, right, batch_size))
    return {name: np.concatenate([p[name] for p in parts]) if parts else np.zeros(0)
            for name in TARGETS}


def run_predictions(run, stereo_file, indices, batch_size=32):
    """The run's outputs on pairs ``indices`` of an open ``StereoFile``: its
    stored predictions for that file when it has them (a published run has
    nothing else), else a forward pass of its model (loaded once, kept on
    ``run["_model"]``; ``forget_model`` drops it)."""
    stored = runs.read_predictions(run["run_dir"], stereo_file.path, indices, TARGETS,
                                   error=EvaluationError)
    if stored is not None:
        return stored
    if run.get("_model") is None:
        run["_model"] = load_model(run)
    return predict_run(run["_model"], stereo_file, indices, batch_size)


def forget_model(run):
    """Drop the model ``run_predictions`` kept on ``run``."""
    run.pop("_model", None)


def store_predictions(run_dir, data_paths, batch_size=32):
    """Store the run's outputs (``runs.write_predictions``): on its own
    dataset's test split, and on every pair of each other file of
    ``data_paths`` (real sets, folders of them). The forward passes are the
    ones the tables make. Returns the paths written."""
    run = load_run(run_dir)
    paths = [run["config"]["data"]] + [p for p in data_paths
                                       if not _same_file(p, run["config"]["data"])]
    written = []
    try:
        for path in paths:
            with open_dataset(path) as data:
                indices, _ = evaluation_indices(run, path, data.num_pairs)
                pred = run_predictions(run, data, indices, batch_size)
            written.append(runs.write_predictions(run_dir, path, indices, pred, TARGETS))
    finally:
        forget_model(run)
    return written


def _same_file(a, b):
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def open_dataset(path):
    """Open and validate a dataset file (EvaluationError on failure)."""
    try:
        return StereoFile(path)
    except DatasetError as error:
        raise EvaluationError(str(error)) from None


def evaluation_indices(run, data_path, num_pairs):
    """``(indices, description)``: the run's test split when ``data_path`` is
    the run's own dataset, else every pair of the file."""
    if _same_file(data_path, run["config"]["data"]):
        test = run["split"]["test"]
        if len(test) == 0 or test.max() >= num_pairs:
            raise EvaluationError(f"{run['run_dir']}: test split does not fit {data_path}")
        return test, f"test split of the run ({len(test)} of {num_pairs} pairs)"
    return np.arange(num_pairs), f"all {num_pairs} pairs of the file"


def truth_targets(labels, indices, released):
    try:
        targets = targets_from_labels(labels, as_released=released)
    except DatasetError as error:
        raise EvaluationError(str(error)) from None
    return {name: np.asarray(targets[name], np.float64)[indices] for name in TARGETS}


def score(truth, predictions, width):
    """Metrics of every target and the FOV-threshold curve."""
    per_target = metrics.parameter_metrics(truth, predictions, names=TARGETS)
    curve = metrics.fov_threshold_curve(truth["fx"], predictions["fx"], width)
    return {"targets": per_target, "fov_within_deg": {
        str(k): float(p) for k, p in zip(metrics.FOV_THRESHOLDS_DEG, curve)}}


def evaluate_run(run_dir, data_path, batch_size=32):
    """Score one run on ``data_path``; returns a JSON-ready dict."""
    run = load_run(run_dir)
    with open_dataset(data_path) as data:
        indices, description = evaluation_indices(run, data_path, data.num_pairs)
        truth = truth_targets(data.labels, indices, as_released(run))
        predictions = run_predictions(run, data, indices, batch_size)
        forget_model(run)
        width = data.image_shape[1]
        metadata = data.metadata
    row = VARIANT_ROWS[run["config"]["variant"]]
    return jsonable({
        "table": None, "data": os.path.abspath(data_path), "data_description": description,
        "data_source": metadata.get("source", metadata.get("protocol")),
        "num_pairs": int(len(indices)), "image_width": int(width), "runs": [run["run_dir"]],
        "rows": {row: {"source": run["run_dir"], "as_released": as_released(run),
                       "num_pairs": int(len(indices)),
                       **score(truth, predictions, width)}},
        "paper": {}, "paper_convention": None,
    })


# ---------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------
def read_paper_table(number, directory=PAPER_DIR):
    """The paper's Table ``number`` as {row: {column: float}} (from CSV)."""
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
    {row: {source, as_released, truth, pred}}. The release's buggy Average
    averaged the release's labels, so it is scored against the release's
    truth (its frame, degrees, StereoBM disparity)."""
    rows = {}
    for row, kind, released in (("Average", "mean", as_released(reference)),
                                ("Average (release bug)", "release", True)):
        pred = {k: np.asarray(v, np.float64)
                for k, v in average_predictions(reference["stats"], len(indices), kind=kind).items()}
        rows[row] = {"source": f"{reference['run_dir']}/train_stats.json ({kind})",
                     "as_released": released, "truth": truth_targets(labels, indices, released),
                     "pred": pred}
    return rows


def geometric_predictions(reference, data, subset):
    """The Geometric baseline on pairs ``subset`` of the open dataset ``data``:
    ``(priors, predictions, statuses)``; its fallbacks are the training means
    (of the run ``reference``) of the unobservable or failed quantities."""
    stats_mean = reference["stats"]["mean"]
    priors = {"baseline": stats_mean["baseline"], "fx": stats_mean["fx"], "fy": stats_mean["fx"]}
    pred, statuses = geo.predict_file(data, subset, priors=priors)
    return priors, pred, statuses


def published(predictions):
    """``predictions`` at the precision of the published predictions files
    (float32, as a network outputs them), as float64 arrays: a table scored in
    memory and one rebuilt from the files agree to the last digit."""
    return {name: np.asarray(predictions[name], np.float32).astype(np.float64)
            for name in TARGETS}


def table_rows(number, run_dirs, data_path=None, geometric=True, geometric_max=None,
               batch_size=32, progress=None):
    """The raw rows of the paper's Table ``number`` (1: synthetic, 2: real):
    ``(context, rows)``, everything ``make_table`` scores.

    ``rows`` maps a row name to ``source``, ``as_released``, ``indices`` (the
    pairs of the dataset file), ``truth`` and ``pred`` (name -> array; the
    Geometric row also ``priors`` and ``statuses``); ``context`` holds the
    table's own fields (``table``, ``data``, ``data_description``,
    ``data_source``, ``data_metadata``, ``num_pairs``, ``image_width``,
    ``runs``). Table 1 evaluates on the runs' own dataset (their common test
    split) unless ``data_path`` is given; Table 2 needs ``data_path``
    (forward pass only).
    """
    if number not in (1, 2):
        raise EvaluationError(f"unknown table {number}; choose 1 or 2")
    if not run_dirs:
        raise EvaluationError("no runs given (--runs RUN_DIR ...)")
    loaded = [load_run(r) for r in run_dirs]
    rows_seen = {}
    for run in loaded:
        row = row_name(run)
        if row in rows_seen:
            raise EvaluationError(f"two runs for {row}: {rows_seen[row]} and {run['run_dir']}")
        rows_seen[row] = run["run_dir"]
    if number == 2 and data_path is None:
        raise EvaluationError("table 2 needs --data REAL.h5")
    reference = loaded[0]
    if data_path is None:
        data_path = reference["config"]["data"]
        for run in loaded[1:]:
            if not _same_file(run["config"]["data"], data_path):
                raise EvaluationError(
                    f"runs use different datasets ({data_path} and {run['config']['data']}); "
                    f"pass --data to evaluate them on one file")
    if not os.path.exists(data_path):
        raise EvaluationError(f"dataset not found: {data_path}")
    with open_dataset(data_path) as data:
        indices, description = evaluation_indices(reference, data_path, data.num_pairs)
        for run in loaded[1:]:
            other, _ = evaluation_indices(run, data_path, data.num_pairs)
            if not np.array_equal(np.sort(other), np.sort(indices)):
                raise EvaluationError(
                    f"{run['run_dir']} has a different test split from {reference['run_dir']}; "
                    f"train the runs with the same --split and --seed")
        width = data.image_shape[1]
        labels = data.labels
        metadata = data.metadata
        n = len(indices)
        rows = {}

        for row, raw in average_rows(reference, labels, indices).items():
            rows[row] = dict(raw, indices=indices, pred=published(raw["pred"]))
        for run in loaded:
            if progress:
                progress(f"forward pass: {run['config']['variant']} ({run['run_dir']})")
            pred = run_predictions(run, data, indices, batch_size)
            forget_model(run)
            rows[row_name(run)] = {
                "source": run["run_dir"], "as_released": as_released(run), "indices": indices,
                "truth": truth_targets(labels, indices, as_released(run)),
                "pred": published(pred)}
        if geometric:
            subset = indices if geometric_max is None else indices[: int(geometric_max)]
            if progress:
                progress(f"geometric baseline on {len(subset)} pairs")
            priors, pred, statuses = geometric_predictions(reference, data, subset)
            rows["Geometric"] = {"source": "cpl_keras.baselines.geometric", "as_released": False,
                                 "indices": subset, "truth": truth_targets(labels, subset, False),
                                 "pred": published(pred), "priors": priors,
                                 "statuses": statuses}
    context = {
        "table": number, "data": os.path.abspath(data_path), "data_description": description,
        "data_source": metadata.get("source", metadata.get("protocol")),
        "data_metadata": {k: v for k, v in metadata.items() if k in (
            "source", "protocol", "seed", "image_size", "crops", "right", "labels", "split")},
        "num_pairs": int(n), "image_width": int(width),
        "runs": [r["run_dir"] for r in loaded],
    }
    return jsonable(context), rows


def table_from_rows(context, rows):
    """Score the raw ``rows`` of ``table_rows`` (or of published predictions
    files) into the table: a JSON-ready dict with every figure."""
    width = context["image_width"]
    scored = {}
    for row, raw in rows.items():
        entry = {"source": raw["source"], "as_released": bool(raw["as_released"]),
                 "num_pairs": int(len(raw["indices"]))}
        if row == "Geometric":
            entry.update(priors=raw["priors"], failures=geo.failure_report(raw["statuses"]))
        scored[row] = dict(entry, **score(raw["truth"], raw["pred"], width))
    number = context["table"]
    table = dict(context)
    table["rows"] = {row: scored[row] for base in ROWS for row in (base, base + RELEASED)
                     if row in scored}
    table["paper"] = read_paper_table(number)
    table["paper_convention"] = PAPER_CONVENTION[number]
    return jsonable(table)


def make_table(number, run_dirs, data_path=None, geometric=True, geometric_max=None,
               batch_size=32, progress=None):
    """Score the rows of the paper's Table ``number`` (1: synthetic, 2: real).

    Table 1 evaluates on the runs' own dataset (their common test split)
    unless ``data_path`` is given; Table 2 needs ``data_path`` (forward pass
    only). Returns a JSON-ready dict with every figure.
    """
    return table_from_rows(*table_rows(number, run_dirs, data_path, geometric, geometric_max,
                                       batch_size, progress))


# ---------------------------------------------------------------------------
# One table over several seeds: mean and spread of every cell
# ---------------------------------------------------------------------------
#: What the spread of a table over seeds is (the "± x" of its cells).
SPREAD = "sample standard deviation over the seeds (n - 1 in the denominator)"
#: The metrics of a target that get a spread.
SPREAD_METRICS = ("mae", "nmae", "nmae_signed")


def _mean_and_spread(values):
    """Mean and sample standard deviation of ``values`` (None = undefined:
    an undefined value in any seed leaves both undefined)."""
    a = np.array([np.nan if v is None else v for v in values], np.float64)
    if not np.all(np.isfinite(a)):
        return None, None
    return float(np.mean(a)), float(np.std(a, ddof=1)) if len(a) > 1 else 0.0


def _row_order(tables):
    """Every row of ``tables`` (a row may be missing from some), in the
    tables' order (``ROWS``, each followed by its as-released row)."""
    names = []
    for table in tables:
        names += [row for row in table["rows"] if row not in names]
    order = [row for base in ROWS for row in (base, base + RELEASED)]
    return sorted(names, key=lambda r: (order.index(r) if r in order else len(order),
                                        names.index(r)))


def _aggregate_rows(tables, seeds):
    """Each row over the seeds that have it: means, its ``seeds``, its
    ``per_seed`` values and (2+ seeds) its ``spread``."""
    rows = {}
    for row in _row_order(tables):
        present = [(s, t["rows"][row]) for s, t in zip(seeds, tables) if row in t["rows"]]
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
                targets[name][key], spread = _mean_and_spread(values)
                if key in SPREAD_METRICS:
                    target_spread[name][key] = spread
        fov, fov_spread = {}, {}
        for k in first["fov_within_deg"]:
            fov[k], fov_spread[k] = _mean_and_spread([p["fov_within_deg"][k] for p in parts])
        entry.update(targets=targets, fov_within_deg=fov)
        if all("field" in p for p in parts):  # (Table 2: the field's focal and FoV metrics)
            entry["field"] = {key: _mean_and_spread([p["field"][key] for p in parts])[0]
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
    table = dict(tables[0])
    table["seeds"] = [int(s) for s in seeds]
    table["spread"] = SPREAD
    table["num_pairs"] = int(sum(t["num_pairs"] for t in tables))
    descriptions = [t["data_description"] for t in tables]
    table["data_description"] = (
        f"{table['num_pairs']} pairs over {len(seeds)} seeds: "
        + "; ".join(f"seed {s}: {d}" for s, d in zip(seeds, descriptions)))
    table["runs"] = [r for t in tables for r in t["runs"]]
    table["rows"] = _aggregate_rows(tables, seeds)
    return table


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
    if "rigs" in tables[0]:
        rigs = list(tables[0]["rigs"])
        for seed, other in zip(seeds[1:], tables[1:]):
            if list(other["rigs"]) != rigs:
                raise EvaluationError(f"seed {seed} has rigs {list(other['rigs'])}, seed "
                                      f"{seeds[0]} has {rigs}")
        table["rigs"] = {rig: _aggregate_table([t["rigs"][rig] for t in tables], seeds)
                         for rig in rigs}
        table["fov_points"] = {
            rig: {row: {key: [x for t in tables if row in t["fov_points"][rig]
                              for x in t["fov_points"][rig][row][key]]
                        for key in ("true_deg", "pred_deg")}
                  for row in _row_order([{"rows": t["fov_points"][rig]} for t in tables])}
            for rig in tables[0]["fov_points"]}
    return jsonable(table)
