"""Rendering of evaluation tables: Markdown, CSV, JSON and the FOV plot.

``cpl_keras.evaluation`` (and ``cpl_keras.real.table2``) score; this module
turns a scored table (a JSON-ready dict) into files: ``markdown`` (one table
per NMAE convention, the best value per column in bold, the paper's numbers
beside ours), ``csv_text``, ``fov_plot`` (percentage within k degrees of
field of view) and ``write_outputs``, which writes them all atomically with
paths relative to the output directory.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

from cpl_keras import metrics, runs
from cpl_keras.camera import PARAMETERS
from cpl_keras.runs import RELEASED

#: Table columns (the paper's names) and the parameter each one is.
COLUMNS = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "theta_p")
COLUMN_PARAMETER = dict(zip(COLUMNS, PARAMETERS))
CONVENTIONS = ("nmae", "nmae_signed")
CONVENTION_TITLES = {
    "nmae": "NMAE = MAE / mean(|y|) (the paper's Eq. NMAE)",
    "nmae_signed": "NMAE = MAE / mean(y), signed mean (what produced the paper's Table 1)",
}


def jsonable(value):
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return metrics.json_value(value)
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    return value


def cell(row_metrics, column, convention):
    value = row_metrics["targets"][COLUMN_PARAMETER[column]][convention]
    return math.nan if value is None else value


def best_rows(table, convention):
    """{column: set of rows with the smallest |value|} (ties all win; undefined
    values never win).

    The paper bolded the smallest *signed* value, so a large negative NMAE
    could be marked best; a magnitude is what an error ratio means, so the
    smallest magnitude wins here."""
    best = {}
    if len(table["rows"]) < 2:
        return best
    for column in COLUMNS:
        candidates = [(abs(cell(m, column, convention)), row)
                      for row, m in table["rows"].items()
                      if math.isfinite(cell(m, column, convention))]
        if candidates:
            smallest = min(value for value, _ in candidates)
            best[column] = {row for value, row in candidates if value == smallest}
    return best


def is_degenerate(row_metrics, column):
    return COLUMN_PARAMETER[column] in row_metrics.get("degenerate", ())


def spread_cell(row_metrics, column, convention):
    """The spread over seeds of a cell (``evaluation.aggregate_seeds``); nan
    when undefined, None when the row is not a mean over seeds."""
    spread = row_metrics.get("spread")
    if spread is None:
        return None
    value = spread["targets"][COLUMN_PARAMETER[column]].get(convention)
    return math.nan if value is None else value


def _with_spread(text, spread, decimals=3):
    """``text`` followed by `` ± spread`` for a mean over seeds."""
    return text if spread is None else f"{text} ± {metrics.format_value(spread, decimals)}"


def row_seeds(table, row):
    """The seeds a row of a table over seeds is a mean over (all the table's
    unless the row says otherwise); None for a table of one seed."""
    if "seeds" not in table:
        return None
    return table["rows"][row].get("seeds", table["seeds"])


def row_label(table, row):
    """The row's name as the Markdown tables and plots show it: marked
    ``(1 seed)`` (``(k seeds)``) when it is a mean over fewer seeds than the
    table's."""
    seeds = row_seeds(table, row)
    if seeds is None or len(seeds) == len(table["seeds"]):
        return row
    mark = f"{len(seeds)} seed{'s' if len(seeds) > 1 else ''}"
    # "MTL-CPL-A (as released)" -> "MTL-CPL-A (as released, 1 seed)"
    return f"{row[:-1]}, {mark})" if row.endswith(")") else f"{row} ({mark})"


def _seed_list(seeds):
    return ("seed " if len(seeds) == 1 else "seeds ") + ", ".join(str(s) for s in seeds)


