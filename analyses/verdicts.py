"""Table 1's verdicts under two rules: the seed spread and a paired bootstrap.

For each split of a reproduction folder (``cvgl``: the paper's frame-level
split, ``cvgl_drive``: the drive split) and each pair of MTL variants, every
column is decided only where the seed-spread rule of the reports and a
paired bootstrap of every seed's test pairs agree
(``cpl_keras.evaluation.verdicts``). Writes ``verdicts.md`` and
``verdicts.json`` in the folder.

    python analyses/verdicts.py                      # paper_results/cpu-8000
    python analyses/verdicts.py --folder paper_results/cpu-8000 --resamples 2000
    python analyses/verdicts.py --folder paper_results/compact-2000

A folder's splits are those with a ``table1_<split>.json``; a pair is
compared where the folder has both variants, over 2 or more seeds (a folder
with one seed's runs, such as a reproduction's ``partial/`` after its first
seed, is refused with one line: the seed-spread rule needs a spread).

Produces: ``verdicts.md`` and ``verdicts.json`` in ``--folder``; committed
for paper_results/cpu-8000/ and paper_results/compact-2000/ (rebuilt from
their committed tables and predictions, no weights needed). The page is
rendered from the JSON (``markdown``), so ``regenerate`` rebuilds a
committed page from verdicts.json and the command on its first line.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import os


#: The splits: predictions-file prefix and title.
SPLITS = {"cvgl": "paper split (frame-level)",
          "cvgl_drive": "drive split (no adjacent frame in training)"}
#: The pairs compared, as (A, B) variants.
PAIRS = (("cpl-a", "baseline"), ("cpl-u", "baseline"), ("cpl-a", "cpl-u"))


def load_rows(folder, split, variant):
    """``{seed: raw}`` and the row's name for one variant of a split, from
    the folder's predictions files (``cpl_keras.prediction_files.load``)."""
    from cpl_keras import prediction_files
    from cpl_keras.evaluation import EvaluationError

    pattern = os.path.join(folder, "runs", f"{split}_{variant}-s*{prediction_files.SUFFIX}")
    items = [prediction_files.load(path) for path in sorted(glob.glob(pattern))]
    items = [item for item in items if item.table == f"table1_{split}"]
    if not items:
        raise EvaluationError(f"no predictions of {variant} on {split} in {folder}/runs")
    files = [os.path.relpath(item.path, folder) for item in items]
    # (the paired bootstrap reads a row's arrays by name)
    rows = {item.seed: {"indices": item.raw.indices, "truth": item.raw.truth,
                        "pred": item.raw.pred, "defined": item.raw.defined} for item in items}
    return rows, items[0].row, files


def has_rows(folder, split, variant):
    """Whether the folder has predictions of ``variant`` on ``split``."""
    from cpl_keras import prediction_files

    return bool(glob.glob(os.path.join(folder, "runs",
                                       f"{split}_{variant}-s*{prediction_files.SUFFIX}")))


def check_against_table(folder, split, name_a, name_b, verdicts):
    """EvaluationError unless both rows' NMAE per seed is the committed table's."""
    from cpl_keras.evaluation import EvaluationError
    from cpl_keras.files import read_json

    table = read_json(os.path.join(folder, f"table1_{split}.json"))
    if table is None:
        return
    for v in verdicts:
        for interval in v.per_seed:
            for row, ours in ((name_a, interval.nmae_a), (name_b, interval.nmae_b)):
                per_seed = table["rows"].get(row, {}).get("per_seed", {})
                if str(interval.seed) not in per_seed:
                    raise EvaluationError(f"table1_{split}.json in {folder} has no seed "
                                          f"{interval.seed} values of {row} (per_seed)")
                cell = per_seed[str(interval.seed)]["targets"]
                stored = cell[v.parameter]["nmae"]
                if abs(stored - ours) > 1e-9 * max(1.0, abs(stored)):
                    raise EvaluationError(f"{row} seed {interval.seed} {v.column}: NMAE "
                                          f"{ours} is not the table's {stored}")


def short(row):
    """``MTL-CPL-A`` -> ``CPL-A`` (the README's short names)."""
    return row.replace("MTL-", "")


def answer_text(answer, name_a, name_b):
    """A rule's answer as a cell: ``<row> lower``, or ``=`` (undecided)."""
    from cpl_keras.evaluation import verdicts as rules

    return {rules.A_LOWER: f"{name_a} lower", rules.B_LOWER: f"{name_b} lower"}.get(answer, "=")


