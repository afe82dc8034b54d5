"""Calibrating stereo pairs of image files with a trained run, from Python:

    from cpl_keras.calibrate import Calibrator

    calibrator = Calibrator.from_run("runs/cpl-a-paper-s0")    # the model, loaded once
    calibration = calibrator.calibrate("left.png", "right.png")
    calibration.camera.fx, calibration.camera.K, calibration.fov_horizontal_deg
    rig = calibrator.calibrate_folder("cpl_keras/real/oakd_stereo")   # medians over the pairs

``Calibration`` (one pair) and ``RigCalibration`` (a folder of pairs of one
rig) are the records (``cpl_keras.calibration_records``): each holds its
``camera``, a ``cpl_keras.stereo_camera.StereoCamera`` (a pair's also its
``disparity`` and its ``point``); ``as_dict()`` and ``to_json()`` give the
JSON that ``python -m cpl_keras.calibrate`` prints (its module doc says what
each value is), and ``cpl_keras.exports`` writes them for OpenCV, ROS and
COLMAP. Bad input is a one-line ``CalibrationError``.

The values are in the input images' own pixel units: the model sees the
pair resized to its input size S, so the focal length and principal point
are scaled back per axis (``fx``, ``u0``, ``disparity`` by W / S, ``fy``,
``v0`` by H / S, with pixel centres at integer coordinates: ``u = (u_S +
0.5) W / S - 0.5``). Metres and radians are unchanged. A run trained
``as_released`` predicts pitch in degrees and the release's StereoBM
disparity; pitch is converted to radians and the disparity is scaled like
the others, with a note that it is the release's quantity.
"""

from __future__ import annotations

import copy
import math
import os
import warnings

import numpy as np

from cpl_keras import priors as known, real_record, runs
from cpl_keras.calibration_records import (
    RIG_PARAMETERS, TTA_CROPS, TTA_FRACTION, Calibration, RigCalibration,
)
from cpl_keras.calibration_warnings import OUTSIDE_RANGE, WarningGroups
from cpl_keras.camera import FLOORS, PARAMETERS
from cpl_keras.data.storage import StereoFile
from cpl_keras.image_pairs import (
    CalibrationError, find_pairs, is_grey, pair_doubts, read_pair,
)
from cpl_keras.images import resize_image
from cpl_keras.models.inference import model_image_shape, predict_images
from cpl_keras.stereo_camera import Point, StereoCamera

#: A spread of fx or fy above this share of the value is warned about.
SPREAD_WARNING = 0.2
#: The widest baseline of a handheld or vehicle stereo rig taken as possible
#: (m): the widest vehicle rigs of the public datasets are under 1 m (KITTI
#: 0.54 m); a calibrated pair's baseline beyond this is named as impossible.
MAX_RIG_BASELINE_M = 5.0
#: The narrowest baseline taken as possible (m): a phone's two cameras are
#: about a centimetre apart; below a millimetre no rig's two views differ.
MIN_RIG_BASELINE_M = 1e-3
#: How fy is reported: "square" pixels (fy = fx), or the "model"'s fy head.
ASPECTS = ("square", "model")


class CalibrationWarning(UserWarning):
    """A calibration's warning, from the Python API without ``warn``."""


def python_warning(line):
    """``Calibrator``'s ``warn`` by default: the line as a ``CalibrationWarning``."""
    warnings.warn(line.removeprefix("warning: "), CalibrationWarning, stacklevel=3)


def crop_windows(width, height, count=TTA_CROPS, seed=0):
    """The windows ``(x0, y0, w, h)`` the spread is measured over: the whole
    image, then ``count`` crops of 80-95 % of each side at seeded positions."""
    rng = np.random.default_rng(seed)
    windows = [(0, 0, width, height)]
    for _ in range(count):
        w = int(round(width * rng.uniform(*TTA_FRACTION)))
        h = int(round(height * rng.uniform(*TTA_FRACTION)))
        windows.append((int(rng.integers(0, width - w + 1)), int(rng.integers(0, height - h + 1)),
                        w, h))
    return windows


def is_demonstration(run):
    """Whether ``run`` is train.py's demonstration run (trained without --data
    on the cached demonstration dataset)."""
    data = os.path.basename(str(run.config.data.path or ""))
    return data.startswith("demo-") or "--data" not in str(run.config.command or "--data")