def seeds_lines(table):
    """Markdown lines saying that the cells are means over seeds, and which
    rows have fewer seeds (none for a table of one seed)."""
    if "seeds" not in table:
        return []
    seeds = ", ".join(str(s) for s in table["seeds"])
    lines = [f"Cells: mean ± spread over {len(table['seeds'])} seeds ({seeds}; each seed its "
             f"own split and initial weights); spread = {table['spread']}."]
    fewer = [row for row in table["rows"] if row_label(table, row) != row]
    if fewer:
        lines.append("Rows marked \"1 seed\" (\"k seeds\") were trained on those seeds only: "
                     + "; ".join(f"{row}: {_seed_list(row_seeds(table, row))}" for row in fewer)
                     + ". A row of one seed gives that run's values, without spread.")
    return [" ".join(lines), ""]


def nmae_tables(table, level="##"):
    """Markdown lines: one NMAE table per convention (heading ``level``), the
    best value per column in bold, the paper's numbers beside ours in the
    paper's convention; a row's ``degenerate`` columns say so."""
    lines = []
    for convention in CONVENTIONS:
        with_paper = convention == table["paper_convention"] and table["paper"]
        lines += [f"{level} {CONVENTION_TITLES[convention]}", ""]
        if with_paper:
            lines += [f"Cells: ours (paper's Table {table['table']}).", ""]
        best = best_rows(table, convention)
        lines.append("| method | " + " | ".join(COLUMNS) + " |")
        lines.append("|---" * (len(COLUMNS) + 1) + "|")
        for row, row_metrics in table["rows"].items():
            cells = []
            for column in COLUMNS:
                if is_degenerate(row_metrics, column):
                    cells.append("degenerate")
                    continue
                text = metrics.format_value(cell(row_metrics, column, convention))
                if row in best.get(column, ()):
                    text = f"**{text}**"
                text = _with_spread(text, spread_cell(row_metrics, column, convention))
                if with_paper:
                    paper_row = row[: -len(RELEASED)] if row.endswith(RELEASED) else row
                    paper_row = "Average" if paper_row == "Average (release bug)" else paper_row
                    paper = table["paper"].get(paper_row, {}).get(column)
                    if paper is not None and row != "Average":
                        text += f" ({paper:.3f})"
                cells.append(text)
            lines.append(f"| {row_label(table, row)} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def fov_table(table, header="{k} deg"):
    """Markdown lines: the percentage within k degrees of FOV, per row."""
    ks = metrics.FOV_THRESHOLDS_DEG
    lines = ["| method | " + " | ".join(header.format(k=k) for k in ks) + " |",
             "|---" * (len(ks) + 1) + "|"]
    for row, row_metrics in table["rows"].items():
        if is_degenerate(row_metrics, "fx"):
            cells = ["degenerate"] * len(ks)
        else:
            spread = (row_metrics.get("spread") or {}).get("fov_within_deg")
            cells = [_with_spread(metrics.format_value(row_metrics["fov_within_deg"][str(k)], 2),
                                  None if spread is None else
                                  (math.nan if spread[str(k)] is None else spread[str(k)]), 2)
                     for k in ks]
        lines.append(f"| {row_label(table, row)} | " + " | ".join(cells) + " |")
    return lines + [""]


def notes(table):
    """Markdown lines: the Geometric row's failures, and targets whose truth
    is defined on part of the pairs only."""
    lines = []
    geo = table["rows"].get("Geometric")
    if geo:
        report = geo["failures"]
        parts = [f"{flag} {report[flag]['count']}/{report['num_pairs']}" for flag in report
                 if isinstance(report[flag], dict)]
        priors = (f"each seed's training-mean priors, {geo['priors']}" if "seeds" in table
                  else f"priors {geo['priors']}")
        lines += [f"Geometric baseline on {geo['num_pairs']} pairs; stage failures (fallback "
                  f"to {priors}): " + ", ".join(parts) + ".", ""]
        if geo.get("degenerate"):
            lines += ["Geometric fx, fy: degenerate on a rectified rig (Bougnoux's formula is "
                      "0/0 when the optical axes are coplanar); no number is reported.", ""]
    first = next(iter(table["rows"].values()), {"targets": {}})
    undefined = [f"{name} ({m['num_defined']} of {table['num_pairs']} pairs)"
                 for name, m in first["targets"].items()
                 if m.get("num_defined", table["num_pairs"]) < table["num_pairs"]]
    if undefined:
        lines += ["Ground truth defined on part of the pairs only: " + ", ".join(undefined)
                  + "; the other pairs are left out of those columns.", ""]
    return lines


def markdown(table, command=None):
    """The table as Markdown: one table per NMAE convention, best marked in
    bold, the paper's numbers beside ours in the paper's convention."""
    number = table["table"]
    title = f"Table {number}" if number else "Evaluation"
    lines = [f"# {title}: NMAE per parameter", ""]
    if command:
        lines += ["Command:", "", "```", command, "```", ""]
    lines += [f"Data: `{table['data']}` ({table['data_description']}; source: "
              f"{table['data_source']}; image width {table['image_width']} px).", ""]
    lines += seeds_lines(table)
    lines += nmae_tables(table, "##")
    lines += ["Best per column (smallest |NMAE|) in bold; `n/a` = undefined (zero mean).",
              "The paper's Average row is placed beside 'Average (release bug)': the",
              "release's Average predicted parameter i as the mean of the 13 labels of",
              "training sample i.", ""]
    lines += ["## Percentage within k degrees of field of view", ""] + fov_table(table)
    return "\n".join(lines + notes(table))


def csv_header(table, lead="method,metric"):
    """The CSV header: ``lead``, the columns and, for a table over seeds,
    ``seeds``."""
    return f"{lead}," + ",".join(COLUMNS) + (",seeds" if "seeds" in table else "")


def csv_rows(table, prefix=""):
    """CSV lines, one per (method, metric) (metric in mae, nmae, nmae_signed;
    for a mean over 2+ seeds also mae_spread, nmae_spread,
    nmae_signed_spread), each starting with ``prefix``; ``n/a`` for undefined
    values. A table over seeds ends each line with the row's seeds
    (space-separated)."""
    lines = []
    for row, row_metrics in table["rows"].items():
        seeds = row_seeds(table, row)
        tail = "" if seeds is None else "," + " ".join(str(s) for s in seeds)
        metrics_ = ("mae",) + CONVENTIONS
        if "spread" in row_metrics:
            metrics_ += tuple(f"{m}_spread" for m in metrics_)
        for metric in metrics_:
            cells = []
            for column in COLUMNS:
                value = (spread_cell(row_metrics, column, metric[: -len("_spread")])
                         if metric.endswith("_spread") else cell(row_metrics, column, metric))
                cells.append("degenerate" if is_degenerate(row_metrics, column) else
                             "n/a" if not math.isfinite(value) else f"{value:.6g}")
            lines.append(f"{prefix}{row},{metric}," + ",".join(cells) + tail)
    return lines


def csv_text(table):
    """One CSV row per (method, metric): metric in mae, nmae, nmae_signed
    (``csv_rows``)."""
    return "\n".join([csv_header(table)] + csv_rows(table)) + "\n"


def fov_plot(table, path):
    """Percentage within k degrees of FOV vs k, one curve per row (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ks = list(metrics.FOV_THRESHOLDS_DEG)
    for row, row_metrics in table["rows"].items():
        values = [row_metrics["fov_within_deg"][str(k)] for k in ks]
        values = [math.nan if v is None else v for v in values]
        ax.plot(ks, values, marker="o", label=row_label(table, row))
    ax.set_xlabel("field-of-view error threshold (degrees)")
    ax.set_ylabel("samples within threshold (%)")
    ax.set_title(f"Table {table['table']}: FOV-threshold curves" if table["table"]
                 else "FOV-threshold curve")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100, format="png")
    plt.close(fig)


def portable(table, out_dir):
    """``table`` with the paths it records (``data``, ``runs``, ``run_dir``,
    ``source``) relative to ``out_dir``, where its files are written: a
    committed table names no machine's directories."""
    def convert(key, value):
        if isinstance(value, dict):
            return {k: convert(k, v) for k, v in value.items()}
        if key == "runs" and isinstance(value, list):
            return [runs.relative(v, out_dir) if os.path.isabs(v) else v for v in value]
        if key in ("data", "run_dir", "source") and isinstance(value, str):
            return ", ".join(one(part) for part in value.split(", "))  # pooled: several
        return value

    def one(text):
        path, sep, rest = text.partition(" (")  # "<path> (<what>)"
        return runs.relative(path, out_dir) + sep + rest if os.path.isabs(path) else text

    return convert(None, table)


def write_outputs(out_dir, stem, table, command, *, render_markdown=markdown,
                  render_csv=csv_text, plots=(("_fov.png", fov_plot),)):
    """Write ``stem``.md/.csv/.json and the plots (``(suffix, draw(table,
    path))``, when the table has rows) into ``out_dir``, created if missing.
    Paths in them are relative to ``out_dir`` (``portable``). Everything is
    rendered to temporary files first and renamed only when all succeeded.
    Returns the paths written."""
    os.makedirs(out_dir, exist_ok=True)
    table = portable(table, out_dir)
    texts = {
        f"{stem}.md": render_markdown(table, command),
        f"{stem}.csv": render_csv(table),
        f"{stem}.json": json.dumps(dict(table, command=command), indent=2, allow_nan=False) + "\n",
    }
    drawn = list(plots) if table.get("rows") else []
    finals = [os.path.join(out_dir, name) for name in texts]
    finals += [os.path.join(out_dir, stem + suffix) for suffix, _ in drawn]
    with runs.atomic_path(*finals) as tmps:
        tmps = tmps if isinstance(tmps, list) else [tmps]
        for tmp, text in zip(tmps, texts.values()):
            with open(tmp, "w") as f:
                f.write(text)
        for tmp, (_, draw) in zip(tmps[len(texts):], drawn):
            draw(table, tmp)
    return finals


def differences_beyond_spread(table):
    """Markdown: for every two rows with a spread over seeds, which has the
    lower NMAE (MAE / mean|y|) per column where the difference of their means
    exceeds the sum of their spreads (``<``: the first row is lower, ``>``:
    the second), and ``=`` where it does not; empty (``[]``) for a table
    without spreads. The report claims an ordering only where this says so."""
    rows = [(name, row) for name, row in table["rows"].items() if row.get("spread")]
    if len(rows) < 2:
        return []
    lines = ["| rows compared | " + " | ".join(COLUMNS) + " | first lower / second lower / "
             "within the spreads |",
             "|---|" + "---|" * (len(COLUMNS) + 1)]
    for i, (first, a) in enumerate(rows):
        for second, b in rows[i + 1:]:
            cells, counts = [], [0, 0, 0]
            for parameter in PARAMETERS:
                mean_a = _number(a["targets"][parameter]["nmae"])
                mean_b = _number(b["targets"][parameter]["nmae"])
                spread = (_number(a["spread"]["targets"][parameter]["nmae"])
                          + _number(b["spread"]["targets"][parameter]["nmae"]))
                if not (np.isfinite(mean_a) and np.isfinite(mean_b) and np.isfinite(spread)):
                    cells.append("n/a")
                    continue
                if abs(mean_a - mean_b) <= spread:
                    cells.append("=")
                    counts[2] += 1
                elif mean_a < mean_b:
                    cells.append("<")
                    counts[0] += 1
                else:
                    cells.append(">")
                    counts[1] += 1
            lines.append(f"| {first} vs {second} | " + " | ".join(cells)
                         + f" | {counts[0]} / {counts[1]} / {counts[2]} |")
    return lines


def _number(value):
    """A JSON cell as a float (None, an undefined cell: NaN)."""
    return math.nan if value is None else float(value)
