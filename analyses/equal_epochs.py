"""Two runs of the same split compared epoch by epoch on validation: is one
behind at every epoch, or only where early stopping ended it? For each
epoch given (default: both runs' kept epochs and their last common epoch),
each run's ``val_nmae`` (the monitor: the sum of the ten validation NMAEs)
and its per-parameter validation NMAEs, and how many columns each run is
lower on. Then, over every epoch both ran, how often A's monitor is lower.

    python analyses/equal_epochs.py \\
        paper_results/inception-2000-ema/runs/cvgl_cpl-a-s0_log.csv \\
        paper_results/inception-2000-ema/runs/cvgl_baseline-s0_log.csv
    python analyses/equal_epochs.py A_log.csv B_log.csv --epochs 5 10 20 \\
        --title "A and B, seed 0, validation at equal epochs" --out runs/equal.md
    python analyses/equal_epochs.py --pair "Seed 0" A0_log.csv B0_log.csv \\
        --pair "Seed 1" A1_log.csv B1_log.csv --title "..." --out runs/equal.md

The two runs must share a split (the same ``--seed`` and ``--split``) for
their validation NMAEs to be comparable. With ``--out PAGE.md`` (and
``--title``), it also writes what it prints as a Markdown page: the title,
``--intro`` where given, the command that prints the comparison in a code
block and the comparison (paths relative to the repository). Each ``--pair
HEADING A B`` (repeatable, instead of A and B) is one section of the page
under its heading, with its own command. Committed as the equal-epochs pages
of paper_results/inception-2000-ema/, inception-2000-ablations/ and
inception-8000/ (``regenerate`` rebuilds one from the logs its command names).
"""

from __future__ import annotations

import argparse
import os
import shlex

from cpl_keras.camera import PARAMETERS
from cpl_keras.runs import read_log

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: How the page's command and the command in its code blocks begin.
PROG = "python analyses/equal_epochs.py"


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
                         + " | ".join(cells) + f" | {len(lower)}"
                         + (f" ({', '.join(lower)}) |" if lower else " |"))
    return lines


def report(path_a, path_b, epochs, shown=None):
    """What the command prints for runs A and B (log.csv files or run
    directories): each run's epochs and kept epoch, the table at ``epochs``
    (default: both kept epochs and the last common one) and at how many
    common epochs A's monitor is lower. ``shown``: the two paths as the text
    names them (default: relative to the working directory)."""
    a, b = validation(path_a), validation(path_b)
    common = sorted(set(a) & set(b))
    if not common:
        raise _error(f"{path_a} and {path_b} share no epoch")
    epochs = sorted(set(epochs or [kept_epoch(a), kept_epoch(b), common[-1]]))
    shown = shown or (os.path.relpath(path_a), os.path.relpath(path_b))
    lines = []
    for name, label, run in (("A", shown[0], a), ("B", shown[1], b)):
        kept = kept_epoch(run)
        lines.append(f"{name}: {label}: {len(run)} epochs, kept {kept} "
                     f"(val_nmae {run[kept]['val_nmae']:.3f})")
    lines += [""] + comparison(a, b, epochs)
    ahead = [e for e in common if a[e]["val_nmae"] < b[e]["val_nmae"]]
    lines += ["", f"Over the {len(common)} epochs both ran (1-{common[-1]}), A's val_nmae is "
              f"lower at {len(ahead)}" + (f" ({', '.join(map(str, ahead))})." if ahead else ".")]
    return "\n".join(lines) + "\n"


