"""The fair fight's runs (paper_results/fair-fight/protocol.md), one after
another, each published the moment it ends.

Every run trains under one recipe (``--recipe``, default ``sound``,
``cpl_keras.models.options.RECIPES``) for a fixed number of epochs with no
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
"""

from __future__ import annotations

import argparse
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


def train_command(towers, arm, seed, data, epochs, recipe, run_dir):
    """``train.py``'s arguments for one run of the protocol."""
    variant, extra = ARMS[arm]
    return (["train.py", "--variant", variant, "--backbone", TOWERS[towers], "--data", data,
             "--split", "paper", "--seed", str(seed), "--epochs", str(epochs),
             "--patience", str(epochs), "--recipe", recipe, "--run-dir", run_dir,
             "--head-units", "--quiet"] + extra)


def claim(run_dir):
    """Whether this process may train ``run_dir``: True unless another live
    process has claimed it (``<run_dir>.claim`` holds its pid), so that two
    of these commands started side by side share the runs instead of both
    training, then both publishing, the same one."""
    path = run_dir.rstrip(os.sep) + ".claim"
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    for _ in range(2):
        try:
            handle = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                with open(path) as f:
                    os.kill(int(f.read().strip() or 0), 0)  # (alive: its claim stands)
                return False
            except (OSError, ValueError):  # (its process has ended: the claim is stale)
                os.remove(path)
                continue
        os.write(handle, str(os.getpid()).encode())
        os.close(handle)
        return True
    return False


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--towers", choices=tuple(TOWERS), required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--arms", nargs="+", choices=tuple(ARMS), default=list(ARMS))
    parser.add_argument("--data", default=DATA)
    parser.add_argument("--epochs", type=int, default=EPOCHS)
    parser.add_argument("--recipe", default="sound")
    parser.add_argument("--runs-dir", default="runs/fair-fight")
    parser.add_argument("--out", default="paper_results/fair-fight")
    parser.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = parser.parse_args(argv)
    if not os.path.isfile(args.data):
        parser.exit(2, f"fair_fight: dataset not found: {args.data} (python -m "
                       "cpl_keras.data.generate --protocol cvgl --pairs 2000 --seed 0 "
                       f"--image-size 112 --out {args.data})\n")
    for seed in args.seeds:
        for arm in args.arms:
            name = f"cvgl_{arm}-s{seed}"
            run_dir = os.path.join(args.runs_dir, args.towers, f"{arm}-s{seed}")
            record = os.path.join(args.out, args.towers, "runs", name)
            command = train_command(args.towers, arm, seed, args.data, args.epochs,
                                    args.recipe, run_dir)
            if args.dry_run:
                print(shlex.join(["python"] + command))
                continue
            if os.path.isdir(record):
                print(f"fair_fight: {record} published, skipped", flush=True)
                continue
            if not claim(run_dir):
                print(f"fair_fight: {name} is being trained by another process, skipped",
                      flush=True)
                continue
            print(f"fair_fight: training {name} ({args.towers}): {shlex.join(command)}",
                  flush=True)
            status = subprocess.call([sys.executable] + command)
            if status:
                return status
            from cpl_keras.reproduce.jobs import publish_run

            publish_run(run_dir, record, [])
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/fair_fight.py")