def training_protocol(run):
    """The data generator's protocol of the run's training set (config.json,
    else the dataset's metadata when the file is still there), or None."""
    if run.config.data.protocol:
        return run.config.data.protocol
    try:
        with StereoFile(run.config.data.path) as data:
            return data.metadata.get("protocol")
    except Exception:  # moved or unreadable: unknown
        return None


def label_ranges(stats):
    """name -> [min, max] of the training labels (train_stats.json), or None
    for a run whose statistics predate the ranges."""
    if "min" not in stats or "max" not in stats:
        return None
    return {name: [stats["min"][name], stats["max"][name]] for name in stats["targets"]
            if name in stats["min"] and name in stats["max"]}


def from_window(values, window, model_size, image_size):
    """The model's outputs ``values`` (a dict of TARGETS' names) on the crop
    ``window`` ``(x0, y0, w, h)`` of an image of ``image_size`` ``(W, H)``,
    resized to its input ``model_size`` ``(S_w, S_h)``, in the image's own
    pixels: the camera seen at the model's input resized back to the window
    and placed in the image, the disparity scaled like u (a new dict)."""
    x0, y0, w, h = window
    seen = StereoCamera.from_labels(values, *model_size)
    sx, _ = seen.resize_scales(w, h)
    labels = seen.resize(w, h).uncrop(x0, y0, *image_size).to_labels(
        disparity=values["disparity"] * sx)
    return dict(values, **{name: labels[name] for name in PARAMETERS})


def predict_windows(model, left, right, windows, released):
    """The model's outputs on each window of the pair (resized to its input):
    ``(raw, mapped)``, two lists of dicts, as the model gives them and in the
    full image's pixels with pitch in radians."""
    size_h, size_w = model_image_shape(model)
    height, width = left.shape[:2]
    pred = predict_images(
        model, np.stack([resize_image(left[y:y + h, x:x + w], size_w, size_h)
                         for x, y, w, h in windows]),
        np.stack([resize_image(right[y:y + h, x:x + w], size_w, size_h)
                  for x, y, w, h in windows]))
    raw, mapped = [], []
    for i, window in enumerate(windows):
        one = {name: float(pred[name][i]) for name in pred}
        raw.append(dict(one))
        if released:  # (the release predicted pitch in degrees)
            one["pitch"] = math.radians(one["pitch"])
        mapped.append(from_window(one, window, (size_w, size_h), (width, height)))
    return raw, mapped


def _check_ranges(raw, ranges, warn):
    """Warn about predictions outside the training labels' range (model units)."""
    outside = [f"{name} {raw[name]:.4g} (trained on {lo:.4g}..{hi:.4g})"
               for name, (lo, hi) in (ranges or {}).items()
               if name in raw and not lo <= raw[name] <= hi]
    if outside:
        warn(f"warning: {OUTSIDE_RANGE}: {', '.join(outside)}")


def impossible_geometry(camera, disparity):
    """What no pair of a handheld or vehicle rig can show, whatever a model
    was trained on: a disparity at or beyond the image width (a point seen
    in both images lies less than a width apart in them); a focal length
    with no field of view between 0 and 180 degrees; the projection pixel's
    depth fx b / d (Eq. 4a) nearer than the baseline (a disparity above
    fx); a baseline over ``MAX_RIG_BASELINE_M``. One line each (empty: none)."""
    lines = []
    d, fx, width, b = disparity, camera.fx, camera.width, camera.baseline
    if d >= width:
        lines.append(f"a disparity of {d:.4g} px is at or beyond the image width ({width} px): "
                     "no point seen in both images can have it")
    if not fx >= FLOORS["focal"]:
        lines.append(f"a focal length of {fx:.4g} px (under {FLOORS['focal']:g} px) gives no "
                     "field of view between 0 and 180 degrees")
    elif d > fx and b > 0:
        lines.append(f"the projection pixel's depth fx b / d = {fx * b / d:.3g} m is nearer "
                     f"than the baseline ({b:.4g} m): a disparity of {d:.4g} px is over fx "
                     f"({fx:.4g} px)")
    if b > MAX_RIG_BASELINE_M:
        lines.append(f"a baseline of {b:.4g} m is wider than any handheld or vehicle stereo "
                     f"rig (over {MAX_RIG_BASELINE_M:g} m)")
    elif not b >= MIN_RIG_BASELINE_M:
        lines.append(f"a baseline of {b:.4g} m is narrower than any stereo rig (under "
                     f"{MIN_RIG_BASELINE_M * 1000:g} mm)")
    return lines


