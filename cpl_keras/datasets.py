"""Training inputs: regression targets, train/val/test splits and a streaming
``keras.utils.PyDataset`` over the project's HDF5 stereo files.

* ``targets_from_labels`` turns stored labels into the 13 regression targets
  (``camera.TARGETS``), either as the paper defines them or with the released
  code's label quirks (``as_released=True``).
* ``make_split`` draws the train / validation / test index arrays.
* ``StereoSequence`` reads one batch at a time from the file, so memory does
  not grow with the dataset (the release held all images in RAM).

Only ``StereoSequence`` needs Keras; it is imported when that class is first
used, so the numpy-side helpers stay light.
"""

from __future__ import annotations

import os
import zipfile

import numpy as np

from cpl_keras import camera
from cpl_keras.camera import TARGETS
from cpl_keras.data.storage import DatasetError, StereoFile

SPLITS = ("paper", "drive", "held-out-config", "released")
#: Labels of the extrinsics in the release's frame and its projection pixel
#: (written by ``cpl_keras.data.generate``; pitch_released in degrees).
RELEASED_EXTRINSICS = ("baseline_released", "tx_released", "ty_released", "tz_released",
                       "pitch_released", "u_released", "v_released")


# ---------------------------------------------------------------------------
# Targets
# ---------------------------------------------------------------------------
def targets_from_labels(labels, as_released=False):
    """The 13 regression targets (float32 arrays, ``TARGETS`` order) from labels.

    Paper mode returns the stored targets. ``as_released=True`` reproduces the
    released code's labels:

    * the extrinsics in the release's frame (``baseline_released``,
      ``tx_released``, ``ty_released``, ``tz_released``: right-minus-left
      vehicle-frame differences in CARLA's conventions, baseline = tx),
    * pitch in degrees, CARLA's sign (``pitch_released``; the release fed
      degrees to sin/cos as radians, and so does the model with these targets),
    * disparity is the release's StereoBM mean (``disparity_released``),
    * X, Y, Z are the camera equations (Eqs. 4a-5c, ``camera.image_to_world``)
      of those values at the release's fixed pixel (``u_released``,
      ``v_released`` = W/2, H/2), not at the label pixel (u, v).

    Labels without the release-frame names (``RELEASED_EXTRINSICS``: files
    that have one frame only, such as the real-data sets) use the stored
    extrinsics with pitch converted to degrees, and the stored (u, v). A
    file imported from the authors' release (``cpl_keras.data.import_cvgl``)
    stores all 13 targets as ``<name>_released``: they are taken as they are,
    and paper mode is refused (the release cannot give the project's
    disparity, X, Y, Z).
    """
    present = [name for name in RELEASED_EXTRINSICS if name in labels]
    if as_released and present and len(present) < len(RELEASED_EXTRINSICS):
        missing = [name for name in RELEASED_EXTRINSICS if name not in labels]
        raise DatasetError(f"missing label(s) {', '.join(missing)}")
    out = _released_targets(labels, present) if as_released else _paper_targets(labels)
    result = {name: out[name].astype(np.float32) for name in TARGETS}
    for name, values in result.items():
        if not np.all(np.isfinite(values)):
            count = int(np.sum(~np.isfinite(values)))
            raise DatasetError(f"target '{name}' has non-finite values on {count} of "
                               f"{values.size} pairs")
    # (as released, the disparity is StereoBM's mean, often negative, and
    # the baseline tx, a signed difference)
    positive = ("fx", "fy") if as_released else POSITIVE_TARGETS
    # (a real set marks a pair without a measured disparity: disparity_valid 0)
    valid = np.asarray(labels["disparity_valid"]) != 0 if "disparity_valid" in labels else True
    for name in positive:
        checked = valid if name == "disparity" else True
        count = int(np.sum((result[name] <= 0) & checked))
        if count:
            raise DatasetError(f"label '{name}' is not positive on {count} of "
                               f"{result[name].size} pairs, which no camera has; fix or drop "
                               f"those pairs")
    return result


def _paper_targets(labels):
    """The stored targets (DatasetError naming those missing; those a file
    imported from the authors' release holds as released only, said so)."""
    missing = [name for name in TARGETS if name not in labels]
    if missing and all(f"{name}_released" in labels for name in missing):
        raise DatasetError(
            f"the labels {', '.join(missing)} are the release's only (a file imported from "
            "the authors' release, which cannot give them): train and evaluate it as released "
            "(--as-released)")
    if missing:
        raise DatasetError(f"missing label(s) {', '.join(missing)}")
    return {name: np.asarray(labels[name], dtype=np.float64) for name in TARGETS}


