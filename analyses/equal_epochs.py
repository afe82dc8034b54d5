"""Two runs of the same split compared epoch by epoch on validation: is one
behind at every epoch, or only where early stopping ended it? For each
epoch given (default: both runs' kept epochs and their last common epoch),
each run's ``val_nmae`` (the monitor: the sum of the ten validation NMAEs)
and its per-parameter validation NMAEs, and how many columns each run is
lower on. Then, over every epoch both ran, how often A's monitor is lower.

    python analyses/equal_epochs.py \\
        paper_results/inception-2000-ema/runs/cvgl_cpl-a-s0_log.csv \\
        paper_results/inception-2000-ema/runs/cvgl_baseline-s0_log.csv

The two runs must share a split (the same ``--seed`` and ``--split``) for
their validation NMAEs to be comparable. Committed output: quoted in
paper_results/inception-2000-ema/README.md.
"""

from __future__ import annotations

import argparse
import os

from cpl_keras.camera import PARAMETERS
from cpl_keras.runs import read_log


def _error(message):
    from cpl_keras.evaluation import EvaluationError

    return EvaluationError(message)


def validation(path):
    """``{epoch: {"val_nmae": ..., parameter: NMAE}}`` of a log.csv
    (EvaluationError, one line, when it lacks the nmae monitor's
    per-parameter columns)."""
    rows = read_log(path)
    needed = ["val_nmae"] + [f"val_nmae_{p}" for p in PARAMETERS]
    if not rows or any(key not in rows[0] for key in needed):
        raise _error(f"{path}: no per-parameter val_nmae columns (a log.csv of "
                       f"train.py's nmae monitor)")
    return {int(row["epoch"]): {"val_nmae": row["val_nmae"],
                                **{p: row[f"val_nmae_{p}"] for p in PARAMETERS}}
            for row in rows}


def kept_epoch(epochs):
    """The epoch of the lowest monitor (the one early stopping keeps)."""
    return min(epochs, key=lambda e: epochs[e]["val_nmae"])


def comparison(a, b, epochs):
    """Markdown rows: at each epoch both ran, each run's monitor and
    parameters, and the columns each is lower on."""
    lines = ["| epoch | run | val_nmae | " + " | ".join(PARAMETERS) + " | lower on |",
             "|---|---|---|" + "---|" * len(PARAMETERS) + "---|"]
    for epoch in epochs:
        if epoch not in a or epoch not in b:
            continue
        for name, run, other in (("A", a, b), ("B", b, a)):
            cells = [f"{run[epoch][p]:.3f}" for p in PARAMETERS]
            lower = [p for p in PARAMETERS if run[epoch][p] < other[epoch][p]]
            lines.append(f"| {epoch} | {name} | {run[epoch]['val_nmae']:.3f} | "
                         + " | ".join(cells) + f" | {len(lower)} ({', '.join(lower)}) |")
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("a", help="run A's log.csv (or its run directory)")
    parser.add_argument("b", help="run B's log.csv (or its run directory)")
    parser.add_argument("--epochs", type=int, nargs="+",
                        help="the epochs to compare (default: both kept epochs and the last "
                             "common one)")
    args = parser.parse_args(argv)
    if args.epochs and min(args.epochs) < 1:
        parser.error("--epochs must be 1 or more")
    a, b = validation(args.a), validation(args.b)
    common = sorted(set(a) & set(b))
    if not common:
        raise _error(f"{args.a} and {args.b} share no epoch")
    epochs = sorted(set(args.epochs or [kept_epoch(a), kept_epoch(b), common[-1]]))
    for name, path, run in (("A", args.a, a), ("B", args.b, b)):
        kept = kept_epoch(run)
        print(f"{name}: {os.path.relpath(path)}: {len(run)} epochs, kept {kept} "
              f"(val_nmae {run[kept]['val_nmae']:.3f})")
    print()
    print("\n".join(comparison(a, b, epochs)))
    ahead = [e for e in common if a[e]["val_nmae"] < b[e]["val_nmae"]]
    print(f"\nOver the {len(common)} epochs both ran (1-{common[-1]}), A's val_nmae is lower "
          f"at {len(ahead)}" + (f" ({', '.join(map(str, ahead))})." if ahead else "."))
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/equal_epochs.py")
