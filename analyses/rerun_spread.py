"""How far apart two trainings of one seed land, and how many of the
"lower on N of 10" columns differ by more than twice that.

    python analyses/rerun_spread.py            # paper_results/spread.{json,md}
    python analyses/rerun_spread.py --check    # recompute, compare with the JSON

A verdict's columns are decided by the spread over seeds and a paired
bootstrap of the test pairs; neither holds the spread between two trainings
of the same seed, settings and data (a different state of the code, a
resumed run). This page measures that spread where a rerun exists, per
variant and column, as |NMAE(rerun) - NMAE(published)| on the same test
pairs:

- compact towers, the defaults: MTL-CPL-A and MTL-Baseline seed 0 of
  compact-2000-ema, each rerun once
  (``inception-2000-ablations/runs/compact_*-gradients-s0``);
- compact towers, the fair fight's recipe: its MTL-CPL-A and MTL-Baseline
  seed 0, each rerun once by the same command, stopped by SIGTERM mid-way
  and resumed (``fair-fight/compact-rerun/runs/``);
- InceptionV3: MTL-Baseline seed 0 of inception-2000-ema, rerun once
  (``cvgl_baseline-gradients-s0``). No InceptionV3 MTL-CPL-A was rerun to
  the same length; what is known is validation: the patience-20 training
  (d) of the same settings against the published run's log, at the
  published run's kept epoch and the largest over the kept epoch +-
  ``WINDOW`` (the same is given for MTL-Baseline, to set the two kinds
  side by side).

Each variant has its own spread per column: its test rerun's, or for
InceptionV3's MTL-CPL-A its validation difference at the kept epoch. For
every committed comparison of MTL-CPL-A with MTL-Baseline (its
verdicts.json; for the one-seed InceptionV3 pairs, at 8,000 pairs and with
patience 20, their gaps.json, decided by the paired bootstrap alone), each
decided column is counted as beyond twice the spread or not by ``RULE``:
|mean A - mean B| over the seeds against twice the larger of the two
variants' own spreads for its towers and training (twice the larger is at
least their sum, so the more cautious rule). For caution the page also
counts them against each variant's widest spread with its towers (its
largest over every training measured, and InceptionV3 MTL-CPL-A's
validation window). Two trainings of one seed by the same code, uninterrupted, are
identical on this machine (the fair fight's settling,
``fair-fight/settling.md``), so the spread measured here is that of code
changes and resumes between trainings, not of the arithmetic.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from committed_numbers import check_or_write  # noqa: E402

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(REPO, "paper_results")
OUT = os.path.join(RESULTS, "spread")
COMMAND = "python analyses/rerun_spread.py"
COLUMNS = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "pitch")
PARAMETER = dict(zip(COLUMNS, ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty",
                               "tz", "pitch")))
ABLATIONS = "inception-2000-ablations/runs"
FIGHT = "fair-fight/compact/runs"
FIGHT_RERUNS = "fair-fight/compact-rerun/runs"
#: Test-pair reruns: (towers, training, variant, published, rerun's run directory, how);
#: published is a table row (``.npz``, its truths inside) or a fair-fight record (no
#: truths: joined to them by ``fair_fight_rows``).
GRADIENTS = "a later state of the code, with --term-gradients"
RESUMED = "the same code, stopped by SIGTERM in epoch 23 and resumed"
RECOMPILED = "the same code, compiled by XLA at optimisation level 0"
RERUNS = (
    ("compact", "defaults", "MTL-CPL-A", "compact-2000-ema/runs/cvgl_cpl-a-s0_predictions.npz",
     f"{ABLATIONS}/compact_cpl-a-gradients-s0", GRADIENTS),
    ("compact", "defaults", "MTL-Baseline",
     "compact-2000-ema/runs/cvgl_baseline-s0_predictions.npz",
     f"{ABLATIONS}/compact_baseline-gradients-s0", GRADIENTS),
    ("compact", "recipe", "MTL-CPL-A", f"{FIGHT}/cvgl_cpl-a-s0", f"{FIGHT_RERUNS}/cvgl_cpl-a-s0",
     RESUMED),
    ("compact", "recipe", "MTL-Baseline", f"{FIGHT}/cvgl_baseline-s0",
     f"{FIGHT_RERUNS}/cvgl_baseline-s0", RESUMED),
    ("compact", "recipe", "MTL-CPL-A", f"{FIGHT}/cvgl_cpl-a-s0",
     f"{FIGHT_RERUNS}/cvgl_cpl-a-o0-s0", RECOMPILED),
    ("compact", "recipe", "MTL-Baseline", f"{FIGHT}/cvgl_baseline-s0",
     f"{FIGHT_RERUNS}/cvgl_baseline-o0-s0", RECOMPILED),
    ("InceptionV3", "defaults", "MTL-Baseline",
     "inception-2000-ema/runs/cvgl_baseline-s0_predictions.npz",
     f"{ABLATIONS}/cvgl_baseline-gradients-s0", GRADIENTS),
)
TRAINING = {"defaults": "the defaults (2,000 pairs, EMA)", "recipe": "the fair fight's recipe"}
#: Validation reruns (InceptionV3): (variant, published log, other training's log).
VALIDATION = (
    ("MTL-CPL-A", "inception-2000-ema/runs/cvgl_cpl-a-s0",
     f"{ABLATIONS}/cvgl_cpl-a-patience20-s0"),
    ("MTL-Baseline", "inception-2000-ema/runs/cvgl_baseline-s0",
     f"{ABLATIONS}/cvgl_baseline-gradients-s0"),
)
#: Epochs either side of the kept one over which the validation window is taken.
WINDOW = 3
#: The comparisons counted: (label, (towers, training) whose spreads it takes, verdicts.json).
COMPARISONS = (
    ("compact, 8,000 pairs", ("compact", "defaults"), "cpu-8000/verdicts.json"),
    ("compact, 2,000 pairs", ("compact", "defaults"), "compact-2000-ema/verdicts.json"),
    ("InceptionV3, 2,000 pairs", ("InceptionV3", "defaults"),
     "inception-2000-ema/verdicts.json"),
    ("fair fight, compact", ("compact", "recipe"), "fair-fight/compact/verdicts.json"),
    ("fair fight, InceptionV3", ("InceptionV3", "defaults"),
     "fair-fight/inception/verdicts.json"),
    ("InceptionV3, 8,000 pairs, seed 0, 12 epochs", ("InceptionV3", "defaults"),
     "inception-8000/gaps.json#InceptionV3, 8,000 pairs, averaged weights, 12 epochs"),
    ("InceptionV3, 2,000 pairs, seed 0, both patience 20 (ablation (d))",
     ("InceptionV3", "defaults"),
     "inception-2000-ablations/patience20-gaps.json#against MTL-Baseline with patience 20"),
)
PAIR = "MTL-CPL-A vs MTL-Baseline"
VARIANTS = ("MTL-CPL-A", "MTL-Baseline")
#: The rule: a decided column is beyond when its gap exceeds twice the larger of
#: the two variants' own spreads (2 max(a, b) >= a + b: the more cautious of the two).
RULE = "gap > 2 * max(spread of MTL-CPL-A, spread of MTL-Baseline), per column"


def _nmae(truth, pred):
    return float(np.mean(np.abs(pred - truth)) / np.mean(np.abs(truth)))


def _record(path):
    """``(indices, {parameter: truth}, {parameter: prediction})`` of a published
    record: a table row's predictions file, or a fair-fight run directory."""
    from cpl_keras import prediction_files

    if path.endswith(".npz"):
        raw = prediction_files.load(os.path.join(RESULTS, path)).raw
        return (np.asarray(raw.indices), raw.truth,
                {k: np.asarray(v, np.float64) for k, v in raw.pred.items()})
    import fair_fight_rows

    folder, name = os.path.split(os.path.join(RESULTS, path))
    (raw,) = fair_fight_rows.rows(folder, name[len("cvgl_"):].rsplit("-s", 1)[0],
                                  seeds=[int(name.rsplit("-s", 1)[1])]).values()
    return np.asarray(raw["indices"]), raw["truth"], raw["pred"]


