"""One convolution at a time: XLA's convolution against PatchConv2D's two paths.

    python bench/bench_conv_shapes.py            # InceptionV3's shapes at 112x112, batch 16
    python bench/bench_conv_shapes.py --batch-size 32 --repeats 10

For each shape (feature map, channels in and out, kernel, padding) the
script times a ``Conv2D`` and ``PatchConv2D`` with the same weights, forced
onto each of its paths where the path applies ("patches": one matmul over
image patches, "same" padding only; "tap-gradient": XLA's forward pass, the
kernel gradient one matmul per kernel tap): the forward pass alone and the
forward pass with the gradients of the input and the kernel, each compiled
with ``jax.jit``. One Markdown table: milliseconds and the path the model
takes for that shape (``PatchConv2D.path``). The shapes are those of the
towers at 112 x 112 where XLA:CPU's kernels differ most.
"""

from __future__ import annotations

import argparse
import os
import time


#: (feature map side, in channels, out channels, kernel (h, w), padding, where in InceptionV3 at 112)
SHAPES = (
    (2, 448, 384, (3, 3), "same", "mixed9/10, 3x3 on 2x2 maps"),
    (2, 384, 384, (1, 3), "same", "mixed9/10, 1x3 on 2x2 maps"),
    (5, 192, 192, (1, 7), "same", "mixed4-7, 1x7 on 5x5 maps"),
    (11, 64, 96, (3, 3), "same", "mixed0-2, 3x3 on 11x11 maps"),
    (55, 32, 32, (3, 3), "valid", "stem conv2d_1"),
    (53, 32, 64, (3, 3), "same", "stem conv2d_2"),
    (26, 80, 192, (3, 3), "valid", "stem conv2d_4"),
    (28, 16, 16, (3, 3), "same", "small_resnet stage1_b"),
)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=5, help="timed calls; the mean is kept")
    return parser.parse_args(argv)


def timed(function, *args, repeats):
    import jax

    jax.block_until_ready(function(*args))  # compiles
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(function(*args))
    return (time.perf_counter() - start) / repeats


def measure(layer, x, repeats):
    """(forward s, forward + input and kernel gradients s) of one built layer."""
    import jax
    from keras import ops

    kernel = layer.kernel.value

    def forward(kernel, x):
        return layer.convolution_op(x, kernel)

    def loss(kernel, x):
        return ops.sum(ops.square(forward(kernel, x)))

    return (timed(jax.jit(forward), kernel, x, repeats=repeats),
            timed(jax.jit(jax.grad(loss, argnums=(0, 1))), kernel, x, repeats=repeats))


def main(argv=None):
    args = parse_args(argv)
    os.environ.setdefault("KERAS_BACKEND", "jax")
    import keras
    import numpy as np

    from cpl_keras.models.fast_layers import PatchConv2D

    if keras.backend.backend() != "jax":
        raise SystemExit("bench_conv_shapes.py times the JAX backend only")
    rng = np.random.default_rng(0)
    lines = ["| shape (where) | model's path | XLA conv: forward, ms | forward + gradients, ms "
             "| patches: forward, ms | forward + gradients, ms "
             "| tap-gradient: forward + gradients, ms |",
             "|---|---|---|---|---|---|---|"]
    for side, cin, cout, kernel, padding, where in SHAPES:
        shape = (args.batch_size, side, side, cin)
        x = keras.ops.convert_to_tensor(rng.standard_normal(shape).astype("float32"))
        conv = keras.layers.Conv2D(cout, kernel, padding=padding, use_bias=False)
        conv.build(shape)
        patch = PatchConv2D.from_config(conv.get_config())
        patch.build(shape)
        patch.set_weights(conv.get_weights())
        model_path = patch.path(shape)
        xla = measure(conv, x, args.repeats)
        patches = tap = (None, None)
        if padding == "same":
            patch.path = lambda input_shape: "patches"  # forced, whatever the model takes
            patches = measure(patch, x, args.repeats)
        if padding == "valid" or (kernel[0] % 2 and kernel[1] % 2):
            patch.path = lambda input_shape: "tap-gradient"
            tap = measure(patch, x, args.repeats)

        def ms(seconds):
            return "n/a" if seconds is None else f"{seconds * 1e3:.2f}"

        lines.append(f"| {side}x{side}x{cin} -> {cout}, {kernel[0]}x{kernel[1]} {padding} ({where}) "
                     f"| {model_path} | {ms(xla[0])} | {ms(xla[1])} | {ms(patches[0])} "
                     f"| {ms(patches[1])} | {ms(tap[1])} |")
    print(f"batch {args.batch_size}, mean of {args.repeats} calls, load average "
          + ", ".join(f"{v:.2f}" for v in os.getloadavg()))
    print("\n".join(lines))


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_conv_shapes.py')
