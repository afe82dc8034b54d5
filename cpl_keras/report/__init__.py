"""Rendering of the scored tables, both of them, in one place.

``cpl_keras.evaluation`` scores Tables 1 and 2; this package turns a scored
table (a ``Table1`` or ``Table2``) into files: Markdown and CSV (``report.text``:
``markdown``, ``csv_text``), the FOV plots (``report.plots``) and
``write_outputs``, which writes them all atomically with paths relative to
the output directory (``portable``). Each function takes either table and
renders it as its kind needs.
"""

from __future__ import annotations

import json
import os

from cpl_keras import files, runs
from cpl_keras.evaluation.tables import table_from_json
from cpl_keras.metrics import jsonable
from cpl_keras.report.plots import fov_plot, fov_scatter_plot
from cpl_keras.report.text import (
    COLUMN_PARAMETER, COLUMNS, CONVENTION_TITLES, CONVENTIONS, FIELD_COLUMNS, best_rows, cell,
    csv_header, csv_rows, csv_text, differences_beyond_spread, field_table, fov_table,
    is_degenerate, is_table2, markdown, nmae_tables, notes, row_label, row_seeds, seeds_lines,
    spread_cell, table1_csv, table1_markdown, table2_csv, table2_markdown,
)


__all__ = [
    "best_rows",
    "regenerate",
    "cell",
    "COLUMN_PARAMETER",
    "COLUMNS",
    "CONVENTION_TITLES",
    "CONVENTIONS",
    "csv_header",
    "csv_rows",
    "csv_text",
    "differences_beyond_spread",
    "FIELD_COLUMNS",
    "field_table",
    "fov_plot",
    "fov_scatter_plot",
    "fov_table",
    "is_degenerate",
    "is_table2",
    "jsonable",
    "markdown",
    "nmae_tables",
    "notes",
    "plots_for",
    "portable",
    "portable_paths",
    "row_label",
    "row_seeds",
    "seeds_lines",
    "spread_cell",
    "table1_csv",
    "table1_markdown",
    "table2_csv",
    "table2_markdown",
    "write_outputs",
]


def plots_for(table):
    """The figures of a table: ``(suffix, draw(table, path))``; Table 2 adds
    the predicted-against-true FOV scatter per rig."""
    plots = (("_fov.png", fov_plot),)
    return plots + (("_fov_scatter.png", fov_scatter_plot),) if is_table2(table) else plots


def portable(table, out_dir):
    """``table`` (a ``Table1`` or ``Table2``) with the paths it records
    relative to ``out_dir`` (``portable_paths``)."""
    return table_from_json(portable_paths(table.to_json(), out_dir))


def portable_paths(data, out_dir):
    """A JSON-ready dict with the paths it records (``data``, ``runs``,
    ``run_dir``, ``source``) relative to ``out_dir``, where its files are
    written: a committed file names no machine's directories."""
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

    return convert(None, data)


def regenerate(page_path):
    """The text ``write_outputs`` wrote for the table page ``page_path``,
    rendered again from its JSON twin (the same name, ``.json``): a
    committed table page regenerates without weights or datasets."""
    _, payload = files.page_source(page_path)
    return markdown(table_from_json(payload), payload.get("command"))


def write_outputs(out_dir, stem, table, command, *, render_markdown=markdown,
                  render_csv=csv_text, plots=None):
    """Write ``stem``.md/.csv/.json and the plots (``(suffix, draw(table,
    path))``; by default the table's own, ``plots_for``; drawn when the table
    has rows) into ``out_dir``, created if missing (and removed again if the
    writes fail). Paths in them are relative to ``out_dir`` (``portable``).
    Everything is rendered to temporary files first and renamed only when
    all succeeded. Returns the paths written."""
    table = portable(table, out_dir)
    texts = {
        f"{stem}.md": render_markdown(table, command),
        f"{stem}.csv": render_csv(table),
        f"{stem}.json": json.dumps(dict(table.to_json(), command=command), indent=2,
                                   allow_nan=False) + "\n",
    }
    drawn = list(plots_for(table) if plots is None else plots) if table.rows else []
    finals = [os.path.join(out_dir, name) for name in texts]
    finals += [os.path.join(out_dir, stem + suffix) for suffix, _ in drawn]
    with files.new_folders(*finals), files.atomic_path(*finals) as tmps:
        tmps = tmps if isinstance(tmps, list) else [tmps]
        for tmp, text in zip(tmps, texts.values()):
            with open(tmp, "w") as f:
                f.write(text)
        for tmp, (_, draw) in zip(tmps[len(texts):], drawn):
            draw(table, tmp)
    return finals

