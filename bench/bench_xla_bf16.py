"""XLA:CPU's float32 and bfloat16 rates on this machine, through JAX.

A 2048 x 2048 matrix product and one 3x3 convolution (16 x 56 x 56 x 64 ->
64, "same"), each jitted, in float32 and in bfloat16, in alternating rounds
(so that a shared machine's load falls on both alike), best of all rounds:
whether JAX reaches the CPU's bfloat16 units (AMX, AVX-512 BF16) at all.
Prints the CPU's bfloat16 flags beside the rates.

    python bench/bench_xla_bf16.py [--rounds 4]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np


def _best(call, repeats=5):
    call()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - start)
    return best


def matmul_rate(dtype, size=2048):
    a = jnp.asarray(np.random.default_rng(0).standard_normal((size, size)), dtype)
    product = jax.jit(lambda x: x @ x)
    return 2 * size ** 3 / _best(lambda: product(a).block_until_ready()) / 1e9


def conv_rate(dtype, batch=16, side=56, channels=64):
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.standard_normal((batch, side, side, channels)), dtype)
    k = jnp.asarray(rng.standard_normal((3, 3, channels, channels)), dtype)
    conv = jax.jit(lambda x, k: jax.lax.conv_general_dilated(
        x, k, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")))
    flop = 2 * batch * side * side * channels * channels * 9
    return flop / _best(lambda: conv(x, k).block_until_ready()) / 1e9


def cpu_flags():
    try:
        with open("/proc/cpuinfo") as f:
            flags = next(line for line in f if line.startswith("flags")).split()
    except (OSError, StopIteration):
        return "unknown"
    return " ".join(sorted(f for f in flags if "bf16" in f or f.startswith("amx"))) or "none"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    args = parser.parse_args(argv)
    print(f"jax {jax.__version__}; CPU bfloat16 flags: {cpu_flags()}")
    dtypes = (("float32", jnp.float32), ("bfloat16", jnp.bfloat16))
    rates = {name: (0.0, 0.0) for name, _ in dtypes}
    for _ in range(args.rounds):
        for name, dtype in dtypes:
            matmul, conv = matmul_rate(dtype), conv_rate(dtype)
            rates[name] = (max(rates[name][0], matmul), max(rates[name][1], conv))
    for name, (matmul, conv) in rates.items():
        print(f"{name:9s} matmul {matmul:7.1f} GFLOP/s   3x3 conv {conv:7.1f} GFLOP/s")
    print(f"bfloat16 / float32: matmul {rates['bfloat16'][0] / rates['float32'][0]:.2f}, "
          f"conv {rates['bfloat16'][1] / rates['float32'][1]:.2f}")


if __name__ == "__main__":
    main()
