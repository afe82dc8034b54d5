"""Does it learn? Validation NMAE per parameter against samples seen.

``curves(run_dir)`` turns a finished (or running) run directory into one
NMAE curve per camera parameter: the validation MAE that training logged
after every epoch (``log.csv``) divided by mean(|y|) over the run's
validation pairs (the paper's NMAE), against the number of training samples
seen. The Average baseline's NMAE on the same pairs (each parameter
predicted as its training mean, ``train_stats.json``) is the level a network
must get below to have learned anything from the images.

    python -m cpl_keras.learning_curves RUN [RUN ...] --out DIR

writes ``DIR/<run name>.png`` (one panel per parameter) and
``DIR/learning_curves.md`` / ``.json`` (best validation NMAE per parameter
beside Average's, the scale of each run). ``--experiment`` first makes the
datasets and trains the runs of docs/training.md's "Does it learn?" section
(resumable: run it again after a kill).
"""

from __future__ import annotations

import json
import math
import os
import shlex
import sys
import time

import numpy as np

from cpl_keras import files, published, runs
from cpl_keras.baselines.average import load_statistics
from cpl_keras.camera import PARAMETERS
from cpl_keras.data.generate import cached_dataset
from cpl_keras.data.storage import StereoFile
from cpl_keras.datasets import load_split, targets_from_labels
from cpl_keras.errors import Error
from cpl_keras.metrics import nmae
from cpl_keras.report.curves import plot_nmae_curves, run_label as label_of_run, val_mae
from cpl_keras.training import train

#: The parameters the write-up quotes.
KEY_PARAMETERS = ("fx", "fy", "baseline", "pitch")


class CurveError(Error):
    """A run directory cannot be read (one line)."""


def read_log(run_dir):
    """log.csv as a list of dicts of floats (one per epoch, ``epoch``
    1-based; older 0-based logs are renumbered: ``runs.read_log``)."""
    path = os.path.join(run_dir, runs.LOG)
    if not os.path.isfile(path):
        raise CurveError(f"{run_dir} has no log.csv")
    return runs.read_log(path)


def curves(run_dir, data=None):
    """Validation NMAE per parameter after every epoch of a run.

    ``data`` is the run's dataset file (default: the path in config.json).
    Returns a dict: ``run_dir``, ``config``, ``samples_seen`` (list),
    ``nmae`` (parameter -> list, one value per epoch), ``average`` (parameter
    -> Average's NMAE on the same validation pairs), ``best`` (parameter ->
    lowest NMAE over the epochs) and ``best_epoch_nmae`` (parameter -> NMAE
    at the epoch early stopping kept).
    """
    run_dir = os.path.abspath(run_dir)
    try:
        config = runs.read_run_config(run_dir)
        if config is None:
            raise OSError(f"no {runs.CONFIG}")
        stats = load_statistics(os.path.join(run_dir, runs.STATS))
        split = load_split(os.path.join(run_dir, runs.SPLIT))
    except (OSError, ValueError, KeyError) as error:
        raise CurveError(f"cannot read run {run_dir}: {error}") from None
    rows = read_log(run_dir)
    data = data or config.data.path
    with StereoFile(data) as f:
        targets = targets_from_labels(f.labels, as_released=config.as_released)
    val = split["val"]
    scale = {}
    average = {}
    for name in PARAMETERS:
        truth = np.asarray(targets[name], np.float64)[val]
        scale[name] = float(np.mean(np.abs(truth)))
        average[name] = nmae(truth, np.full_like(truth, stats["mean"][name]))
    out = {name: [val_mae(row, name) / scale[name] if scale[name] > 0 else math.nan
                  for row in rows] for name in PARAMETERS}
    num_train = int(len(split["train"]) if config.data.num_train is None
                    else config.data.num_train)
    best_epoch = config.best_epoch
    if not best_epoch and rows:
        # a run still going (or killed): the epoch early stopping keeps so far
        best_epoch = 1 + int(np.nanargmin([row.get("val_loss", math.nan) for row in rows]))
    return {
        "run_dir": run_dir, "config": config, "rows": rows, "kept_epoch": best_epoch,
        "samples_seen": [int(row["epoch"]) * num_train for row in rows],
        "nmae": out, "average": average,
        "best": {name: float(np.nanmin(v)) if v and not np.all(np.isnan(v)) else math.nan
                 for name, v in out.items()},
        "best_epoch_nmae": {name: v[best_epoch - 1] if best_epoch and len(v) >= best_epoch
                            else math.nan for name, v in out.items()},
    }


def run_label(curve):
    return label_of_run(curve["config"])


