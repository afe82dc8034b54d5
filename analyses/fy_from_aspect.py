"""Does a run learn fy from the image, or return fx again? Median relative
errors of fx, fy and fy / fx, and the correlation of the predicted with the
true log(fy / fx), for runs on the test split of a ``cameras`` dataset
(source images of real cameras' aspect ratios squashed to the square
input, ``cpl_keras.data.protocols``).

    python analyses/fy_from_aspect.py --data runs/aspect/cameras_1500.h5 \\
        --split-of runs/aspect/cameras-baseline \\
        --runs runs/aspect/cameras-baseline runs/aspect/random-baseline

The pairs are the test split of ``--split-of`` (a run trained on
``--data``); every run is scored on the same pairs.

Produces: one line per run on stdout. Committed output:
paper_results/aspect/fy_from_aspect.txt (the commands in that folder's
README.md); paper_results/real-cameras/README.md quotes a run on held-out
rendered rigs.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("KERAS_BACKEND", "jax")

import numpy as np  # noqa: E402


def median_relative(pred, true):
    return float(np.median(np.abs(pred - true) / np.abs(true)))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a cameras-protocol HDF5 dataset")
    parser.add_argument("--split-of", required=True, help="the run whose test split is scored")
    parser.add_argument("--runs", nargs="+", required=True, help="run directories to score")
    args = parser.parse_args(argv)

    from cpl_keras import runs
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import targets_from_labels
    from cpl_keras.models.inference import predict_images

    test = runs.load_run(args.split_of).split["test"]
    with StereoFile(args.data) as f:
        targets = targets_from_labels(f.labels)
        left, right = f.read_pairs(test)
    fx_true, fy_true = targets["fx"][test], targets["fy"][test]
    ratio_true = fy_true / fx_true
    print(f"{len(test)} test pairs of {args.data}; true fy / fx "
          f"{ratio_true.min():.2f} .. {np.median(ratio_true):.2f} (median) .. "
          f"{ratio_true.max():.2f}")
    for run_dir in args.runs:
        run = runs.load_run(run_dir)
        out = predict_images(runs.load_model(run), left, right)
        fx, fy = out["fx"], out["fy"]
        ratio = fy / np.where(np.abs(fx) > 1e-6, fx, 1e-6)
        positive = (fx > 0) & (fy > 0)
        correlation = np.corrcoef(np.log(ratio[positive]), np.log(ratio_true[positive]))[0, 1]
        print(f"{run_dir}: median relative error fx {median_relative(fx, fx_true):.3f}, "
              f"fy {median_relative(fy, fy_true):.3f}, fy/fx {median_relative(ratio, ratio_true):.3f}; "
              f"correlation of log(fy/fx) with the truth {correlation:.2f}", flush=True)


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'analyses/fy_from_aspect.py')
