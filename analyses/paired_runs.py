"""Runs of one seed side by side on their shared test split, with a paired
bootstrap of every run against two references.

    python analyses/paired_runs.py --data DATA.h5 \\
        --run MTL-CPL-A=paper_results/inception-2000-ema/runs/cvgl_cpl-a-s0 \\
        --run MTL-Baseline=paper_results/inception-2000-ema/runs/cvgl_baseline-s0 \\
        --run "MTL-CPL-U=paper_results/inception-2000-ablations/runs/cvgl_cpl-u-s0" \\
        --out paper_results/inception-2000-ablations/seed0.md

For ablations and other one-seed experiments: every run must share its
test split (the same seed and dataset file; a run directory, published or
not, read through its stored predictions when it has them). The first two
``--run`` are the references. Writes a Markdown page (and the same as JSON
beside it): each run's test NMAE per column, its epochs, and for every
other run and column the paired bootstrap interval (95 %, 2,000 resamples
of the test pairs, ``cpl_keras.evaluation.verdicts.seed_intervals``) of its
NMAE minus each reference's, with the side it decides ("lower", "higher")
or "=". ``regenerate`` rebuilds a committed page from its JSON and the
command on its first line (no dataset needed).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def parse_args(argv=None):
    from cpl_keras.cli import named_path

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="the runs' dataset file")
    parser.add_argument("--run", action="append", required=True, metavar="NAME=RUN_DIR",
                        type=named_path,
                        help="a run and its name (repeatable; the first two are the references)")
    parser.add_argument("--out", required=True, help="the Markdown page to write (.md)")
    parser.add_argument("--resamples", type=int, default=2000)
    args = parser.parse_args(argv)
    args.runs = args.run
    if len(args.runs) < 3:
        parser.error("give two references and at least one more run")
    if not args.out.endswith(".md"):
        parser.error(f"--out must end in .md, got {args.out}")
    return args


def compare(runs, data_path, resamples):
    """The page's content: per run its NMAEs and epochs; per other run and
    reference, the bootstrap intervals by column."""
    from cpl_keras.evaluation.forward_pass import paired_outputs
    from cpl_keras.evaluation.pairs import EvaluationError
    from cpl_keras.evaluation.verdicts import (A_LOWER, B_LOWER, COLUMN_PARAMETER, COLUMNS,
                                               seed_intervals)

    loaded = {name: paired_outputs(path, data_path) for name, path in runs}
    seeds = {config.training.seed for _, config in loaded.values()}
    if len(seeds) != 1:
        raise EvaluationError(f"the runs have different seeds: {sorted(seeds)}")
    seed = seeds.pop()
    references = [name for name, _ in runs[:2]]
    result = {"data": os.path.basename(data_path), "seed": seed, "references": references,
              "runs": {}, "intervals": {}}
    for name, path in runs:
        raw, config = loaded[name]
        intervals = seed_intervals(seed, raw, loaded[references[0]][0], resamples=resamples)
        result["runs"][name] = {
            "run": os.path.relpath(os.path.abspath(path), REPO),
            "command": config.command, "epochs_run": config.epochs_run,
            "best_epoch": config.best_epoch, "wall_time_s": config.wall_time_s,
            "nmae": {c: intervals[COLUMN_PARAMETER[c]].nmae_a for c in COLUMNS}}
    side = {A_LOWER: "lower", B_LOWER: "higher"}
    for name, _ in runs[2:]:
        for reference in references:
            intervals = seed_intervals(seed, loaded[name][0], loaded[reference][0],
                                       resamples=resamples)
            result["intervals"][f"{name} - {reference}"] = {
                c: {"low": intervals[COLUMN_PARAMETER[c]].low,
                    "high": intervals[COLUMN_PARAMETER[c]].high,
                    "answer": side.get(intervals[COLUMN_PARAMETER[c]].answer, "=")}
                for c in COLUMNS}
    return result


def markdown(result, command):
    """The page of ``result`` (``compare``'s, or its JSON) written by ``command``."""
    from cpl_keras import files
    from cpl_keras.evaluation.verdicts import COLUMNS

    lines = [files.generated_line(command), "",
             f"# Seed {result['seed']} runs on one test split", "", "```", command, "```", "",
             f"Dataset `{result['data']}`; test NMAE per column:", "",
             "| run | epochs (kept) | " + " | ".join(COLUMNS) + " |",
             "|---|---|" + "---|" * len(COLUMNS)]
    for name, run in result["runs"].items():
        lines.append(f"| {name} | {run['epochs_run']} ({run['best_epoch']}) | "
                     + " | ".join(f"{run['nmae'][c]:.3f}" for c in COLUMNS) + " |")
    lines += ["", "Paired bootstrap of the NMAE difference (run minus reference; 95 % "
              "interval over resampled test pairs): `lower` or `higher` where the interval "
              "excludes 0, else `=`.", "",
              "| run - reference | " + " | ".join(COLUMNS) + " | lower / higher |",
              "|---|" + "---|" * (len(COLUMNS) + 1)]
    for pair, cells in result["intervals"].items():
        answers = [cells[c]["answer"] for c in COLUMNS]
        lines.append(f"| {pair} | " + " | ".join(
            f"{a} [{cells[c]['low']:+.3f}, {cells[c]['high']:+.3f}]"
            for c, a in zip(COLUMNS, answers))
            + f" | {answers.count('lower')} / {answers.count('higher')} |")
    return "\n".join(lines) + "\n"


def regenerate(page_path):
    """The committed page ``page_path`` as this script writes it, from its
    JSON beside it and the command on its first line."""
    from cpl_keras import files

    command, payload = files.page_source(page_path)
    parse_args(shlex.split(command)[2:])  # (a command this script takes)
    return markdown(payload, command)


def main(argv=None):
    from cpl_keras import files

    args = parse_args(argv)
    result = compare(args.runs, args.data, args.resamples)
    command = "python analyses/paired_runs.py " + " ".join(
        [f"--data {args.data}"] + [f"--run '{n}={p}'" for n, p in args.runs]
        + [f"--out {args.out}"])
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    files.write_page(args.out, markdown(result, command), result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    from cpl_keras import cli

    cli.run(main, "analyses/paired_runs.py")
