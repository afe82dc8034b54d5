"""MTL-CPL-A's test NMAE over MTL-Baseline's, setting by setting and column
by column, with a paired bootstrap interval: the README's figure.

    python analyses/forest_plot.py                 # paper_results/forest.{json,png}
    python analyses/forest_plot.py --check         # recompute, compare with the JSON

Each setting is a committed folder: one whose table-row predictions files
hold both variants over the same seeds (``verdicts.load_rows``), or the fair
fight's published runs with their test pairs' truths (``fair_fight_rows``).
The early-stopping InceptionV3 comparison (``inception-2000-ema``: patience
5 stopped the two variants after unequal lengths) is superseded by the fair
fight and left out. The fair fight's InceptionV3 runs to a plateau
(``fair-fight/inception-plateau``) join the figure once all their seeds are
published (``WHEN_PUBLISHED``). Per column the
ratio is the mean over the seeds of MTL-CPL-A's NMAE over the mean of
MTL-Baseline's (NMAE = MAE / mean|y| on each seed's test pairs, as the
tables); its interval resamples every seed's test pairs (the same pairs for
both variants) ``--resamples`` times and takes the 2.5 and 97.5
percentiles; each seed's own ratio is drawn beside it (the seeds of a
setting can disagree, which the interval over test pairs does not show).
Below 1: MTL-CPL-A lower. The numbers plotted are written
beside the figure as JSON; ``--check`` recomputes them from the committed
predictions and fails (exit 1) on a difference.
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from committed_numbers import check_or_write  # noqa: E402

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The settings, in the README's order: (label, folder under paper_results,
#: how its rows are read: "rows" table-row predictions, "fair-fight" records).
SETTINGS = (("compact, 8,000 pairs", "cpu-8000", "rows"),
            ("compact, 2,000 pairs", "compact-2000-ema", "rows"),
            ("fair fight, compact, 50 epochs", "fair-fight/compact", "fair-fight"),
            ("fair fight, InceptionV3, 50 epochs", "fair-fight/inception", "fair-fight"))
#: Settings drawn once every seed of both variants is published: the fair
#: fight's InceptionV3 runs to a plateau (fair-fight/protocol-plateau.md),
#: below the 50-epoch row they continue.
WHEN_PUBLISHED = (("fair fight, InceptionV3, plateau", "fair-fight/inception-plateau",
                   "fair-fight"),)
#: The seeds a setting of WHEN_PUBLISHED needs of each variant.
SEEDS = (0, 1, 2)
COLUMNS = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "pitch")
PARAMETER = dict(zip(COLUMNS, ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty",
                               "tz", "pitch")))
RESULTS = os.path.join(REPO, "paper_results")
OUT = os.path.join(RESULTS, "forest")


def _nmae(truth, pred):
    return np.mean(np.abs(pred - truth), axis=-1) / np.mean(np.abs(truth), axis=-1)


def load(folder, kind):
    """``(rows_a, rows_b)``: MTL-CPL-A's and MTL-Baseline's ``{seed: raw}``."""
    if kind == "fair-fight":
        import fair_fight_rows

        runs = os.path.join(folder, "runs")
        return fair_fight_rows.rows(runs, "cpl-a"), fair_fight_rows.rows(runs, "baseline")
    import verdicts as page

    return (page.load_rows(folder, "cvgl", "cpl-a")[0],
            page.load_rows(folder, "cvgl", "baseline")[0])


def setting_ratios(folder, resamples, seed=0, kind="rows"):
    """``{column: {"ratio", "low", "high", "seeds"}}`` for one folder."""
    rows_a, rows_b = load(folder, kind)
    seeds = sorted(set(rows_a) & set(rows_b))
    rng = np.random.default_rng(seed)
    draws = {s: rng.integers(0, len(rows_a[s]["indices"]), (resamples,
                                                            len(rows_a[s]["indices"])))
             for s in seeds}
    out = {}
    for column in COLUMNS:
        name = PARAMETER[column]
        point_a, point_b, boot_a, boot_b = [], [], [], []
        for s in seeds:
            a, b = rows_a[s], rows_b[s]
            if not np.array_equal(a["indices"], b["indices"]):
                raise ValueError(f"{folder}: seed {s}'s rows have different test pairs")
            truth = np.asarray(a["truth"][name], np.float64)
            pred_a = np.asarray(a["pred"][name], np.float64)
            pred_b = np.asarray(b["pred"][name], np.float64)
            point_a.append(_nmae(truth, pred_a))
            point_b.append(_nmae(truth, pred_b))
            index = draws[s]
            boot_a.append(_nmae(truth[index], pred_a[index]))
            boot_b.append(_nmae(truth[index], pred_b[index]))
        ratio = np.mean(point_a) / np.mean(point_b)
        boot = np.mean(boot_a, axis=0) / np.mean(boot_b, axis=0)
        out[column] = {"ratio": round(float(ratio), 4),
                       "low": round(float(np.percentile(boot, 2.5)), 4),
                       "high": round(float(np.percentile(boot, 97.5)), 4), "seeds": seeds,
                       "per_seed": [round(float(a / b), 4) for a, b in zip(point_a, point_b)]}
    return out


def settings(root):
    """SETTINGS, then each of WHEN_PUBLISHED whose records under ``root``
    (a paper_results folder) hold both variants for every one of SEEDS."""
    def published(folder):
        return all(os.path.isdir(os.path.join(root, folder, "runs", f"cvgl_{arm}-s{seed}"))
                   for arm in ("cpl-a", "baseline") for seed in SEEDS)

    return SETTINGS + tuple(s for s in WHEN_PUBLISHED if published(s[1]))


def compute(resamples, root=RESULTS):
    return {"what": "MTL-CPL-A's test NMAE over MTL-Baseline's (mean over seeds), 95 % "
                    "paired bootstrap interval over each seed's test pairs",
            "resamples": resamples,
            "settings": {label: {"folder": f"paper_results/{folder}",
                                 "columns": setting_ratios(
                                     os.path.join(root, folder), resamples, kind=kind)}
                         for label, folder, kind in settings(root)}}


def plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    labels, ratios, lows, highs = [], [], [], []
    for setting, entry in result["settings"].items():
        for column, cell in entry["columns"].items():
            labels.append(f"{setting}: {column}")
            ratios.append(cell["ratio"])
            lows.append(cell["low"])
            highs.append(cell["high"])
    y = np.arange(len(labels))[::-1]
    fig, ax = plt.subplots(figsize=(7, 0.24 * len(labels) + 1.2))
    ax.errorbar(ratios, y, xerr=[np.subtract(ratios, lows), np.subtract(highs, ratios)],
                fmt="o", ms=3, capsize=2, label="mean over the seeds, 95 % interval over "
                "test pairs")
    per_seed = [(cell["per_seed"], row) for row, cell in zip(y, (
        cell for entry in result["settings"].values() for cell in entry["columns"].values()))]
    ax.plot([r for seeds, _ in per_seed for r in seeds],
            [row for seeds, row in per_seed for _ in seeds], "x", ms=3, color="grey",
            label="each seed")
    ax.legend(fontsize=7, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2,
              frameon=False)
    ax.axvline(1.0, color="grey", lw=1)
    for boundary in range(len(COLUMNS), len(labels), len(COLUMNS)):  # (between settings)
        ax.axhline(len(labels) - boundary - 0.5, color="lightgrey", lw=0.8)
    ax.set_xscale("log")
    ticks = [t for t in (0.1, 0.2, 0.3, 0.5, 1, 2, 3, 5, 10)
             if min(ax.get_xlim()) <= t <= max(ax.get_xlim())]
    ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_yticks(y, labels, fontsize=7)
    ax.set_xlabel("MTL-CPL-A NMAE / MTL-Baseline NMAE (below 1: MTL-CPL-A lower)")
    fig.tight_layout()
    fig.savefig(path, dpi=120, metadata={"Software": None})
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resamples", type=int, default=1000)
    parser.add_argument("--check", action="store_true",
                        help="recompute and compare with the committed JSON (exit 1 if not)")
    args = parser.parse_args(argv)
    result = compute(args.resamples)
    return check_or_write("forest_plot", OUT, result, check=args.check,
                          draw=lambda: plot(result, OUT + ".png"))


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/forest_plot.py")
