"""The collapsed pitch head: predicted against true pitch on the test pairs
of the InceptionV3 towers (2,000 pairs), MTL-CPL-A and MTL-Baseline, seed by
seed, the pairs on one output value marked: a figure.

    python analyses/collapsed_pitch.py             # paper_results/collapsed-pitch.{json,png}
    python analyses/collapsed_pitch.py --check     # recompute, compare with the JSON

The predictions are the committed table-row files of
``paper_results/inception-2000-ema/runs/`` (``verdicts.load_rows``). What
a collapsed pair is comes from ``analyses/collapsed_heads.py``
(``collapse``, the page ``paper_results/inception-2000-ablations/
collapsed-heads.md``): the pairs on the run's most common output value (to
1e-6 of it, relative), a value a working head, whose outputs differ from
pair to pair, does not share over many pairs. Where they are
``MIN_SHARE`` of the test pairs or more (that page's ``--min-share``) the
figure marks them. Per run the JSON holds the value, the pairs on it and
their share, the share of the pitch's absolute error they carry, the MAE on
them and on the others, the truth's range on them, and for MTL-CPL-A the
MAE of MTL-Baseline of the same seed on the same pairs. ``--check``
recomputes them from the committed predictions and fails (exit 1) on a
difference.
"""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from committed_numbers import check_or_write, parser, save  # noqa: E402

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FOLDER = os.path.join("paper_results", "inception-2000-ema")
#: (variant in the predictions files, table row); the second is the reference.
VARIANTS = (("cpl-a", "MTL-CPL-A"), ("baseline", "MTL-Baseline"))
COLUMN = "pitch"
#: The share of the test pairs on one value that the figure marks
#: (collapsed_heads.py's ``--min-share`` default).
MIN_SHARE = 0.05
#: The cells of ``collapsed_heads.collapse`` kept in the JSON, rounded.
FIELDS = ("value", "pairs", "share", "error_share", "mae_on", "mae_off", "truth_min",
          "truth_max", "others_inside", "reference_on", "reference_off")
COLOURS = {"MTL-CPL-A": "tab:red", "MTL-Baseline": "tab:blue"}
OUT = os.path.join(REPO, "paper_results", "collapsed-pitch")


def _analyses():
    """The sibling scripts this one reuses, imported as modules."""
    here = os.path.dirname(os.path.abspath(__file__))
    if here not in sys.path:
        sys.path.insert(0, here)
    import collapsed_heads
    import verdicts

    return collapsed_heads, verdicts


def _round(value):
    if isinstance(value, float):
        return round(value, 4)
    return value


def load():
    """``{row: {seed: (file, raw)}}``: the folder's predictions of both variants."""
    _, verdicts = _analyses()
    folder = os.path.join(REPO, FOLDER)
    out = {}
    for variant, row in VARIANTS:
        rows, name, files = verdicts.load_rows(folder, "cvgl", variant)
        if name != row:
            raise ValueError(f"{FOLDER}: {variant}'s predictions are of row {name}, not {row}")
        out[row] = {seed: (os.path.join(FOLDER, path), raw)
                    for (seed, raw), path in zip(rows.items(), files)}
    return out


def compute(data=None):
    collapsed_heads, _ = _analyses()
    from cpl_keras.evaluation.verdicts import COLUMN_PARAMETER

    data = data or load()
    name = COLUMN_PARAMETER[COLUMN]
    (_, row_a), (_, row_b) = VARIANTS
    runs = {}
    for row, seeds in data.items():
        runs[row] = {}
        for seed, (path, raw) in sorted(seeds.items()):
            reference = None
            if row == row_a and seed in data[row_b]:
                reference = data[row_b][seed][1]
                if not np.array_equal(reference["indices"], raw["indices"]):
                    raise ValueError(f"{path}: its test pairs are not {row_b}'s of seed {seed}")
            cell = collapsed_heads.collapse(raw, reference)[COLUMN]
            truth = np.asarray(raw["truth"][name], np.float64)
            error = np.abs(np.asarray(raw["pred"][name], np.float64) - truth)
            entry = {"file": path, "test_pairs": int(len(truth)),
                     "mae": _round(float(error.mean())),
                     "nmae": _round(float(error.mean() / np.abs(truth).mean())),
                     "marked": bool(cell["share"] >= MIN_SHARE)}
            entry.update({k: _round(cell[k]) for k in FIELDS if k in cell})
            runs[row][str(seed)] = entry
    return {"what": f"{COLUMN} (radians) on the test pairs of {FOLDER}: the pairs on the "
                    "run's most common output value (collapsed_heads.collapse), their share, "
                    "the share of the absolute error on them, the MAE on them and on the "
                    f"others (reference: {row_b}'s of the same seed on the same pairs)",
            "column": COLUMN, "min_share": MIN_SHARE, "runs": runs}


