"""Calibrate each shipped real rig, as a user would, with the model that
never saw it: ``python -m cpl_keras.calibrate --folder`` on the rig's whole
images (640 x 480 chessboard and OAK-D pairs, the 741 x 500 Middlebury
Motorcycle pair), against the rig's true calibration at full resolution.

    python bench/calibrate_held_out.py --runs-dir runs/zoom-crops \\
        --out paper_results/real-cameras/zoom-with-crops/calibrate [--aspect square]

``--runs-dir`` holds ``without-<rig>`` runs (``bench/leave_one_rig_out.py
--with-real-crops``). For each rig it writes what calibrate writes (the JSON
without this machine's paths, the OpenCV and ROS YAML files, the warnings)
and one table, ``--out/summary.md``: the rig's fx, fy and horizontal field of
view, true and calibrated, the relative errors, the spreads over the pairs,
and the warnings calibrate printed. ``summary_markdown`` renders it from the
files written beside it and the true focal lengths of the committed rigs
(``true_focals``), so ``regenerate`` rebuilds the committed page without
the runs.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import tempfile

from cpl_keras import files

os.environ.setdefault("KERAS_BACKEND", "jax")


#: The shipped rigs, each calibrated with its ``without-<rig>`` run.
RIGS = ("chessboard", "middlebury", "oakd")


def true_focals(rig):
    """The rig's true (fx, fy) at full resolution, from the committed rigs
    (``cpl_keras/real``: the chessboard pairs' calibration, the OAK-D's
    calibration file, the Motorcycle pair's documented focal length)."""
    from cpl_keras.real import chessboard, middlebury, oakd

    if rig == "chessboard":
        cal = chessboard.calibrate()["rig"]
    elif rig == "oakd":
        cal = oakd.load_calibration()
    else:
        cal = {"fx": middlebury.CALIBRATION["focal"], "fy": middlebury.CALIBRATION["focal"]}
    return cal["fx"], cal["fy"]


def folders():
    """rig -> a function returning its folder of whole pairs (the
    Motorcycle pair written to a temporary folder)."""
    from cpl_keras.real import chessboard, oakd

    def motorcycle():
        import cv2

        from cpl_keras.real import middlebury

        left, right, _, _ = middlebury.load_motorcycle()
        folder = tempfile.mkdtemp(prefix="motorcycle-")
        for side, image in (("left", left), ("right", right)):
            cv2.imwrite(os.path.join(folder, f"motorcycle_{side}.png"),
                        cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        return folder

    return {"chessboard": lambda: chessboard.DATA_DIR, "middlebury": motorcycle,
            "oakd": lambda: oakd.DATA_DIR}


def without_paths(result, folder_name):
    """calibrate's JSON of the ``RigCalibration`` ``result`` without this
    machine's paths (file names only)."""
    result = result.as_dict()
    rig = dict(result["rig"], folder=folder_name, run=os.path.basename(result["rig"]["run"]))
    pairs = [dict(p, left=os.path.basename(p["left"]), right=os.path.basename(p["right"]),
                  run=os.path.basename(p["run"])) for p in result["pairs"]]
    return {"rig": rig, "pairs": pairs}


def held_out_runs(runs_dir):
    """rig -> its ``without-<rig>`` run directory in ``runs_dir`` (the rigs
    that have one); RunError when ``runs_dir`` is not a folder or holds none."""
    from cpl_keras.runs import RunError

    if not os.path.isdir(runs_dir):
        raise RunError(f"--runs-dir is not a directory: {runs_dir}")
    found = {rig: os.path.join(runs_dir, f"without-{rig}") for rig in RIGS
             if os.path.isdir(os.path.join(runs_dir, f"without-{rig}"))}
    if not found:
        raise RunError(f"no without-<rig> run ({', '.join(RIGS)}) in {runs_dir}")
    return found


def summary_markdown(out, rigs, command):
    """summary.md of the calibrations in ``out`` (``<rig>.json`` and
    ``<rig>_warnings.txt`` of each of ``rigs``) against the true focal
    lengths (``true_focals``), its generated line naming ``command`` first."""
    import numpy as np

    lines = [files.generated_line(command), "",
             "# Calibrating each shipped rig with the model that never saw it", "",
             f"`{command}`: `calibrate --folder` on the rig's whole images, the rig's parameters "
             "the medians over its pairs (network fy: the median of the network's own fy head "
             "over the pairs).", "",
             "| rig | pairs | image | fx true / calibrated (rel. error) | fy true / calibrated "
             "(rel. error) | network fy (rel. error) | hFoV true / calibrated | fx spread over "
             "pairs | warnings |", "|---|---|---|---|---|---|---|---|---|"]
    for rig in rigs:
        with open(os.path.join(out, f"{rig}.json")) as f:
            result = json.load(f)
        with open(os.path.join(out, f"{rig}_warnings.txt")) as f:
            warnings = f.read().splitlines()
        calib, (fx, fy) = result["rig"], true_focals(rig)
        p, width = calib["parameters"], calib["image_width"]
        network_fy = float(np.median([pair["network_fy"] for pair in result["pairs"]]))
        hfov = math.degrees(2 * math.atan2(width, 2 * fx))
        lines.append(
            f"| {rig} | {calib['num_pairs']} | {width} x {calib['image_height']} | "
            f"{fx:.1f} / {p['fx']:.1f} ({abs(p['fx'] / fx - 1):.3f}) | "
            f"{fy:.1f} / {p['fy']:.1f} ({abs(p['fy'] / fy - 1):.3f}) | "
            f"{network_fy:.1f} ({abs(network_fy / fy - 1):.3f}) | "
            f"{hfov:.1f} / {calib['fov_horizontal_deg']:.1f} deg | "
            f"{calib['spread_over_pairs']['fx']:.1f} px | {len(warnings)} |")
    return "\n".join(lines) + "\n"


def regenerate(page_path):
    """The text ``main`` wrote for the committed summary.md ``page_path``:
    the rigs calibrated beside it, the command from its first line."""
    out = os.path.dirname(page_path)
    with open(page_path) as f:
        command = files.generated_command(f.read())
    rigs = [rig for rig in RIGS if os.path.exists(os.path.join(out, f"{rig}.json"))]
    return summary_markdown(out, rigs, command)


def main(argv=None):
    from cpl_keras import cli

    parser = cli.Parser(prog="bench/calibrate_held_out.py",
                        description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs-dir", required=True, help="folder of without-<rig> runs")
    parser.add_argument("--out", required=True, help="folder for the calibrations and summary.md")
    parser.add_argument("--aspect", default="square", choices=("square", "model"))
    args = parser.parse_args(argv)
    runs = held_out_runs(args.runs_dir)  # (before anything is written)

    from cpl_keras import exports
    from cpl_keras.calibrate import Calibrator

    os.makedirs(args.out, exist_ok=True)
    done = []
    for rig, folder_of in folders().items():
        run_dir = runs.get(rig)
        if run_dir is None:
            print(f"{rig}: no run without-{rig} in {args.runs_dir}, skipped", flush=True)
            continue
        folder = folder_of()
        warnings = []
        calib = Calibrator.from_run(run_dir).calibrate_folder(
            folder, aspect=args.aspect, warn=warnings.append)
        files.write_json(os.path.join(args.out, f"{rig}.json"),
                         without_paths(calib, os.path.basename(folder.rstrip("/"))))
        files.write_text(os.path.join(args.out, f"{rig}_warnings.txt"), "".join(
            line.replace(os.path.join(folder, ""), "") + "\n" for line in warnings))
        published = dataclasses.replace(calib, run=os.path.basename(calib.run))  # no paths
        exports.write_opencv_yaml(os.path.join(args.out, f"{rig}_opencv.yml"), published)
        exports.write_ros_yaml(os.path.join(args.out, f"{rig}_ros"), published)
        done.append(rig)
        print(f"{rig}: calibrated", flush=True)
    command = f"python bench/calibrate_held_out.py {' '.join(argv or sys.argv[1:])}"
    text = summary_markdown(args.out, done, command)
    files.write_text(os.path.join(args.out, "summary.md"), text)
    print(text)
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/calibrate_held_out.py')
