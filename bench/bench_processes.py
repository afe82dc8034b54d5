"""The cost of training over two local processes: the same run on two
devices of one process and on two processes of one device each.

    python bench/bench_processes.py [--pairs 200] [--epochs 4] [--image-size 32]
        [--backbone small] [--batch-size 16]

Renders a cvgl dataset of ``--pairs`` pairs, then trains MTL-CPL-U with
``train.py --data-parallel`` twice: once in one process with two forced
host devices (``XLA_FLAGS=--xla_force_host_platform_device_count=2``), once
in two processes joined through Keras's ``KERAS_DISTRIBUTION_*`` variables.
Prints each one's wall time (start to exit), its training seconds per epoch
after the first (from log.csv's ``wall_time_s``) and whether their
validation losses agree. On one machine the two processes share its cores:
this measures the group's overhead (its connection, the collectives over
Gloo, the coordination), not a speed-up, which needs real hosts.
"""

from __future__ import annotations

import csv
import os
import socket
import subprocess
import sys
import tempfile
import time


from cpl_keras import cli  # noqa: E402

PROG = "bench/bench_processes.py"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def build_parser():
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=cli.positive_int, default=200)
    parser.add_argument("--epochs", type=cli.positive_int, default=4)
    parser.add_argument("--image-size", type=cli.positive_int, default=32)
    parser.add_argument("--backbone", default="small")
    parser.add_argument("--batch-size", type=cli.positive_int, default=16)
    parser.add_argument("--timeout", type=cli.positive_int, default=1800,
                        help="seconds each training may take")
    return parser


def _train(data, run_dir, args, env_list, timeout):
    argv = [sys.executable, os.path.join(ROOT, "train.py"), "--variant", "cpl-u", "--data",
            data, "--backbone", args.backbone, "--epochs", str(args.epochs), "--batch-size",
            str(args.batch_size), "--patience", str(args.epochs), "--data-parallel",
            "--run-dir", run_dir, "--quiet"]
    start = time.perf_counter()
    processes = [subprocess.Popen(argv, env=dict(os.environ, KERAS_BACKEND="jax", **env),
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                 for env in env_list]
    for process in processes:
        output, _ = process.communicate(timeout=timeout)
        if process.returncode != 0:
            raise cli.Error(f"training failed ({process.returncode}): "
                            f"{output.strip().splitlines()[-1] if output.strip() else ''}")
    with open(os.path.join(run_dir, "log.csv")) as f:
        rows = list(csv.DictReader(f))
    times = [float(row["wall_time_s"]) for row in rows]
    per_epoch = (times[-1] - times[0]) / max(len(times) - 1, 1)
    return time.perf_counter() - start, per_epoch, [float(r["val_loss"]) for r in rows]


def main(argv=None):
    args = build_parser().parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_processes_") as tmp:
        data = os.path.join(tmp, "cvgl.h5")
        subprocess.run([sys.executable, "-m", "cpl_keras.data.generate", "--protocol", "cvgl",
                        "--pairs", str(args.pairs), "--image-size", str(args.image_size),
                        "--out", data], check=True, capture_output=True, timeout=args.timeout)
        with socket.socket() as s:
            s.bind(("localhost", 0))
            port = s.getsockname()[1]
        group = [{"KERAS_DISTRIBUTION_JOB_ADDRESSES": f"localhost:{port}",
                  "KERAS_DISTRIBUTION_NUM_PROCESSES": "2",
                  "KERAS_DISTRIBUTION_PROCESS_ID": str(i)} for i in range(2)]
        settings = {
            "1 process x 2 devices": [{"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}],
            "2 processes x 1 device": group,
        }
        results = {}
        for name, env_list in settings.items():
            results[name] = _train(data, os.path.join(tmp, name.replace(" ", "_")), args,
                                   env_list, args.timeout)
    print(f"{args.pairs} cvgl pairs at {args.image_size} px, {args.backbone} backbone, batch "
          f"{args.batch_size}, {args.epochs} epochs, {os.cpu_count()} cores")
    for name, (wall, per_epoch, _) in results.items():
        print(f"{name:24s} wall {wall:7.1f} s   training {per_epoch:6.2f} s/epoch after the first")
    (wall_a, epoch_a, val_a), (wall_b, epoch_b, val_b) = results.values()
    agree = max(abs(a - b) / max(abs(a), 1e-9) for a, b in zip(val_a, val_b))
    print(f"two processes / one: {wall_b / wall_a:.2f}x wall, {epoch_b / epoch_a:.2f}x per epoch; "
          f"validation losses agree to {agree:.1e} (relative)")
    return 0


if __name__ == "__main__":
    cli.run(main, PROG)
