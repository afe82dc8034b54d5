"""Evaluate trained runs: one model, or the paper's Table 1 / Table 2.

    python evaluate.py --run RUN_DIR --data DATA.h5
    python evaluate.py --table 1 --runs RUN_DIR [RUN_DIR ...] [--data DATA.h5]
    python evaluate.py --table 2 --runs RUN_DIR [RUN_DIR ...] --data data/real [MORE.h5 ...]
    python evaluate.py --reproduce [--quick] [--pairs N --epochs E ...]

``--reproduce`` regenerates everything in paper_results/ (datasets, training
runs, both tables, REPORT.md); ``--quick`` runs that pipeline on tiny
settings in minutes (cpl_keras/reproduce.py).

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
    parser.add_argument("--data", nargs="+", help="dataset file (HDF5); Table 2: one or more "
                        "real sets or folders of them (cpl_keras.real.build all), scored per "
                        "rig and pooled")
    parser.add_argument("--out", help="output directory (default: paper_results/; "
                        "with --reproduce --quick: runs/quick/paper_results)")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--no-geometric", action="store_true", help="leave out the Geometric row")
    parser.add_argument("--geometric-max", type=int,
                        help="run the Geometric baseline on the first N evaluation pairs only")
    group = parser.add_argument_group("reproduce (cpl_keras/reproduce.py)")
    group.add_argument("--reproduce", action="store_true",
                       help="regenerate every dataset, run, table and REPORT.md")
    group.add_argument("--quick", action="store_true", help="tiny settings (minutes)")
    group.add_argument("--pairs", type=int, help="cvgl-protocol pairs (paper: 123017)")
    group.add_argument("--random-pairs", type=int, help="random-protocol pairs")
    group.add_argument("--epochs", type=int, help="maximum epochs per run (paper: 200)")
    group.add_argument("--patience", type=int, help="early stopping patience (paper: 5)")
    group.add_argument("--backbone", choices=("inception_v3", "small"))
    group.add_argument("--image-size", type=int)
    group.add_argument("--crops", type=int, help="Middlebury crops for Table 2")
    group.add_argument("--seed", type=int, default=0)
    group.add_argument("--data-dir", help="where the datasets go (default data/reproduce)")
    group.add_argument("--runs-dir", help="where the runs go (default runs/reproduce)")
    group.add_argument("--discussion", help="Markdown file appended to REPORT.md as the "
                       "comparison with the paper (default paper_results/discussion.md "
                       "when writing to paper_results/)")
    args = parser.parse_args(argv)
    if args.reproduce:
        if args.run is not None or args.table is not None:
            parser.error("--reproduce makes every table itself; drop --run/--table")
        quick = "quick" if args.quick else "reproduce"
        args.out = args.out or (os.path.join("runs", "quick", "paper_results") if args.quick else PAPER_DIR)
        args.data_dir = args.data_dir or os.path.join("data", quick)
        args.runs_dir = args.runs_dir or os.path.join("runs", quick)
        if args.discussion is None and os.path.abspath(args.out) == os.path.abspath(PAPER_DIR):
            args.discussion = os.path.join(PAPER_DIR, "discussion.md")
        return args
    if args.quick:
        parser.error("--quick goes with --reproduce")
    args.out = args.out or PAPER_DIR
    if (args.run is None) == (args.table is None):
        parser.error("give either --run RUN_DIR --data DATA.h5 or --table {1,2} --runs ...")
    if args.run is not None and args.data is None:
        parser.error("--run needs --data DATA.h5")
    if args.table is not None and not args.runs:
        parser.error("--table needs --runs RUN_DIR [RUN_DIR ...]")
    if args.data is not None and args.table != 2:
        if len(args.data) > 1:
            parser.error("several --data files go with --table 2 only")
        args.data = args.data[0]
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
    if args.reproduce:
        return run_reproduce(args, command)
    try:
        if not os.path.isdir(args.out):
            raise evaluation.EvaluationError(f"output directory does not exist: {args.out}")
        if args.run is not None:
            table = evaluation.evaluate_run(args.run, args.data, args.batch_size)
            stem = "eval_" + os.path.basename(os.path.normpath(args.run))
        elif args.table == 2:
            from cpl_keras.real import table2

            table = table2.make_table2(
                args.runs, args.data, geometric=not args.no_geometric,
                geometric_max=args.geometric_max,
                progress=lambda message: print(message, file=sys.stderr))
            paths = table2.write_table2(args.out, "table2", table, command)
            print(table2.markdown(table))
            print("wrote " + ", ".join(paths), file=sys.stderr)
            return 0
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


def run_reproduce(args, command):
    from cpl_keras import evaluation, reproduce
    from cpl_keras.data.storage import DatasetError

    try:
        config = reproduce.settings(
            args.quick, pairs=args.pairs, random_pairs=args.random_pairs, epochs=args.epochs,
            patience=args.patience, backbone=args.backbone, image_size=args.image_size,
            crops=args.crops, geometric_max=args.geometric_max,
        )
        report = reproduce.reproduce(
            out_dir=args.out, data_dir=args.data_dir, runs_dir=args.runs_dir, config=config,
            seed=args.seed, command=command, discussion_file=args.discussion,
        )
    except (ValueError, evaluation.EvaluationError, DatasetError, OSError) as error:
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        print(f"error: {message}", file=sys.stderr)
        return 2
    print(f"report written to {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
