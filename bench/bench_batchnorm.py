"""BatchNorm lag: the loss of one network in training mode, in inference mode,
and in inference mode after recomputing the statistics.

    python bench/bench_batchnorm.py --data data/cvgl.h5 [--backbone inception_v3]
        [--image-size 75] [--steps 200] [--momentum 0.99 0.9]

Trains MTL-Baseline from scratch for ``--steps`` steps (batch 16, Adam 1e-3)
once per BatchNorm momentum, then prints its loss on 8 training batches and
8 validation batches:

* training mode (batch statistics): the network that was trained;
* inference mode with Keras's moving averages (what validation, evaluation
  and saved models used before statistics were recomputed);
* inference mode after ``recompute_batchnorm_statistics`` on 16 training
  batches (what training now does before every validation).

The images must match ``--image-size`` (make a dataset at that size with
``python -m cpl_keras.data.generate --image-size 75 ...``).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("KERAS_BACKEND", "jax")

import numpy as np  # noqa: E402


def mean_loss(model, batches, training):
    """The model's own loss over ``batches`` (training or inference mode)."""
    losses = []
    for x, y in batches:
        y_pred = model(x, training=training)
        loss = model.compute_loss(x=x, y=y, y_pred=y_pred, training=False)
        losses.append(float(np.asarray(loss)))
    return float(np.mean(losses))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--backbone", default="inception_v3")
    parser.add_argument("--image-size", type=int, default=75)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--momentum", type=float, nargs="+", default=[0.99, 0.9])
    args = parser.parse_args(argv)

    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import make_split, targets_from_labels

    with StereoFile(args.data) as f:  # (a bad file is refused before Keras's import)
        labels = f.labels
        if f.image_shape[:2] != (args.image_size, args.image_size):
            parser.error(f"{args.data} has {f.image_shape[0]}px images, not {args.image_size}")

    from cpl_keras import build_model, compile_model
    from cpl_keras.models.batchnorm import batchnorm_layers, recompute_batchnorm_statistics
    from cpl_keras.training.sequence import StereoSequence

    targets = targets_from_labels(labels)
    split = make_split(labels, seed=0)
    train = StereoSequence(args.data, split["train"], targets=targets, batch_size=16,
                           shuffle=True, seed=0)
    val = StereoSequence(args.data, split["val"], targets=targets, batch_size=16)
    train_eval = [train[i] for i in range(min(8, len(train)))]
    val_eval = [val[i] for i in range(min(8, len(val)))]
    print(f"MTL-Baseline, {args.backbone} towers, {args.image_size}px, batch 16, "
          f"{args.steps} steps; load average {os.getloadavg()[0]:.2f}")
    print(f"{'momentum':>8} | {'mode':<38} | {'train batches':>13} | {'val batches':>11}")
    for momentum in args.momentum:
        model = compile_model(build_model("baseline", backbone=args.backbone,
                                          image_size=args.image_size, seed=0))
        for layer in batchnorm_layers(model):
            layer.momentum = momentum
        start = time.perf_counter()
        for step in range(args.steps):
            x, y = train[step % len(train)]
            model.train_on_batch(x, y)
        seconds = time.perf_counter() - start
        rows = [("training mode (batch statistics)", True),
                ("inference mode, moving averages", False)]
        for label, training in rows:
            print(f"{momentum:>8} | {label:<38} | {mean_loss(model, train_eval, training):>13.1f} | "
                  f"{mean_loss(model, val_eval, training):>11.1f}")
        recompute_batchnorm_statistics(model, (train[i] for i in range(min(16, len(train)))))
        print(f"{momentum:>8} | {'inference mode, recomputed (16 batches)':<38} | "
              f"{mean_loss(model, train_eval, False):>13.1f} | {mean_loss(model, val_eval, False):>11.1f}")
        print(f"{'':>8} | ({args.steps} steps in {seconds:.0f} s)")
    train.close()
    val.close()
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_batchnorm.py')
