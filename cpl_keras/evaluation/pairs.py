"""What a table scores a run on: the runs of a table, the dataset file, the
pairs and the truth; and evaluation's one error.

* ``load_table_runs`` reads a table's runs (``cpl_keras.runs``), one per row;
  ``open_dataset`` opens a dataset file.
* ``evaluation_indices`` picks the pairs a run is scored on (its test split
  on its own dataset, every pair of any other file) and ``truth_targets``
  the targets it is scored against (the release's for an as-released run).
"""

from __future__ import annotations

import os

import numpy as np

from cpl_keras import runs
from cpl_keras.camera import TARGETS
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.datasets import targets_from_labels
from cpl_keras.runs import load_run


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
    own = run.config.data.path
    if _same_file(data_path, own) or (
            os.path.basename(own) == own and os.path.basename(os.fspath(data_path)) == own
            and num_pairs == run.config.data.num_pairs):
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
