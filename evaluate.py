"""Evaluate trained runs: one model, or the paper's Table 1 / Table 2.

    python evaluate.py --run RUN_DIR --data DATA.h5
    python evaluate.py --table 1 --runs RUN_DIR [RUN_DIR ...] [--data DATA.h5]
    python evaluate.py --table 2 --runs RUN_DIR [RUN_DIR ...] --data data/real [MORE.h5 ...]
    python evaluate.py --reproduce [--quick | --preset NAME] [--pairs N --epochs E ...]
    python evaluate.py --reproduce --from-predictions DIR

``--reproduce`` regenerates everything in paper_results/ (datasets, training
runs, published predictions, both tables, REPORT.md); ``--quick`` runs that
pipeline on tiny settings in minutes, ``--preset`` at a named scale;
``--from-predictions DIR`` rebuilds DIR's tables and REPORT.md from its
published predictions alone (cpl_keras/reproduce/).

Writes Markdown, CSV and JSON tables and a FOV-threshold plot, atomically:
``--table`` to runs/tables/ (git-ignored; or --out DIR, created if missing),
``--run R`` next to the run (``eval_<run>.*`` in R's parent directory)
unless --out is given. ``python -m cpl_keras.reproduce`` is the same as
``--reproduce``. The command itself is cpl_keras/commands/evaluate.py
(installed: ``cpl-evaluate``). See docs/evaluation.md.
"""

from __future__ import annotations

from cpl_keras import cli  # (first, and light: the Ctrl-C guard starts at once)

PROG = "evaluate.py"


def main(argv=None):
    """The command line; Ctrl-C at any moment ends it with one line and exit
    status 130 (tables are written atomically: none is left half-written)."""
    try:
        # (imported inside cli.run's Ctrl-C guard)
        from cpl_keras.commands import evaluate

        return evaluate.main(argv, prog=PROG)
    except KeyboardInterrupt:  # (during the import)
        return cli.interrupted(PROG, note="nothing was written")


def parse_args(argv=None):
    from cpl_keras.commands import evaluate

    return evaluate.parse_args(argv, prog=PROG)


def __getattr__(name):
    # the command's other names (TABLES_DIR, ...), from its module
    from cpl_keras.commands import evaluate

    return getattr(evaluate, name)


if __name__ == "__main__":
    # (the same line when the guard itself ends a process stuck in compilation)
    cli.run(main, PROG, note="nothing was written")
