"""When a head dies: the live units of each regression head's first layer,
epoch by epoch, from the logs of runs trained with ``--head-units``.

    python analyses/head_units.py \\
        --run "MTL-CPL-A=runs/inception-8000/cpl-a-s0" \\
        --run "MTL-Baseline=runs/inception-8000/baseline-s0" \\
        --head pitch --out runs/head-units.md

Reads each run's log.csv (``RUN/log.csv``, or ``RUN_log.csv`` beside a
published run's folder): ``dead_<head>``, the share of the run's 64 probe
pairs (its first 64 training pairs) with every unit of the head's first
layer at or below zero, where a ReLU head puts out its biases' value; and
``units_<head>``, its units above zero for at least one of them, of 120
(``cpl_keras.training.head_units``). Writes a Markdown page (and the same as
JSON beside it): per run and head, the epochs logged, the first epoch with
a dead share of ``--dead-share`` or more, the units at the first and the last
logged epoch and their fewest; then, for each ``--head``, both numbers of
every logged epoch, the runs side by side. ``regenerate`` rebuilds a
committed page from its JSON and the command on its first line.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HEADS = ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty", "tz", "pitch")


def parse_args(argv=None):
    from cpl_keras.cli import named_path

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", required=True, metavar="NAME=RUN",
                        type=named_path, help="a run and its name (repeatable)")
    parser.add_argument("--head", action="append", choices=HEADS, default=[],
                        help="a head whose every epoch the page lists (repeatable)")
    parser.add_argument("--dead-share", type=float, default=0.25,
                        help="a head counts as dead from the first epoch with this share of "
                        "the probe pairs dead or more (default 0.25)")
    parser.add_argument("--out", required=True, help="the Markdown page to write (.md)")
    args = parser.parse_args(argv)
    if not args.out.endswith(".md"):
        parser.error(f"--out must end in .md, got {args.out}")
    if not 0 < args.dead_share <= 1:
        parser.error(f"--dead-share must be in (0, 1], got {args.dead_share}")
    return args


def summarise(rows, dead_share):
    """``{"epochs": [...], "heads": {head: {...}}, "by_epoch": {...}}`` of one
    log's rows (``runs.read_log``): the epochs whose ``dead_``/``units_``
    columns are filled, and per head what the module docstring lists."""
    logged = [r for r in rows if all(f"{k}_{h}" in r for h in HEADS for k in ("dead", "units"))]
    if not logged:
        raise ValueError("no dead_<head>/units_<head> columns (train with --head-units)")
    heads, by_epoch = {}, {}
    for head in HEADS:
        dead = [r[f"dead_{head}"] for r in logged]
        units = [int(r[f"units_{head}"]) for r in logged]
        first_dead = next((int(r["epoch"]) for r, d in zip(logged, dead) if d >= dead_share), None)
        heads[head] = {"first_dead_epoch": first_dead, "units_first": units[0],
                       "units_last": units[-1], "units_fewest": min(units),
                       "dead_last": dead[-1]}
        by_epoch[head] = [[int(r["epoch"]), d, u] for r, d, u in zip(logged, dead, units)]
    return {"epochs": [int(r["epoch"]) for r in logged], "heads": heads, "by_epoch": by_epoch}


def page(summaries, args, command):
    """The page of ``summaries`` (``summarise``'s per run, or their JSON)
    written by ``command`` (``args``, its options)."""
    from cpl_keras import files

    lines = [files.generated_line(command), "",
             "# Head units, epoch by epoch", "", "```", command, "```", "",
             "Per run and head: the first epoch with the dead share (of the 64 probe pairs, "
             f"every first-layer unit at or below zero) {args.dead_share:g} or more, then the "
             "units above zero for some probe pair at the first and last logged epoch and "
             "their fewest, of 120:", "",
             "| run | epochs logged | " + " | ".join(HEADS) + " |",
             "|---|---" + "|---" * len(HEADS) + "|"]
    for name, s in summaries.items():
        cells = []
        for head in HEADS:
            h = s["heads"][head]
            dead = "" if h["first_dead_epoch"] is None else f"dead {h['first_dead_epoch']}; "
            cells.append(f"{dead}{h['units_first']} -> {h['units_last']} "
                         f"(min {h['units_fewest']})")
        lines.append(f"| {name} | {s['epochs'][0]}-{s['epochs'][-1]} | " + " | ".join(cells) + " |")
    for head in args.head:
        names = list(summaries)
        epochs = sorted({e for s in summaries.values() for e, _, _ in s["by_epoch"][head]})
        lines += ["", f"The {head} head: dead share, units above zero", "",
                  "| epoch | " + " | ".join(names) + " |", "|---" + "|---" * len(names) + "|"]
        for epoch in epochs:
            cells = [next((f"{d:.2f}, {u}" for e, d, u in summaries[n]["by_epoch"][head]
                           if e == epoch), "-") for n in names]
            lines.append(f"| {epoch} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def regenerate(page_path):
    """The committed page ``page_path`` as this script writes it, from its
    JSON beside it and the command on its first line (its options)."""
    from cpl_keras import files

    command, payload = files.page_source(page_path)
    args = parse_args(shlex.split(command)[2:])
    return page(payload, args, command)


def command_line(args):
    runs = [f'--run "{name}={os.path.relpath(run, REPO)}"' for name, run in args.run]
    return " ".join(["python analyses/head_units.py"] + runs
                    + [f"--head {h}" for h in args.head]
                    + ([f"--dead-share {args.dead_share:g}"] if args.dead_share != 0.25 else [])
                    + [f"--out {os.path.relpath(args.out, REPO)}"])


def main(argv=None):
    from cpl_keras import files
    from cpl_keras.runs import log_file, read_log

    args = parse_args(argv)
    summaries = {}
    for name, run in args.run:
        try:
            summaries[name] = summarise(read_log(log_file(run)), args.dead_share)
        except (OSError, ValueError) as error:  # (RunError is a ValueError)
            print(f"analyses/head_units.py: error: {run}: {error}", file=sys.stderr)
            return 2
    written = files.write_page(args.out, page(summaries, args, command_line(args)), summaries)
    print(f"wrote {args.out} and {written}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    from cpl_keras import cli

    cli.run(main, "analyses/head_units.py")