def _released_targets(labels, present):
    """The release's targets (``targets_from_labels(..., as_released=True)``):
    each target's ``<name>_released`` label where the file has one (an
    imported release has all 13), the release's disparity, and X, Y, Z of
    the camera equations at the release's pixel where not stored."""
    def label(name):
        found = labels.get(f"{name}_released", labels.get(name))
        if found is None:
            raise DatasetError(f"missing label(s) {name}")
        return np.asarray(found, dtype=np.float64)

    out = {name: label(name) for name in camera.PARAMETERS if name != "disparity"}
    out["disparity"] = label("disparity_released")
    if not present:   # (one frame only, pitch in radians: the release's degrees)
        out["pitch"] = np.degrees(out["pitch"])
    if all(f"{name}_released" in labels for name in ("X", "Y", "Z")):
        out.update({name: label(f"{name}_released") for name in ("X", "Y", "Z")})
        return out
    u, v = (label("u_released"), label("v_released")) if present else (label("u"), label("v"))
    params = {name: out[name] for name in camera.PARAMETERS}
    out["X"], out["Y"], out["Z"] = camera.image_to_world(**params, u=u, v=v)
    return out


#: The targets no camera has at or below zero: focal lengths (px), the
#: baseline (m: the distance between the cameras; a negative one puts the
#: point of Eq. 4a behind them) and the disparity (px; the camera graph
#: divides by it, Eq. 4a). Paper mode only: as released, the baseline is
#: tx, a signed difference, and the disparity StereoBM's mean.
POSITIVE_TARGETS = ("fx", "fy", "baseline", "disparity")


# ---------------------------------------------------------------------------
# Splits
# ---------------------------------------------------------------------------
def _labels_of(source):
    if isinstance(source, StereoFile):
        return source.labels
    if isinstance(source, (str, os.PathLike)):
        with StereoFile(source) as f:
            return f.labels
    return source


def _fraction_count(fraction, n, name):
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"{name} must be in (0, 1), got {fraction}")
    return int(round(fraction * n))


def make_split(stereo_file_or_labels, kind="paper", seed=0, test_fraction=0.3,
               val_fraction=0.1, as_released=False):
    """Train / validation / test index arrays (sorted int64) of a dataset.

    ``kind="paper"``: the release's split, frames shuffled (here with ``seed``),
    the first ``1 - test_fraction`` for training and the rest for testing.
    Its test frames are mostly neighbours of training frames: each rig's
    frames are a drive, consecutive frames a few metres apart, and 83-87 % of
    the paper split's test pairs have the frame before or after in training
    (``adjacent_fraction``), so it measures recall of seen rigs *and* of
    nearly seen views.
    ``kind="drive"``: every rig is seen in training, but each rig's drive
    (its frames in driving order, ``config_id`` and ``frame_index``) is cut
    in time: the last ``test_fraction`` of it is the test stretch, the
    ``val_fraction`` of the rest just before it the validation stretch, the
    beginning the training stretch, so no test frame is next to a training
    frame. Seen rigs, unseen views.
    ``kind="held-out-config"``: whole rig configurations (``config_id``) are
    kept out of training, so the test measures unseen rigs; about
    ``test_fraction`` of the frames go to test.

    The validation set (for early stopping) is carved out of the training part
    -- ``val_fraction`` of its frames for ``"paper"``, whole configurations
    for ``"held-out-config"`` -- and never overlaps the test set. With
    ``as_released=True`` the validation set *is* the test set, as in the
    released code (which early-stopped on its test data).

    ``kind="released"``: the split as the authors' release made it, on rows
    it had shuffled once before saving them: the first ``int(0.7 N)`` rows
    (``1 - test_fraction``) train, the rest is the validation *and* the
    test set; never reshuffled (``seed`` does not enter).

    ``stereo_file_or_labels`` is a ``StereoFile``, a path or a label dict.
    """
    if kind not in SPLITS:
        raise ValueError(f"unknown split {kind!r}; choose one of {', '.join(SPLITS)}")
    labels = _labels_of(stereo_file_or_labels)
    n = len(next(iter(labels.values())))
    rng = np.random.default_rng(seed)
    split_of = {"released": _released_split, "paper": _paper_split, "drive": _drive_split,
                "held-out-config": _config_split}[kind]
    train, val, test = split_of(labels, n, rng, test_fraction, val_fraction, as_released)
    split = {"train": np.sort(train), "val": np.sort(val), "test": np.sort(test)}
    for name, indices in split.items():
        if len(indices) == 0:
            raise DatasetError(
                f"{kind} split of {n} pairs leaves the {name} set empty; use more pairs"
            )
        split[name] = indices.astype(np.int64)
    return split


def _released_split(labels, n, rng, test_fraction, val_fraction, as_released):
    """The ``released`` split: the first ``int((1 - test_fraction) N)`` rows
    train, the rest is validation and test (``rng`` unused: no shuffle)."""
    _fraction_count(test_fraction, n, "test_fraction")
    cut = int((1 - test_fraction) * n)
    return np.arange(cut), np.arange(cut, n), np.arange(cut, n)


