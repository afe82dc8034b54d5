"""Tables 1 and 2 as text: Markdown and CSV.

``markdown`` and ``csv_text`` render either table (a ``Table1`` or a
pooled ``Table2`` from ``cpl_keras.evaluation``): one table per NMAE
convention, the best value per column in bold, the paper's numbers beside
ours in the paper's convention, mean ± spread for a table over seeds, and
for Table 2 one section per rig and the focal and field-of-view metrics
calibration papers report. ``differences_beyond_spread`` says which row is
lower where the difference exceeds the seeds' spread.
"""

from __future__ import annotations

import math


from cpl_keras import files, metrics
from cpl_keras.camera import PARAMETERS
from cpl_keras.evaluation.seeds import beyond_spread
from cpl_keras.evaluation.tables import Table2
from cpl_keras.runs import RELEASED

#: Table columns (the paper's names) and the parameter each one is.
COLUMNS = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "theta_p")
COLUMN_PARAMETER = dict(zip(COLUMNS, PARAMETERS))
CONVENTIONS = ("nmae", "nmae_signed")
CONVENTION_TITLES = {
    "nmae": "NMAE = MAE / mean(|y|) (the paper's Eq. NMAE)",
    "nmae_signed": "NMAE = MAE / mean(y), signed mean (what produced the paper's Table 1)",
}


def cell(row_metrics, column, convention):
    value = row_metrics["targets"][COLUMN_PARAMETER[column]][convention]
    return math.nan if value is None else value


def best_rows(rows, convention):
    """{column: set of rows with the smallest |value|} among ``rows`` (a
    table's rows; ties all win; undefined values never win).

    The paper bolded the smallest *signed* value, so a large negative NMAE
    could be marked best; a magnitude is what an error ratio means, so the
    smallest magnitude wins here. Only the rows scored on the most pairs
    compete (a Geometric row run on fewer pairs of a real rig does not)."""
    best = {}
    if len(rows) < 2:
        return best
    for column in COLUMNS:
        pairs = {row: m["targets"].get(COLUMN_PARAMETER[column], {}).get("num_defined")
                 for row, m in rows.items()}
        most = max((n for n in pairs.values() if n is not None), default=None)
        candidates = [(abs(cell(m, column, convention)), row)
                      for row, m in rows.items()
                      if math.isfinite(cell(m, column, convention))
                      and pairs[row] in (None, most)]
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
    if table.seeds is None:
        return None
    return table.rows[row].get("seeds", table.seeds)


def row_label(table, row):
    """The row's name as the Markdown tables and plots show it: marked
    ``(1 seed)`` (``(k seeds)``) when it is a mean over fewer seeds than the
    table's."""
    seeds = row_seeds(table, row)
    if seeds is None or len(seeds) == len(table.seeds):
        return row
    mark = f"{len(seeds)} seed{'s' if len(seeds) > 1 else ''}"
    # "MTL-CPL-A (as released)" -> "MTL-CPL-A (as released, 1 seed)"
    return f"{row[:-1]}, {mark})" if row.endswith(")") else f"{row} ({mark})"


def _seed_list(seeds):
    return ("seed " if len(seeds) == 1 else "seeds ") + ", ".join(str(s) for s in seeds)


def seeds_lines(table):
    """Markdown lines saying that the cells are means over seeds, and which
    rows have fewer seeds (none for a table of one seed)."""
    if table.seeds is None:
        return []
    seeds = ", ".join(str(s) for s in table.seeds)
    lines = [f"Cells: mean ± spread over {len(table.seeds)} seeds ({seeds}; each seed its "
             f"own split and initial weights); spread = {table.spread}."]
    fewer = [row for row in table.rows if row_label(table, row) != row]
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
        with_paper = convention == table.paper_convention and table.paper
        lines += [f"{level} {CONVENTION_TITLES[convention]}", ""]
        if with_paper:
            lines += [f"Cells: ours (paper's Table {table.table}).", ""]
        best = best_rows(table.rows, convention)
        lines.append("| method | " + " | ".join(COLUMNS) + " |")
        lines.append("|---" * (len(COLUMNS) + 1) + "|")
        for row, row_metrics in table.rows.items():
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
                    paper = table.paper.get(paper_row, {}).get(column)
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
    for row, row_metrics in table.rows.items():
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
    geo = table.rows.get("Geometric")
    if geo:
        report = geo["failures"]
        parts = [f"{flag} {report[flag]['count']}/{report['num_pairs']}" for flag in report
                 if isinstance(report[flag], dict)]
        priors = (f"each seed's training-mean priors, {geo['priors']}" if table.seeds is not None
                  else f"priors {geo['priors']}")
        lines += [f"Geometric baseline on {geo['num_pairs']} pairs; stage failures (fallback "
                  f"to {priors}): " + ", ".join(parts) + ".", ""]
        if geo.get("degenerate"):
            lines += ["Geometric fx, fy: degenerate on a rectified rig (Bougnoux's formula is "
                      "0/0 when the optical axes are coplanar); no number is reported.", ""]
    return lines + coverage_notes(table)


