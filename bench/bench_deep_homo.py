"""Deep-Homo's training step with each convolution path of ``PatchConv2D``.

Deep-Homo dominates the ``cpu`` reproduction preset (its step costs 15-18
compact-tower steps). Its convolutions are
``cpl_keras.models.fast_layers.PatchConv2D`` layers; this measures what their
paths gain: the same network (same layers, names and weights) trained with
XLA's own convolutions ("plain"), with the paths ``PatchConv2D`` picks (the
default: a kernel gradient of matrix products, one per kernel row, on the
larger maps; "tap-gradient"), and with every such convolution computed as
one matrix product over image patches ("patches"). Rounds alternate the three models so that a machine's
load falls on all alike. It prints the best and median step time of each,
the step's arithmetic (multiply-adds of the convolutions and dense layers,
times 2 for FLOP, times 3 for forward plus both gradients) and the rate
that makes, beside a float32 matrix product's rate measured in the same
process.

    python bench/bench_deep_homo.py [--image-size 112] [--batch-size 16] [--rounds 4]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import time

os.environ.setdefault("KERAS_BACKEND", "jax")

import keras  # noqa: E402
import numpy as np  # noqa: E402

from cpl_keras import models  # noqa: E402
from cpl_keras.camera import TARGETS  # noqa: E402
from cpl_keras.models import fast_layers  # noqa: E402


def build(path, size, x, y):
    """Deep-Homo with its PatchConv2D layers on the path ``path`` ("plain":
    XLA's convolutions everywhere; "tap-gradient": the paths PatchConv2D
    picks, the default; "patches": one matrix product over image patches where
    it picks the tap gradient; same layers and weights either way), compiled
    and traced by one training step on ``x``, ``y``."""
    original_path = fast_layers.PatchConv2D.path

    def patches_everywhere(layer, shape):
        chosen = original_path(layer, shape)
        return "patches" if chosen == "tap-gradient" else chosen

    model = models.build_model("deep-homo", image_size=[size, size], seed=0)
    # (the paths are chosen when the step is traced)
    with contextlib.ExitStack() as paths_chosen:
        if path == "plain":
            paths_chosen.enter_context(fast_layers.xla_layers_only())
        elif path == "patches":
            fast_layers.PatchConv2D.path = patches_everywhere
            paths_chosen.callback(setattr, fast_layers.PatchConv2D, "path", original_path)
        paths = [(layer.name, layer.path(layer.input.shape)) for layer in model.layers
                 if isinstance(layer, (fast_layers.PatchConv2D, fast_layers.ViewMaxPooling2D))]
        models.compile_model(model)
        model.train_on_batch(x, y)
    return model, paths


def step_flop(model):
    """FLOP of one training step per sample: 2 x multiply-adds of every
    Conv2D and Dense layer, x 3 (forward, input and kernel gradients)."""
    macs = 0
    for layer in model.layers:
        if isinstance(layer, keras.layers.Conv2D):
            _, h, w, c_out = layer.output.shape
            kh, kw = layer.kernel_size
            macs += h * w * c_out * kh * kw * layer.input.shape[-1]
        elif isinstance(layer, keras.layers.Dense):
            macs += layer.input.shape[-1] * layer.units
    return 2 * 3 * macs


def matmul_rate(size=2048, repeats=5):
    """GFLOP/s of a float32 (size x size) matrix product (jitted, best of ``repeats``)."""
    import jax
    import jax.numpy as jnp

    a = jnp.asarray(np.random.default_rng(0).standard_normal((size, size)), jnp.float32)
    product = jax.jit(lambda x: x @ x)
    product(a).block_until_ready()
    best = min(_timed(lambda: product(a).block_until_ready()) for _ in range(repeats))
    return 2 * size ** 3 / best / 1e9


def _timed(call):
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--image-size", type=int, default=112)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=4, help="timed rounds per path")
    parser.add_argument("--steps", type=int, default=3, help="steps per round")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    shape = (args.batch_size, args.image_size, args.image_size, 3)
    x = {"left_image": rng.uniform(0, 255, shape).astype("float32"),
         "right_image": rng.uniform(0, 255, shape).astype("float32")}
    y = {name: rng.normal(size=(args.batch_size, 1)).astype("float32") for name in TARGETS}
    built = {}
    for path in ("plain", "tap-gradient", "patches"):
        model, paths = build(path, args.image_size, x, y)
        built[path] = model
        print(f"{path}: " + (", ".join(f"{n} {p}" for n, p in paths) or "XLA's Conv2D"),
              flush=True)
    times = {path: [] for path in built}
    for _ in range(args.rounds):
        for path, model in built.items():
            times[path].append(_timed(lambda model=model: [model.train_on_batch(x, y)
                                                           for _ in range(args.steps)])
                               / args.steps)
    flop = step_flop(built["plain"]) * args.batch_size
    rate = matmul_rate()
    print(f"step arithmetic: {flop / 1e9:.1f} GFLOP (batch {args.batch_size}, "
          f"{args.image_size}x{args.image_size}); float32 matmul here: {rate:.1f} GFLOP/s; "
          f"load average {os.getloadavg()[0]:.2f}")
    plain = min(times["plain"])
    for path, values in times.items():
        best = min(values)
        print(f"{path:13s} best {best:.3f} s/step, median {statistics.median(values):.3f}; "
              f"{flop / best / 1e9:.1f} GFLOP/s ({flop / best / 1e9 / rate:.2f} of matmul); "
              f"plain / this {plain / best:.2f}", flush=True)


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_deep_homo.py')
