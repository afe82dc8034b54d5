"""Calibrate a stereo pair of image files with a trained run.

    python -m cpl_keras.calibrate LEFT.png RIGHT.png --run RUN_DIR [--json-out FILE]
        [--opencv-yaml FILE] [--ros-yaml DIR] [--colmap DIR]
        [--baseline METRES] [--focal PX|exif]
    python -m cpl_keras.calibrate --folder DIR --run RUN_DIR [...]

Prints JSON with the 10 camera parameters, the point X, Y, Z and the
horizontal and vertical fields of view, in the input images' own pixel
units: the model sees the pair resized to its input size S, so the focal
length and principal point are scaled back per axis (``fx``, ``u0``,
``disparity`` by W / S, ``fy``, ``v0`` by H / S, with pixel centres at
integer coordinates: ``u = (u_S + 0.5) W / S - 0.5``). Metres and radians
are unchanged. A run trained ``as_released`` predicts pitch in degrees and
the release's StereoBM disparity; pitch is converted to radians and the
disparity is scaled like the others, with a note that it is the release's
quantity.

Bad input (unreadable or non-image files, images of different sizes or
smaller than the model's input, identical left and right images, a run
directory without weights) prints one line and exits with status 2; no
output file is written then. A grey image, and predictions outside the range
of the run's training labels (train_stats.json), are warned about on stderr,
one line each. The JSON says what the run was trained on (``training``: its
protocol, split and training label ranges, in the model's input units), the
spread of each value over crops of the pair (``spread``), which quantities
one pair determines and which are scale priors (``scale_free``,
``scale_priors``), what every field means (``fields``), and whether the run
is the demonstration model (then also warned about). One line on stderr,
and ``real_camera_record`` in the JSON, give the run's record on real
cameras (``cpl_keras.real_record``): the real rigs it was scored on without
having seen them, with its median relative fx error beside the Average
row's, or that it was never validated on one.

Known values replace the network's guesses (``cpl_keras.priors``):
``--baseline METRES`` scales the metric quantities, ``--focal PX`` (or
``exif``: a JPEG's 35 mm equivalent) sets fx, fy and the depth through
them; ``priors`` and ``from_prior`` in the JSON say which values came from
them.

``--aspect square`` (the default) takes the pixels as square, as real
cameras' are: fy = fx in the input image's pixels, the network's own fy
kept as ``network_fy``. The network sees the pair squashed to a square, so
its fy must guess the image's aspect ratio from content, and on real rigs it
did worse than fx (docs/evaluation.md, "Models for real cameras");
``--aspect model`` reports the network's fy.

``--folder DIR`` calibrates every pair of one rig (``find_pairs``) and
prints ``{"rig": ..., "pairs": [...]}``: the rig's parameters are the
medians over the pairs (the disparity, which belongs to each pair's scene,
is left out), ``spread_over_pairs`` their standard deviations; the YAML
exports describe the rig.
"""

from __future__ import annotations

import json
import math
import os
import sys

from cpl_keras import evaluation, exports, files
from cpl_keras.data.storage import StereoFile
from cpl_keras.errors import Error
from cpl_keras.images import resize_image

import numpy as np

from cpl_keras import cli, priors as known, real_record, runs
from cpl_keras.camera import PARAMETERS, UNITS, from_window, fov_from_focal
from cpl_keras.image_pairs import CalibrationError, find_pairs, is_grey, read_pair

PROG = "python -m cpl_keras.calibrate"