def plot_title(curve):
    """The title of a run's learning-curve figure: the run, its training
    pairs and epochs, how it stopped."""
    row = summary_rows(curve)
    return (f"{run_label(curve)}: {row['num_train']} training pairs, {row['epochs_run']} epochs "
            f"({row['stopped'] or 'epoch cap'})")


def summary_rows(curve, load=None):
    config, rows = curve["config"], curve["rows"]
    loads = [row["load_average"] for row in rows if "load_average" in row]
    stopped = config.stopped
    if config.status != "finished":
        stopped = f"not finished ({config.status}): {len(rows)} epochs so far"
    row = {
        "run": os.path.basename(curve["run_dir"]), "label": run_label(curve),
        "num_train": config.data.num_train, "num_val": config.data.num_val,
        "epochs_run": len(rows), "best_epoch": curve["kept_epoch"],
        "stopped": stopped,
        "wall_time_s": rows[-1].get("wall_time_s", config.wall_time_s) if rows
        else config.wall_time_s,
        "load_average": float(np.mean(loads)) if loads else load,
        "best_epoch_nmae": curve["best_epoch_nmae"], "average_nmae": curve["average"],
    }
    return row


def markdown(rows):
    lines = ["# Does it learn? Validation NMAE (MAE / mean|y|) at the kept epoch, "
             "beside the Average baseline", ""]
    header = "| run | pairs (train/val) | epochs (kept) | stopped | wall time | mean load |"
    header += "".join(f" {p} | Avg {p} |" for p in KEY_PARAMETERS)
    lines += [header, "|" + "---|" * (6 + 2 * len(KEY_PARAMETERS))]
    for row in rows:
        cells = [row["label"], f"{row['num_train']}/{row['num_val']}",
                 f"{row['epochs_run']} ({row['best_epoch']})", row["stopped"] or "epoch cap",
                 f"{(row['wall_time_s'] or 0) / 60:.1f} min",
                 "" if row["load_average"] is None else f"{row['load_average']:.1f}"]
        for p in KEY_PARAMETERS:
            cells += [f"{row['best_epoch_nmae'][p]:.3f}", f"{row['average_nmae'][p]:.3f}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    kept = [row["run"] for row in rows if row.get("kept_from_earlier")]
    if kept:
        lines.append(f"Kept from an earlier drawing (run directory not given this time): "
                     f"{', '.join(kept)}.")
        lines.append("")
    lines.append("All ten parameters of each run are in the JSON file and the figures.")
    return "\n".join(lines) + "\n"


def _finite(value):
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def earlier_rows(out_dir):
    """The rows of ``out_dir/learning_curves.json`` (an earlier drawing), or []."""
    path = os.path.join(out_dir, "learning_curves.json")
    if not os.path.isfile(path):
        return []
    try:
        with open(path) as f:
            payload = json.load(f)
        if not isinstance(payload, list) or not all("run" in row for row in payload):
            raise ValueError("not a list of runs")
    except (OSError, ValueError) as error:
        raise CurveError(f"{path} cannot be read: {error}") from None
    return payload


def budget_table(payload, epoch):
    """Markdown: every run's validation NMAE after ``epoch`` epochs (the same
    training budget in samples for runs on the same data), with the mean over
    the ten parameters and the wall time the run had taken by then."""
    lines = [f"## Validation NMAE after {epoch} epochs (equal budget)", "",
             "| run | mean of 10 | " + " | ".join(KEY_PARAMETERS) + " | wall time |",
             "|" + "---|" * (3 + len(KEY_PARAMETERS))]
    for row in payload:
        values = {p: v[epoch - 1] if len(v) >= epoch else None for p, v in row["nmae"].items()}
        if any(v is None for v in values.values()):
            lines.append(f"| {row['label']} | fewer than {epoch} epochs |" + " |" *
                         (1 + len(KEY_PARAMETERS)))
            continue
        finite = [v for v in values.values() if v is not None and math.isfinite(v)]
        wall = (row.get("wall_times") or [])[epoch - 1:epoch]
        cells = [row["label"], f"{np.mean(finite):.3f}"]
        cells += [f"{values[p]:.3f}" for p in KEY_PARAMETERS]
        cells.append(f"{wall[0] / 60:.1f} min" if wall and wall[0] is not None else "n/a")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def page(payload, at_epoch=None, command=None):
    """learning_curves.md from its JSON (``payload``, one entry per run):
    the kept-epoch table, with ``at_epoch`` the equal-budget table, and
    with ``command`` the generated line first (``files.generated_line``)."""
    rows = [{k: v for k, v in row.items() if k not in ("samples_seen", "nmae", "wall_times")}
            for row in payload]
    text = markdown(rows)
    if at_epoch:
        text += "\n" + budget_table(_finite(payload), at_epoch)
    return (files.generated_line(command) + "\n\n" if command else "") + text


def regenerate(page_path):
    """The text ``write_outputs`` wrote for ``page_path`` (a committed
    learning_curves.md), from its JSON beside it and the command on its
    first line (for ``--at-epoch``)."""
    command, payload = files.page_source(page_path)
    words = shlex.split(command or "")
    at_epoch = int(words[words.index("--at-epoch") + 1]) if "--at-epoch" in words else None
    return page(payload, at_epoch, command)


def write_outputs(run_dirs, out_dir, loads=None, keep_earlier=False, at_epoch=None,
                  command=None):
    """Figures and the summary table of ``run_dirs`` into ``out_dir``, and
    each run's log.csv and curves.png into ``out_dir/runs/``.

    ``keep_earlier``: the rows of runs drawn into ``out_dir`` before (its
    ``learning_curves.json``) that are not among ``run_dirs`` stay in the
    table, marked ``kept_from_earlier`` (their figures stay too), so a run
    whose directory is gone keeps its published row."""
    os.makedirs(out_dir, exist_ok=True)
    names = {os.path.basename(os.path.abspath(r)) for r in run_dirs}
    kept = [dict(row, kept_from_earlier=True) for row in earlier_rows(out_dir)
            if row["run"] not in names] if keep_earlier else []
    rows = [{k: v for k, v in row.items() if k not in ("samples_seen", "nmae", "wall_times")}
            for row in kept]
    payload = list(kept)
    for run_dir in run_dirs:
        curve = curves(run_dir)
        name = os.path.basename(os.path.abspath(run_dir))
        plot_nmae_curves(curve, os.path.join(out_dir, f"{name}.png"), plot_title(curve))
        published.publish_files(run_dir, os.path.join(out_dir, "runs"), name)
        row = summary_rows(curve, (loads or {}).get(name))
        rows.append(row)
        payload.append(dict(row, samples_seen=curve["samples_seen"], nmae=curve["nmae"],
                            wall_times=[r.get("wall_time_s") for r in curve["rows"]]))
    table = page(payload, at_epoch, command)
    for filename, text in (("learning_curves.md", table),
                           ("learning_curves.json", json.dumps(_finite(payload), indent=1))):
        files.write_text(os.path.join(out_dir, filename), text)
    return rows


# ---------------------------------------------------------------------------
# The experiment of docs/training.md, "Does it learn?"
# ---------------------------------------------------------------------------
#: (protocol, split, variant) of each run.
EXPERIMENT_RUNS = (
    ("cvgl", "paper", "cpl-a"), ("cvgl", "paper", "baseline"),
    ("random", "held-out-config", "cpl-a"), ("random", "held-out-config", "baseline"),
)


def run_experiment(*, data_dir, runs_dir, out_dir, pairs, backbone, image_size=112,
                   patience=5, max_epochs=200, seed=0, only=None, verbose=0):
    """Make the datasets, train the runs (resuming any that were killed) and
    write the curves. Returns the summary rows."""
    os.makedirs(data_dir, exist_ok=True)
    run_dirs, loads = [], {}
    for protocol, split, variant in EXPERIMENT_RUNS:
        data = cached_dataset(data_dir, protocol=protocol, pairs=pairs,
                              seed=seed + (protocol == "random"), image_size=image_size,
                              log=lambda line: print(line, file=sys.stderr))
        name = f"{protocol}-{variant}-{backbone}"
        run_dir = os.path.join(runs_dir, name)
        run_dirs.append(run_dir)
        if only and name not in only:
            continue
        start = time.time()
        summary = train(data, variant=variant, run_dir=run_dir, epochs=max_epochs,
                        backbone=backbone, split=split, seed=seed, patience=patience,
                        verbose=verbose, command="python -m cpl_keras.learning_curves --experiment")
        loads[name] = os.getloadavg()[2] if time.time() - start > 600 else os.getloadavg()[1]
        print(f"{name}: {summary.config.epochs_run} epochs, {summary.config.stopped}",
              file=sys.stderr)
    run_dirs = [r for r in run_dirs if os.path.exists(os.path.join(r, "log.csv"))]
    return write_outputs(run_dirs, out_dir, loads,
                         command=f"python -m cpl_keras.learning_curves --experiment --out {out_dir}")


if __name__ == "__main__":  # the command line: cpl_keras/commands/learning_curves.py
    import runpy

    runpy.run_module("cpl_keras.commands.learning_curves", run_name="__main__")
