"""Which loss terms drive the towers: the gradient logs of several runs side
by side.

    python analyses/term_gradients.py \\
        --run "MTL-CPL-A, rate 1=paper_results/inception-2000-ablations/runs/cvgl_cpl-a-rate1-s0" \\
        --run "MTL-CPL-U=paper_results/inception-2000-ablations/runs/cvgl_cpl-u-s0" \\
        --out paper_results/inception-2000-ablations/term-gradients.md

Reads each run's log.csv (``RUN_log.csv`` beside a published run's folder,
or ``RUN/log.csv``): the ``grad_<target>`` columns that ``train.py
--term-gradients`` writes, the norm of the gradient that each weighted loss
term sends into the towers' shared features on the run's first 64 training
pairs, once an epoch (``cpl_keras.training.gradients``). Writes a Markdown
page (and the same as JSON beside it) with, per run and term: the median
norm over the logged epochs, its median share of the sum over the terms,
and in how many epochs the term sent the largest and the smallest gradient;
and, where the log has them, the median of Eq. 9's weights ``alpha_<target>``.
``regenerate`` rebuilds a committed page from its JSON and the command on
its first line.
"""

from __future__ import annotations

import argparse
import csv
import os
import shlex
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TARGETS = ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty", "tz", "pitch",
           "X", "Y", "Z")


def parse_args(argv=None):
    from cpl_keras.cli import named_path

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", required=True, metavar="NAME=RUN",
                        type=named_path, help="a run and its name (repeatable)")
    parser.add_argument("--until", type=int, metavar="EPOCH",
                        help="only the epochs up to this one (1 = the first)")
    parser.add_argument("--out", required=True, help="the Markdown page to write (.md)")
    args = parser.parse_args(argv)
    args.runs = args.run
    if not args.out.endswith(".md"):
        parser.error(f"--out must end in .md, got {args.out}")
    return args


def summarise(path, until=None):
    """``{"epochs": [...], "terms": {target: {...}}, "alphas": {...}}`` of one
    log: the epochs with every ``grad_`` column filled (up to ``until``,
    where given), and per term its median norm, median share and the
    epochs it was largest and smallest."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    logged = [r for r in rows if all(r.get(f"grad_{t}") not in (None, "") for t in TARGETS)
              and (until is None or int(r["epoch"]) <= until)]
    if not logged:
        raise ValueError(f"{path} has no grad_<target> columns (train.py --term-gradients)")
    norms = np.array([[float(r[f"grad_{t}"]) for t in TARGETS] for r in logged])
    shares = norms / np.maximum(norms.sum(axis=1, keepdims=True), np.finfo(float).tiny)
    largest, smallest = norms.argmax(axis=1), norms.argmin(axis=1)
    terms = {t: {"median_norm": float(np.median(norms[:, i])),
                 "median_share": float(np.median(shares[:, i])),
                 "epochs_largest": int(np.sum(largest == i)),
                 "epochs_smallest": int(np.sum(smallest == i))}
             for i, t in enumerate(TARGETS)}
    alphas = {t: float(np.median([float(r[f"alpha_{t}"]) for r in logged]))
              for t in TARGETS if all(r.get(f"alpha_{t}") not in (None, "") for r in logged)}
    return {"log": os.path.relpath(path, REPO), "epochs": [int(r["epoch"]) for r in logged],
            "terms": terms, "alphas": alphas}


def _figure(value):
    return "0" if value == 0 else f"{value:.2g}"


def page(summaries, command):
    """The page of ``summaries`` (``summarise``'s per run, or their JSON)
    written by ``command``."""
    from cpl_keras import files

    lines = [files.generated_line(command), "",
             "# Which loss terms drive the towers", "", "Command:", "", "```", command, "```", "",
             "Per run and loss term: the median over the logged epochs of the norm of the "
             "gradient the weighted term sends into the towers' shared features (first 64 "
             "training pairs), its median share of the sum over the 13 terms, and the "
             "epochs in which it sent the largest (`max`) and the smallest (`min`) gradient; "
             "alpha: the median of Eq. 9's weight where the run has them.", ""]
    for name, s in summaries.items():
        epochs = s["epochs"]
        lines += [f"## {name}", "", f"`{s['log']}`: {len(epochs)} logged epochs "
                  f"({epochs[0]}-{epochs[-1]}).", "",
                  "| term | median norm | median share | max | min |"
                  + (" alpha |" if s["alphas"] else ""),
                  "|---|---|---|---|---|" + ("---|" if s["alphas"] else "")]
        for t, m in s["terms"].items():
            alpha = f" {_figure(s['alphas'][t])} |" if t in s["alphas"] else (
                " |" if s["alphas"] else "")
            lines.append(f"| {t} | {_figure(m['median_norm'])} | {m['median_share']:.3f} | "
                         f"{m['epochs_largest']} | {m['epochs_smallest']} |{alpha}")
        lines.append("")
    return "\n".join(lines)


def regenerate(page_path):
    """The committed page ``page_path`` as this script writes it, from its
    JSON beside it and the command on its first line."""
    from cpl_keras import files

    command, payload = files.page_source(page_path)
    parse_args(shlex.split(command)[2:])  # (a command this script takes)
    return page(payload, command)


def main(argv=None):
    from cpl_keras.runs import log_file  # (its RunError is a ValueError)

    args = parse_args(argv)
    try:
        summaries = {name: summarise(log_file(run), args.until) for name, run in args.runs}
    except (OSError, ValueError) as error:
        print(f"analyses/term_gradients.py: error: {error}", file=sys.stderr)
        return 2
    command = "python analyses/term_gradients.py " + " ".join(
        f'--run "{name}={os.path.relpath(run, REPO)}"' for name, run in args.runs) + \
        (f" --until {args.until}" if args.until else "") + \
        f" --out {os.path.relpath(args.out, REPO)}"
    from cpl_keras import files

    print(f"wrote {args.out} and {files.write_page(args.out, page(summaries, command), summaries)}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    from cpl_keras import cli

    cli.run(main, "analyses/term_gradients.py")
