"""The Average baseline: predict every parameter as its training-set mean.

``training_statistics`` computes what the baseline needs from the training
targets (saved by training as ``run_dir/train_stats.json``);
``average_predictions`` turns those statistics into predictions for ``n``
test pairs.

The released code had a bug the paper's Average rows come from: parameter
``i`` (``i = 0..12`` in ``TARGETS`` order) was predicted as the mean of the 13
labels of *training sample* ``i`` -- the release's labels (its extrinsic
frame, pitch in degrees, StereoBM disparity), so ``release_average`` is
computed from the as-released targets and the row is scored against them.
``kind="release"`` reproduces it.
"""

from __future__ import annotations

import json
import os

import numpy as np

from cpl_keras.camera import TARGETS
from cpl_keras.files import write_json

KINDS = ("mean", "release")


def training_statistics(targets, train_indices, release_targets=None):
    """Per-target mean and standard deviation over the training pairs.

    Args:
        targets: dict name -> (N,) array over the whole dataset (``TARGETS``).
        train_indices: the training pairs, in the training set's order (the
            release's bug depends on that order: sample ``i`` is
            ``train_indices[i]``).
        release_targets: the release's labels (``datasets.targets_from_labels(
            labels, as_released=True)``), which the release's buggy Average
            averaged; ``None`` uses ``targets``.

    Returns a JSON-ready dict: ``targets`` (the names, in order), ``mean``,
    ``std``, ``min`` and ``max`` (name -> float), ``num_train`` and
    ``release_average`` (name -> float, the release's buggy prediction).
    """
    train_indices = np.asarray(train_indices, dtype=np.int64)
    if len(train_indices) < len(TARGETS):
        raise ValueError(
            f"need at least {len(TARGETS)} training pairs for the release's Average, "
            f"got {len(train_indices)}"
        )
    table = np.stack([np.asarray(targets[name], np.float64)[train_indices] for name in TARGETS], 1)
    mean, std = table.mean(axis=0), table.std(axis=0)
    # The release's bug: row i (training sample i) averaged over its 13 labels
    # (the release's labels: its frame, degrees, StereoBM disparity).
    if release_targets is None:
        release_table = table
    else:
        release_table = np.stack([np.asarray(release_targets[name], np.float64)[train_indices]
                                  for name in TARGETS], 1)
    release = release_table[: len(TARGETS)].mean(axis=1)
    return {
        "targets": list(TARGETS),
        "mean": {name: float(m) for name, m in zip(TARGETS, mean)},
        "std": {name: float(s) for name, s in zip(TARGETS, std)},
        "min": {name: float(v) for name, v in zip(TARGETS, table.min(axis=0))},
        "max": {name: float(v) for name, v in zip(TARGETS, table.max(axis=0))},
        "num_train": int(len(train_indices)),
        "release_average": {name: float(r) for name, r in zip(TARGETS, release)},
    }


def average_predictions(stats, n, kind="mean"):
    """Predictions of the Average baseline for ``n`` pairs: dict name -> (n,).

    ``kind="mean"`` predicts each target's training mean (the baseline as
    described); ``kind="release"`` the released code's buggy values.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown Average kind {kind!r}; choose one of {', '.join(KINDS)}")
    values = stats["mean"] if kind == "mean" else stats["release_average"]
    return {name: np.full(int(n), values[name], dtype=np.float32) for name in TARGETS}


def save_statistics(path, stats):
    """Write statistics as JSON (atomically)."""

    write_json(os.fspath(path), stats)


def load_statistics(path):
    """Read statistics written by ``save_statistics``."""
    with open(path) as f:
        stats = json.load(f)
    missing = [key for key in ("targets", "mean", "std", "num_train", "release_average")
               if key not in stats]
    if missing:
        raise ValueError(f"{path}: training statistics lack {', '.join(missing)}")
    return stats
