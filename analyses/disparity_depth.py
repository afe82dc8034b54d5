"""Is a network's disparity error a trade for depth? The disparity's NMAE
beside the error of the depth it implies (Eq. 4a, xCam = fx * b / d, with
fx and b at their truth: Eq. 7's disparity term), for Table 1 rows of
reproduction folders, seed by seed and as a mean over seeds.

    python analyses/disparity_depth.py --folders paper_results/compact-2000 paper_results/cpu-8000

The camera projection loss learns the disparity through the depth it
implies, whose error for a given disparity error shrinks as 1 / d^2. If
MTL-CPL-A's higher disparity NMAE were that trade, its depth error from the
disparity would be the lower of the two; this prints both, from each
folder's published predictions (``runs/*_predictions.npz``, Table 1 rows
of the networks; no weights, no datasets).

Columns: ``d`` is the disparity's NMAE (mean |d_pred - d| over mean |d|);
``depth`` the NMAE of xCam(fx, b, d_pred) against xCam(fx, b, d); ``median
depth`` the median of |xCam(fx, b, d_pred) - xCam| / xCam. Committed output:
paper_results/notes/disparity-and-depth.md.
"""

from __future__ import annotations

import argparse
import glob
import os

import numpy as np

#: The Table 1 rows of networks, in the order printed.
VARIANTS = ("baseline", "cpl-u", "cpl-a")


def disparity_and_depth(truth, pred):
    """``(d, depth, median_depth)`` of one row's ``truth`` and ``pred``
    (name -> array; a predictions file's row, ``prediction_files.load``)."""
    from cpl_keras import camera

    depth = camera.depth_from_disparity(truth["fx"], truth["baseline"], truth["disparity"])
    implied = camera.depth_from_disparity(truth["fx"], truth["baseline"], pred["disparity"])
    d_error = np.mean(np.abs(pred["disparity"] - truth["disparity"]))
    return (float(d_error / np.mean(np.abs(truth["disparity"]))),
            float(np.mean(np.abs(implied - depth)) / np.mean(np.abs(depth))),
            float(np.median(np.abs(implied - depth) / np.abs(depth))))


def folder_rows(folder):
    """``{table: {variant: [(seed, (d, depth, median_depth)), ...]}}`` of a
    folder's Table 1 rows on its own test splits (``table1_cvgl``,
    ``table1_cvgl_drive``; not the real sets' rows)."""
    from cpl_keras import prediction_files

    rows = {}
    for path in sorted(glob.glob(os.path.join(folder, "runs", "*_predictions.npz"))):
        if "_on_" in os.path.basename(path):
            continue
        item = prediction_files.load(path)
        if item.table_number != 1 or item.variant not in VARIANTS or item.raw.as_released:
            continue
        rows.setdefault(item.table, {}).setdefault(item.variant, []).append(
            (item.seed, disparity_and_depth(item.raw.truth, item.raw.pred)))
    if not rows:
        from cpl_keras.evaluation import EvaluationError

        raise EvaluationError(f"no Table 1 network rows in {folder}/runs/*_predictions.npz")
    return rows


def markdown(folder, table, rows):
    lines = [f"### {folder}, {table}", "", "| row | seed | d | depth | median depth |",
             "|---|---|---|---|---|"]
    for variant in VARIANTS:
        for seed, values in sorted(rows.get(variant, [])):
            lines.append(f"| {variant} | {seed} | " + " | ".join(f"{v:.3f}" for v in values)
                         + " |")
        if len(rows.get(variant, [])) > 1:
            mean = np.mean([values for _, values in rows[variant]], axis=0)
            lines.append(f"| {variant} | mean | " + " | ".join(f"**{v:.3f}**" for v in mean)
                         + " |")
    return lines + [""]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folders", nargs="+", required=True,
                        help="reproduction folders (each with runs/*_predictions.npz)")
    args = parser.parse_args(argv)
    for folder in args.folders:
        for table, rows in folder_rows(folder).items():
            print("\n".join(markdown(folder, table, rows)))
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/disparity_depth.py")