def _check_spread(spread, camera, aspect, warn, between="crops of the pair", of="value"):
    """Warn about fx (and the network's fy) moving by over SPREAD_WARNING."""
    for name in ("fx", "fy") if aspect == "model" else ("fx",):   # (square: fy is fx)
        value = getattr(camera, name)
        if spread[name] > SPREAD_WARNING * abs(value):
            warn(f"warning: {name} changes by {spread[name]:.4g} px (std) between {between}, "
                 f"over {100 * SPREAD_WARNING:.0f} % of its {of} {value:.4g}: "
                 "an unreliable estimate")


def _check_arguments(aspect, priors):
    if aspect not in ASPECTS:
        raise CalibrationError(f"unknown aspect {aspect!r}; choose one of {', '.join(ASPECTS)}")
    if priors is not None and not isinstance(priors, known.Priors):
        raise CalibrationError(f"priors must be a cpl_keras.priors.Priors, not "
                               f"{type(priors).__name__}")


def _resolve_priors(priors, left_path, width, height):
    """``priors`` with an EXIF focal length read from the left image."""
    if priors.focal_source != "exif":
        return priors
    focal, source = known.exif_focal_px(left_path, width, height)
    return known.Priors(baseline_m=priors.baseline_m, focal_px=focal, focal_source=source)


class Calibrator:
    """A trained run's model, loaded once, that calibrates pairs of image
    files (``calibrate``) and folders of one rig's pairs
    (``calibrate_folder``). ``warn(line)``, when given, is called with each
    warning (a grey image, a prediction outside the training labels' range,
    a large spread, the demonstration model, an impossible value); without
    it each is a Python warning (``CalibrationWarning``), so the API is
    never silent about them. Impossible values are also on the result
    (``impossible``)."""

    def __init__(self, run, model):
        self.run, self.model = run, model

    @classmethod
    def from_run(cls, run_dir):
        """The calibrator of the run in ``run_dir`` (its model loaded)."""
        run = runs.load_run(run_dir)
        return cls(run, runs.load_model(run))

    def calibrate(self, left, right, *, aspect="square", priors=None, warn=None):
        """The ``Calibration`` of the pair of image files ``left``,
        ``right``; ``aspect`` one of ``ASPECTS``, ``priors`` a
        ``cpl_keras.priors.Priors`` of known values (its ``focal_source``
        "exif": the left image's EXIF)."""
        _check_arguments(aspect, priors)
        warn = warn or python_warning
        run, (size_h, size_w) = self.run, model_image_shape(self.model)
        left_image, right_image = _read_pair(left, right, size_w, size_h, warn)
        height, width = left_image.shape[:2]
        windows = crop_windows(width, height)
        raw, per_window = predict_windows(self.model, left_image, right_image, windows,
                                          run.as_released)
        network_fy, network_baseline = per_window[0]["fy"], per_window[0]["baseline"]
        if aspect == "square":                  # fy = fx on the input images (and every crop)
            for one in per_window:
                one["fy"] = one["fx"]
        priors = _resolve_priors(known.Priors() if priors is None else priors, left, width,
                                 height)
        if priors:                              # what the user knows, in place of the guess
            per_window = [known.apply(one, priors, aspect) for one in per_window]
        values = per_window[0]                  # the whole image
        if not all(math.isfinite(v) for v in values.values()):
            raise CalibrationError("the model predicted non-finite values")
        camera = StereoCamera.from_labels(values, width, height)
        ranges = label_ranges(run.stats)
        _check_ranges(raw[0], ranges, warn)
        impossible = impossible_geometry(camera, values["disparity"])
        for line in impossible:
            warn(f"warning: impossible for any pair: {line}")
        spread = {name: float(np.std([v[name] for v in per_window], ddof=1))
                  for name in PARAMETERS + ("X", "Y", "Z")}
        _check_spread(spread, camera, aspect, warn)
        demo = is_demonstration(run)
        if demo:
            warn("warning: this run is the demonstration model (800 pairs, small towers, 8 "
                 "epochs): its values show the pipeline working, not a calibration")
        return Calibration(
            left=os.path.abspath(left), right=os.path.abspath(right),
            model_input=(size_h, size_w), run=run.run_dir, variant=run.config.variant,
            camera=camera, disparity=values["disparity"],
            point=Point(values["X"], values["Y"], values["Z"]), spread=spread,
            windows=len(windows), demonstration_model=demo, aspect=aspect,
            network_fy=network_fy, training=_training(run, ranges, size_w, size_h),
            real_camera_record=real_record.summarise(run), priors=priors,
            baseline_factor=priors.baseline_m / network_baseline if priors.baseline_m else None,
            impossible=tuple(impossible))

    def calibrate_folder(self, folder, *, aspect="square", priors=None, warn=None,
                         progress=None):
        """The ``RigCalibration`` of every pair of ``folder`` (``find_pairs``):
        each pair calibrated as by ``calibrate``, the rig's parameters (all
        but the disparity, which is the scene's) the medians over the pairs,
        with their spread over the pairs. The pairs' warnings are given once
        they are all calibrated, one line for each kind of warning with the
        pairs it concerns (``calibration_warnings``). ``progress``, when
        given, makes a bar from the number of pairs (``update(n)`` after
        each, ``close()``: ``cli.ProgressBar``)."""
        _check_arguments(aspect, priors)
        warn = warn or python_warning
        pairs, said, results = find_pairs(folder), WarningGroups(), []
        bar = progress(len(pairs)) if progress is not None else None
        try:
            for left, right in pairs:
                name = os.path.basename(left)
                results.append(self.calibrate(
                    left, right, aspect=aspect, priors=priors,
                    warn=lambda line, name=name, paths=(left, right): said.add(
                        None if "demonstration model" in line else name, line, paths)))
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        for line in said.lines(len(pairs)):
            warn(line)
        return _rig(folder, results, aspect, warn)