def test_spread(published, rerun):
    """``{column: |NMAE(rerun) - NMAE(published)|}`` on the published row's test pairs."""
    from cpl_keras import prediction_files

    indices, truths, preds = _record(published)
    stored = os.path.join(RESULTS, rerun, "predictions")
    (path,) = [os.path.join(stored, f) for f in sorted(os.listdir(stored))]
    with np.load(path, allow_pickle=False) as data:
        stored_names = [str(n) for n in data["outputs"]]
    outputs = prediction_files.read_run_outputs(path, indices, stored_names)
    out = {}
    for column in COLUMNS:
        name = PARAMETER[column]
        truth = np.asarray(truths[name], np.float64)
        out[column] = abs(_nmae(truth, outputs[name]) - _nmae(truth, preds[name]))
    return out


def _log(run):
    folder, name = os.path.split(os.path.join(RESULTS, run))
    with open(os.path.join(folder, name + "_log.csv"), newline="") as f:
        return {int(row["epoch"]): row for row in csv.DictReader(f)}


def validation_spread(published, other):
    """The kept epoch of ``published``, ``{column: |val NMAE difference|}`` there, and
    per column the largest such difference over the kept epoch +- ``WINDOW``."""
    with open(os.path.join(RESULTS, published, "config.json")) as f:
        epoch = int(json.load(f)["best_epoch"])
    a, b = _log(published), _log(other)

    def gap(e, c):
        key = f"val_nmae_{PARAMETER[c]}"
        return abs(float(a[e][key]) - float(b[e][key]))

    near = [e for e in range(epoch - WINDOW, epoch + WINDOW + 1) if e in a and e in b]
    return epoch, {c: gap(epoch, c) for c in COLUMNS}, \
        {c: max(gap(e, c) for e in near) for c in COLUMNS}


