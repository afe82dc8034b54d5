"""Evaluation of trained runs and baselines: the paper's Tables 1 and 2.

* ``load_run`` reads a run directory written by ``cpl_keras.training``
  (config.json, model.keras, train_stats.json, split.npz) and checks it.
* ``predict_run`` runs a model's forward pass over pairs of a dataset file.
* ``evaluate_run`` scores one run (on its test split when the data is the
  run's own dataset, else on the whole file).
* ``make_table`` scores the rows of the paper's tables -- Average, the
  release's buggy Average, Deep-Homo, MTL-CPL-U, MTL-Baseline, MTL-CPL-A and
  the Geometric baseline -- in both NMAE conventions (``cpl_keras.metrics``),
  and ``write_table`` writes Markdown, CSV, JSON and a FOV-threshold plot
  atomically.

Each row is scored against the targets its method predicts: a run trained
with ``as_released`` against the release's targets
(``datasets.targets_from_labels(..., as_released=True)``), the Average rows
against the targets of the run whose statistics they use, the Geometric
baseline against the paper's targets. The truth convention of every row is
recorded in the JSON.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

from cpl_keras import metrics
from cpl_keras.camera import PARAMETERS, TARGETS
from cpl_keras.data.storage import DatasetError, StereoFile

#: Row order of the paper's tables (plus our two extra rows).
ROWS = ("Average", "Average (release bug)", "Deep-Homo", "MTL-CPL-U", "MTL-Baseline",
        "MTL-CPL-A", "Geometric")
#: Table row of each model variant.
VARIANT_ROWS = {"deep-homo": "Deep-Homo", "cpl-u": "MTL-CPL-U", "baseline": "MTL-Baseline",
                "cpl-a": "MTL-CPL-A"}
#: Table columns (the paper's names) and the parameter each one is.
#: Suffix of the row of a run trained with ``as_released`` (its own row, so
#: the paper's and the release's version of a model can share a table).
RELEASED = " (as released)"
COLUMNS = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "theta_p")
COLUMN_PARAMETER = dict(zip(COLUMNS, PARAMETERS))
#: Which NMAE convention the paper used for each table (REPRODUCTION_NOTES.md).
PAPER_CONVENTION = {1: "nmae_signed", 2: "nmae"}
CONVENTIONS = ("nmae", "nmae_signed")
CONVENTION_TITLES = {
    "nmae": "NMAE = MAE / mean(|y|) (the paper's Eq. NMAE)",
    "nmae_signed": "NMAE = MAE / mean(y), signed mean (what produced the paper's Table 1)",
}
PAPER_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                         "paper_results")


class EvaluationError(ValueError):
    """A run directory, dataset or argument cannot be evaluated (one line)."""


# ---------------------------------------------------------------------------
# Runs and predictions
# ---------------------------------------------------------------------------
def load_run(run_dir):
    """The run's files as a dict: ``run_dir``, ``config``, ``stats``,
    ``split`` (train/val/test arrays), ``model_path``. Raises
    ``EvaluationError`` naming the first missing or malformed file."""
    run_dir = os.path.abspath(os.fspath(run_dir))
    if not os.path.isdir(run_dir):
        raise EvaluationError(f"run directory not found: {run_dir}")
    paths = {name: os.path.join(run_dir, name) for name in
             ("config.json", "model.keras", "train_stats.json", "split.npz")}
    for name, path in paths.items():
        if not os.path.isfile(path):
            what = "weights (model.keras)" if name == "model.keras" else name
            raise EvaluationError(f"run directory {run_dir} has no {what}")
    from cpl_keras.baselines.average import load_statistics
    from cpl_keras.datasets import load_split

    run = {"run_dir": run_dir, "model_path": paths["model.keras"]}
    try:
        with open(paths["config.json"]) as f:
            run["config"] = json.load(f)
    except (OSError, json.JSONDecodeError) as error:
        raise EvaluationError(f"cannot read {paths['config.json']}: {error}") from None
    try:
        run["stats"] = load_statistics(paths["train_stats.json"])
    except (OSError, ValueError) as error:  # JSONDecodeError is a ValueError
        raise EvaluationError(f"cannot read {paths['train_stats.json']}: {error}") from None
    for key in ("variant", "build", "data"):
        if key not in run["config"]:
            raise EvaluationError(f"{paths['config.json']} has no '{key}'")
    if run["config"]["variant"] not in VARIANT_ROWS:
        raise EvaluationError(f"{paths['config.json']}: unknown variant {run['config']['variant']!r}")
    try:
        run["split"] = load_split(paths["split.npz"])
    except (OSError, ValueError, KeyError) as error:
        raise EvaluationError(f"cannot read {paths['split.npz']}: {error}") from None
    return run


def as_released(run):
    return bool(run["config"].get("as_released", run["config"]["build"].get("as_released", False)))


def load_model(run):
    """The run's best model (``keras.saving.load_model(..., safe_mode=True)``)."""
    import keras

    import cpl_keras.models  # noqa: F401  (registers the custom layers)

    try:
        return keras.saving.load_model(run["model_path"], safe_mode=True)
    except Exception as error:  # corrupt archives raise many kinds of errors
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise EvaluationError(f"cannot load {run['model_path']}: {message}") from None


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
    from cpl_keras.datasets import targets_from_labels

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
        model = load_model(run)
        predictions = predict_run(model, data, indices, batch_size)
        width = data.image_shape[1]
        metadata = data.metadata
    row = VARIANT_ROWS[run["config"]["variant"]]
    return _jsonable({
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


def make_table(number, run_dirs, data_path=None, geometric=True, geometric_max=None,
               batch_size=32, progress=None):
    """Score the rows of the paper's Table ``number`` (1: synthetic, 2: real).

    Table 1 evaluates on the runs' own dataset (their common test split)
    unless ``data_path`` is given; Table 2 needs ``data_path`` (forward pass
    only). Returns a JSON-ready dict with every figure.
    """
    if number not in (1, 2):
        raise EvaluationError(f"unknown table {number}; choose 1 or 2")
    if not run_dirs:
        raise EvaluationError("no runs given (--runs RUN_DIR ...)")
    runs = [load_run(r) for r in run_dirs]
    rows_seen = {}
    for run in runs:
        row = row_name(run)
        if row in rows_seen:
            raise EvaluationError(f"two runs for {row}: {rows_seen[row]} and {run['run_dir']}")
        rows_seen[row] = run["run_dir"]
    if number == 2 and data_path is None:
        raise EvaluationError("table 2 needs --data REAL.h5")
    reference = runs[0]
    if data_path is None:
        data_path = reference["config"]["data"]
        for run in runs[1:]:
            if not _same_file(run["config"]["data"], data_path):
                raise EvaluationError(
                    f"runs use different datasets ({data_path} and {run['config']['data']}); "
                    f"pass --data to evaluate them on one file")
    if not os.path.exists(data_path):
        raise EvaluationError(f"dataset not found: {data_path}")
    with open_dataset(data_path) as data:
        indices, description = evaluation_indices(reference, data_path, data.num_pairs)
        for run in runs[1:]:
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

        from cpl_keras.baselines.average import average_predictions

        # the release's buggy Average averaged the release's labels: scored
        # against the release's truth (its frame, degrees, StereoBM disparity)
        for row, kind, released in (("Average", "mean", as_released(reference)),
                                    ("Average (release bug)", "release", True)):
            truth_ref = truth_targets(labels, indices, released)
            pred = {k: np.asarray(v, np.float64)
                    for k, v in average_predictions(reference["stats"], n, kind=kind).items()}
            rows[row] = {"source": f"{reference['run_dir']}/train_stats.json ({kind})",
                         "as_released": released, "num_pairs": n,
                         **score(truth_ref, pred, width)}
        for run in runs:
            if progress:
                progress(f"forward pass: {run['config']['variant']} ({run['run_dir']})")
            model = load_model(run)
            pred = predict_run(model, data, indices, batch_size)
            truth = truth_targets(labels, indices, as_released(run))
            rows[row_name(run)] = {
                "source": run["run_dir"], "as_released": as_released(run), "num_pairs": n,
                **score(truth, pred, width)}
            del model
        if geometric:
            from cpl_keras.baselines import geometric as geo

            subset = indices if geometric_max is None else indices[: int(geometric_max)]
            if progress:
                progress(f"geometric baseline on {len(subset)} pairs")
            stats_mean = reference["stats"]["mean"]
            # fallbacks: the training means of the unobservable / failed quantities
            priors = {"baseline": stats_mean["baseline"], "fx": stats_mean["fx"],
                      "fy": stats_mean["fx"]}
            pred, statuses = geo.predict_file(data, subset, priors=priors)
            truth = truth_targets(labels, subset, False)
            rows["Geometric"] = {"source": "cpl_keras.baselines.geometric", "as_released": False,
                                 "num_pairs": int(len(subset)), "priors": priors,
                                 "failures": geo.failure_report(statuses),
                                 **score(truth, pred, width)}
    table = {
        "table": number, "data": os.path.abspath(data_path), "data_description": description,
        "data_source": metadata.get("source", metadata.get("protocol")),
        "data_metadata": {k: v for k, v in metadata.items() if k in (
            "source", "protocol", "seed", "image_size", "crops", "right", "labels", "split")},
        "num_pairs": int(n), "image_width": int(width),
        "runs": [r["run_dir"] for r in runs],
        "rows": {row: rows[row] for base in ROWS for row in (base, base + RELEASED) if row in rows},
        "paper": read_paper_table(number), "paper_convention": PAPER_CONVENTION[number],
    }
    return _jsonable(table)


def row_name(run):
    """The table row of a run: its variant's row, marked when trained as released."""
    row = VARIANT_ROWS[run["config"]["variant"]]
    return row + RELEASED if as_released(run) else row


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return metrics.json_value(value)
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    return value


def _cell(row_metrics, column, convention):
    value = row_metrics["targets"][COLUMN_PARAMETER[column]][convention]
    return math.nan if value is None else value


def best_rows(table, convention):
    """{column: set of rows with the smallest |value|} (ties all win; undefined
    values never win).

    The paper bolded the smallest *signed* value, so a large negative NMAE
    could be marked best; a magnitude is what an error ratio means, so the
    smallest magnitude wins here."""
    best = {}
    if len(table["rows"]) < 2:
        return best
    for column in COLUMNS:
        candidates = [(abs(_cell(m, column, convention)), row)
                      for row, m in table["rows"].items()
                      if math.isfinite(_cell(m, column, convention))]
        if candidates:
            smallest = min(value for value, _ in candidates)
            best[column] = {row for value, row in candidates if value == smallest}
    return best


def markdown(table, command=None):
    """The table as Markdown: one table per NMAE convention, best marked in
    bold, the paper's numbers beside ours in the paper's convention."""
    number = table["table"]
    title = f"Table {number}" if number else "Evaluation"
    lines = [f"# {title}: NMAE per parameter", ""]
    if command:
        lines += ["Command:", "", "```", command, "```", ""]
    lines += [f"Data: `{table['data']}` ({table['data_description']}; source: "
              f"{table['data_source']}; image width {table['image_width']} px).", ""]
    for convention in CONVENTIONS:
        with_paper = convention == table["paper_convention"] and table["paper"]
        lines += [f"## {CONVENTION_TITLES[convention]}", ""]
        if with_paper:
            lines += [f"Cells: ours (paper's Table {number}).", ""]
        best = best_rows(table, convention)
        lines.append("| method | " + " | ".join(COLUMNS) + " |")
        lines.append("|---" * (len(COLUMNS) + 1) + "|")
        for row, row_metrics in table["rows"].items():
            cells = []
            for column in COLUMNS:
                text = metrics.format_value(_cell(row_metrics, column, convention))
                if row in best.get(column, ()):
                    text = f"**{text}**"
                if with_paper:
                    paper_row = row[: -len(RELEASED)] if row.endswith(RELEASED) else row
                    paper_row = "Average" if paper_row == "Average (release bug)" else paper_row
                    paper = table["paper"].get(paper_row, {}).get(column)
                    if paper is not None and row != "Average":
                        text += f" ({paper:.3f})"
                cells.append(text)
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["Best per column (smallest |NMAE|) in bold; `n/a` = undefined (zero mean).",
              "The paper's Average row is placed beside 'Average (release bug)': the",
              "release's Average predicted parameter i as the mean of the 13 labels of",
              "training sample i.", ""]
    lines += ["## Percentage within k degrees of field of view", "",
              "| method | " + " | ".join(f"{k} deg" for k in metrics.FOV_THRESHOLDS_DEG) + " |",
              "|---" * (len(metrics.FOV_THRESHOLDS_DEG) + 1) + "|"]
    for row, row_metrics in table["rows"].items():
        cells = [metrics.format_value(row_metrics["fov_within_deg"][str(k)], 2)
                 for k in metrics.FOV_THRESHOLDS_DEG]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    lines.append("")
    geo = table["rows"].get("Geometric")
    if geo:
        report = geo["failures"]
        parts = [f"{flag} {report[flag]['count']}/{report['num_pairs']}" for flag in report
                 if isinstance(report[flag], dict)]
        lines += [f"Geometric baseline on {geo['num_pairs']} pairs; stage failures (fallback "
                  f"to priors {geo['priors']}): " + ", ".join(parts) + ".", ""]
    return "\n".join(lines)


def csv_text(table):
    """One CSV row per (method, metric): metric in mae, nmae, nmae_signed."""
    lines = ["method,metric," + ",".join(COLUMNS)]
    for row, row_metrics in table["rows"].items():
        for metric in ("mae",) + CONVENTIONS:
            values = [_cell(row_metrics, column, metric) for column in COLUMNS]
            lines.append(f"{row},{metric}," + ",".join(
                "n/a" if not math.isfinite(v) else f"{v:.6g}" for v in values))
    return "\n".join(lines) + "\n"


def fov_plot(table, path):
    """Percentage within k degrees of FOV vs k, one curve per row (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ks = list(metrics.FOV_THRESHOLDS_DEG)
    for row, row_metrics in table["rows"].items():
        values = [row_metrics["fov_within_deg"][str(k)] for k in ks]
        values = [math.nan if v is None else v for v in values]
        ax.plot(ks, values, marker="o", label=row)
    ax.set_xlabel("field-of-view error threshold (degrees)")
    ax.set_ylabel("samples within threshold (%)")
    ax.set_title(f"Table {table['table']}: FOV-threshold curves" if table["table"]
                 else "FOV-threshold curve")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100, format="png")
    plt.close(fig)


def write_outputs(out_dir, stem, table, command):
    """Write ``stem``.md/.csv/.json/_fov.png into ``out_dir``: everything is
    rendered to temporary files first and renamed only when all succeeded."""
    if not os.path.isdir(out_dir):
        raise EvaluationError(f"output directory does not exist: {out_dir}")
    payload = dict(table, command=command)
    targets = {
        f"{stem}.md": markdown(table, command),
        f"{stem}.csv": csv_text(table),
        f"{stem}.json": json.dumps(payload, indent=2, allow_nan=False) + "\n",
    }
    written = []
    try:
        for name, text in targets.items():
            tmp = os.path.join(out_dir, f".{name}.partial")
            written.append((tmp, os.path.join(out_dir, name)))  # cleaned up on failure
            with open(tmp, "w") as f:
                f.write(text)
        if table.get("rows"):
            tmp = os.path.join(out_dir, f".{stem}_fov.png.partial")
            written.append((tmp, os.path.join(out_dir, f"{stem}_fov.png")))
            fov_plot(table, tmp)
    except Exception:
        for tmp, _ in written:
            if os.path.exists(tmp):
                os.remove(tmp)
        raise
    for tmp, final in written:
        os.replace(tmp, final)
    return [final for _, final in written]