def _paper_split(labels, n, rng, test_fraction, val_fraction, as_released):
    """The ``paper`` split: frames shuffled, the last ``test_fraction`` test,
    the end of the rest validation (the test set itself as released)."""
    n_test = _fraction_count(test_fraction, n, "test_fraction")
    order = rng.permutation(n)
    train, test = order[: n - n_test], order[n - n_test:]
    n_val = _fraction_count(val_fraction, len(train), "val_fraction")
    if as_released:
        return train, test, test
    return train[: len(train) - n_val], train[len(train) - n_val:], test


def _config_split(labels, n, rng, test_fraction, val_fraction, as_released):
    """The ``held-out-config`` split: whole rig configurations to test, then
    to validation (the test set itself as released), the rest to training."""
    if "config_id" not in labels:
        raise DatasetError("held-out-config split needs the label 'config_id'")
    config_id = np.asarray(labels["config_id"])
    configs = rng.permutation(np.unique(config_id))
    needed = 2 if as_released else 3
    if len(configs) < needed:
        raise DatasetError(
            f"held-out-config split needs at least {needed} configurations, "
            f"the dataset has {len(configs)}"
        )
    counts = np.array([(config_id == c).sum() for c in configs])
    test_configs = _take_configs(counts, _fraction_count(test_fraction, n, "test_fraction"))
    rest = np.arange(len(configs))[len(test_configs):]
    if as_released:
        val_configs = test_configs
    else:
        n_val = _fraction_count(val_fraction, counts[rest].sum(), "val_fraction")
        val_configs = rest[: len(_take_configs(counts[rest], n_val, keep=1))]
    train_configs = np.setdiff1d(rest, val_configs)
    pick = lambda idx: np.flatnonzero(np.isin(config_id, configs[idx]))  # noqa: E731
    return pick(train_configs), pick(val_configs), pick(test_configs)


def _drive_split(labels, n, rng, test_fraction, val_fraction, as_released):
    """The ``drive`` split: per rig, the end of its drive is test, the stretch
    before it validation, the beginning training."""
    for key in ("config_id", "frame_index"):
        if key not in labels:
            raise DatasetError(f"drive split needs the label {key!r}")
    _fraction_count(test_fraction, 1, "test_fraction")
    _fraction_count(val_fraction, 1, "val_fraction")
    config_id = np.asarray(labels["config_id"])
    frame = np.asarray(labels["frame_index"])
    train, val, test = [], [], []
    for c in np.unique(config_id):
        drive = np.flatnonzero(config_id == c)
        drive = drive[np.argsort(frame[drive], kind="stable")]
        n_test = int(round(test_fraction * len(drive)))
        rest = len(drive) - n_test
        # (at least one validation frame per drive of 2+ frames left)
        n_val = 0 if as_released or rest < 2 else max(1, int(round(val_fraction * rest)))
        train.append(drive[: rest - n_val])
        val.append(drive[rest - n_val: rest])
        test.append(drive[rest:])
    train, val, test = (np.concatenate(part) for part in (train, val, test))
    return train, (test if as_released else val), test


def adjacent_fraction(labels, split, near="train"):
    """The fraction of ``split["test"]`` pairs whose rig has a frame at
    ``frame_index`` +-1 in ``split[near]``: how much of a test set is the
    next frame of a drive the network was trained on (paper split at 1,000
    cvgl pairs: 0.83-0.87; drive split: 0)."""
    config_id = np.asarray(labels["config_id"])
    frame = np.asarray(labels["frame_index"])
    seen = set(zip(config_id[split[near]].tolist(), frame[split[near]].tolist()))
    test = split["test"]
    hits = [((c, f - 1) in seen) or ((c, f + 1) in seen)
            for c, f in zip(config_id[test].tolist(), frame[test].tolist())]
    return float(np.mean(hits)) if hits else 0.0


def _take_configs(counts, target, keep=2):
    """Positions 0..k-1 of ``counts`` whose frames first reach ``target``
    (at least one configuration, leaving at least ``keep``)."""
    k = int(np.searchsorted(np.cumsum(counts), max(target, 1))) + 1
    return np.arange(min(max(k, 1), len(counts) - keep))


def save_split(path, split):
    """Write a split as ``split.npz`` (train, val, test int64 arrays)."""
    np.savez(path, **{name: np.asarray(split[name], np.int64) for name in ("train", "val", "test")})


def load_split(path):
    """Read a split written by ``save_split`` (no pickle); DatasetError (one
    line naming the file) when it is missing, damaged or not a split."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name].astype(np.int64) for name in ("train", "val", "test")}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as problem:
        first = (str(problem).strip().splitlines() or [type(problem).__name__])[0]
        raise DatasetError(f"cannot read the split {path} ({first})") from None