def _pair_columns(verdicts, setting=None):
    """``[(column, mean_a, mean_b, verdict)]`` of the MTL-CPL-A / MTL-Baseline pair."""
    if setting is not None:  # (analyses/variant_gaps.py's pages: one seed, the bootstrap)
        sides = {"lower": "A lower", "higher": "B lower"}
        return [(column, r["a"], r["b"], sides.get(r["answer"], "undecided"))
                for column, r in verdicts[setting]["columns"].items()]
    if "splits" in verdicts:  # (analyses/verdicts.py's pages)
        rows = verdicts["splits"]["cvgl"]["pairs"][PAIR]["columns"]
    else:  # (the fair fight's)
        rows = verdicts["pairs"][PAIR]["detail"]
    return [(r["column"], r["mean_a"], r["mean_b"], r["verdict"]) for r in rows]


def own_spreads(reruns, validation):
    """``{"<towers>, <training>": {variant: {column: spread}, "from": {variant: what}}}``:
    each variant's own spread, per column the largest of its test reruns, or
    (InceptionV3's MTL-CPL-A, never rerun on the test pairs) its validation
    difference at the kept epoch."""
    out = {}
    for r in reruns:
        group = out.setdefault(f"{r['towers']}, {r['training']}", {"from": {}})
        mine = group.setdefault(r["variant"], dict(r["columns"]))
        for c in COLUMNS:
            mine[c] = max(mine[c], r["columns"][c])
        group["from"].setdefault(r["variant"], []).append(r["rerun"])
    for group in out.values():
        group["from"] = {v: ("test pairs, the largest of " if len(f) > 1 else "test pairs, ")
                         + " and ".join(f) for v, f in group["from"].items()}
    for r in validation:
        group = out[f"{r['towers']}, defaults"]
        if r["variant"] not in group:
            group[r["variant"]] = r["columns"]
            group["from"][r["variant"]] = f"validation at epoch {r['epoch']}, {r['other']}"
    return out


def beyond(gap, spreads, column):
    """The rule (``RULE``): the gap beyond twice the larger own spread."""
    return bool(gap > 2 * max(spreads[v][column] for v in VARIANTS))


