"""The fair fight's runs (paper_results/fair-fight/protocol.md), one after
another, each published the moment it ends.

Every run trains under one recipe (``--recipe``, default ``sound``,
``cpl_keras.training_options.RECIPES``) for a fixed number of epochs with no
early stopping (patience = epochs), keeping the best validation epoch by the
default monitor; the arms differ only in the variant and Eq. 9's weights:

    baseline     MTL-Baseline
    cpl-a        MTL-CPL-A, Eq. 9's weights learned (the paper's)
    cpl-a-range  MTL-CPL-A, Eq. 9's weights fixed at 1 / mean|y_i| of the
                 training split (``--adaptive-weights range``)

    python analyses/fair_fight.py --towers compact --seeds 0 1 2
    python analyses/fair_fight.py --towers inception --seeds 0 --arms cpl-a
    python analyses/fair_fight.py --towers compact --dry-run   # the commands only

A killed run resumes when the same command is run again (``train.py``'s
resume); a run already published is skipped. Two of these commands may run
side by side (``--seeds 0 1 2`` and ``--seeds 2 1 0 --arms cpl-a-range cpl-a
baseline``): each claims a run before training it
(``<run dir>.claim``, its pid) and skips one the other has claimed. Each run's test predictions,
log, curves, config and split go to ``--out/<towers>/runs/cvgl_<arm>-s<seed>``
(``cpl_keras.reproduce.jobs.publish_run``); weights stay in ``--runs-dir``.

``--plateau`` makes the amendment's runs (``protocol-plateau.md``):
InceptionV3 MTL-Baseline and MTL-CPL-A, seeds 0-2, each trained until its
monitor has not improved for 20 epochs, at most 200; they train in
``--home`` (default ``~/cpl-runs``, outside the work tree: the dataset at
``<home>/data/``, the run directories at ``<home>/fair-fight-plateau/``, the
commands run from there so that their records name no machine's path) and
are published into ``--out/<towers>-plateau/runs/``; each start is added to
the run's ledger beside its record (``run_starts.py``), which is copied into
the record when it is published:

    python analyses/fair_fight.py --plateau --towers inception --dry-run

``--verdicts`` trains nothing: from the published runs it writes
``<out>/<towers>/verdicts.md`` and ``.json`` (``fair_fight_verdicts.py``):
each pair of arms by the protocol's rules (over the seeds both arms have,
two at least), its validation at equal epochs, each arm's test NMAE beside
the Average row's and each run's collapsed-head shares.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shlex
import subprocess
import sys

#: The towers of each setting (``--backbone``).
TOWERS = {"compact": "small_resnet", "inception": "inception_v3"}
#: Each arm: its variant and the options beside the recipe's.
ARMS = {"baseline": ("baseline", []), "cpl-a": ("cpl-a", []),
        "cpl-a-range": ("cpl-a", ["--adaptive-weights", "range"])}
#: The protocol's data: the inception-2000-ema preset's 2,000 cvgl pairs.
DATA = "data/reproduce-inception-2000-ema/cvgl_2000_112px_s0_v3.0.h5"
#: The protocol's budget: epochs, every run alike, no early stopping.
EPOCHS = 50
#: The protocol's seeds: a verdict over fewer is marked as not yet the protocol's.
PROTOCOL_SEEDS = [0, 1, 2]
#: The plateau amendment (protocol-plateau.md): its arms, epoch cap and
#: patience, where it trains (``~/cpl-runs``: the dataset and run
#: directories, relative to it) and the epochs of its validation at equal epochs.
PLATEAU = {"towers": "inception", "arms": ["baseline", "cpl-a"], "epochs": 200,
           "patience": 20, "home": os.path.join("~", "cpl-runs"),
           "data": os.path.join("data", os.path.basename(DATA)),
           "runs_dir": "fair-fight-plateau", "equal_epochs": tuple(range(10, 201, 10))}


def train_command(towers, arm, seed, data, epochs, recipe, run_dir, patience=None):
    """``train.py``'s arguments for one run of the protocol (patience =
    epochs: no early stopping) or of its plateau amendment (``patience``)."""
    variant, extra = ARMS[arm]
    return (["train.py", "--variant", variant, "--backbone", TOWERS[towers], "--data", data,
             "--split", "paper", "--seed", str(seed), "--epochs", str(epochs),
             "--patience", str(patience or epochs), "--recipe", recipe, "--run-dir", run_dir,
             "--head-units", "--quiet"] + extra)


def claimed(run_dir):
    """Whether a live process claims ``run_dir`` (``<run_dir>.claim`` holds
    its pid); False for no claim or a stale one (its process has ended)."""
    try:
        with open(run_dir.rstrip(os.sep) + ".claim") as f:
            os.kill(int(f.read().strip() or 0), 0)
        return True
    except (OSError, ValueError):
        return False


def claim(run_dir):
    """Whether this process may train ``run_dir``: True unless another live
    process has claimed it (``claimed``), so that two
    of these commands started side by side share the runs instead of both
    training, then both publishing, the same one."""
    path = run_dir.rstrip(os.sep) + ".claim"
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    for _ in range(2):
        try:
            handle = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            if claimed(run_dir):  # (alive: its claim stands)
                return False
            try:  # (its process has ended: the claim is stale)
                os.remove(path)
            except FileNotFoundError:
                pass
            continue
        os.write(handle, str(os.getpid()).encode())
        os.close(handle)
        return True
    return False


#: The pairs of arms the protocol decides, as (A, B).
PAIRS = (("cpl-a", "baseline"), ("cpl-a-range", "baseline"), ("cpl-a", "cpl-a-range"))
#: The arms' names on the pages.
NAMES = {"baseline": "MTL-Baseline", "cpl-a": "MTL-CPL-A",
         "cpl-a-range": "MTL-CPL-A (range weights)"}


def sibling(name):
    """The script ``analyses/<name>.py`` as a module (imported once)."""
    folder = os.path.dirname(os.path.abspath(__file__))
    if folder not in sys.path:
        sys.path.insert(0, folder)
    return importlib.import_module(name)


def regenerate(page_path):
    """The committed ``<towers>/verdicts.md`` from verdicts.json beside it
    (``fair_fight_verdicts.regenerate``: the page's command is this script's)."""
    return sibling("fair_fight_verdicts").regenerate(page_path)


def parse(argv):
    """The command line's arguments, the plateau amendment's defaults filled
    in (``--plateau``: its paths relative to ``--home``, which runs the
    commands); exit 2 in one line when they do not hold."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--towers", choices=tuple(TOWERS), required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=PROTOCOL_SEEDS)
    parser.add_argument("--arms", nargs="+", choices=tuple(ARMS))
    parser.add_argument("--data")
    parser.add_argument("--epochs", type=int)
    parser.add_argument("--recipe", default="sound")
    parser.add_argument("--runs-dir")
    parser.add_argument("--out", default="paper_results/fair-fight")
    parser.add_argument("--plateau", action="store_true",
                        help="the amendment's runs (protocol-plateau.md): InceptionV3 "
                        "MTL-Baseline and MTL-CPL-A, patience 20, at most 200 epochs, trained "
                        "in --home, published into <out>/<towers>-plateau/")
    parser.add_argument("--home", help="with --plateau: where the dataset and run directories "
                        "are (--data and --runs-dir relative to it) and the commands run "
                        f"(default {PLATEAU['home']})")
    parser.add_argument("--dry-run", action="store_true", help="print the commands only")
    parser.add_argument("--verdicts", action="store_true",
                        help="train nothing: write <out>/<towers>/verdicts.md and .json from "
                        "the published runs")
    args = parser.parse_args(argv)
    if args.plateau and args.towers != PLATEAU["towers"]:
        parser.exit(2, f"fair_fight: the plateau amendment trains the {PLATEAU['towers']} "
                       f"towers only, not {args.towers}\n")
    if args.home and not args.plateau:
        parser.exit(2, "fair_fight: --home is the plateau runs' (--plateau)\n")
    plateau = PLATEAU if args.plateau else {}
    args.home = os.path.expanduser(args.home or plateau.get("home", "."))
    args.arms = args.arms or list(plateau.get("arms", ARMS))
    args.data = args.data or plateau.get("data", DATA)
    args.epochs = args.epochs or plateau.get("epochs", EPOCHS)
    args.patience = plateau.get("patience")
    args.runs_dir = args.runs_dir or plateau.get("runs_dir", "runs/fair-fight")
    args.folder = args.towers + ("-plateau" if args.plateau else "")
    if not os.path.isfile(os.path.join(args.home, args.data)):
        where = os.path.join(args.home, args.data)
        parser.exit(2, f"fair_fight: dataset not found: {where} (python -m "
                       "cpl_keras.data.generate --protocol cvgl --pairs 2000 --seed 0 "
                       f"--image-size 112 --out {where})\n")
    return args