def parser():
    """The command's options (also ``regenerate``'s reading of a page's command)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("a", nargs="?", help="run A's log.csv (or its run directory)")
    parser.add_argument("b", nargs="?", help="run B's log.csv (or its run directory)")
    parser.add_argument("--pair", nargs=3, action="append", default=[],
                        metavar=("HEADING", "A", "B"),
                        help="a pair of runs under a heading of their own (repeatable, "
                             "instead of A and B)")
    parser.add_argument("--epochs", type=int, nargs="+",
                        help="the epochs to compare (default: both kept epochs and the last "
                             "common one)")
    parser.add_argument("--out", help="also write the page PAGE.md: the title, --intro, the "
                                      "command in a code block and what it prints")
    parser.add_argument("--title", help="the page's title (with --out)")
    parser.add_argument("--intro", help="a paragraph under the title (with --out)")
    return parser


def parse_args(argv=None):
    """The parsed options, checked: A and B or ``--pair``, and a page's title."""
    p = parser()
    args = p.parse_args(argv)
    if args.epochs and min(args.epochs) < 1:
        p.error("--epochs must be 1 or more")
    if args.pair and (args.a or args.b):
        p.error("give A and B or --pair, not both")
    if not args.pair and not (args.a and args.b):
        p.error("give run A and run B (or --pair HEADING A B)")
    if args.out is not None:
        if not args.out.endswith(".md"):
            p.error(f"--out must end in .md, got {args.out}")
        if not args.title:
            p.error("--out needs --title")
    elif args.title or args.intro:
        p.error("--title and --intro are the page's: give --out PAGE.md")
    return args


def _pairs(args):
    """``[(heading or None, A, B)]``: the pairs the command compares."""
    return [tuple(pair) for pair in args.pair] or [(None, args.a, args.b)]


def pair_command(a, b, epochs):
    """The command that prints the comparison of A and B (a page's code block)."""
    return " ".join([PROG] + [shlex.quote(x) for x in (a, b)]
                    + (["--epochs"] + [str(e) for e in epochs] if epochs else []))


def page_command(args):
    """The command that writes ``args.out`` again (the page's first line)."""
    words = [shlex.quote(x) for x in (args.a, args.b) if x]
    for heading, a, b in args.pair:
        words += ["--pair"] + [shlex.quote(x) for x in (heading, a, b)]
    if args.epochs:
        words += ["--epochs"] + [str(e) for e in args.epochs]
    words += ["--title", shlex.quote(args.title)]
    if args.intro:
        words += ["--intro", shlex.quote(args.intro)]
    return " ".join([PROG] + words + ["--out", shlex.quote(args.out)])


def body(args, root=None):
    """What the command prints: each pair's comparison, under its heading and
    command where the pairs have headings (``--pair``). With ``root``, the
    paths are relative to it (a page's: the repository) and named as given."""
    sections = []
    for heading, a, b in _pairs(args):
        paths = (a, b) if root is None else (os.path.join(root, a), os.path.join(root, b))
        text = report(*paths, args.epochs, shown=None if root is None else (a, b))
        if heading is not None:
            text = "\n".join([f"## {heading}", "", "```", pair_command(a, b, args.epochs),
                              "```", "", text])
        sections.append(text)
    return "\n".join(sections)


def page(args, printed):
    """The page ``--out`` names: the generated line, the title, ``--intro``,
    then what the command printed (``printed``, ``body``'s; after its
    command, where it is one pair)."""
    from cpl_keras import files

    lines = [files.generated_line(page_command(args)), "", f"# {args.title}", ""]
    if args.intro:
        lines += [args.intro, ""]
    if not args.pair:
        lines += ["```", pair_command(args.a, args.b, args.epochs), "```", ""]
    return "\n".join(lines) + "\n" + printed


def _repository_paths(args):
    """``args`` with its paths relative to the repository (a page names them so)."""
    def relative(path):
        return os.path.relpath(os.path.abspath(path), REPO)

    if args.a:
        args.a, args.b = relative(args.a), relative(args.b)
    args.pair = [[heading, relative(a), relative(b)] for heading, a, b in args.pair]
    args.out = relative(args.out)
    return args


def regenerate(page_path):
    """The page ``page_path`` as its command (its first line) writes it, from
    the logs that command names (committed beside the runs)."""
    from cpl_keras import files

    with open(page_path) as f:
        command = files.generated_command(f.read())
    words = shlex.split(command)
    if words[:2] != PROG.split():
        raise ValueError(f"{page_path}: not a page of {PROG} ({command!r})")
    args = parse_args(words[2:])
    return page(args, body(args, REPO))


def main(argv=None):
    args = parse_args(argv)
    if args.out is None:
        print(body(args), end="")
        return 0
    from cpl_keras import files

    args = _repository_paths(args)
    printed = body(args, REPO)
    print(printed, end="")
    files.write_text(os.path.join(REPO, args.out), page(args, printed))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/equal_epochs.py")