def widest_spreads(reruns, validation):
    """``{towers: {variant: {column: spread}}}``: each variant's widest spread with its
    towers, per column the largest of its test reruns under any training and (for
    InceptionV3's MTL-CPL-A) of its validation window."""
    out = {}
    for r in reruns:
        mine = out.setdefault(r["towers"], {}).setdefault(r["variant"], dict(r["columns"]))
        for c in COLUMNS:
            mine[c] = max(mine[c], r["columns"][c])
    for r in validation:
        mine = out[r["towers"]].setdefault(r["variant"], dict(r["window"]))
        for c in COLUMNS:
            mine[c] = max(mine[c], r["window"][c])
    return out


def _comparison(label, group, page, spreads, widest):
    page, _, setting = page.partition("#")
    with open(os.path.join(RESULTS, page)) as f:
        verdicts = json.load(f)
    rows = _pair_columns(verdicts, setting or None)
    seeds = verdicts["pairs"][PAIR]["seeds"] if "pairs" in verdicts else [0, 1, 2]
    # (a fair fight still in progress: its page names the protocol's seeds)
    if seeds != verdicts.get("protocol_seeds", seeds):
        label = f"{label}, seeds {', '.join(map(str, seeds))} so far"
    spread = spreads[", ".join(group)]
    decided = {}
    for column, mean_a, mean_b, verdict in rows:
        if verdict == "undecided":
            continue
        gap = abs(mean_a - mean_b)
        decided[column] = {"verdict": verdict, "gap": round(gap, 4),
                           "beyond_twice_spread": beyond(gap, spread, column)}
        decided[column]["beyond_twice_widest"] = beyond(gap, widest[group[0]], column)
    counts = {side: {"decided": sum(1 for d in decided.values() if d["verdict"] == side),
                     "beyond": sum(1 for d in decided.values()
                                   if d["verdict"] == side and d["beyond_twice_spread"]),
                     "beyond_widest": sum(1 for d in decided.values()
                                          if d["verdict"] == side and d["beyond_twice_widest"])}
              for side in ("A lower", "B lower")}
    return {"setting": label, "spreads": ", ".join(group), "verdicts": page,
            "rule": "the paired bootstrap of one seed" if setting else
                    f"the seed spread and the paired bootstrap, {len(seeds)} seeds",
            "counts": counts, "columns": decided}


def compute():
    reruns = [{"towers": towers, "training": training, "variant": variant,
               "published": published, "rerun": rerun, "how": how,
               "columns": {c: round(v, 4) for c, v in test_spread(published, rerun).items()}}
              for towers, training, variant, published, rerun, how in RERUNS]
    validation = []
    for variant, published, other in VALIDATION:
        epoch, spread, window = validation_spread(published, other)
        validation.append({"towers": "InceptionV3", "variant": variant, "published": published,
                           "other": other, "epoch": epoch,
                           "columns": {c: round(v, 4) for c, v in spread.items()},
                           "window": {c: round(v, 4) for c, v in window.items()}})
    spreads = own_spreads(reruns, validation)
    widest = widest_spreads(reruns, validation)
    comparisons = [_comparison(label, group, page, spreads, widest)
                   for label, group, page in COMPARISONS]
    return {"command": COMMAND, "what": "|NMAE(rerun) - NMAE(published)| of one seed, and the "
            "decided columns of MTL-CPL-A against MTL-Baseline beyond twice it",
            "rule": RULE, "reruns": reruns, "validation": validation, "spreads": spreads,
            "widest": widest, "comparisons": comparisons}


def _row(cells, values):
    return "| " + " | ".join(cells) + " | " + " | ".join(f"{values[c]:.4f}" for c in COLUMNS) + " |"