def plot(result, data, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cpl_keras.evaluation.verdicts import COLUMN_PARAMETER

    name = COLUMN_PARAMETER[result["column"]]
    rows = list(result["runs"])
    seeds = sorted({s for r in rows for s in result["runs"][r]}, key=int)
    fig, axes = plt.subplots(len(rows), len(seeds), figsize=(3.4 * len(seeds), 3.5 * len(rows)),
                             squeeze=False, sharex=True, sharey=True)
    truths = [np.asarray(raw["truth"][name]) for s in data.values() for _, raw in s.values()]
    preds = [np.asarray(raw["pred"][name]) for s in data.values() for _, raw in s.values()]
    low = min(min(t.min() for t in truths), min(p.min() for p in preds))
    high = max(max(t.max() for t in truths), max(p.max() for p in preds))
    pad = 0.04 * (high - low)
    span = (low - pad, high + pad)
    for i, row in enumerate(rows):
        for j, seed in enumerate(seeds):
            ax = axes[i, j]
            entry = result["runs"][row].get(seed)
            if entry is None:
                ax.set_visible(False)
                continue
            raw = data[row][int(seed)][1]
            truth = np.asarray(raw["truth"][name], np.float64)
            pred = np.asarray(raw["pred"][name], np.float64)
            on = np.zeros(len(truth), bool)
            if entry["marked"]:
                collapsed_heads, _ = _analyses()
                _, on = collapsed_heads.modal_value(pred)
            ax.plot(span, span, color="grey", lw=0.8, zorder=1)
            ax.scatter(truth[~on], pred[~on], s=6, color=COLOURS.get(row, "tab:grey"),
                       alpha=0.6, lw=0, zorder=2, label="other pairs")
            if on.any():
                ax.scatter(truth[on], pred[on], s=14, marker="x", color="black", lw=0.8,
                           zorder=3, label=f"on one value ({entry['value']:.3f})")
                caption = (f"{entry['pairs']} pairs ({entry['share']:.0%}) on "
                           f"{entry['value']:.3f},\n{entry['error_share']:.0%} of the error")
            elif entry["pairs"]:
                caption = f"{entry['pairs']} pairs ({entry['share']:.0%}) on one value"
            else:
                caption = "no two pairs on one value"
            ax.set_title(f"{row}, seed {seed}\n{caption}", fontsize=8)
            ax.text(0.97, 0.03, f"MAE {entry['mae']:.3f} rad", transform=ax.transAxes,
                    ha="right", va="bottom", fontsize=7)
            ax.set_xlim(span)
            ax.set_ylim(span)
            ax.set_aspect("equal")
            ax.grid(True, alpha=0.25)
            if on.any():
                ax.legend(fontsize=6, loc="upper left")
            if i == len(rows) - 1:
                ax.set_xlabel(f"true {result['column']} (rad)")
            if j == 0:
                ax.set_ylabel(f"predicted {result['column']} (rad)")
    fig.suptitle(f"InceptionV3 towers, 2,000 pairs: test pairs ({FOLDER})", fontsize=9)
    save(fig, path)


def main(argv=None):
    args = parser(__doc__).parse_args(argv)
    data = load()
    result = compute(data)
    return check_or_write("collapsed_pitch", OUT, result, check=args.check,
                          draw=lambda: plot(result, data, OUT + ".png"))


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/collapsed_pitch.py")
