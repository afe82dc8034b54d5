"""MTL-CPL-A's and MTL-Baseline's validation curves, seed by seed, for the
InceptionV3 and the compact towers on 2,000 pairs: a figure.

    python analyses/validation_curves.py           # paper_results/validation-curves.{json,png}
    python analyses/validation_curves.py --check   # recompute, compare with the JSON

Each run is a committed run directory of ``paper_results/inception-2000-ema/``
or ``paper_results/compact-2000-ema/`` (its ``config.json`` names the variant
and the seed). Its curve is ``val_nmae`` of its ``log.csv`` epoch by epoch,
the monitor that early stopping and the kept epoch follow (the sum over the
ten parameters of the validation MAE over the training split's mean |y|);
its kept epoch (``best_epoch``) and its last epoch come from ``config.json``.
Beside the curves, per seed: both variants' ``val_nmae`` at MTL-CPL-A's kept
epoch (the same epoch for both; ``null`` where MTL-Baseline stopped before it)
and MTL-Baseline's lowest up to that epoch. The numbers plotted are written beside the
figure as JSON; ``--check`` recomputes them from the committed logs and fails
(exit 1) on a difference.
"""

from __future__ import annotations

import csv
import glob
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from committed_numbers import check_or_write, parser, save  # noqa: E402

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The towers, in the figure's order: (label, folder under paper_results).
SETTINGS = (("InceptionV3", "inception-2000-ema"), ("compact", "compact-2000-ema"))
#: The variants drawn: (variant in config.json, table row).
VARIANTS = (("cpl-a", "MTL-CPL-A"), ("baseline", "MTL-Baseline"))
MONITOR = "val_nmae"
COLOURS = {"MTL-CPL-A": "tab:red", "MTL-Baseline": "tab:blue"}
LINESTYLES = ("-", "--", ":", "-.")
OUT = os.path.join(REPO, "paper_results", "validation-curves")


def read_curve(run_dir):
    """``[(epoch, val_nmae), ...]`` from a run's log.csv."""
    with open(os.path.join(run_dir, "log.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or MONITOR not in rows[0]:
        raise ValueError(f"{run_dir}/log.csv: no {MONITOR} column")
    return [(int(r["epoch"]), float(r[MONITOR])) for r in rows]


def run_entry(run_dir):
    """One run's curve, kept and last epoch (``ValueError`` where its log and
    config.json disagree on the epochs)."""
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    curve = read_curve(run_dir)
    epochs = [e for e, _ in curve]
    if epochs != list(range(1, config["epochs_run"] + 1)):
        raise ValueError(f"{run_dir}: log.csv's epochs are not 1 to epochs_run "
                         f"({config['epochs_run']})")
    values = dict(curve)
    kept = config["best_epoch"]
    lowest = epochs[int(np.argmin([v for _, v in curve]))]
    return {"run": os.path.relpath(run_dir, REPO),
            "curve": [[e, round(v, 5)] for e, v in curve],
            "kept_epoch": kept, "kept_value": round(values[kept], 5),
            "lowest_epoch": lowest, "last_epoch": epochs[-1],
            "last_value": round(values[epochs[-1]], 5), "stopped": config.get("stopped")}


def towers_entry(folder):
    """``{"variants": {row: {seed: run}}, "at_cpl_a_kept_epoch": {seed: ...}}``."""
    rows = dict(VARIANTS)
    runs = {row: {} for row in rows.values()}
    for path in sorted(glob.glob(os.path.join(folder, "runs", "*", "config.json"))):
        with open(path) as f:
            config = json.load(f)
        if config.get("variant") in rows:
            seed = str(config["seed"])
            row = rows[config["variant"]]
            if seed in runs[row]:
                raise ValueError(f"{folder}: two {row} runs of seed {seed}")
            runs[row][seed] = run_entry(os.path.dirname(path))
    a, b = (row for _, row in VARIANTS)
    equal = {}
    for seed in sorted(set(runs[a]) & set(runs[b]), key=int):
        epoch = runs[a][seed]["kept_epoch"]
        curve_b = [v for e, v in runs[b][seed]["curve"] if e <= epoch]
        equal[seed] = {"epoch": epoch, a: runs[a][seed]["kept_value"],
                       b: curve_b[-1] if len(curve_b) == epoch else None,
                       f"{b}, lowest by then": min(curve_b) if curve_b else None}
    return {"folder": os.path.relpath(folder, REPO), "variants": runs,
            "at_cpl_a_kept_epoch": equal}


def compute():
    return {"what": f"validation {MONITOR} (sum over the ten parameters of validation MAE "
                    "over the training split's mean |y|) per epoch, per towers, variant and "
                    "seed; kept epoch = config.json's best_epoch",
            "monitor": MONITOR,
            "towers": {label: towers_entry(os.path.join(REPO, "paper_results", folder))
                       for label, folder in SETTINGS}}


def plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, LogLocator


    towers = result["towers"]
    fig, axes = plt.subplots(1, len(towers), figsize=(5.5 * len(towers), 4.3))
    axes = np.atleast_1d(axes)
    seeds = sorted({s for t in towers.values() for v in t["variants"].values() for s in v},
                   key=int)
    for ax, (label, entry) in zip(axes, towers.items()):
        for row, runs in entry["variants"].items():
            for seed, run in runs.items():
                epochs, values = np.asarray(run["curve"], np.float64).T
                style = LINESTYLES[seeds.index(seed) % len(LINESTYLES)]
                ax.plot(epochs, values, color=COLOURS[row], ls=style, lw=1.2)
                ax.plot(run["kept_epoch"], run["kept_value"], "o", color=COLOURS[row], ms=6,
                        mec="black", mew=0.6)
                ax.plot(run["last_epoch"], run["last_value"], "x", color=COLOURS[row], ms=7,
                        mew=1.5)
        ax.set_yscale("log")
        ax.yaxis.set_minor_locator(LogLocator(subs=(2, 3, 5)))
        for axis in (ax.yaxis.set_major_formatter, ax.yaxis.set_minor_formatter):
            axis(FuncFormatter(lambda y, _: f"{y:g}"))
        ax.set_xlim(left=0)
        ax.grid(True, which="both", alpha=0.25)
        ax.set_title(f"{label} towers, 2,000 pairs ({entry['folder']})", fontsize=9)
        ax.set_xlabel("epoch")
        ax.set_ylabel(f"validation {result['monitor']} (log scale)")
    handles = ([Line2D([], [], color=c, lw=2, label=row) for row, c in COLOURS.items()]
               + [Line2D([], [], color="grey", ls=LINESTYLES[i % len(LINESTYLES)],
                         label=f"seed {s}") for i, s in enumerate(seeds)]
               + [Line2D([], [], color="grey", marker="o", ls="", mec="black",
                         label="kept epoch"),
                  Line2D([], [], color="grey", marker="x", ls="", mew=1.5,
                         label="last epoch (early stop)")])
    axes[-1].legend(handles=handles, fontsize=8, loc="upper right")
    save(fig, path)


def main(argv=None):
    args = parser(__doc__).parse_args(argv)
    result = compute()
    return check_or_write("validation_curves", OUT, result, check=args.check,
                          draw=lambda: plot(result, OUT + ".png"))


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/validation_curves.py")