def _spread_tables(result):
    head = " | ".join(COLUMNS) + " |"
    rule = "|---" * (len(COLUMNS) + 3) + "|"
    lines = ["|NMAE(rerun) - NMAE(published)| on the same 600 test pairs (seed 0, "
             "the published run against a rerun of its settings):", "",
             "| towers | training | variant | the rerun | " + head, "|---" + rule]
    lines += [_row((r["towers"], TRAINING[r["training"]], r["variant"], r["how"]),
                   r["columns"]) for r in result["reruns"]]
    lines += ["", "InceptionV3's MTL-CPL-A was not rerun to the same length. On validation "
              "(140 pairs), another training of the same settings (patience 20, ablation (d)) "
              "against the published run, at the published run's kept epoch and the "
              f"largest over the kept epoch +- {WINDOW}; MTL-Baseline's rerun beside it:", "",
              "| variant | epoch | at | " + head, rule]
    for r in result["validation"]:
        e = r["epoch"]
        lines.append(_row((r["variant"], str(e), "the kept epoch"), r["columns"]))
        lines.append(_row((r["variant"], f"{e - WINDOW}-{e + WINDOW}", "largest"), r["window"]))
    return lines


def _count_lines(result):
    lines = ["Each decided column of MTL-CPL-A against MTL-Baseline, counted as beyond "
             "twice the spread or not. The rule: beyond when |mean A - mean B| > 2 max(s_A, "
             "s_B), s_A and s_B each variant's own spread on that column for the towers and "
             "training named (2 max(s_A, s_B) >= s_A + s_B, so the more cautious of the two "
             "natural rules). The own spreads:", ""]
    for group, spread in result["spreads"].items():
        lines.append(f"- {group}: " + "; ".join(f"{v} from {spread['from'][v]}"
                                                for v in VARIANTS))
    lines += ["", "| setting | spreads of | MTL-CPL-A lower: beyond twice the spread / decided "
              "| MTL-Baseline lower: beyond / decided | columns within twice the spread "
              "| beyond twice the widest spread, A lower / B lower | within twice the widest |",
              "|---|---|---|---|---|---|---|"]
    for c in result["comparisons"]:
        a, b = c["counts"]["A lower"], c["counts"]["B lower"]
        within = [k for k, d in c["columns"].items() if not d["beyond_twice_spread"]]
        wide = [k for k, d in c["columns"].items() if not d["beyond_twice_widest"]]
        link = c["verdicts"].split("#")[0].replace(".json", ".md")
        lines.append(f"| {c['setting']} ([{os.path.basename(link)}]({link})) | {c['spreads']} "
                     f"| {a['beyond']} / {a['decided']} | {b['beyond']} / {b['decided']} "
                     f"| {', '.join(within) or 'none'} | {a['beyond_widest']} / "
                     f"{b['beyond_widest']} | {', '.join(wide) or 'none'} |")
    lines += ["", "The widest spread, for caution: per variant and column the largest measured "
              "with its towers under either training (compact: its three test reruns; "
              "InceptionV3: MTL-Baseline's test rerun, and MTL-CPL-A's largest validation "
              f"difference over its kept epoch +- {WINDOW}, above), twice the larger of the two "
              "variants' as before."]
    return lines


def markdown(result):
    from cpl_keras import files

    lines = [files.generated_line(COMMAND), "",
             "# Two trainings of one seed: how far apart, and which verdicts exceed twice that",
             "", *_spread_tables(result), "", *_count_lines(result)]
    lines += ["", "The compact defaults' spreads are measured at 2,000 pairs; the 8,000-pair "
              "setting borrows them. The fair fight's compact runs have their own, measured "
              "under its recipe; its InceptionV3 runs borrow InceptionV3's under the defaults "
              "(no InceptionV3 run of the recipe was trained twice). The InceptionV3 pairs at "
              "8,000 pairs and with patience 20 are one seed, their columns decided by the "
              "paired bootstrap alone.", ""]
    return "\n".join(lines)


def regenerate(page_path):
    """spread.md as this script writes it, from the committed files."""
    return markdown(json.loads(json.dumps(compute())))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="recompute and compare with the committed JSON and page (exit 1 if not)")
    args = parser.parse_args(argv)
    result = json.loads(json.dumps(compute()))
    return check_or_write("rerun_spread", OUT, result, check=args.check, draw=lambda: None,
                          pages={OUT + ".md": markdown(result)})

if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/rerun_spread.py")
