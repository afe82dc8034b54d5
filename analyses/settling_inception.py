"""The fair fight's settling rule where it was not checked: InceptionV3
MTL-Baseline under the recipe against under the old defaults, from the
committed predictions (no dataset, no training).

    python analyses/settling_inception.py    # paper_results/fair-fight/settling-inception.md

The recipe was settled on the compact towers (``fair-fight/settling.md``):
it stood because MTL-Baseline under it was no worse than under the defaults.
Here the same question with the paper's towers, over seeds 0-2: A is the
fair fight's MTL-Baseline (``--recipe sound``, 50 epochs), B the
``inception-2000-ema`` MTL-Baseline (the defaults, early stopping at
patience 5), trained on the same dataset file with the same split and seeds,
so scored on the same test pairs. Both of the protocol's rules, Welch's p and
the rig bootstrap (``cpl_keras.evaluation.verdicts``), and per column the
ratio of the means. For context: it changes nothing of the protocol, and the
two sides differ in training length as well as in the recipe.
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RECIPE = os.path.join("paper_results", "fair-fight", "inception", "runs")
DEFAULTS = os.path.join("paper_results", "inception-2000-ema")
OUT = os.path.join("paper_results", "fair-fight", "settling-inception.md")
COMMAND = "python analyses/settling_inception.py"
SEEDS = (0, 1, 2)
RESAMPLES = 2000


def compute(resamples=RESAMPLES):
    """``(verdicts, epochs)``: the column verdicts of A (recipe) against B
    (defaults), and each run's (side, seed, epochs run, kept epoch)."""
    import fair_fight_rows
    import verdicts as page

    from cpl_keras import runs
    from cpl_keras.evaluation import verdicts as rules

    recipe = fair_fight_rows.rows(os.path.join(REPO, RECIPE), "baseline", SEEDS)
    defaults, _, _ = page.load_rows(os.path.join(REPO, DEFAULTS), "cvgl", "baseline")
    found = rules.compare(recipe, {s: defaults[s] for s in SEEDS}, resamples=resamples,
                          bootstrap_seed=0)
    epochs = []
    for side, folder in (("recipe", os.path.join(RECIPE, "cvgl_baseline-s{}")),
                         ("defaults", os.path.join(DEFAULTS, "runs", "cvgl_baseline-s{}"))):
        for seed in SEEDS:
            config = runs.read_run_config(os.path.join(REPO, folder.format(seed)))
            epochs.append((side, seed, config.epochs_run, config.best_epoch))
    return found, epochs


def render(found, epochs):
    import verdicts as page

    from cpl_keras import files

    md = [files.generated_line(COMMAND), "",
          "# The settling rule with the paper's towers: InceptionV3 MTL-Baseline, recipe "
          "against defaults", "",
          " ".join(__doc__.split("\n\n")[2].split()).replace("``", "`"), "",
          "| side | seed | epochs (kept) |", "|---|---|---|"]
    md += [f"| {side} | {seed} | {run} ({kept}) |" for side, seed, run, kept in epochs]
    md += [""] + page.pair_markdown("MTL-Baseline, recipe", "MTL-Baseline, defaults", found)
    md += ["Ratio of the means over the seeds, recipe / defaults (above 1: worse under the "
           "recipe):", "", "| " + " | ".join(v.column for v in found) + " |",
           "|" + "---|" * len(found),
           "| " + " | ".join(f"{v.mean_a / v.mean_b:.2f}" for v in found) + " |", ""]
    return "\n".join(md)


def regenerate(page_path):
    """The committed page, again from the committed predictions."""
    return render(*compute())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join(REPO, OUT))
    args = parser.parse_args(argv)
    from cpl_keras import files

    files.write_text(args.out, render(*compute()))
    print(args.out)
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/settling_inception.py")
