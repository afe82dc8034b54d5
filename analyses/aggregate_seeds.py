"""One table over several seeds, from the same table made for each seed,
with the rows' differences beyond the spread.

    python analyses/aggregate_seeds.py paper_results/cpu-8000/interim-drive-s0/table1.json \\
        paper_results/cpu-8000/interim-drive-s1/table1.json --seeds 0 1 \\
        --out paper_results/cpu-8000/interim-drive-2seeds

Each TABLE.json is a table that evaluate.py wrote (``table1.json`` or
``table2.json``) for one seed, in the order of ``--seeds``;
``cpl_keras.evaluation.aggregate_seeds`` makes every cell the mean over the
seeds with its spread. Writes the aggregated table as evaluate.py writes
one (``report.write_outputs``: ``<stem>.md``, ``.csv``, ``.json`` and the
plots; the stem of the inputs') into ``--out``, the page followed by a
"Beyond the spread" section (``report.differences_beyond_spread``: which
row is lower per column where the means differ by more than the spreads).

Produces: ``paper_results/cpu-8000/{interim-drive-2seeds,
interim-drive-3seeds,paper-split-3seeds}/table1.*`` (the commands in
``paper_results/cpu-8000/README.md``); ``regenerate`` rebuilds a committed
page from the committed tables its first line names.
"""

from __future__ import annotations

import json
import os
import shlex

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = "analyses/aggregate_seeds.py"


def parser():
    from cpl_keras import cli

    p = cli.Parser(prog=SCRIPT, description=__doc__.split("\n\n")[0])
    p.add_argument("tables", nargs="+", metavar="TABLE.json",
                   help="the same table (evaluate.py's JSON) for each seed, two or more")
    p.add_argument("--seeds", nargs="+", type=int, required=True,
                   help="the seed of each table, in the same order")
    p.add_argument("--out", required=True, help="folder for the aggregated table's files")
    return p


def aggregate(paths, seeds, root=None):
    """The aggregated table of the tables at ``paths`` (relative to ``root``
    when given), one per seed of ``seeds``."""
    from cpl_keras.evaluation import aggregate_seeds
    from cpl_keras.evaluation.tables import table_from_json

    tables = []
    for path in paths:
        with open(os.path.join(root, path) if root else path) as f:
            tables.append(table_from_json(json.load(f)))
    return aggregate_seeds(tables, seeds)


def markdown(table, command):
    """The aggregated table's page: ``report.markdown`` (its generated line
    first) and the "Beyond the spread" section."""
    from cpl_keras import report

    return (report.markdown(table, command) + "\n\n## Beyond the spread\n\n"
            + "\n".join(report.differences_beyond_spread(table.rows)) + "\n")


def stem_of(table):
    from cpl_keras import report

    return "table2" if report.is_table2(table) else "table1"


def regenerate(page_path):
    """The text ``main`` wrote for the committed page ``page_path``: the
    command on its first line run again on the committed tables it names
    (paths relative to the repository), without writing."""
    from cpl_keras import files, report

    with open(page_path) as f:
        command = files.generated_command(f.read())
    words = shlex.split(command)
    if words[:2] != ["python", SCRIPT]:
        raise ValueError(f"{page_path}: not written by {SCRIPT}: {command}")
    args = parser().parse_args(words[2:])
    table = aggregate(args.tables, args.seeds, root=REPO)
    return markdown(report.portable(table, os.path.join(REPO, args.out)), command)


def main(argv=None):
    p = parser()
    args = p.parse_args(argv)
    if len(args.tables) < 2:
        p.error("give two or more tables, one per seed")
    if len(args.seeds) != len(args.tables):
        p.error(f"{len(args.tables)} tables but {len(args.seeds)} seeds")

    from cpl_keras import cli, report

    table = aggregate(args.tables, args.seeds)
    command = cli.command_line(SCRIPT, argv)
    written = report.write_outputs(args.out, stem_of(table), table, command,
                                   render_markdown=markdown)
    print("\n".join(written))
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, SCRIPT)