def summary(verdicts, field="verdict"):
    """``{"A lower": [columns], "B lower": [...], "undecided": [...]}``."""
    from cpl_keras.evaluation import verdicts as rules

    return {answer: [v.column for v in verdicts if getattr(v, field) == answer]
            for answer in (rules.A_LOWER, rules.B_LOWER, rules.UNDECIDED)}


def same_quantity_note(same):
    """One sentence on the columns that are the same quantity in the labels."""
    parts = [" = ".join(group) for group in same["identical"]]
    constant = ", ".join(f"{c} = {v:g}" for c, v in same["constant"].items())
    return ("Same quantity in the test labels (to 1e-9, every pair of every seed): "
            + ("; ".join(parts) or "none") + (f"; constant: {constant}" if constant else "")
            + ". Their verdicts are not independent evidence.")


def pair_markdown(name_a, name_b, verdicts):
    """Markdown lines: one pair's table, a row per column."""
    a, b = short(name_a), short(name_b)
    lines = [f"### {name_a} (A) vs {name_b} (B)", "",
             (f"| column | {a} | {b} | seed spread | bootstrap, seeds "
              f"{', '.join(str(i.seed) for i in verdicts[0].per_seed)} | bootstrap | verdict "
              "| Welch's p | rig bootstrap |"),
             "|---|---|---|---|---|---|---|---|---|"]
    for v in verdicts:
        seeds = ", ".join({"A lower": "A", "B lower": "B"}.get(i.answer, "=") for i in v.per_seed)
        lines.append(f"| {v.column} | {v.mean_a:.3f} ± {v.spread_a:.3f} | {v.mean_b:.3f} ± "
                     f"{v.spread_b:.3f} | {answer_text(v.spread_rule, a, b)} | {seeds} | "
                     f"{answer_text(v.bootstrap_rule, a, b)} | "
                     f"**{answer_text(v.verdict, a, b)}** | {v.welch_p:.3g} | "
                     f"{answer_text(v.rig_bootstrap, a, b)} |")
    counts = summary(verdicts)
    lines += ["", (f"Both rules: {a} lower on {len(counts['A lower'])} "
                   f"({', '.join(counts['A lower']) or 'none'}), {b} lower on "
                   f"{len(counts['B lower'])} ({', '.join(counts['B lower']) or 'none'}), "
                   f"undecided on {len(counts['undecided'])}."), ""]
    return lines


#: The two rules and the verdict, as verdicts.json states them.
RULES = {"seed_spread": "|mean A - mean B| > SD A + SD B over the seeds "
                        "(report.differences_beyond_spread)",
         "bootstrap": "per seed, the paired percentile interval of NMAE(A) - NMAE(B) over "
                      "resampled test pairs excludes 0; a side when every seed gives it",
         "verdict": "the rules' answer where they agree, else undecided",
         "welch_p": "for context: Welch's two-sided p of the seeds' NMAEs",
         "rig_bootstrap": "for context: per seed, the percentile interval over resampled "
                          "rigs (camera configurations); a side when every seed gives it"}


def header(resamples, level, seed):
    """verdicts.md's title and the rules in words."""
    return ["# Table 1 verdicts under two rules", "",
            ("A column is decided only where both rules agree. Seed spread: the two means "
             "over the seeds differ by more than the sum of their sample SDs (the rule of "
             "README.md and REPORT.md). Bootstrap: for each seed, its test pairs resampled "
             f"{resamples} times (the same pairs for both rows), NMAE(A) - NMAE(B) "
             "(NMAE = MAE / mean|y| over the resampled pairs); a seed gives a side when its "
             f"{level:.0%} percentile interval excludes 0, the rule when every seed gives "
             "the same side. `=`: undecided. Cells: NMAE, mean ± sample SD over the seeds. "
             f"`python analyses/verdicts.py` (bootstrap seed {seed}). For context, not "
             "the verdict: Welch's p, the two-sided p of Welch's t-test of the seeds' "
             "NMAEs (3 a side), and the rig bootstrap, the same bootstrap resampling whole "
             "rigs (camera configurations, known from the labels a rig fixes) instead of "
             "single pairs, a side when every seed gives it."), ""]


