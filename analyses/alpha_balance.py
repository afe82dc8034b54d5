"""How close MTL-CPL-A's adaptive weights are to Eq. 9's optimum.

Eq. 9 with alpha_i = exp(-s_i) and the regulariser sum_i s_i is minimised at
alpha_i = 1 / L_i, so at balance every weighted term alpha_i L_i is 1. This
script loads a finished MTL-CPL-A run (its best model), computes the 13
disentangled terms L_i of Eq. 7 on training batches of its own dataset
(mean over ``--batches`` batches, in inference mode) and prints alpha_i,
L_i and alpha_i L_i per term, and the spread of alpha_i L_i.

    python analyses/alpha_balance.py runs/faithful/cvgl-cpl-a-small_resnet [RUN ...]

Produces: the table on stdout. Its figures for the two paces of the
adaptive weights are quoted in paper_results/faithful-2000/README.md ("The
adaptive weights' pace").
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("KERAS_BACKEND", "jax")


def balance(run_dir, batches=8, batch_size=16):
    """``{target: (alpha, L, alpha * L)}`` of a run's best model."""
    import numpy as np
    from keras import ops

    from cpl_keras import camera, runs
    from cpl_keras.datasets import targets_from_labels
    from cpl_keras.training.sequence import StereoSequence
    from cpl_keras.data.storage import StereoFile

    run = runs.load_run(run_dir)
    model = runs.load_model(run)
    if model.adaptive_weights() is None:
        raise SystemExit(f"{run_dir}: not an MTL-CPL-A run (no adaptive weights)")
    with StereoFile(run.config.data.path) as f:
        targets = targets_from_labels(f.labels)
    sequence = StereoSequence(run.config.data.path, run.split["train"], targets=targets,
                              batch_size=batch_size, shuffle=True, seed=0)
    sums = np.zeros(len(camera.TARGETS))
    count = min(batches, len(sequence))
    for index in range(count):
        x, y = sequence[index]
        pred = model(x, training=False)
        terms = model.projection_terms(y, pred)
        sums += np.array([float(ops.convert_to_numpy(t)) for t in terms])
    sequence.close()
    alphas = model.adaptive_weights()
    terms = sums / count
    return {name: (alphas[name], float(t), alphas[name] * float(t))
            for name, t in zip(camera.TARGETS, terms)}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="finished MTL-CPL-A run directories")
    parser.add_argument("--batches", type=int, default=8, help="training batches (default 8)")
    args = parser.parse_args(argv)

    import numpy as np

    for run_dir in args.runs:
        table = balance(run_dir, args.batches)
        products = np.array([p for _, _, p in table.values()])
        print(f"{run_dir}: alpha_i L_i from {products.min():.3g} to {products.max():.3g} "
              f"(median {np.median(products):.3g}; 1 at Eq. 9's optimum)")
        print("  term        alpha_i        L_i   alpha_i L_i")
        for name, (alpha, term, product) in table.items():
            print(f"  {name:10s} {alpha:9.4g} {term:10.4g} {product:12.3g}")


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'analyses/alpha_balance.py')
