"""Calibrate a stereo pair of image files with a trained run.

    python -m cpl_keras.calibrate LEFT.png RIGHT.png --run RUN_DIR [--json-out FILE]

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

Bad input (unreadable or non-image files, images of different sizes, a run
directory without weights) prints one line and exits with status 2; no
output file is written then.
"""

from __future__ import annotations

import json
import math
import os
import sys

os.environ.setdefault("KERAS_BACKEND", "jax")

import numpy as np  # noqa: E402

from cpl_keras import cli, runs  # noqa: E402
from cpl_keras.camera import PARAMETERS, UNITS, fov_from_focal  # noqa: E402
from cpl_keras.real import crop_resize_coordinate  # noqa: E402

PROG = "python -m cpl_keras.calibrate"


class CalibrationError(ValueError):
    """Bad input to calibrate (one-line message)."""


def read_image(path):
    """A uint8 RGB image from ``path`` (CalibrationError if unreadable)."""
    import cv2

    if not os.path.isfile(path):
        raise CalibrationError(f"image not found: {path}")
    image = cv2.imread(os.fspath(path), cv2.IMREAD_COLOR)
    if image is None:
        raise CalibrationError(f"cannot read {path} as an image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def to_input_pixels(values, width, height, size_w, size_h):
    """Scale predicted pixel quantities from the model's S x S grid back to
    the input image's W x H grid (see the module doc): the inverse of the
    builders' resize, ``real.crop_resize_coordinate`` with the inverse scale."""
    sx, sy = width / size_w, height / size_h
    out = dict(values)
    out["fx"] = values["fx"] * sx
    out["fy"] = values["fy"] * sy
    out["u0"] = float(crop_resize_coordinate(values["u0"], 0, sx))
    out["v0"] = float(crop_resize_coordinate(values["v0"], 0, sy))
    out["disparity"] = values["disparity"] * sx
    return out


def calibrate_pair(left_path, right_path, run_dir):
    """The calibration of one pair as a JSON-ready dict."""
    from cpl_keras import evaluation
    from cpl_keras.real import resize_image

    left = read_image(left_path)
    right = read_image(right_path)
    if left.shape != right.shape:
        raise CalibrationError(
            f"left and right images differ in size: {left.shape[1]}x{left.shape[0]} "
            f"and {right.shape[1]}x{right.shape[0]}")
    run = runs.load_run(run_dir, error=CalibrationError)
    model = runs.load_model(run, error=CalibrationError)
    size_h, size_w = evaluation.model_image_shape(model)
    height, width = left.shape[:2]
    pred = evaluation.predict_images(
        model, resize_image(left, size_w, size_h)[None], resize_image(right, size_w, size_h)[None])
    values = {name: float(pred[name][0]) for name in pred}
    released = runs.as_released(run)
    notes = []
    if released:
        values["pitch"] = math.radians(values["pitch"])
        notes.append("run trained as released: pitch converted from degrees; disparity is the "
                     "release's StereoBM mean label, not a pixel disparity")
    values = to_input_pixels(values, width, height, size_w, size_h)
    if not all(math.isfinite(v) for v in values.values()):
        raise CalibrationError("the model predicted non-finite values")
    result = {
        "left": os.path.abspath(left_path), "right": os.path.abspath(right_path),
        "image_width": width, "image_height": height, "model_input": [size_h, size_w],
        "run": run["run_dir"], "variant": run["config"]["variant"],
        "parameters": {name: values[name] for name in PARAMETERS},
        "point": {name: values[name] for name in ("X", "Y", "Z")},
        "pitch_deg": math.degrees(values["pitch"]),
        "fov_horizontal_deg": float(np.degrees(fov_from_focal(values["fx"], width))),
        "fov_vertical_deg": float(np.degrees(fov_from_focal(values["fy"], height))),
        "units": {name: UNITS[name] for name in PARAMETERS},
    }
    if notes:
        result["notes"] = notes
    return result


def main(argv=None):
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("left")
    parser.add_argument("right")
    parser.add_argument("--run", required=True, help="run directory of a trained model")
    parser.add_argument("--json-out", help="also write the JSON to this file")
    args = parser.parse_args(argv)
    try:
        if args.json_out:
            directory = os.path.dirname(os.path.abspath(args.json_out))
            if not os.path.isdir(directory):
                raise CalibrationError(f"output directory does not exist: {directory}")
            if os.path.isdir(args.json_out):
                raise CalibrationError(f"--json-out is a directory: {args.json_out}")
        result = calibrate_pair(args.left, args.right, args.run)
        text = json.dumps(result, indent=2, allow_nan=False)
        if args.json_out:
            runs.write_text(args.json_out, text + "\n")
    except (CalibrationError, OSError) as error:
        return cli.fail(PROG, error)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