def decide_split(folder, split, resamples, seed):
    """One split's JSON entry: every pair of ``PAIRS`` the folder has."""
    from cpl_keras.evaluation import verdicts as rules

    title = SPLITS[split]
    entry = {"title": title, "table": f"table1_{split}.json", "pairs": {}}
    for variant_a, variant_b in PAIRS:
        if not (has_rows(folder, split, variant_a) and has_rows(folder, split, variant_b)):
            continue  # (a folder without that variant: inception-2000 has no MTL-CPL-U)
        rows_a, name_a, files_a = load_rows(folder, split, variant_a)
        rows_b, name_b, files_b = load_rows(folder, split, variant_b)
        if len(rows_a) < 2 or len(rows_b) < 2:
            from cpl_keras.evaluation import EvaluationError

            raise EvaluationError(
                f"the verdicts need 2 or more seeds of each row: {folder} has {split} "
                f"predictions of {name_a} seed(s) {sorted(rows_a)} and {name_b} seed(s) "
                f"{sorted(rows_b)}")
        if "same_quantity" not in entry:
            entry["same_quantity"] = rules.same_quantities([rows_b[s]["truth"]
                                                            for s in sorted(rows_b)])
        verdicts = rules.compare(rows_a, rows_b, resamples=resamples, bootstrap_seed=seed)
        check_against_table(folder, split, name_a, name_b, verdicts)
        entry["pairs"][f"{name_a} vs {name_b}"] = {
            "a": name_a, "b": name_b, "files": files_a + files_b,
            "verdict": summary(verdicts), "seed_spread": summary(verdicts, "spread_rule"),
            "bootstrap": summary(verdicts, "bootstrap_rule"),
            "columns": [dataclasses.asdict(v) for v in verdicts]}
        print(f"{split} {name_a} vs {name_b}: {summary(verdicts)}")
    return entry


def verdict_from_json(cell):
    """A column of verdicts.json as ``pair_markdown`` reads a verdict (its
    attributes; an undefined Welch's p, null there, as NaN)."""
    from types import SimpleNamespace

    welch_p = float("nan") if cell["welch_p"] is None else cell["welch_p"]
    return SimpleNamespace(**{**cell, "welch_p": welch_p,
                              "per_seed": [SimpleNamespace(**i) for i in cell["per_seed"]]})


def markdown(result, command):
    """verdicts.md from verdicts.json's content ``result``, written by ``command``."""
    from cpl_keras import files

    md = [files.generated_line(command), ""]
    md += header(result["resamples"], result["level"], result["bootstrap_seed"])
    for entry in result["splits"].values():
        title = entry["title"]
        md += [f"## {title[0].upper() + title[1:]}", ""]
        if "same_quantity" in entry:
            md += [same_quantity_note(entry["same_quantity"]), ""]
        for pair in entry["pairs"].values():
            md += pair_markdown(pair["a"], pair["b"], [verdict_from_json(c) for c in pair["columns"]])
    return "\n".join(md).rstrip() + "\n"


def regenerate(page_path):
    """The committed verdicts.md ``page_path`` as this script writes it, from
    verdicts.json beside it and the command on its first line."""
    from cpl_keras import files

    with open(page_path) as f:
        command = files.generated_command(f.read())
    return markdown(files.read_json(os.path.join(os.path.dirname(page_path), "verdicts.json")),
                    command)


def main(argv=None):
    """Decide every split's pairs and write verdicts.md and verdicts.json."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", default="paper_results/cpu-8000",
                        help="a reproduction folder (its runs/ and table1_*.json)")
    parser.add_argument("--resamples", type=int, default=2000, help="bootstrap resamples")
    parser.add_argument("--seed", type=int, default=0, help="the bootstrap Generator's seed")
    args = parser.parse_args(argv)

    from cpl_keras import cli
    from cpl_keras.evaluation import verdicts as rules
    from cpl_keras.files import write_json, write_text
    from cpl_keras.metrics import jsonable

    out = {"rules": RULES, "resamples": args.resamples, "level": rules.LEVEL,
           "bootstrap_seed": args.seed, "splits": {}}
    splits = [split for split in SPLITS
              if os.path.isfile(os.path.join(args.folder, f"table1_{split}.json"))]
    if not splits:
        from cpl_keras.evaluation import EvaluationError

        raise EvaluationError(f"no table1_{{{','.join(SPLITS)}}}.json in {args.folder}")
    for split in splits:  # (the splits the folder has: compact-2000 the paper's only)
        out["splits"][split] = decide_split(args.folder, split, args.resamples, args.seed)
    out = jsonable(out)
    command = cli.command_line("analyses/verdicts.py", argv)
    write_json(os.path.join(args.folder, "verdicts.json"), out)
    write_text(os.path.join(args.folder, "verdicts.md"), markdown(out, command))
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/verdicts.py")
