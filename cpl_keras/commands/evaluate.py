"""Evaluate trained runs: one model, or the paper's Table 1 / Table 2.

``evaluate.py`` and ``cpl-evaluate``. Writes Markdown, CSV and JSON tables
and a FOV-threshold plot, atomically: ``--table`` to runs/tables/
(git-ignored; or --out DIR, created if missing), ``--run R`` next to the run
(``eval_<run>.*`` in R's parent directory) unless --out is given. The
reproduction of paper_results/ is its own command, ``cpl-reproduce``
(``python -m cpl_keras.reproduce``): ``--reproduce`` says so and stops.
``main(argv, prog)``: ``prog`` is the name in the command's lines and in
the command it records. See docs/evaluation.md.
"""

from __future__ import annotations

import os
import sys

from cpl_keras import cli, evaluation, report
from cpl_keras.cache import enable_compile_cache
from cpl_keras.errors import Error

#: Where --table writes without --out (git-ignored, like every run).
TABLES_DIR = os.path.join("runs", "tables")
#: The name the command goes by (``evaluate.py`` passes its own).
PROG = "cpl-evaluate"
#: The reproduction's command, installed and not (``evaluate.py --reproduce`` names them).
REPRODUCE = ("cpl-reproduce", "python -m cpl_keras.reproduce")


def parse_args(argv=None, prog=PROG):
    parser = cli.Parser(prog=prog, description=__doc__.split("\n")[0],
                        epilog=f"The reproduction of paper_results/ is its own command: "
                        f"{REPRODUCE[0]} ({REPRODUCE[1]}).")
    parser.add_argument("--run", help="evaluate one run directory (with --data)")
    parser.add_argument("--table", type=int, choices=(1, 2), help="make the paper's Table 1 or 2")
    parser.add_argument("--runs", nargs="+", help="run directories for --table")
    parser.add_argument("--data", nargs="+", help="dataset file (HDF5); Table 2: one or more "
                        "real sets or folders of them (cpl_keras.real.build all), scored per "
                        "rig and pooled")
    parser.add_argument("--out", type=cli.path, help="output directory, created if missing (default: "
                        f"{TABLES_DIR}/ for --table, so the committed paper_results/ is never "
                        "overwritten; with --run: the run's parent directory)")
    parser.add_argument("--batch-size", type=cli.positive_int, default=32,
                        help="pairs per forward pass (default 32; the results do not depend on it)")
    parser.add_argument("--no-geometric", action="store_true", help="leave out the Geometric row")
    parser.add_argument("--geometric-max", type=cli.positive_int,
                        help="run the Geometric baseline on the first N evaluation pairs only")
    given = list(sys.argv[1:] if argv is None else argv)
    if "--reproduce" in given:  # (the reproduction is its own command)
        rest = [a for a in given if a != "--reproduce"]
        installed, module = (cli.command_line(name, rest) for name in REPRODUCE)
        parser.error(f"--reproduce moved: run {installed} (or {module})")
    args = parser.parse_args(argv)
    if (args.run is None) == (args.table is None):
        parser.error("give either --run RUN_DIR --data DATA.h5 or --table {1,2} --runs ...")
    if args.run is not None and args.data is None:
        parser.error("--run needs --data DATA.h5")
    if args.run is not None:
        args.out = args.out or os.path.dirname(os.path.abspath(os.path.normpath(args.run)))
    args.out = args.out or TABLES_DIR
    if args.table is not None and not args.runs:
        parser.error("--table needs --runs RUN_DIR [RUN_DIR ...]")
    if args.data is not None and args.table != 2:
        if len(args.data) > 1:
            parser.error("several --data files go with --table 2 only")
        args.data = args.data[0]
    return args


def main(argv=None, prog=PROG):
    """The command line; Ctrl-C at any moment ends it with one line and exit
    status 130 (tables are written atomically: none is left half-written)."""
    try:
        return _main(argv, prog)
    except KeyboardInterrupt:
        return cli.interrupted(prog, note="nothing was written")


def _main(argv, prog):
    args = parse_args(argv, prog)
    command = cli.command_line(prog, argv)

    def progress(message):
        cli.check_interrupt()  # (a Ctrl-C swallowed by a callback stops here)
        print(message, file=sys.stderr)

    enable_compile_cache()  # (a second evaluation of a model loads its programs)
    with cli.interruptible():
        return _evaluate(args, command, progress, prog)


def _evaluate(args, command, progress, prog):
    try:
        cli.check_output_dir(args.out)  # (a file, not writable, a full disk: before the work)
        if args.run is not None:
            table = evaluation.evaluate_run(args.run, args.data, args.batch_size)
            stem = "eval_" + os.path.basename(os.path.normpath(args.run))
        elif args.table == 2:
            table = evaluation.make_table2(
                args.runs, args.data, geometric=not args.no_geometric,
                geometric_max=args.geometric_max, progress=progress)
            stem = "table2"
        else:
            table = evaluation.make_table(
                args.table, args.runs, args.data, geometric=not args.no_geometric,
                geometric_max=args.geometric_max, batch_size=args.batch_size,
                progress=progress)
            stem = f"table{args.table}"
        cli.check_interrupt()
        paths = report.write_outputs(args.out, stem, table, command)
    except (Error, OSError) as error:  # (EvaluationError, RunError, DatasetError, ...)
        return cli.fail(prog, error)
    print(report.markdown(report.portable(table, args.out)))
    print("wrote " + ", ".join(paths), file=sys.stderr)
    return 0

