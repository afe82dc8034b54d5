"""A run's forward pass on a dataset file, or the stored outputs that stand
for it.

* ``predict_run`` runs a model's forward pass over pairs of a dataset file
  (``cpl_keras.models.inference.predict_images`` on image arrays);
  ``run_predictions`` prefers the run's stored predictions (a published run
  has nothing else) and ``store_predictions`` writes them
  (``cpl_keras.prediction_files``' format).
* ``paired_outputs``: a run's outputs and truth as the paired bootstrap
  reads them; ``published``: predictions at the stored files' precision.

Which pairs and which truth: ``cpl_keras.evaluation.pairs``.
"""

from __future__ import annotations

import numpy as np

from cpl_keras import prediction_files, runs
from cpl_keras.camera import PARAMETERS, TARGETS
from cpl_keras.datasets import targets_from_labels
from cpl_keras.evaluation.pairs import (
    EvaluationError, _same_file, evaluation_indices, open_dataset,
)
from cpl_keras.models import inference
from cpl_keras.models.inference import model_image_shape
from cpl_keras.runs import load_model, load_run


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
    paths = [run.config.data.path] + [p for p in data_paths
                                      if not _same_file(p, run.config.data.path)]
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


def published(predictions):
    """``predictions`` at the precision of the published predictions files
    (float32, as a network outputs them), as float64 arrays: a table scored in
    memory and one rebuilt from the files agree to the last digit."""
    return {name: np.asarray(predictions[name], np.float32).astype(np.float64)
            for name in TARGETS}
