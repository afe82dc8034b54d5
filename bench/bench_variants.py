"""Training time of the paper's variants relative to MTL-Baseline, in one process.

    python bench/bench_variants.py                      # small_resnet towers, 112x112, batch 16
    python bench/bench_variants.py --variants deep-homo baseline --rounds 6

Every variant is built with ``cpl_keras.build_model`` and compiled with
``compile_model`` (as ``train.py`` does), fitted once on random images (XLA
compilation), then timed in alternating rounds: round r fits ``--steps``
training steps of every variant in turn, so a load change on a shared machine
hits all of them alike and the ratio to MTL-Baseline is the stable figure.
Reported per variant: the first fit (compilation included), the median
round, samples/s and the ratio to the ``baseline`` variant's median. This is
what the ``cpu`` preset's budget in paper_results/cpu/README.md takes Deep-Homo's
epoch from (Deep-Homo has its own 8-convolution network at full resolution,
whatever ``--backbone`` says).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("KERAS_BACKEND", "jax")


def parse_args(argv=None):
    from cpl_keras.models.variants import TABLE_ORDER

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=list(TABLE_ORDER))
    parser.add_argument("--backbone", default="small_resnet")
    parser.add_argument("--image-size", type=int, default=112)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--steps", type=int, default=4, help="training steps per round")
    parser.add_argument("--rounds", type=int, default=4)
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    import numpy as np

    from cpl_keras import build_model, compile_model
    from cpl_keras.camera import TARGETS

    variants = list(dict.fromkeys(["baseline"] + args.variants))
    rng = np.random.default_rng(0)
    n, size = args.batch_size * args.steps, args.image_size
    x = {k: rng.uniform(0, 255, (n, size, size, 3)).astype(np.float32)
         for k in ("left_image", "right_image")}
    y = {k: rng.standard_normal((n, 1)).astype(np.float32) for k in TARGETS}

    def fit(model):
        start = time.perf_counter()
        model.fit(x, y, batch_size=args.batch_size, epochs=1, verbose=0, shuffle=False)
        return time.perf_counter() - start

    print(f"load average at start: {os.getloadavg()}", flush=True)
    models, first = {}, {}
    for variant in variants:
        models[variant] = build_model(variant, backbone=args.backbone, image_size=size, seed=0)
        compile_model(models[variant], jit_compile="auto")
        first[variant] = fit(models[variant])
    times = {v: [] for v in variants}
    for _ in range(args.rounds):
        for variant, model in models.items():
            times[variant].append(fit(model))
    print(f"load average at end: {os.getloadavg()}")
    median = {v: statistics.median(t) for v, t in times.items()}
    print(f"{args.backbone} towers (MTL variants), {size}x{size}, batch {args.batch_size}, "
          f"{args.rounds} rounds of {args.steps} steps")
    print("| variant | first fit s | median round s | train samples/s | x MTL-Baseline's time |")
    print("|---|---|---|---|---|")
    for variant in variants:
        print(f"| {variant} | {first[variant]:.1f} | {median[variant]:.3f} | "
              f"{n / median[variant]:.1f} | {median[variant] / median['baseline']:.2f} |")


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_variants.py')
