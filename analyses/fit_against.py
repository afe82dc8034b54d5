"""How a run's training fit follows a reference run's, epoch by epoch: the
training MAE of each target and Eq. 9's weights, side by side.

    python analyses/fit_against.py \\
        --pair "compact=runs/cpl-a-s0,runs/baseline-s0" --out fit.md

Each ``--pair NAME=RUN,REFERENCE`` reads the two runs' log.csv (``RUN/log.csv``
or ``RUN_log.csv`` beside a published run's folder). A target's training MAE
is the log's ``<target>_mae`` (a metric of the camera-projection variants) or,
where there is none, ``<target>_loss`` (MTL-Baseline's loss of that output: its
MAE): the running mean over the epoch's training batches, as Keras logs it.
Per pair and target the page gives the run's MAE over the reference's at the
chosen epochs and at the run's last epoch, the first epoch at which the run's
MAE is below the reference's, and in how many of the run's epochs it is; and
the run's ``alpha_<target>`` (Eq. 9's weights) at the same epochs, where it
has them. The same figures go to a JSON file beside the page;
``regenerate`` rebuilds a committed page from it and the command on the
page's first line.
"""

from __future__ import annotations

import argparse
import csv
import os
import shlex
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TARGETS = ("baseline", "tx", "tz", "fx", "disparity", "pitch")
EPOCHS = (5, 10, 20)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pair", action="append", required=True, metavar="NAME=RUN,REFERENCE",
                        type=_pair, help="a run, its reference and their name (repeatable)")
    parser.add_argument("--targets", nargs="+", default=list(TARGETS), metavar="TARGET")
    parser.add_argument("--epochs", nargs="+", type=int, default=list(EPOCHS), metavar="N")
    parser.add_argument("--out", required=True, help="the Markdown page to write (.md)")
    args = parser.parse_args(argv)
    if not args.out.endswith(".md"):
        parser.error(f"--out must end in .md, got {args.out}")
    return args


def _pair(text):
    name, _, paths = text.partition("=")
    run, _, reference = paths.partition(",")
    if not (name and run and reference):
        raise argparse.ArgumentTypeError(f"expected NAME=RUN,REFERENCE, got {text!r}")
    return name, run, reference


def read_log(run):
    """``{epoch: row}`` of a run's log.csv (``RUN/log.csv`` or ``RUN_log.csv``)."""
    for path in (os.path.join(run, "log.csv"), run.rstrip("/") + "_log.csv"):
        if os.path.isfile(path):
            with open(path, newline="") as f:
                return {int(row["epoch"]): row for row in csv.DictReader(f)}
    raise ValueError(f"no log.csv for {run} (looked for RUN/log.csv and RUN_log.csv)")


def training_mae(log, target):
    """``{epoch: MAE}``: ``<target>_mae`` where logged, else ``<target>_loss``."""
    for column in (f"{target}_mae", f"{target}_loss"):
        values = {e: float(r[column]) for e, r in log.items() if r.get(column) not in (None, "")}
        if values:
            return values
    raise ValueError(f"the log has neither {target}_mae nor {target}_loss")


def compare(run_log, reference_log, target, epochs):
    """One target's figures (see the module's docstring)."""
    mine, theirs = training_mae(run_log, target), training_mae(reference_log, target)
    shared = [e for e in sorted(mine) if e in theirs]
    last = max(mine)
    below = [e for e in shared if mine[e] < theirs[e]]
    alphas = {e: float(run_log[e][f"alpha_{target}"]) for e in list(epochs) + [last]
              if e in run_log and run_log[e].get(f"alpha_{target}") not in (None, "")}
    return {"ratio": {e: mine[e] / theirs[e] for e in epochs if e in shared},
            "last_epoch": last,
            "ratio_last": mine[last] / theirs[last] if last in theirs else None,
            "first_below": below[0] if below else None,
            "epochs_below": len(below), "epochs_compared": len(shared),
            "alpha": alphas}


def _f(value, digits=2):
    return "" if value is None else f"{value:.{digits}f}"


def page(results, epochs, command):
    """The page of ``results`` (per pair and target, ``compare``'s) at
    ``epochs``, written by ``command``."""
    from cpl_keras import files

    at = ", ".join(str(e) for e in epochs)
    lines = [files.generated_line(command), "",
             "# Training fit against a reference run", "", "Command:", "", "```", command, "```",
             "", "The run's training MAE over the reference's (below 1: the run fits the "
             f"training pairs better) at epochs {at} and at the run's last epoch; the first "
             "epoch at which the run is below the reference, and in how many of the epochs "
             "both logged; and the run's Eq. 9 weight alpha at the same epochs. Training MAE: "
             "the log's `<target>_mae`, else `<target>_loss` (the running mean over an "
             "epoch's training batches).", ""]
    for name, targets in results.items():
        lines += [f"## {name}", "",
                  "| target | " + " | ".join(f"ratio @{e}" for e in epochs)
                  + " | last epoch | ratio @last | first below | below in | "
                  + " | ".join(f"alpha @{e}" for e in epochs) + " | alpha @last |",
                  "|---" * (2 * len(epochs) + 6) + "|"]
        for target, r in targets.items():
            alpha = [r["alpha"].get(e) for e in epochs] + [r["alpha"].get(r["last_epoch"])]
            lines.append(
                f"| {target} | " + " | ".join(_f(r["ratio"].get(e)) for e in epochs)
                + f" | {r['last_epoch']} | {_f(r['ratio_last'])} | "
                + f"{r['first_below'] or 'never'} | {r['epochs_below']} of {r['epochs_compared']} | "
                + " | ".join(_f(a, 3) for a in alpha) + " |")
        lines.append("")
    return "\n".join(lines)


def from_json(results):
    """``results`` as read back from the JSON (its epochs, keys there, are
    strings): the epochs numbers again, as ``page`` takes them."""
    return {name: {target: {**r, "ratio": {int(e): v for e, v in r["ratio"].items()},
                            "alpha": {int(e): v for e, v in r["alpha"].items()}}
                   for target, r in targets.items()}
            for name, targets in results.items()}


def regenerate(page_path):
    """The committed page ``page_path`` as this script writes it, from its
    JSON beside it and the command on its first line (its ``--epochs``)."""
    from cpl_keras import files

    command, payload = files.page_source(page_path)
    args = parse_args(shlex.split(command)[2:])
    results = from_json(payload)
    return page(results, args.epochs, command)


def command_line(args):
    """The command that writes ``args.out`` again (at the top of the page)."""
    words = ["python analyses/fit_against.py"]
    words += [f'--pair "{name}={os.path.relpath(run, REPO)},{os.path.relpath(reference, REPO)}"'
              for name, run, reference in args.pair]
    if list(args.targets) != list(TARGETS):
        words.append("--targets " + " ".join(args.targets))
    if list(args.epochs) != list(EPOCHS):
        words.append("--epochs " + " ".join(map(str, args.epochs)))
    return " ".join(words + [f"--out {os.path.relpath(args.out, REPO)}"])


def main(argv=None):
    args = parse_args(argv)
    try:
        results = {}
        for name, run, reference in args.pair:
            run_log, reference_log = read_log(run), read_log(reference)
            results[name] = {t: compare(run_log, reference_log, t, args.epochs)
                             for t in args.targets}
    except (OSError, ValueError) as error:
        print(f"analyses/fit_against.py: error: {error}", file=sys.stderr)
        return 2
    from cpl_keras import files

    text = page(results, args.epochs, command_line(args))
    print(f"wrote {args.out} and {files.write_page(args.out, text, results)}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    from cpl_keras import cli

    cli.run(main, "analyses/fit_against.py")
