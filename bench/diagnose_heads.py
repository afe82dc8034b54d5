"""Why does a parameter head not learn? Its outputs and the two parts of its
gradient, traced through training.

For a CPL variant, the disentangled term of parameter p (Eq. 7) is::

    L_p = 1/13 * (|p' - p| + |X(p') - X| + |Y(p') - Y| + |Z(p') - Z|)

Its gradient with respect to the head's output p' has a direct part (the
first absolute error: +-1/13 per pair) and a projection part (the other
three). This script trains a model on a dataset for a few steps and, every
``--every`` steps, prints for each parameter in ``--params`` the head's
outputs on one fixed training batch (mean, how many are negative), its MAE
there, and the batch mean of both gradient parts (a positive value pushes
p' down). A head whose projection part outweighs its direct part while the
output sits on the wrong side of a pole is trapped there.

    python bench/diagnose_heads.py --data data/cvgl.h5 --backbone inception_v3 \
        --variant cpl-a --steps 120 --every 20 --params fx fy disparity
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("KERAS_BACKEND", "jax")


def gradient_parts(model, batch_targets, outputs, name):
    """(direct, projection) batch-mean gradients of L_name w.r.t. the head's output."""
    import jax
    import jax.numpy as jnp

    from cpl_keras import camera
    from cpl_keras.models import losses

    index = camera.TARGETS.index(name)
    y_true = {k: jnp.asarray(v, "float32").reshape(-1, 1) for k, v in batch_targets.items()}
    y_pred = {k: jnp.asarray(v, "float32").reshape(-1, 1) for k, v in outputs.items()}

    def term(p):
        return losses.projection_terms(y_true, dict(y_pred, **{name: p}), model.floors)[index]

    total = jax.grad(term)(y_pred[name])
    batch = y_pred[name].shape[0]
    direct = jnp.sign(y_pred[name] - y_true[name]) / (len(camera.TARGETS) * batch)
    # per-pair sums, as a batch mean gradient times the batch size
    return float(jnp.sum(direct)), float(jnp.sum(total - direct))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="an HDF5 dataset (cpl_keras.data.generate)")
    parser.add_argument("--variant", default="cpl-a", help="a CPL variant (default cpl-a)")
    parser.add_argument("--backbone", default="inception_v3", help="default inception_v3")
    parser.add_argument("--steps", type=int, default=120, help="training steps (default 120)")
    parser.add_argument("--every", type=int, default=20, help="print every N steps (default 20)")
    parser.add_argument("--batch-size", type=int, default=16, help="default 16")
    parser.add_argument("--seed", type=int, default=0, help="model and split seed (default 0)")
    parser.add_argument("--params", nargs="+", default=["fx", "fy", "disparity"],
                        help="parameters to trace (default fx fy disparity)")
    parser.add_argument("--linear-focal-head", action="store_true",
                        help="the release's linear fy head (the model before the fix)")
    args = parser.parse_args(argv)

    import numpy as np

    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import make_split, targets_from_labels

    with StereoFile(args.data) as f:  # (a bad file is refused before Keras's import)
        labels = f.labels
        size = f.image_shape[0]

    from cpl_keras.models import build_model, compile_model
    from cpl_keras.training.sequence import StereoSequence

    targets = targets_from_labels(labels)
    split = make_split(labels, kind="paper", seed=args.seed)
    build = {}
    if args.linear_focal_head:
        build["positive_focal_head"] = False
    model = build_model(args.variant, backbone=args.backbone, image_size=size, seed=args.seed,
                        **build)
    compile_model(model)
    sequence = StereoSequence(args.data, split["train"], targets=targets,
                              batch_size=args.batch_size, shuffle=True, seed=args.seed)
    probe_x, probe_y = sequence[0]
    model.initialise_adaptive_weights(probe_y)
    print(f"{args.variant}, {args.backbone}, {args.data}: {len(split['train'])} training "
          f"pairs; probe batch of {len(probe_y['fy'])}; fy labels "
          f"{np.min(probe_y['fy']):.1f}..{np.max(probe_y['fy']):.1f} px")
    print("step  param  mean(pred)  negative  MAE  direct-grad  projection-grad  alpha")
    step = 0
    epoch = 0
    while step <= args.steps:
        if step % args.every == 0:
            outputs = dict(zip(model.output_names, model(probe_x, training=True)))
            outputs = {k: np.asarray(v) for k, v in outputs.items()}
            alphas = model.adaptive_weights() or {}
            for name in args.params:
                pred = outputs[name].reshape(-1)
                truth = np.asarray(probe_y[name]).reshape(-1)
                direct, projection = gradient_parts(model, probe_y, outputs, name)
                print(f"{step:4d}  {name:9s} {pred.mean():10.2f}  {np.sum(pred < 0):3d}/"
                      f"{len(pred)}  {np.mean(np.abs(pred - truth)):8.2f}  {direct:+10.4f}  "
                      f"{projection:+12.4f}  {alphas.get(name, float('nan')):.3f}", flush=True)
        if step == args.steps:
            break
        index = step % len(sequence)
        if index == 0 and step:
            epoch += 1
            sequence.set_epoch(epoch)
        x, y = sequence[index]
        model.train_on_batch(x, y)
        step += 1
    sequence.close()


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/diagnose_heads.py')