def coverage_notes(table):
    """Markdown lines: the columns scored on part of the pairs, and the rows
    scored on fewer pairs than the others (a Geometric row run on fewer)."""
    counts = {row: {name: m.get("num_defined", table.num_pairs) for name, m in r["targets"].items()}
              for row, r in table.rows.items()}
    if not counts:
        return []
    most = {name: max(c[name] for c in counts.values()) for name in next(iter(counts.values()))}
    lines = []
    partial = [f"{name} ({n} of {table.num_pairs} pairs)" for name, n in most.items()
               if n < table.num_pairs]
    if partial:
        lines += ["Columns scored on part of the pairs only (the other pairs have no ground "
                  "truth for them, or, for theta_p, are of a rectified rig, whose relative "
                  "pitch is 0 by construction): " + ", ".join(partial) + ".", ""]
    fewer = [f"{row_label(table, row)}: " + ", ".join(
        f"{name} {c[name]}" for name in most if c[name] < most[name])
        for row, c in counts.items() if any(c[name] < most[name] for name in most)]
    if fewer:
        lines += ["Rows scored on fewer pairs than the others (pairs per column): "
                  + "; ".join(fewer) + ".", ""]
    return lines


def _generated(command):
    """A page's first line when a command wrote it (``files.generated_line``)."""
    return [files.generated_line(command), ""] if command else []


def table1_markdown(table, command=None):
    """Table 1 (or one run's scores) as Markdown: one table per NMAE convention, best marked in
    bold, the paper's numbers beside ours in the paper's convention."""
    number = table.table
    title = f"Table {number}" if number else "Evaluation"
    lines = _generated(command) + [f"# {title}: NMAE per parameter", ""]
    if command:
        lines += ["Command:", "", "```", command, "```", ""]
    lines += [f"Data: `{table.data}` ({table.data_description}; source: "
              f"{table.data_source}; image width {table.image_width} px).", ""]
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
    return f"{lead}," + ",".join(COLUMNS) + (",seeds" if table.seeds is not None else "")


def csv_rows(table, prefix=""):
    """CSV lines, one per (method, metric) (metric in mae, nmae, nmae_signed;
    for a mean over 2+ seeds also mae_spread, nmae_spread,
    nmae_signed_spread), each starting with ``prefix``; ``n/a`` for undefined
    values. A table over seeds ends each line with the row's seeds
    (space-separated)."""
    lines = []
    for row, row_metrics in table.rows.items():
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


def table1_csv(table):
    """Table 1 (or one run's scores) as CSV: one row per (method, metric),
    metric in mae, nmae, nmae_signed (``csv_rows``)."""
    return "\n".join([csv_header(table)] + csv_rows(table)) + "\n"


def differences_beyond_spread(rows):
    """Markdown: for every two of ``rows`` (a table's rows) with a spread over seeds, which has the
    lower NMAE (MAE / mean|y|) per column where the difference of their means
    exceeds the sum of their spreads (``<``: the first row is lower, ``>``:
    the second), and ``=`` where it does not; empty (``[]``) for a table
    without spreads. The report claims an ordering only where this says so."""
    rows = [(name, row) for name, row in rows.items() if row.get("spread")]
    if len(rows) < 2:
        return []
    lines = ["| rows compared | " + " | ".join(COLUMNS) + " | first lower / second lower / "
             "within the spreads |",
             "|---|" + "---|" * (len(COLUMNS) + 1)]
    for i, (first, a) in enumerate(rows):
        for second, b in rows[i + 1:]:
            cells = [beyond_spread(a["targets"][p]["nmae"], a["spread"]["targets"][p]["nmae"],
                                   b["targets"][p]["nmae"], b["spread"]["targets"][p]["nmae"])
                     for p in PARAMETERS]
            counts = [cells.count(answer) for answer in ("<", ">", "=")]
            lines.append(f"| {first} vs {second} | " + " | ".join(cells)
                         + f" | {counts[0]} / {counts[1]} / {counts[2]} |")
    return lines



