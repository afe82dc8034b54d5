"""Evaluate trained runs: one model, or the paper's Table 1 / Table 2.

    python evaluate.py --run RUN_DIR --data DATA.h5
    python evaluate.py --table 1 --runs RUN_DIR [RUN_DIR ...] [--data DATA.h5]
    python evaluate.py --table 2 --runs RUN_DIR [RUN_DIR ...] --data REAL.h5

Writes Markdown, CSV and JSON tables and a FOV-threshold plot to
paper_results/ (or --out DIR), atomically; see docs/evaluation.md.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

os.environ.setdefault("KERAS_BACKEND", "jax")


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(2)


def parse_args(argv=None):
    from cpl_keras.evaluation import PAPER_DIR

    parser = _Parser(prog="evaluate.py", description=__doc__.split("\n")[0])
    parser.add_argument("--run", help="evaluate one run directory (with --data)")
    parser.add_argument("--table", type=int, choices=(1, 2), help="make the paper's Table 1 or 2")
    parser.add_argument("--runs", nargs="+", help="run directories for --table")
    parser.add_argument("--data", help="dataset file (HDF5)")
    parser.add_argument("--out", default=PAPER_DIR, help="output directory (default: paper_results/)")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--no-geometric", action="store_true", help="leave out the Geometric row")
    parser.add_argument("--geometric-max", type=int,
                        help="run the Geometric baseline on the first N evaluation pairs only")
    args = parser.parse_args(argv)
    if (args.run is None) == (args.table is None):
        parser.error("give either --run RUN_DIR --data DATA.h5 or --table {1,2} --runs ...")
    if args.run is not None and args.data is None:
        parser.error("--run needs --data DATA.h5")
    if args.table is not None and not args.runs:
        parser.error("--table needs --runs RUN_DIR [RUN_DIR ...]")
    if args.batch_size < 1:
        parser.error(f"--batch-size must be positive, got {args.batch_size}")
    if args.geometric_max is not None and args.geometric_max < 1:
        parser.error(f"--geometric-max must be positive, got {args.geometric_max}")
    return args


def main(argv=None):
    args = parse_args(argv)
    from cpl_keras import evaluation
    from cpl_keras.data.storage import DatasetError

    command = "python evaluate.py " + shlex.join(sys.argv[1:] if argv is None else list(argv))
    try:
        if not os.path.isdir(args.out):
            raise evaluation.EvaluationError(f"output directory does not exist: {args.out}")
        if args.run is not None:
            table = evaluation.evaluate_run(args.run, args.data, args.batch_size)
            stem = "eval_" + os.path.basename(os.path.normpath(args.run))
        else:
            table = evaluation.make_table(
                args.table, args.runs, args.data, geometric=not args.no_geometric,
                geometric_max=args.geometric_max, batch_size=args.batch_size,
                progress=lambda message: print(message, file=sys.stderr))
            stem = f"table{args.table}"
        paths = evaluation.write_outputs(args.out, stem, table, command)
    except (evaluation.EvaluationError, DatasetError, OSError) as error:
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        print(f"error: {message}", file=sys.stderr)
        return 2
    print(evaluation.markdown(table))
    print("wrote " + ", ".join(paths), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
