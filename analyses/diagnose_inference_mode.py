"""How much does a trained run's validation error depend on the BatchNorm
statistics it is evaluated with?

Training validates in inference mode after recomputing every BatchNorm
layer's statistics over the first ``bn_recompute_batches`` batches of the
epoch's shuffled training order (``cpl_keras.models.batchnorm``). This script
loads a finished run's saved model and prints its validation MAE per
parameter (and the model's own loss) under:

* ``saved``: the statistics saved with the model (those of its best epoch);
* ``recompute K #i``: recomputed over K training batches, for ``--draws``
  different random draws of K batches (what training did each epoch with
  ``bn_statistics="epoch"``), and ``population K #i`` the same batches with
  the population variance (with K = 64, what ``bn_statistics="fixed"``
  recomputes, from a set of another seed);
* ``recompute all``: recomputed over every training batch;
* ``batch stats``: training-mode BatchNorm on each validation batch (no
  stored statistics at all).

Beside the validation loss, ``capped`` is the loss of the same network with
the disparity head's ceiling at twice the largest training label
(``layers.PositiveDisparity``, training's default since), and ``d capped``
the disparity's MAE with its predictions clipped there.

A spread between the draws far above the difference between ``recompute all``
and ``batch stats`` says that the recompute's sample, not the fit, moves the
validation figures.

    python analyses/diagnose_inference_mode.py --run runs/faithful/cvgl-cpl-a-inception_v3 \\
        --batches 16 --draws 4

Produces: the table on stdout. Committed outputs, with the commands in their
folders' README.md: paper_results/faithful-2000/diagnose_inference_mode.txt,
paper_results/faithful-2000-steady/diagnose_fixed_64.txt and
diagnose_epoch_16.txt.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("KERAS_BACKEND", "jax")

import numpy as np  # noqa: E402

from cpl_keras.camera import TARGETS  # noqa: E402

COLUMNS = ("fx", "fy", "u0", "v0", "baseline", "disparity", "d capped", "d median", "tx", "ty",
           "tz", "pitch")


def validation_figures(model, batches, training, ceiling):
    """Mean loss, per-parameter MAE, and the disparity's MAE and median
    absolute error with its predictions clipped at ``ceiling``."""
    losses, errors, count, disparity = [], {name: 0.0 for name in TARGETS}, 0, []
    for x, y in batches:
        outputs = model(x, training=training)
        y_pred = dict(zip(model.output_names, outputs))
        loss = model.compute_loss(x=x, y=y, y_pred=outputs, training=False)
        losses.append(float(np.asarray(loss)))
        for name in TARGETS:
            errors[name] += float(np.sum(np.abs(np.asarray(y_pred[name]).reshape(-1)
                                                - np.asarray(y[name]).reshape(-1))))
        count += len(y[TARGETS[0]])
        disparity.append(np.stack([np.asarray(y_pred["disparity"]).reshape(-1),
                                   np.asarray(y["disparity"]).reshape(-1)]))
    pred, true = np.concatenate(disparity, axis=1)
    mae = {name: errors[name] / count for name in TARGETS}
    mae["d capped"] = float(np.mean(np.abs(np.minimum(pred, ceiling) - true)))
    mae["d median"] = float(np.median(np.abs(pred - true)))
    return float(np.mean(losses)), mae


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, help="a finished run directory with its model")
    parser.add_argument("--batches", type=int, default=16,
                        help="training batches per recompute (default 16, training's default)")
    parser.add_argument("--draws", type=int, default=4, help="random draws (default 4)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    parser.add_argument("--epoch-order", type=int, nargs="*", default=[],
                        help="also recompute over the first K batches of these epochs' shuffled "
                             "order (0-based), as training did")
    parser.add_argument("--no-all", action="store_true", help="skip the all-batches recompute")
    parser.add_argument("--variance", choices=("both", "average", "population"), default="both",
                        help="the draws' variance: the average batch variance (training's "
                        "bn_statistics=epoch), the population variance (bn_statistics=fixed, "
                        "whose draws are fixed sets of other seeds), or both (default)")
    args = parser.parse_args(argv)

    from cpl_keras import runs
    from cpl_keras.datasets import targets_from_labels
    import keras

    from cpl_keras.layers import PositiveDisparity, positive_disparity
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.models.batchnorm import recompute_batchnorm_statistics
    from cpl_keras.training.sequence import StereoSequence

    run = runs.load_run(args.run)
    data = run.config.data.path
    with StereoFile(data) as f:
        targets = targets_from_labels(f.labels, as_released=run.as_released)
    batch = int(run.config.training.batch_size or 16)
    ceiling = 2.0 * float(np.max(targets["disparity"][run.split["train"]]))
    val = StereoSequence(data, run.split["val"], targets=targets, batch_size=batch)
    val_batches = [val[i] for i in range(len(val))]
    model = runs.load_model(run)
    print(f"{args.run}: {run.config.variant}, {run.config.build['backbone']}, best epoch "
          f"{run.config.best_epoch}; {len(run.split['train'])} training pairs, {len(val)} validation "
          f"batches of {batch}; 'd capped': the disparity's MAE with its predictions "
          f"clipped at twice the largest training label ({ceiling:.0f} px), 'd median': its "
          "median absolute error, 'capped': the validation loss with the disparity head's "
          "ceiling there (layers.PositiveDisparity)", flush=True)
    print("statistics          val_loss  capped  " + "  ".join(f"{c:>9s}" for c in COLUMNS), flush=True)

    head = model.get_layer("disparity")
    activation = head.activation
    if isinstance(activation, PositiveDisparity) or activation is positive_disparity:
        capped = PositiveDisparity(ceiling=ceiling)
    else:  # a linear head (MTL-Baseline, or as released): clipped at the ceiling
        def capped(x):
            return keras.ops.minimum(activation(x), ceiling)

    def report(label, training=False):
        start = time.perf_counter()
        loss, mae = validation_figures(model, val_batches, training, ceiling)
        head.activation = capped  # the same network with the head's ceiling
        try:
            capped_loss, _ = validation_figures(model, val_batches, training, ceiling)
        finally:
            head.activation = activation
        print(f"{label:18s} {loss:9.3f} {capped_loss:9.3f}  "
              + "  ".join(f"{mae[c]:9.4g}" for c in COLUMNS)
              + f"   ({time.perf_counter() - start:.0f} s)", flush=True)

    saved = [v.numpy() if hasattr(v, "numpy") else np.asarray(v)
             for v in model.non_trainable_variables]
    report("saved")
    # Batches of shuffled orders, as training draws them (the split's index
    # order is sorted, so unshuffled batches hold adjacent frames of a drive).
    shuffled = StereoSequence(data, run.split["train"], targets=targets, batch_size=batch,
                              shuffle=True, seed=int(run.config.training.seed))

    def first_batches(epoch, count):
        shuffled.set_epoch(epoch)
        return (shuffled[i] for i in range(min(count, len(shuffled))))

    for epoch in args.epoch_order:
        recompute_batchnorm_statistics(model, first_batches(epoch, args.batches))
        report(f"epoch {epoch}'s first {args.batches}")
    variances = {"both": (False, True), "average": (False,), "population": (True,)}
    for draw in range(args.draws):
        epoch = 1000 + args.seed * 100 + draw  # an order no training epoch used
        for population in variances[args.variance]:
            recompute_batchnorm_statistics(model, first_batches(epoch, args.batches),
                                           population=population)
            report(f"{'population' if population else 'recompute'} {args.batches} #{draw + 1}")
    if not args.no_all:
        for population in (False, True):
            recompute_batchnorm_statistics(model, first_batches(1000, len(shuffled)),
                                           population=population)
            report(f"{'population' if population else 'recompute'} all {len(shuffled)}")
    for variable, value in zip(model.non_trainable_variables, saved):
        variable.assign(value)
    report("batch stats", training=True)
    shuffled.close()
    val.close()


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'analyses/diagnose_inference_mode.py')