def _table2_sections(table, level):
    return (nmae_tables(table, level)
            + fov_table(table, header="within {k} deg FOV") + field_table(table)
            + notes(table))


#: The field's metrics (``metrics.focal_metrics``): (key, column header, decimals).
FIELD_COLUMNS = (
    ("relative_fx_median", "rel. fx err (median)", 3),
    ("relative_fy_median", "rel. fy err (median)", 3),
    ("hfov_error_deg_median", "hFoV err deg (median)", 2),
    ("vfov_error_deg_median", "vFoV err deg (median)", 2),
) + tuple((f"{a}fov_auc_{t}deg", f"{a}FoV AUC@{t}", 3)
          for a in ("h", "v") for t in metrics.AUC_THRESHOLDS_DEG)


def field_table(table):
    """Markdown lines: the metrics calibration papers report (relative focal
    error, FoV error in degrees, its AUC), per row that has them."""
    rows = [(row, m["field"]) for row, m in table.rows.items() if m.get("field")]
    if not rows:
        return []
    lines = ["| method | " + " | ".join(h for _, h, _ in FIELD_COLUMNS) + " |",
             "|---" * (len(FIELD_COLUMNS) + 1) + "|"]
    for row, field in rows:
        degenerate = is_degenerate(table.rows[row], "fx")
        cells = ["degenerate" if degenerate else metrics.format_value(field.get(key), decimals)
                 for key, _, decimals in FIELD_COLUMNS]
        lines.append(f"| {row_label(table, row)} | " + " | ".join(cells) + " |")
    seeds = (" Over several seeds, each cell is the mean of the seeds' values." if
             table.seeds and len(table.seeds) > 1 else "")
    return lines + ["", "Relative focal error |f - f*| / f* and FoV error per pair, their "
                    "medians; AUC of the FoV error's cumulative curve up to 1, 5 and 10 deg "
                    f"(1 = every pair exact).{seeds}", ""]


def table2_markdown(table, command=None):
    """Table 2 as Markdown: the pooled table (with the paper's numbers), then one section per rig."""
    lines = _generated(command) + ["# Table 2: NMAE per parameter on real rigs", ""]
    if command:
        lines += ["Command:", "", "```", command, "```", ""]
    lines += [f"Pooled: {table.data_description}; image width {table.image_width} px. "
              "Forward pass only (no fine-tuning). Each row is scored on every pair that "
              "has ground truth for the column, the Geometric row on the pairs it ran on. "
              "`n/a` = undefined (zero mean, or no pair with ground truth).",
              ""] + seeds_lines(table) + ["## Pooled over all rigs", ""]
    lines += _table2_sections(table, "###")
    if table.shared is not None:
        lines += ["## Pooled over all rigs, every row on the same pairs", "",
                  "Each column only on the pairs on which every row above has it (the "
                  "Geometric row's pairs).", ""]
        lines += nmae_tables(table.shared, "###") + coverage_notes(table.shared)
    for name, rig in table.rigs.items():
        kind = "rectified" if rig.rectified else "not rectified"
        lines += [f"## Rig: {name} ({kind})", "",
                  f"Data: `{rig.data}` ({rig.data_description}; source: "
                  f"{rig.data_source}).", ""]
        lines += _table2_sections(rig, "###")
    lines += ["Best per column (smallest |NMAE|) in bold, among the rows scored on the most "
              "pairs. The paper's Average row is placed "
              "beside 'Average (release bug)'. Plot of predicted against true horizontal field "
              "of view per rig: `*_fov_scatter.png`.", ""]
    return "\n".join(lines)


def table2_csv(table):
    """Table 2 as CSV: ``rig,method,metric,<columns>[,seeds]``; rig ``pooled`` for the pooled table."""
    lines = [csv_header(table, "rig,method,metric")]
    shared = [] if table.shared is None else [("pooled on shared pairs", table.shared)]
    for rig, sub in [("pooled", table)] + shared + list(table.rigs.items()):
        lines += csv_rows(sub, prefix=f"{rig},")
    return "\n".join(lines) + "\n"



def is_table2(table):
    """Whether a scored table is Table 2 over real rigs (per rig and pooled)."""
    return isinstance(table, Table2) and table.pooled


def markdown(table, command=None):
    """Either table as Markdown (``table1_markdown``, ``table2_markdown``)."""
    return (table2_markdown if is_table2(table) else table1_markdown)(table, command)


def csv_text(table):
    """Either table as CSV (``table1_csv``, ``table2_csv``)."""
    return (table2_csv if is_table2(table) else table1_csv)(table)
