"""Training throughput of one model under Keras's JAX, TensorFlow and PyTorch backends.

    python bench/bench_backends.py                                  # faithful model, all three
    python bench/bench_backends.py --python /path/to/venv/bin/python --rounds 3
    python bench/bench_backends.py --backbone small_resnet --steps 20
    python bench/bench_backends.py --backends jax --jax-flags onednn=--xla_cpu_use_onednn=true
    python bench/bench_backends.py --plain-conv-row --bf16 tensorflow --bf16 torch

Every measurement is one ``bench/bench_train.py`` process (same model, batch,
image size and random in-memory data), so the backends never share a
process. The rounds alternate: round r runs the backends in a rotated order,
so a load change on a shared machine hits every backend alike. The JAX run
counts the training step's FLOPs (XLA's cost analysis); the same model does
the same arithmetic under every backend, so the others' achieved GFLOP/s use
that count. Each process also measures a float32 matmul's GFLOP/s (through
its own backend) and ``model.predict``'s pairs/s.

The package itself imports neither TensorFlow nor PyTorch: install them in a
separate environment for this benchmark only, e.g.

    python -m venv bench-venv && bench-venv/bin/pip install -r requirements.txt tensorflow-cpu torch
    python bench/bench_backends.py --python bench-venv/bin/python

Printed: one Markdown table of medians over the rounds (first epoch with
compilation, training samples/s, achieved GFLOP/s, matmul GFLOP/s, fraction
of the matmul rate, predict pairs/s, ratio to TensorFlow), the load average
during the runs and the versions. ``--json`` writes every process's result
line as well.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
BENCH_TRAIN = os.path.join(HERE, "bench_train.py")

VERSIONS = {
    "jax": "import jax, keras; print(f'keras {keras.__version__}, jax {jax.__version__}')",
    "tensorflow": "import tensorflow as tf; print(f'tensorflow {tf.__version__}')",
    "torch": "import torch; print(f'torch {torch.__version__}, "
             "{torch.get_num_threads()} threads')",
}


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", default=sys.executable,
                        help="interpreter of an environment with the backends installed")
    parser.add_argument("--backends", nargs="+", default=["jax", "tensorflow", "torch"],
                        choices=("jax", "tensorflow", "torch"))
    parser.add_argument("--jax-flags", action="append", default=[], metavar="NAME=XLA_FLAGS",
                        help="also time JAX with these XLA_FLAGS, as a row named jax+NAME "
                             "(repeatable)")
    parser.add_argument("--bf16", action="append", default=[], metavar="BACKEND",
                        choices=("jax", "tensorflow", "torch"),
                        help="also time BACKEND under the mixed_bfloat16 dtype policy, as a row "
                             "named BACKEND+bf16 (repeatable)")
    parser.add_argument("--plain-conv-row", action="store_true",
                        help="also time JAX with plain Conv2D everywhere (no PatchConv2D), "
                             "as a row named jax+plain-conv")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--variant", default="baseline")
    parser.add_argument("--backbone", default="inception_v3")
    parser.add_argument("--image-size", type=int, default=112)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--steps", type=int, default=6, help="timed training steps per repeat")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--matmul-size", type=int, default=4096)
    parser.add_argument("--json", help="append every process's result line to this file")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.steps < 1 or args.repeats < 1:
        parser.error("--rounds, --steps and --repeats must be at least 1")
    for spec in args.jax_flags:
        if "=" not in spec:
            parser.error(f"--jax-flags takes NAME=XLA_FLAGS, got {spec!r}")
    return args


def configurations(args):
    """(row name, backend, extra environment, extra bench_train.py arguments)
    of every measured configuration."""
    rows = [(backend, backend, {}, []) for backend in args.backends]
    for spec in args.jax_flags:
        name, flags = spec.split("=", 1)
        rows.append((f"jax+{name}", "jax", {"XLA_FLAGS": flags}, []))
    if args.plain_conv_row:
        rows.append(("jax+plain-conv", "jax", {}, ["--plain-conv"]))
    for backend in args.bf16:
        rows.append((f"{backend}+bf16", backend, {}, ["--dtype-policy", "mixed_bfloat16"]))
    return rows


def measure(args, backend, extra_env, extra_args=(), flops=None):
    """One bench_train.py process; returns its result dict."""
    command = [args.python, BENCH_TRAIN, "--backend", backend, "--variant", args.variant,
               "--backbone", args.backbone, "--image-size", str(args.image_size),
               "--batch-size", str(args.batch_size), "--steps", str(args.steps),
               "--repeats", str(args.repeats), "--matmul-size", str(args.matmul_size)]
    command += list(extra_args)
    if flops:
        command += ["--flops-per-step", repr(flops)]
    env = dict(os.environ, KERAS_BACKEND=backend, TF_CPP_MIN_LOG_LEVEL="3", **extra_env)
    before = os.getloadavg()[0]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"bench_backends.py: error: {backend} run failed: {tail}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["load_before"] = round(before, 2)
    return result


def version(args, backend):
    done = subprocess.run([args.python, "-c", VERSIONS[backend]], capture_output=True, text=True,
                          env=dict(os.environ, TF_CPP_MIN_LOG_LEVEL="3"))
    return done.stdout.strip() or f"{backend}: not importable"


def table(results, names):
    """Markdown table of medians per configuration."""
    def med(name, key):
        values = [r[key] for r in results[name] if r.get(key) is not None]
        return statistics.median(values) if values else None

    reference = med("tensorflow", "samples_per_s") if "tensorflow" in results else None
    lines = ["| backend | first epoch, s | samples/s | achieved GFLOP/s | matmul GFLOP/s "
             "| fraction of matmul | predict pairs/s | vs TensorFlow |",
             "|---|---|---|---|---|---|---|---|"]
    for name in names:
        speed = med(name, "samples_per_s")
        achieved = med(name, "achieved_gflops")
        matmul = med(name, "matmul_gflops")
        fraction = statistics.median(r["achieved_gflops"] / r["matmul_gflops"]
                                     for r in results[name]) if achieved else None
        cells = [name, f"{med(name, 'first_epoch_s'):.1f}", f"{speed:.2f}",
                 f"{achieved:.1f}" if achieved else "n/a", f"{matmul:.1f}",
                 f"{fraction:.2f}" if fraction else "n/a",
                 f"{med(name, 'predict_pairs_per_s'):.2f}",
                 f"{speed / reference:.2f}x" if reference else "n/a"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None):
    args = parse_args(argv)
    rows = configurations(args)
    names = [name for name, *_ in rows]
    results = {name: [] for name in names}
    flops = None
    for round_index in range(args.rounds):
        shift = round_index % len(rows)
        order = rows[shift:] + rows[:shift]
        # the FLOP count comes from the default JAX run; measure it first in round 1
        if flops is None and "jax" in args.backends:
            order = sorted(order, key=lambda row: row[0] != "jax")
        for name, backend, extra_env, extra_args in order:
            result = measure(args, backend, extra_env, extra_args, flops)
            if name == "jax" and result.get("gflop_per_step"):
                flops = result["gflop_per_step"] * 1e9
            results[name].append(result)
            print(f"round {round_index + 1}, {name}: {result['samples_per_s']} samples/s "
                  f"(load {result['load_before']} -> {result['load_average'][0]})",
                  file=sys.stderr)
            if args.json:
                with open(args.json, "a") as f:
                    f.write(json.dumps(dict(result, row=name, round=round_index + 1)) + "\n")
    loads = [r["load_before"] for rs in results.values() for r in rs] + \
            [r["load_average"][0] for rs in results.values() for r in rs]
    first = next(iter(results.values()))[0]
    print(f"{args.variant}, {args.backbone} towers, {args.image_size}x{args.image_size}, "
          f"batch {args.batch_size}, {first['num_parameters']:,} parameters, "
          f"{flops / 1e9 if flops else float('nan'):.2f} GFLOP per training step; medians of "
          f"{args.rounds} rounds x {args.repeats} repeats of {args.steps} steps; "
          f"{os.cpu_count()} CPUs, 1-min load average {min(loads):.1f}-{max(loads):.1f}")
    print("; ".join(version(args, backend) for backend in args.backends))
    print(table(results, names))


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_backends.py')