def main(argv=None):
    args = parse(argv)
    if args.verdicts:
        from cpl_keras import cli

        command = cli.command_line("analyses/fair_fight.py", argv)
        page = sibling("fair_fight_verdicts")  # (analyses/fair_fight_verdicts.py)
        print(page.write_verdicts(args.folder, args.out, os.path.join(args.home, args.data),
                                  command, epochs=PLATEAU["equal_epochs"] if args.patience
                                  else page.EQUAL_EPOCHS))
        return 0
    starts = sibling("run_starts")  # (analyses/run_starts.py: each start's ledger)
    here = "" if args.home == "." else f"cd {shlex.quote(args.home)} && "
    train = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                         "train.py") if here else "train.py"
    for seed in args.seeds:
        for arm in args.arms:
            name = f"cvgl_{arm}-s{seed}"
            run_dir = os.path.join(args.runs_dir, args.towers, f"{arm}-s{seed}")
            record = os.path.join(args.out, args.folder, "runs", name)
            command = train_command(args.towers, arm, seed, args.data, args.epochs,
                                    args.recipe, run_dir, args.patience)
            if args.dry_run:
                print(here + shlex.join(["python", train] + command[1:]))
                continue
            if os.path.isdir(record):
                print(f"fair_fight: {record} published, skipped", flush=True)
                continue
            run_dir = os.path.join(args.home, run_dir) if here else run_dir
            if not claim(run_dir):
                print(f"fair_fight: {name} is being trained by another process, skipped",
                      flush=True)
                continue
            if args.patience:  # (the amendment's ledger of starts, before training)
                try:
                    starts.record_start(record, run_dir)
                except starts.LostTwice as lost:
                    print(f"fair_fight: {lost}", file=sys.stderr)
                    return 2
            print(f"fair_fight: training {name} ({args.folder}): {shlex.join(command)}",
                  flush=True)
            status = subprocess.call([sys.executable, train] + command[1:], cwd=args.home)
            if status:
                return status
            from cpl_keras.reproduce.jobs import publish_run

            publish_run(run_dir, record, [])
            if args.patience:
                starts.copy_into(record)
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/fair_fight.py")
