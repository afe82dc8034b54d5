"""XLA:CPU's float32 and bfloat16 rates on this machine, through JAX.

A 2048 x 2048 matrix product and one 3x3 convolution (16 x 56 x 56 x 64 ->
64, "same"), each jitted, in float32 and in bfloat16, in alternating rounds
(so that a shared machine's load falls on both alike), best of all rounds:
whether JAX reaches the CPU's bfloat16 units (AMX, AVX-512 BF16) at all.
Prints the CPU's bfloat16 flags beside the rates.

``--xla-flags NAME=FLAGS`` (repeatable) measures the same in a fresh process
per setting with ``XLA_FLAGS=FLAGS`` (XLA reads its flags once, at start),
beside a process with none: whether one of XLA:CPU's library paths (oneDNN,
YNNPACK, XNNPACK) reaches the bfloat16 units where the default does not.

    python bench/bench_xla_bf16.py [--rounds 4]
    python bench/bench_xla_bf16.py --rounds 2 \
        --xla-flags "onednn=--xla_cpu_use_onednn=true" \
        --xla-flags "no-ynn=--xla_cpu_experimental_ynn_fusion_type="
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
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
    parser.add_argument("--xla-flags", action="append", default=[], metavar="NAME=FLAGS",
                        help="also measure with XLA_FLAGS=FLAGS, in a process of its own")
    args = parser.parse_args(argv)
    if args.xla_flags:
        return compare_flags(args.rounds, args.xla_flags)
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


def compare_flags(rounds, settings):
    """Each setting's rates in a process of its own (XLA_FLAGS is read at
    start), the default first; a table of the four rates and the ratios."""
    rows = [("default", "")]
    for setting in settings:
        name, sep, flags = setting.partition("=")
        if not sep or not name:
            raise SystemExit(f"--xla-flags takes NAME=FLAGS, got {setting!r}")
        rows.append((name, flags))
    print(f"jax {jax.__version__}; CPU bfloat16 flags: {cpu_flags()}; rounds {rounds}")
    print("| XLA_FLAGS | f32 matmul | bf16 matmul | f32 conv | bf16 conv | bf16/f32 matmul "
          "| bf16/f32 conv |")
    print("|---|---|---|---|---|---|---|")
    for name, flags in rows:
        env = dict(os.environ, XLA_FLAGS=flags)
        done = subprocess.run([sys.executable, os.path.abspath(__file__), "--rounds",
                               str(rounds)], env=env, capture_output=True, text=True,
                              timeout=1800)
        rates = {}
        for line in done.stdout.splitlines():
            parts = line.split()
            if len(parts) > 6 and parts[0] in ("float32", "bfloat16") and parts[1] == "matmul":
                rates[parts[0]] = (float(parts[2]), float(parts[6]))
        if done.returncode or len(rates) != 2:
            print(f"| {name} (`{flags}`) | failed: {done.stderr.strip().splitlines()[-1:]} "
                  "| | | | | |")
            continue
        (fm, fc), (bm, bc) = rates["float32"], rates["bfloat16"]
        print(f"| {name} (`{flags or 'none'}`) | {fm:.1f} | {bm:.1f} | {fc:.1f} | {bc:.1f} "
              f"| {bm / fm:.2f} | {bc / fc:.2f} |", flush=True)


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_xla_bf16.py')
