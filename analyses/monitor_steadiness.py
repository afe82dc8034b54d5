"""How steady is a run's early-stopping monitor? For each log.csv given: its
epochs, the kept epoch and its ``val_nmae``, the median and largest
epoch-to-epoch relative change of ``val_nmae`` from ``--from-epoch`` on, and
how many of those steps went up. With two or more logs, whether they trained
the same weights: the epochs over which their training losses are equal
(``--weight-ema`` changes only what is validated, so a run with it and one
without follow the same training trajectory).

    python analyses/monitor_steadiness.py --from-epoch 10 \\
        paper_results/compact-2000/runs/cvgl_cpl-a-s0/log.csv \\
        paper_results/weight-ema/runs/compact-cpl-a-s0-ema99/log.csv

Committed output: quoted in paper_results/weight-ema/README.md.
"""

from __future__ import annotations

import argparse
import csv
import os

import numpy as np


def read(path):
    """``(epochs, val_nmae, loss)`` of a log.csv (OSError or EvaluationError,
    one line, for a missing or malformed file)."""
    with open(path) as f:
        rows = list(csv.DictReader(f))
    if not rows or "val_nmae" not in rows[0]:
        from cpl_keras.evaluation import EvaluationError

        raise EvaluationError(f"{path}: no val_nmae column (a log.csv of train.py's nmae "
                              f"monitor)")
    return (np.array([int(r["epoch"]) for r in rows]),
            np.array([float(r["val_nmae"]) for r in rows]),
            np.array([float(r["loss"]) for r in rows]))


def steadiness(val_nmae, from_epoch):
    """Median and largest |relative change| between consecutive epochs from
    epoch ``from_epoch`` (1-based) on, and the number of rises."""
    tail = val_nmae[from_epoch - 1:]
    if len(tail) < 2:
        return float("nan"), float("nan"), 0
    change = np.diff(tail) / tail[:-1]
    return float(np.median(np.abs(change))), float(np.max(np.abs(change))), int(np.sum(change > 0))


def same_training(losses):
    """The number of leading epochs over which every log's training loss is equal."""
    common = min(len(loss) for loss in losses)
    equal = np.all([loss[:common] == losses[0][:common] for loss in losses], axis=0)
    return int(common if equal.all() else np.argmin(equal))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", help="log.csv files of train.py runs")
    parser.add_argument("--from-epoch", type=int, default=10,
                        help="the first epoch of the changes measured (default 10)")
    args = parser.parse_args(argv)
    if args.from_epoch < 1:
        parser.error("--from-epoch must be 1 or more")
    logs = [read(path) for path in args.logs]
    print(f"| log | epochs | kept (val_nmae) | median change | largest change | rises "
          f"(from epoch {args.from_epoch}) |")
    print("|---|---|---|---|---|---|")
    for path, (epochs, val, _) in zip(args.logs, logs):
        median, largest, rises = steadiness(val, args.from_epoch)
        kept = int(np.argmin(val))
        print(f"| {os.path.relpath(path)} | {len(epochs)} | {epochs[kept]} ({val[kept]:.3f}) | "
              f"{median:.1%} | {largest:.1%} | {rises} of {max(len(val) - args.from_epoch, 0)} |")
    if len(logs) > 1:
        print(f"\nTraining losses equal over the first {same_training([log[2] for log in logs])} "
              f"epochs of every log.")
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/monitor_steadiness.py")
