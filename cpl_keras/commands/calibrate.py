"""``python -m cpl_keras.calibrate`` (``cpl-calibrate``): calibrate a stereo
pair, or a folder of pairs of one rig, with a trained run (what it prints and
writes: ``cpl_keras.calibrate``'s documentation, docs/calibrate.md)."""

from __future__ import annotations

import argparse
import os
import sys

from cpl_keras import cli, exports, priors as known
from cpl_keras.cache import enable_compile_cache
from cpl_keras.calibrate import __doc__ as CALIBRATE_DOC
from cpl_keras.calibration import ASPECTS, Calibrator, CalibrationError
from cpl_keras.errors import Error

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


def calibrate(calibrator, args, priors, warn):
    """The calibration ``args`` ask for: of a pair, or of a folder's pairs
    with a progress bar on a terminal (none with --no-progress)."""
    if not args.folder:
        return calibrator.calibrate(args.left, args.right, aspect=args.aspect, priors=priors,
                                    warn=warn)
    shown = not args.no_progress and sys.stderr.isatty()
    return calibrator.calibrate_folder(
        args.folder, aspect=args.aspect, priors=priors, warn=warn,
        progress=lambda total: cli.ProgressBar(total, "calibrating", shown))


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


def notices(calibration):
    """What is said on stderr of a calibration once it is made: the run's
    record on real cameras, and a rig that is not a side-by-side pair (as
    its exports say it)."""
    layout = exports.exported_rig(calibration).note
    return [calibration.real_camera_record["line"]] + ([f"warning: {layout}"] if layout else [])


def main(argv=None):
    parser = cli.Parser(prog=PROG, description=CALIBRATE_DOC.split("\n")[0])
    parser.add_argument("left", nargs="?", help="left image file (PNG, JPEG, ...)")
    parser.add_argument("right", nargs="?", help="right image file of the same pair")
    parser.add_argument("--folder", metavar="DIR",
                        help="calibrate every pair of DIR (names with left/right, or left/ and "
                        "right/ folders) as one rig: each parameter the median over the pairs, "
                        "with its spread over them (instead of LEFT RIGHT)")
    parser.add_argument("--run", required=True, help="run directory of a trained model")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar for --folder (shown on a terminal)")
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
    parser.add_argument("--json-out", type=cli.path, help="also write the JSON to this file")
    parser.add_argument("--opencv-yaml", type=cli.path, metavar="FILE",
                        help="also write the calibration as OpenCV's stereo YAML (M1, D1, M2, "
                        "D2, R, T; cv2.FileStorage reads it)")
    parser.add_argument("--ros-yaml", type=cli.path, metavar="DIR",
                        help="also write ROS camera_info files DIR/left.yaml and DIR/right.yaml")
    parser.add_argument("--colmap", type=cli.path, metavar="DIR",
                        help="also write COLMAP's DIR/cameras.txt (PINHOLE, the left and right "
                        "cameras) and DIR/rig_config.json (the pair's pose)")
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
        calibration = calibrate(Calibrator.from_run(args.run), args, priors, warn)
        for line in notices(calibration):
            warn(line)
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
