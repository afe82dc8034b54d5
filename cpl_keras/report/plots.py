"""Tables 1 and 2 as figures (PNG, matplotlib imported on first use).

``fov_plot``: the percentage of pairs within k degrees of field of view
against k, one curve per row (both tables); ``fov_scatter_plot``: predicted
against true horizontal field of view, one panel per rig (Table 2).
"""

from __future__ import annotations

import math

from cpl_keras import files, metrics
from cpl_keras.report.text import row_label


def fov_plot(table, path):
    """Percentage within k degrees of FOV vs k, one curve per row (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ks = list(metrics.FOV_THRESHOLDS_DEG)
    for row, row_metrics in table.rows.items():
        values = [row_metrics["fov_within_deg"][str(k)] for k in ks]
        values = [math.nan if v is None else v for v in values]
        ax.plot(ks, values, marker="o", label=row_label(table, row))
    ax.set_xlabel("field-of-view error threshold (degrees)")
    ax.set_ylabel("samples within threshold (%)")
    ax.set_title(f"Table {table.table}: FOV-threshold curves" if table.table
                 else "FOV-threshold curve")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    with files.glyphs_quiet():  # (a run's name in characters no font has)
        fig.tight_layout()
        fig.savefig(path, dpi=100, format="png")
    plt.close(fig)



def fov_scatter_plot(table, path):
    """Predicted against true horizontal FOV, one panel per rig, one colour
    per method (degenerate rows left out)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rigs = list(table.fov_points.items())
    fig, axes = plt.subplots(1, len(rigs), figsize=(4.5 * len(rigs), 4.2), squeeze=False)
    for ax, (rig, rows) in zip(axes[0], rigs):
        values = []
        for row, points in rows.items():
            if points["true_deg"]:
                ax.scatter(points["true_deg"], points["pred_deg"], s=8, alpha=0.6, label=row)
                values += points["true_deg"] + points["pred_deg"]
        if values:
            lo, hi = min(values), max(values)
            ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set_title(rig)
        ax.set_xlabel("true horizontal FOV (deg)")
        ax.set_ylabel("predicted horizontal FOV (deg)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    with files.glyphs_quiet():  # (a run's name in characters no font has)
        fig.tight_layout()
        fig.savefig(path, dpi=100, format="png")
    plt.close(fig)

