"""CPU time of the test suite's typical work under different XLA_FLAGS.

    python bench/bench_suite_xla.py                          # XLA's defaults against level 0
    python bench/bench_suite_xla.py --work build train --rounds 2
    python bench/bench_suite_xla.py --pytest tests/test_backbones.py -k patch_conv2d

The suite builds many small models and trains them for a few steps, each in
a process that compiles its programs anew, so XLA's compile time is much of
its CPU time. This script measures a setting of XLA_FLAGS against XLA's
defaults (the suite keeps the defaults: paper_results/notes/
pipeline-and-suite.md): each piece of work runs in a fresh process per
setting (XLA reads its flags once, at start), and the CPU time of that
process (user + system, its children included) is printed, per round and
as the median, with the ratio to the first setting. CPU time rather than
wall time, so that a busy machine changes the figures little. The pieces:

* ``build``: the first MTL-Baseline of the compact towers at 32 px in a
  process (its random initialisers compile one program per kernel shape);
* ``train``: ``train()`` of MTL-CPL-A, small backbone, 2 epochs on 40
  rendered cvgl pairs of 32 px (what the suite's variant runs do);
* ``pytest``: the pytest selection given with ``--pytest`` (one process,
  ``-p no:cacheprovider``).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WORK = ("build", "train")
LEVEL_0 = "--xla_backend_optimization_level=0"


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flags", action="append", metavar="NAME=XLA_FLAGS",
                        help="a setting to measure (repeatable); default: "
                             f"'default=' and 'level-0={LEVEL_0}'")
    parser.add_argument("--work", nargs="+", choices=WORK, default=list(WORK),
                        help="the pieces of work to time (default: both)")
    parser.add_argument("--pytest", nargs=argparse.REMAINDER, default=None,
                        help="also time this pytest selection (the rest of the command line)")
    parser.add_argument("--rounds", type=int, default=1, help="rounds per piece and setting")
    parser.add_argument("--child", choices=WORK, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    specs = args.flags or ["default=", f"level-0={LEVEL_0}"]
    args.settings = []
    for spec in specs:
        name, sep, flags = spec.partition("=")
        if not sep or not name:
            parser.error(f"--flags takes NAME=XLA_FLAGS, got {spec!r}")
        args.settings.append((name, flags))
    if args.rounds < 1:
        parser.error(f"--rounds must be at least 1, got {args.rounds}")
    return args


def child(work):
    """One piece of work in this (fresh) process."""
    os.environ.setdefault("KERAS_BACKEND", "jax")
    if work == "build":
        from cpl_keras import build_model

        build_model("baseline", backbone="small_resnet", image_size=32, seed=0)
        return
    from cpl_keras.data.generate import generate_dataset
    from cpl_keras.training import train

    with tempfile.TemporaryDirectory() as root:
        data = generate_dataset(os.path.join(root, "cvgl.h5"), protocol="cvgl", pairs=40,
                                seed=0, image_size=32, workers=1, progress=False)
        train(data, variant="cpl-a", run_dir=os.path.join(root, "run"), backbone="small",
              epochs=2, batch_size=5, seed=1, verbose=0)


def cpu_seconds(argv, flags):
    """User + system CPU seconds of ``argv`` (children included) under XLA_FLAGS=flags."""
    env = dict(os.environ, KERAS_BACKEND="jax", XLA_FLAGS=flags)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # no persistent cache: every compile counts
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = subprocess.run(argv, env=env, cwd=REPO, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if result.returncode != 0:
        from cpl_keras.errors import Error

        last = (result.stderr.strip().splitlines() or [""])[-1]
        raise Error(f"{' '.join(argv[1:])} failed (exit {result.returncode}) with "
                    f"XLA_FLAGS={flags!r}: {last}")
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv=None):
    args = parse_args(argv)
    if args.child:
        child(args.child)
        return
    pieces = [(work, [sys.executable, os.path.abspath(__file__), "--child", work])
              for work in args.work]
    if args.pytest is not None:
        pieces.append(("pytest " + " ".join(args.pytest),
                       [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                        *args.pytest]))
    print(f"load average at start: {os.getloadavg()}", flush=True)
    start = time.perf_counter()
    rows = []
    for label, argv in pieces:
        medians = []
        for name, flags in args.settings:
            times = [cpu_seconds(argv, flags) for _ in range(args.rounds)]
            medians.append(statistics.median(times))
            print(f"{label} [{name}]: " + ", ".join(f"{t:.1f}" for t in times) + " s of CPU",
                  flush=True)
        rows.append((label, medians))
    names = [name for name, _ in args.settings]
    print()
    print("| work | " + " | ".join(f"{n} (CPU s)" for n in names) + " | "
          + " | ".join(f"{n} / {names[0]}" for n in names[1:]) + " |")
    print("|---" * (2 * len(names)) + "|")
    for label, medians in rows:
        ratios = [f"{m / medians[0]:.2f}" for m in medians[1:]]
        print(f"| {label} | " + " | ".join(f"{m:.1f}" for m in medians) + " | "
              + " | ".join(ratios) + " |")
    print(f"\nmedian of {args.rounds} round(s) each; {time.perf_counter() - start:.0f} s in all; "
          f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "bench/bench_suite_xla.py")
