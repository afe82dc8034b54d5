"""A run's outputs on a dataset file: its stored predictions, or a forward pass.

* ``predict_run`` runs a model's forward pass over pairs of a dataset file;
  ``run_predictions`` prefers the run's stored predictions (a published run
  has nothing else) and ``store_predictions`` writes them.
* ``evaluation_indices`` picks the pairs a run is scored on (its test split
  on its own dataset, every pair of any other file) and ``truth_targets``
  the targets it is scored against (the release's for an as-released run).

Runs are read through ``cpl_keras.runs``.
"""

from __future__ import annotations

import os

import numpy as np

from cpl_keras import prediction_files, runs
from cpl_keras.camera import PARAMETERS, TARGETS
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.datasets import targets_from_labels
from cpl_keras.models import inference
from cpl_keras.models.inference import model_image_shape
from cpl_keras.runs import load_model, load_run


class EvaluationError(runs.RunError):
    """A run directory, dataset or argument cannot be evaluated (one line)."""


def load_table_runs(run_dirs):
    """The runs of one table (``runs.Run``), one per row: EvaluationError when
    none is given or two are runs of the same row."""
    if not run_dirs:
        raise EvaluationError("no runs given (--runs RUN_DIR ...)")
    loaded, seen = [], {}
    for run in map(load_run, run_dirs):
        if run.row in seen:
            raise EvaluationError(f"two runs for {run.row}: {seen[run.row]} and {run.run_dir}")
        seen[run.row] = run.run_dir
        loaded.append(run)
    return loaded


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
        parts.append(inference.predict_images(model, left, right, batch_size))
    return {name: np.concatenate([p[name] for p in parts]) if parts else np.zeros(0)
            for name in TARGETS}


def run_predictions(run, stereo_file, indices, batch_size=32):
    """The run's outputs on pairs ``indices`` of an open ``StereoFile``: its
    stored predictions for that file when it has them (a published run has
    nothing else), else a forward pass of its model (loaded once, kept on
    ``run.model``; ``forget_model`` drops it)."""
    stored = prediction_files.read_run_outputs(
        runs.predictions_path(run.run_dir, stereo_file.path), indices, TARGETS)
    if stored is not None:
        return stored
    if run.model is None:
        run.model = load_model(run)
    return predict_run(run.model, stereo_file, indices, batch_size)


def forget_model(run):
    """Drop the model ``run_predictions`` kept on ``run``."""
    run.model = None


def paired_outputs(run_dir, data_path):
    """``(raw, config)``: a run's outputs on ``data_path`` as the paired
    bootstrap (``verdicts.seed_intervals``) reads them -- ``indices``,
    ``truth`` (the ten parameters, as the file stores them) and ``pred`` --
    on its test split when the file is its own dataset, else on every pair;
    and the run's config."""
    run = load_run(run_dir)
    try:
        with open_dataset(data_path) as data:
            indices, _ = evaluation_indices(run, data_path, data.num_pairs)
            pred = run_predictions(run, data, indices)
            targets = targets_from_labels(data.labels, as_released=run.as_released)
    finally:
        forget_model(run)
    truth = {name: targets[name][indices] for name in PARAMETERS}
    return {"indices": indices, "truth": truth, "pred": pred}, run.config


def store_predictions(run_dir, data_paths, batch_size=32):
    """Store the run's outputs (``prediction_files.write_run_outputs``): on its own
    dataset's test split, and on every pair of each other file of
    ``data_paths`` (real sets, folders of them). The forward passes are the
    ones the tables make. Returns the paths written."""
    run = load_run(run_dir)
    paths = [run.config.data] + [p for p in data_paths if not _same_file(p, run.config.data)]
    written = []
    try:
        for path in paths:
            with open_dataset(path) as data:
                indices, _ = evaluation_indices(run, path, data.num_pairs)
                pred = run_predictions(run, data, indices, batch_size)
            written.append(prediction_files.write_run_outputs(
                runs.predictions_path(run_dir, path), path, indices, pred, TARGETS))
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
    the run's own dataset, else every pair of the file. A published record
    (``published.publish_run_dir``) names its dataset without a folder: a file of
    that name and the run's number of pairs is its own."""
    own = run.config.data
    if _same_file(data_path, own) or (
            os.path.basename(own) == own and os.path.basename(os.fspath(data_path)) == own
            and num_pairs == run.config.num_pairs):
        test = run.split["test"]
        if len(test) == 0 or test.max() >= num_pairs:
            raise EvaluationError(f"{run.run_dir}: test split does not fit {data_path}")
        return test, f"test split of the run ({len(test)} of {num_pairs} pairs)"
    return np.arange(num_pairs), f"all {num_pairs} pairs of the file"


def truth_targets(labels, indices, released):
    try:
        targets = targets_from_labels(labels, as_released=released)
    except DatasetError as error:
        raise EvaluationError(str(error)) from None
    return {name: np.asarray(targets[name], np.float64)[indices] for name in TARGETS}


def published(predictions):
    """``predictions`` at the precision of the published predictions files
    (float32, as a network outputs them), as float64 arrays: a table scored in
    memory and one rebuilt from the files agree to the last digit."""
    return {name: np.asarray(predictions[name], np.float32).astype(np.float64)
            for name in TARGETS}

