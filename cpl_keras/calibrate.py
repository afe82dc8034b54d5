"""Calibrate a stereo pair of image files with a trained run.

    python -m cpl_keras.calibrate LEFT.png RIGHT.png --run RUN_DIR [--json-out FILE]
        [--opencv-yaml FILE] [--ros-yaml DIR] [--colmap DIR]
        [--baseline METRES] [--focal PX|exif]
    python -m cpl_keras.calibrate --folder DIR --run RUN_DIR [...]

Prints JSON with the 10 camera parameters, the point X, Y, Z and the
horizontal and vertical fields of view, in the input images' own pixel
units (``cpl_keras.calibration``, whose ``Calibrator`` this command is a
thin layer over, says how they are scaled back from the model's input).

Bad input (unreadable or non-image files, images of different sizes or
smaller than the model's input, identical left and right images, a run
directory without weights) prints one line and exits with status 2; no
output file is written then. A grey image, and predictions outside the range
of the run's training labels (train_stats.json), are warned about on stderr,
one line each. The JSON says what the run was trained on (``training``: its
protocol, split and training label ranges, in the model's input units), the
spread of each value over crops of the pair (``spread``: its standard
deviation over the whole image and 8 crops, ``spread_method`` says so), what
rests on the pair rather than on a scene scale and which values are scale
priors (``from_the_pair``, ``scale_priors``), what every field means (``fields``), and whether the run
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
did worse than fx (docs/real-data.md, "Models for real cameras");
``--aspect model`` reports the network's fy.

``--folder DIR`` calibrates every pair of one rig (``find_pairs``) and
prints ``{"rig": ..., "pairs": [...]}``: the rig's parameters are the
medians over the pairs (the disparity, which belongs to each pair's scene,
is left out), ``spread_over_pairs`` their standard deviations; the YAML
exports describe the rig.
"""

from __future__ import annotations

import argparse
import os
import sys

from cpl_keras import cli, exports, priors as known
from cpl_keras.cache import enable_compile_cache
from cpl_keras.calibration import (ASPECTS, Calibration, Calibrator, CalibrationError,
                                   RigCalibration)
from cpl_keras.errors import Error

__all__ = ["Calibration", "CalibrationError", "Calibrator", "RigCalibration", "main"]

PROG = "python -m cpl_keras.calibrate"


def focal_argument(text):
    """argparse type of --focal: ``exif``, or a positive number of pixels up
    to ``priors.MAX_FOCAL_PX``; ``(pixels or None, source)``."""
    if text == "exif":
        return None, "exif"
    value = cli.positive_float(text)
    if value > known.MAX_FOCAL_PX:
        raise argparse.ArgumentTypeError(f"must be at most {known.MAX_FOCAL_PX:,.0f} px (a focal "
                                         f"length in pixels of the input images), got {text}")
    return value, "--focal"


def check_outputs(args):
    """The output files and folders that ``args`` asks for, checked before
    the work (``CalibrationError`` or ``cli.OutputError``, one line): the
    folder of ``--json-out`` and ``--opencv-yaml`` exists, each output can
    be written, and its device has space left."""
    for flag, path in (("--json-out", args.json_out), ("--opencv-yaml", args.opencv_yaml)):
        if path:
            directory = os.path.dirname(os.path.abspath(path))
            if not os.path.isdir(directory):
                raise CalibrationError(f"output directory does not exist: {directory}")
            if os.path.isdir(path):
                raise CalibrationError(f"{flag} is a directory: {path}")
            cli.check_output_file(path)
    for flag, folder in (("--ros-yaml", args.ros_yaml), ("--colmap", args.colmap)):
        if folder and os.path.exists(folder) and not os.path.isdir(folder):
            raise CalibrationError(f"{flag} is a file, not a directory: {folder}")
        if folder:
            cli.check_output_dir(folder)


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
                        help="the known focal length in pixels of the input images (a "
                        f"positive number up to {known.MAX_FOCAL_PX:,.0f}), or exif: the left "
                        "image's 35 mm equivalent (JPEG EXIF); fx, fy and the depth X, Y, Z "
                        "follow it")
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
        check_outputs(args)
        focal, source = args.focal or (None, None)
        priors = known.Priors(baseline_m=args.baseline, focal_px=focal, focal_source=source)
        def warn(line):
            print(f"{PROG}: {line}", file=sys.stderr)

        enable_compile_cache()  # (the next pair of the same model loads its programs)
        calibrator = Calibrator.from_run(args.run)
        if args.folder:
            calibration = calibrator.calibrate_folder(args.folder, aspect=args.aspect,
                                                      priors=priors, warn=warn)
        else:
            calibration = calibrator.calibrate(args.left, args.right, aspect=args.aspect,
                                               priors=priors, warn=warn)
        warn(calibration.real_camera_record["line"])
        text = calibration.to_json()
        exports.write_all(calibration, json_text=text, json_out=args.json_out,
                          opencv_yaml=args.opencv_yaml, ros_yaml=args.ros_yaml,
                          colmap=args.colmap)  # (all of them or none)
    except (Error, OSError) as error:  # (CalibrationError, RunError, DatasetError, ...)
        return cli.fail(PROG, error)
    print(text)
    return 0


if __name__ == "__main__":
    cli.run(main, PROG)
