"""The kernel gradient of one 3x3 "same" convolution, four ways, through JAX.

Deep-Homo's largest single op is the kernel gradient of conv1_2 (16 x 112 x
112 x 64 -> 64): XLA:CPU computes it as one convolution with a window the
size of the map. This times that against three formulations as matrix
products over shifted views of the padded input (one product per kernel tap;
one per kernel row, its three column shifts side by side; one over all nine
taps, im2col), beside the forward convolution and the input gradient of the
same layer (the same arithmetic), and checks each against XLA's result.

    python bench/bench_kernel_gradient.py [--side 112] [--channels 64] [--batch 16]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np


def _conv(x, k):
    return jax.lax.conv_general_dilated(x, k, (1, 1), "SAME",
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"))


def kernel_gradient_xla(x, g, k):
    return jax.vjp(lambda kernel: _conv(x, kernel), k)[1](g)[0]


def _shifted(x, side):
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    return [[padded[:, i:i + side, j:j + side, :] for j in range(3)] for i in range(3)]


def kernel_gradient_taps(x, g, k):
    views, flat = _shifted(x, x.shape[1]), g.reshape(-1, g.shape[-1])
    return jnp.stack([view.reshape(-1, x.shape[-1]).T @ flat
                      for row in views for view in row]).reshape(k.shape)


def kernel_gradient_rows(x, g, k):
    views, flat = _shifted(x, x.shape[1]), g.reshape(-1, g.shape[-1])
    return jnp.stack([
        (jnp.concatenate(row, -1).reshape(-1, 3 * x.shape[-1]).T @ flat).reshape(k.shape[1:])
        for row in views])


def kernel_gradient_shifted_gradient(x, g, k):
    """Per kernel row, with the output gradient shifted by each kernel column
    (made once) instead of the input (PatchConv2D's tap-gradient path)."""
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    side, c, f = x.shape[1], x.shape[-1], g.shape[-1]
    shifted = jnp.concatenate([jnp.pad(g, ((0, 0), (0, 0), (j, 2 - j), (0, 0)))
                               for j in range(3)], -1).reshape(-1, 3 * f)
    return jnp.stack([(padded[:, i:i + side].reshape(-1, c).T @ shifted)
                      .reshape(c, 3, f).transpose(1, 0, 2) for i in range(3)])


def kernel_gradient_rows_padded(x, g, k):
    """As ``kernel_gradient_shifted_gradient``, each kernel row's input rows
    made by padding the input (its rows i - 1 .. i + side - 2, zero outside)
    instead of slicing the padded input."""
    side, c, f = x.shape[1], x.shape[-1], g.shape[-1]
    shifted = jnp.concatenate([jnp.pad(g, ((0, 0), (0, 0), (j, 2 - j), (0, 0)))
                               for j in range(3)], -1).reshape(-1, 3 * f)
    rows = [jnp.pad(x[:, :side - 1], ((0, 0), (1, 0), (1, 1), (0, 0))),
            jnp.pad(x, ((0, 0), (0, 0), (1, 1), (0, 0))),
            jnp.pad(x[:, 1:], ((0, 0), (0, 1), (1, 1), (0, 0)))]
    return jnp.stack([(row.reshape(-1, c).T @ shifted).reshape(c, 3, f).transpose(1, 0, 2)
                      for row in rows])


def kernel_gradient_nine_shifts(x, g, k):
    """One product: the whole padded input, transposed, times the output
    gradient shifted by each of the nine taps (side by side)."""
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    c, f = x.shape[-1], g.shape[-1]
    shifted = jnp.concatenate([jnp.pad(g, ((0, 0), (i, 2 - i), (j, 2 - j), (0, 0)))
                               for i in range(3) for j in range(3)], -1)
    return (padded.reshape(-1, c).T @ shifted.reshape(-1, 9 * f)).reshape(c, 3, 3, f) \
        .transpose(1, 2, 0, 3)


def kernel_gradient_both_shifted(x, g, k):
    """Per kernel row, the whole padded input (no slice of it) times the
    output gradient shifted by that row and by each kernel column."""
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    c, f = x.shape[-1], g.shape[-1]
    flat = padded.reshape(-1, c)
    return jnp.stack([
        (flat.T @ jnp.concatenate([jnp.pad(g, ((0, 0), (i, 2 - i), (j, 2 - j), (0, 0)))
                                   for j in range(3)], -1).reshape(-1, 3 * f))
        .reshape(c, 3, f).transpose(1, 0, 2) for i in range(3)])


def kernel_gradient_tall(x, g, k):
    """Per kernel row, the batch stacked into one tall image: the padded
    input's rows i .. (a contiguous block of the stacked maps) times the
    output gradient with two zero rows below each map, shifted by each
    kernel column."""
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    n, side, c, f = x.shape[0], x.shape[1], x.shape[-1], g.shape[-1]
    rows = n * (side + 2) - 2
    tall = padded.reshape(n * (side + 2), side + 2, c)
    shifted = jnp.concatenate([jnp.pad(g, ((0, 0), (0, 2), (j, 2 - j), (0, 0)))
                               for j in range(3)], -1)
    shifted = shifted.reshape(n * (side + 2), side + 2, 3 * f)[:rows].reshape(-1, 3 * f)
    return jnp.stack([(tall[i:i + rows].reshape(-1, c).T @ shifted)
                      .reshape(c, 3, f).transpose(1, 0, 2) for i in range(3)])


def kernel_gradient_im2col(x, g, k):
    views = _shifted(x, x.shape[1])
    patches = jnp.concatenate([view for row in views for view in row], -1)
    return (patches.reshape(-1, 9 * x.shape[-1]).T @ g.reshape(-1, g.shape[-1])).reshape(k.shape)


def forward(x, g, k):
    return _conv(x, k)


def input_gradient(x, g, k):
    return jax.vjp(lambda inputs: _conv(inputs, k), x)[1](g)[0]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--side", type=int, default=112)
    parser.add_argument("--channels", type=int, default=64)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=4)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    n, side, c = args.batch, args.side, args.channels
    x = jnp.asarray(rng.standard_normal((n, side, side, c)), jnp.float32)
    g = jnp.asarray(rng.standard_normal((n, side, side, c)), jnp.float32)
    k = jnp.asarray(rng.standard_normal((3, 3, c, c)), jnp.float32)
    flop = 2 * n * side * side * c * c * 9
    reference = jax.jit(kernel_gradient_xla)(x, g, k)
    print(f"{n} x {side} x {side} x {c} -> {c}, 3x3 same: {flop / 1e9:.1f} GFLOP per op")
    for name, function in (("kernel gradient, XLA", kernel_gradient_xla),
                           ("kernel gradient, per tap", kernel_gradient_taps),
                           ("kernel gradient, per kernel row", kernel_gradient_rows),
                           ("kernel gradient, per row, gradient shifted",
                            kernel_gradient_shifted_gradient),
                           ("kernel gradient, per row, input rows padded", kernel_gradient_rows_padded),
                           ("kernel gradient, nine gradient shifts", kernel_gradient_nine_shifts),
                           ("kernel gradient, per row, batch stacked", kernel_gradient_tall),
                           ("kernel gradient, per row, gradient shifted both ways",
                            kernel_gradient_both_shifted),
                           ("kernel gradient, im2col", kernel_gradient_im2col),
                           ("forward", forward), ("input gradient, XLA", input_gradient)):
        compiled = jax.jit(function)
        result = compiled(x, g, k).block_until_ready()
        best = float("inf")
        for _ in range(args.repeats):
            start = time.perf_counter()
            compiled(x, g, k).block_until_ready()
            best = min(best, time.perf_counter() - start)
        check = ""
        if result.shape == reference.shape:
            error = float(jnp.max(jnp.abs(result - reference)) / jnp.max(jnp.abs(reference)))
            check = f"; max error {error:.1e} of XLA's largest value"
        print(f"{name:42s} {best * 1e3:7.1f} ms  {flop / best / 1e9:6.1f} GFLOP/s{check}",
              flush=True)


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_kernel_gradient.py')