#: Test-time crops for the spread: how many, and their side as a share of the image.
TTA_CROPS = 8
TTA_FRACTION = (0.8, 0.95)
#: A spread of fx or fy above this share of the value is warned about.
SPREAD_WARNING = 0.2
#: What each printed field means, with its unit.
FIELDS = {
    "fx": "focal length along u (px of the input images)",
    "fy": "focal length along v (px)",
    "u0": "principal point u (px; pixel centres at integers)",
    "v0": "principal point v (px)",
    "baseline": "distance between the camera centres (m; a scale prior, see scale_free)",
    "disparity": "disparity of the projection pixel (px; Eq. 4a: fx * baseline / xCam)",
    "tx": "right camera's position along the left camera's forward axis (m; scale prior)",
    "ty": "right camera's position along the left camera's left axis (m; scale prior)",
    "tz": "right camera's position along the left camera's up axis (m; scale prior)",
    "pitch": "right camera's pitch relative to the left one (rad; positive: down)",
    "X": "the projection pixel's point, forward (m, left camera frame; scale prior)",
    "Y": "the point, to the left (m; scale prior)",
    "Z": "the point, up (m; scale prior)",
}


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
    data = os.path.basename(str(run.config.data or ""))
    return data.startswith("demo-") or "--data" not in str(run.config.command or "--data")


def training_protocol(run):
    """The data generator's protocol of the run's training set (config.json,
    else the dataset's metadata when the file is still there), or None."""
    if run.config.protocol:
        return run.config.protocol
    try:
        with StereoFile(run.config.data) as data:
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


