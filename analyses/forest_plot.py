"""MTL-CPL-A's test NMAE over MTL-Baseline's, setting by setting and column
by column, with a paired bootstrap interval: the README's figure.

    python analyses/forest_plot.py                 # paper_results/forest.{json,png}
    python analyses/forest_plot.py --check         # recompute, compare with the JSON

Each setting is a committed folder whose table-row predictions files hold
both variants over the same seeds (``verdicts.load_rows``). Per column the
ratio is the mean over the seeds of MTL-CPL-A's NMAE over the mean of
MTL-Baseline's (NMAE = MAE / mean|y| on each seed's test pairs, as the
tables); its interval resamples every seed's test pairs (the same pairs for
both variants) ``--resamples`` times and takes the 2.5 and 97.5
percentiles. Below 1: MTL-CPL-A lower. The numbers plotted are written
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
#: The settings, in the README's order: (label, folder under paper_results).
SETTINGS = (("compact, 8,000 pairs", "cpu-8000"),
            ("compact, 2,000 pairs", "compact-2000-ema"),
            ("InceptionV3, 2,000 pairs", "inception-2000-ema"))
COLUMNS = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "pitch")
PARAMETER = dict(zip(COLUMNS, ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty",
                               "tz", "pitch")))
OUT = os.path.join(REPO, "paper_results", "forest")


def _nmae(truth, pred):
    return np.mean(np.abs(pred - truth), axis=-1) / np.mean(np.abs(truth), axis=-1)


def setting_ratios(folder, resamples, seed=0):
    """``{column: {"ratio", "low", "high", "seeds"}}`` for one folder."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import verdicts as page

    rows_a, _, _ = page.load_rows(folder, "cvgl", "cpl-a")
    rows_b, _, _ = page.load_rows(folder, "cvgl", "baseline")
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
                       "high": round(float(np.percentile(boot, 97.5)), 4), "seeds": seeds}
    return out


def compute(resamples):
    return {"what": "MTL-CPL-A's test NMAE over MTL-Baseline's (mean over seeds), 95 % "
                    "paired bootstrap interval over each seed's test pairs",
            "resamples": resamples,
            "settings": {label: {"folder": f"paper_results/{folder}",
                                 "columns": setting_ratios(
                                     os.path.join(REPO, "paper_results", folder), resamples)}
                         for label, folder in SETTINGS}}


def plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
                fmt="o", ms=3, capsize=2)
    ax.axvline(1.0, color="grey", lw=1)
    ax.set_xscale("log")
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