def _training(run, ranges, size_w, size_h):
    """The JSON's ``training``: what the run was trained on."""
    return {"protocol": training_protocol(run), "split": run.config.training.split,
            "as_released": run.as_released, "label_ranges": ranges,
            "label_ranges_units": f"the model's input ({size_w}x{size_h} px), targets as trained"}


def _read_pair(left, right, size_w, size_h, warn):
    """The pair's images, checked against the model's input size; a grey
    image, and one turned against the other or a swapped pair, warned about."""
    left_image, right_image = read_pair(left, right)
    height, width = left_image.shape[:2]
    if height < size_h or width < size_w:
        raise CalibrationError(
            f"images are {width}x{height}, smaller than the model's input {size_w}x{size_h}")
    for side, path, image in (("left", left, left_image), ("right", right, right_image)):
        if is_grey(image):
            warn(f"warning: the {side} image {path} is grey; the model was trained on "
                 "colour images")
    for line in pair_doubts(left_image, right_image, left, right):
        warn(f"warning: {line}")
    return left_image, right_image


def _rig(folder, results, aspect, warn):
    """The ``RigCalibration`` of ``folder`` from its pairs' ``results``."""
    sizes = sorted({(r.image_width, r.image_height) for r in results})
    if len(sizes) > 1:
        raise CalibrationError(f"the pairs of {folder} have different image sizes "
                               f"({sizes[0][0]}x{sizes[0][1]}, {sizes[1][0]}x{sizes[1][1]}); "
                               "one rig has one")
    per_pair = {name: [getattr(r.camera, name) for r in results] for name in RIG_PARAMETERS}
    camera = StereoCamera.from_labels({name: float(np.median(v)) for name, v in per_pair.items()},
                                      *sizes[0])
    spread = {name: float(np.std(v, ddof=1)) if len(v) > 1 else 0.0
              for name, v in per_pair.items()}
    _check_spread(spread, camera, aspect, warn, between=f"the {len(results)} pairs",
                  of="median")
    first = results[0]
    # what no pair can show: the rig's own (its medians) and each pair's
    impossible = [f"the rig: {line}" for line in impossible_geometry(
        camera, float(np.median([r.disparity for r in results])))]
    for line in impossible:
        warn(f"warning: impossible for any pair: {line}")
    impossible += [f"{os.path.basename(r.left)}: {line}" for r in results for line in r.impossible]
    return RigCalibration(
        folder=os.path.abspath(folder), run=first.run, variant=first.variant, camera=camera,
        spread_over_pairs=spread, demonstration_model=first.demonstration_model, aspect=aspect,
        real_camera_record=copy.deepcopy(first.real_camera_record), priors=first.priors,
        pairs=tuple(results), impossible=tuple(impossible))