def predict_windows(model, left, right, windows, released):
    """The model's outputs on each window of the pair (resized to its input):
    ``(raw, mapped)``, two lists of dicts, as the model gives them and in the
    full image's pixels with pitch in radians."""
    size_h, size_w = evaluation.model_image_shape(model)
    pred = evaluation.predict_images(
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
        mapped.append(from_window(one, window, size_w, size_h))
    return raw, mapped


def _check_ranges(raw, ranges, warn):
    """Warn about predictions outside the training labels' range (model units)."""
    outside = [f"{name} {raw[name]:.4g} (trained on {lo:.4g}..{hi:.4g})"
               for name, (lo, hi) in (ranges or {}).items()
               if name in raw and not lo <= raw[name] <= hi]
    if outside:
        warn("warning: predictions outside the training labels' range, in the model's "
             f"input units: {', '.join(outside)}")


def load(run_dir):
    """The run and its model, for calibrating one pair or many."""
    run = runs.load_run(run_dir)
    return run, runs.load_model(run)


#: How fy is reported: "square" pixels (fy = fx), or the "model"'s fy head.
ASPECTS = ("square", "model")


def calibrate_pair(left_path, right_path, run_dir, warn=None, loaded=None, aspect="square",
                   priors=None):
    """The calibration of one pair as a JSON-ready dict; ``warn(line)`` is
    called with each warning (a grey image, a prediction outside the
    training labels' range, a large spread, the demonstration model).
    ``loaded``: ``load(run_dir)``'s result, when already loaded; ``aspect``
    one of ``ASPECTS`` (the module doc); ``priors``: a ``priors.Priors``
    of known values (its ``focal_source`` "exif": the left image's EXIF)."""
    if aspect not in ASPECTS:
        raise CalibrationError(f"unknown aspect {aspect!r}; choose one of {', '.join(ASPECTS)}")
    warn = warn or (lambda line: None)
    left, right = read_pair(left_path, right_path)
    run, model = loaded or load(run_dir)
    size_h, size_w = evaluation.model_image_shape(model)
    height, width = left.shape[:2]
    if height < size_h or width < size_w:
        raise CalibrationError(
            f"images are {width}x{height}, smaller than the model's input {size_w}x{size_h}")
    for side, path, image in (("left", left_path, left), ("right", right_path, right)):
        if is_grey(image):
            warn(f"warning: the {side} image {path} is grey; the model was trained on colour "
                 "images")
    released = run.as_released
    windows = crop_windows(width, height)
    raw, per_window = predict_windows(model, left, right, windows, released)
    network_fy = per_window[0]["fy"]
    if aspect == "square":                      # fy = fx on the input images (and every crop)
        for one in per_window:
            one["fy"] = one["fx"]
    priors = _resolve_priors(known.Priors() if priors is None else priors, left_path, width,
                             height)
    network_baseline = per_window[0]["baseline"]
    if priors:                                  # what the user knows, in place of the guess
        per_window = [known.apply(one, priors, aspect) for one in per_window]
    values = per_window[0]                      # the whole image
    if not all(math.isfinite(v) for v in values.values()):
        raise CalibrationError("the model predicted non-finite values")
    ranges = label_ranges(run.stats)
    _check_ranges(raw[0], ranges, warn)
    spread = {name: float(np.std([v[name] for v in per_window], ddof=1))
              for name in PARAMETERS + ("X", "Y", "Z")}
    for name in ("fx", "fy") if aspect == "model" else ("fx",):   # (square: fy is fx)
        if spread[name] > SPREAD_WARNING * abs(values[name]):
            warn(f"warning: {name} changes by {spread[name]:.4g} px (std) between crops of the "
                 f"pair, over {100 * SPREAD_WARNING:.0f} % of its value {values[name]:.4g}: "
                 "an unreliable estimate")
    demo = is_demonstration(run)
    if demo:
        warn("warning: this run is the demonstration model (800 pairs, small towers, 8 "
             "epochs): its values show the pipeline working, not a calibration")
    result = {
        "left": os.path.abspath(left_path), "right": os.path.abspath(right_path),
        "image_width": width, "image_height": height, "model_input": [size_h, size_w],
        "run": run.run_dir, "variant": run.config.variant,
        "parameters": {name: values[name] for name in PARAMETERS},
        "point": {name: values[name] for name in ("X", "Y", "Z")},
        "pitch_deg": math.degrees(values["pitch"]),
        "fov_horizontal_deg": float(np.degrees(fov_from_focal(values["fx"], width))),
        "fov_vertical_deg": float(np.degrees(fov_from_focal(values["fy"], height))),
        "units": {name: UNITS[name] for name in PARAMETERS},
        "spread": spread, "spread_method": SPREAD_METHOD.format(len(windows) - 1),
        "scale_free": {"disparity_px": values["disparity"],
                       "baseline_over_depth": values["disparity"] / values["fx"],
                       "note": SCALE_NOTE},
        "scale_priors": list(SCALE_PRIORS), "fields": dict(FIELDS),
        "demonstration_model": demo,
        "aspect": aspect, "network_fy": network_fy, "aspect_note": ASPECT_NOTES[aspect],
        "training": {
            "protocol": training_protocol(run), "split": run.config.split,
            "as_released": released, "label_ranges": ranges,
            "label_ranges_units": f"the model's input ({size_w}x{size_h} px), targets as trained",
        },
    }
    if released:
        result["notes"] = ["run trained as released: pitch converted from degrees; disparity "
                           "is the release's StereoBM mean label, not a pixel disparity"]
    return _with_record_and_priors(result, run, priors, network_baseline)


def _with_record_and_priors(result, run, priors, network_baseline):
    """``result`` with the run's real-camera record and what came from the
    user's known values (``network_baseline``: the network's, before)."""
    result["real_camera_record"] = real_record.summarise(run)
    result["priors"] = known.describe(priors, factor=(
        priors.baseline_m / network_baseline if priors.baseline_m else None))
    result["from_prior"] = known.from_prior(priors)
    return result


def _resolve_priors(priors, left_path, width, height):
    """``priors`` with an EXIF focal length read from the left image."""
    if priors.focal_source != "exif":
        return priors
    focal, source = known.exif_focal_px(left_path, width, height)
    return known.Priors(baseline_m=priors.baseline_m, focal_px=focal, focal_source=source)


# ---------------------------------------------------------------------------
# A folder of pairs from one rig
# ---------------------------------------------------------------------------
#: The rig's parameters (the disparity belongs to each pair's scene).
RIG_PARAMETERS = tuple(name for name in PARAMETERS if name != "disparity")
RIG_METHOD = ("median over the pairs; spread_over_pairs: standard deviation over the pairs "
              "(n - 1 in the denominator)")
def calibrate_rig(folder, run_dir, warn=None, aspect="square", priors=None):
    """Every pair of ``folder`` (``find_pairs``) calibrated by the run, and
    the rig's calibration from them: each parameter but the disparity (the
    scene's) is the median over the pairs, with its spread over the pairs.
    Warnings name their pair; each is given once."""
    warn = warn or (lambda line: None)
    pairs = find_pairs(folder)
    loaded = load(run_dir)
    said, results = set(), []

    def warn_once(line):
        if line not in said:
            said.add(line)
            warn(line)

    for left, right in pairs:
        name = os.path.basename(left)
        results.append(calibrate_pair(
            left, right, run_dir, loaded=loaded, aspect=aspect, priors=priors,
            warn=lambda line, name=name: warn_once(
                line if "demonstration model" in line else f"{name}: {line}")))
    sizes = sorted({(r["image_width"], r["image_height"]) for r in results})
    if len(sizes) > 1:
        raise CalibrationError(f"the pairs of {folder} have different image sizes "
                               f"({sizes[0][0]}x{sizes[0][1]}, {sizes[1][0]}x{sizes[1][1]}); "
                               "one rig has one")
    width, height = sizes[0]
    per_pair = {name: [r["parameters"][name] for r in results] for name in RIG_PARAMETERS}
    parameters = {name: float(np.median(v)) for name, v in per_pair.items()}
    spread = {name: float(np.std(v, ddof=1)) if len(v) > 1 else 0.0
              for name, v in per_pair.items()}
    for name in ("fx", "fy") if aspect == "model" else ("fx",):
        if spread[name] > SPREAD_WARNING * abs(parameters[name]):
            warn(f"warning: {name} changes by {spread[name]:.4g} px (std) between the "
                 f"{len(results)} pairs, over {100 * SPREAD_WARNING:.0f} % of its median "
                 f"{parameters[name]:.4g}: an unreliable estimate")
    rig = {
        "folder": os.path.abspath(folder), "num_pairs": len(results), "run": results[0]["run"],
        "variant": results[0]["variant"], "image_width": width, "image_height": height,
        "parameters": parameters, "spread_over_pairs": spread, "method": RIG_METHOD,
        "pitch_deg": math.degrees(parameters["pitch"]),
        "fov_horizontal_deg": float(np.degrees(fov_from_focal(parameters["fx"], width))),
        "fov_vertical_deg": float(np.degrees(fov_from_focal(parameters["fy"], height))),
        "units": {name: UNITS[name] for name in RIG_PARAMETERS},
        "scale_priors": [n for n in SCALE_PRIORS if n in RIG_PARAMETERS],
        "demonstration_model": results[0]["demonstration_model"],
        "aspect": aspect, "aspect_note": ASPECT_NOTES[aspect],
        "real_camera_record": results[0]["real_camera_record"],
        "priors": {name: {k: v for k, v in said.items() if k != "scale_factor"}
                   for name, said in results[0]["priors"].items()},
        "from_prior": results[0]["from_prior"],
    }
    return {"rig": rig, "pairs": results}


#: What calibrate's JSON says of the quantities a pair does not fix.
SCALE_PRIORS = ("baseline", "tx", "ty", "tz", "X", "Y", "Z")
SCALE_NOTE = ("the pair's matches fix the disparity in pixels; for a rectified or nearly "
              "rectified rig (parallel optical axes) they carry nothing of fx, fy, u0, v0 "
              "(its fundamental matrix does not depend on them), so those come from how "
              "scenes looked in training, as does baseline / depth = disparity / fx through "
              "fx; the metres of baseline, tx, ty, tz and X, Y, Z come from the scene scale "
              "seen in training (scale priors)")
ASPECT_NOTES = {
    "square": "square pixels: fy = fx (px of the input images); network_fy is the network's "
              "own fy, which guesses the aspect ratio of the squashed image from content",
    "model": "fy is the network's fy head (the pair squashed to the model's square input)",
}
SPREAD_METHOD = (f"standard deviation over the whole image and {{}} crops of "
                 f"{int(100 * TTA_FRACTION[0])}-{int(100 * TTA_FRACTION[1])} % of each side, "
                 "each mapped back to the full image's pixels")


def focal_argument(text):
    """argparse type of --focal: ``exif``, or a positive number of pixels;
    ``(pixels or None, source)``."""
    if text == "exif":
        return None, "exif"
    return cli.positive_float(text), "--focal"


def main(argv=None):
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("left", nargs="?", help="left image file (PNG, JPEG, ...)")
    parser.add_argument("right", nargs="?", help="right image file of the same pair")
    parser.add_argument("--folder", metavar="DIR",
                        help="calibrate every pair of DIR (names with left/right, or left/ and "
                        "right/ folders) as one rig: each parameter the median over the pairs, "
                        "with its spread over them (instead of LEFT RIGHT)")
    parser.add_argument("--run", required=True, help="run directory of a trained model")
    parser.add_argument("--aspect", choices=ASPECTS, default="square",
                        help="square: fy = fx, as on real cameras' square pixels (default); "
                        "model: the network's fy")
    parser.add_argument("--baseline", type=cli.positive_float, metavar="METRES",
                        help="the rig's known baseline: baseline, tx, ty, tz and X, Y, Z are "
                        "scaled to it (the output names what came from it)")
    parser.add_argument("--focal", type=focal_argument, metavar="PX|exif",
                        help="the known focal length in pixels of the input images, or exif: "
                        "the left image's 35 mm equivalent (JPEG EXIF); fx, fy and the depth "
                        "X, Y, Z follow it")
    parser.add_argument("--json-out", help="also write the JSON to this file")
    parser.add_argument("--opencv-yaml", metavar="FILE",
                        help="also write the calibration as OpenCV's stereo YAML (M1, D1, M2, "
                        "D2, R, T; cv2.FileStorage reads it)")
    parser.add_argument("--ros-yaml", metavar="DIR",
                        help="also write ROS camera_info files DIR/left.yaml and DIR/right.yaml")
    parser.add_argument("--colmap", metavar="DIR",
                        help="also write COLMAP's DIR/cameras.txt (PINHOLE, the left and right "
                        "cameras)")
    args = parser.parse_args(argv)
    if args.folder and (args.left or args.right):
        parser.error("give LEFT RIGHT or --folder DIR, not both")
    if not args.folder and not (args.left and args.right):
        parser.error("give the two images of a pair (LEFT RIGHT) or --folder DIR")
    try:
        for flag, path in (("--json-out", args.json_out), ("--opencv-yaml", args.opencv_yaml)):
            if path:
                directory = os.path.dirname(os.path.abspath(path))
                if not os.path.isdir(directory):
                    raise CalibrationError(f"output directory does not exist: {directory}")
                if os.path.isdir(path):
                    raise CalibrationError(f"{flag} is a directory: {path}")
        for flag, folder in (("--ros-yaml", args.ros_yaml), ("--colmap", args.colmap)):
            if folder and os.path.exists(folder) and not os.path.isdir(folder):
                raise CalibrationError(f"{flag} is a file, not a directory: {folder}")
        focal, source = args.focal or (None, None)
        priors = known.Priors(baseline_m=args.baseline, focal_px=focal, focal_source=source)
        def warn(line):
            print(f"{PROG}: {line}", file=sys.stderr)

        if args.folder:
            result = calibrate_rig(args.folder, args.run, warn=warn, aspect=args.aspect,
                                   priors=priors)
            calibration = result["rig"]
        else:
            result = calibration = calibrate_pair(args.left, args.right, args.run, warn=warn,
                                                  aspect=args.aspect, priors=priors)
        warn(calibration["real_camera_record"]["line"])
        text = json.dumps(result, indent=2, allow_nan=False)
        if args.json_out:
            files.write_text(args.json_out, text + "\n")
        if args.opencv_yaml:
            exports.write_opencv_yaml(args.opencv_yaml, calibration)
        if args.ros_yaml:
            exports.write_ros_yaml(args.ros_yaml, calibration)
        if args.colmap:
            exports.write_colmap_cameras(args.colmap, calibration)
    except (Error, OSError) as error:  # (CalibrationError, RunError, DatasetError, ...)
        return cli.fail(PROG, error)
    print(text)
    return 0


if __name__ == "__main__":
    cli.run(main, PROG)
