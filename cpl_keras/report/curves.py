"""Learning-curve figures, in one place (PNG, matplotlib imported on first
use): a run's ``curves.png`` (``plot_curves``: loss and the alpha_i of Eq. 9
per epoch, written by training), validation NMAE per parameter against
samples seen (``plot_nmae_curves``: ``cpl_keras.learning_curves``) and the
validation MAE of several runs per epoch (``plot_mae_curves``: the
reproduction's page). ``val_mae`` reads a parameter's validation MAE from a
row of log.csv.
"""

from __future__ import annotations

import math
import os
import textwrap

import numpy as np

from cpl_keras import files
from cpl_keras.camera import PARAMETERS
from cpl_keras.files import save_figure
from cpl_keras.models.variants import ALPHA_RATE
from cpl_keras.runs import RELEASED


def val_mae(row, name):
    """The logged validation MAE of output ``name`` (``_mae`` metric or, for
    the per-output MAE loss, ``_loss``)."""
    for key in (f"val_{name}_mae", f"val_{name}_loss"):
        if key in row:
            return row[key]
    return math.nan


def plot_curves(path, rows, best_epoch=None, title=None):
    """Training and validation loss per epoch (log scale when positive), and
    the adaptive weights alpha_i of Eq. 9 beside them when the run has them.
    ``rows`` and ``best_epoch`` are the state's (0-based); the axis numbers
    epochs from 1."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    epochs = [row["epoch"] + 1 for row in rows]
    alpha_keys = sorted({k for row in rows for k in row if k.startswith("alpha_")})
    fig, axes = plt.subplots(1, 2 if alpha_keys else 1, figsize=(11 if alpha_keys else 6, 4),
                             squeeze=False)
    ax = axes[0, 0]
    for key, label in (("loss", "training"), ("val_loss", "validation")):
        values = [row.get(key, np.nan) for row in rows]
        ax.plot(epochs, values, marker="o", markersize=3, label=label)
    losses = [row.get(k) for row in rows for k in ("loss", "val_loss") if row.get(k) is not None]
    if losses and all(math.isfinite(v) and v > 0 for v in losses):
        ax.set_yscale("log")
    if best_epoch is not None:
        ax.axvline(best_epoch + 1, color="grey", linestyle="--",
                   label=f"best (epoch {best_epoch + 1})")
    ax.set_xlabel("epoch")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("loss")
    ax.legend()
    ax.grid(True, alpha=0.3)
    if alpha_keys:
        ax = axes[0, 1]
        for key in alpha_keys:
            ax.plot(epochs, [row.get(key, np.nan) for row in rows], label=key[len("alpha_"):])
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel("alpha_i (Eq. 9)")
        ax.legend(fontsize=7, ncol=2)
        ax.grid(True, alpha=0.3)
    if title:
        columns = 120 if alpha_keys else 64  # (characters that fit the figure's width)
        lines = [wrapped for line in title.split("\n") for wrapped in textwrap.wrap(line, columns)]
        fig.suptitle("\n".join(lines), fontsize=9)
    with files.glyphs_quiet():  # (a file name's characters no font has)
        fig.tight_layout()
    save_figure(fig, path, dpi=100)


def plot_nmae_curves(curve, path, title):
    """One panel per camera parameter: validation NMAE (log scale) against
    samples seen, Average's level dashed, the kept epoch marked (``curve``:
    ``learning_curves.curves``'s)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 5, figsize=(16, 6.2), sharex=True)
    seen = np.asarray(curve["samples_seen"]) / 1000.0
    best_epoch = curve["kept_epoch"]
    for ax, name in zip(axes.ravel(), PARAMETERS):
        values = np.asarray(curve["nmae"][name], np.float64)
        ax.plot(seen, values, marker="o", markersize=2.5, label="network (validation)")
        level = curve["average"][name]
        if math.isfinite(level):
            ax.axhline(level, color="tab:red", linestyle="--", label="Average")
        if best_epoch and best_epoch <= len(seen):
            ax.axvline(seen[best_epoch - 1], color="grey", linestyle=":", label="kept epoch")
        finite = values[np.isfinite(values)]
        if finite.size and np.all(finite > 0) and (not math.isfinite(level) or level > 0):
            ax.set_yscale("log")
        ax.set_title(name, fontsize=10)
        ax.grid(True, alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("training samples seen (thousands)")
    for ax in axes[:, 0]:
        ax.set_ylabel("validation NMAE")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    with files.glyphs_quiet():  # (a file name's characters no font has)
        fig.tight_layout()
    save_figure(fig, path, dpi=90)


def plot_mae_curves(path, series, parameters, title):
    """One panel per name in ``parameters``: the validation MAE per epoch (log
    scale) of every series ``(label, rows, colour, style, best_epoch)``
    (``rows``: log.csv's, epochs 1-based; ``colour``: an index into tab10;
    ``style``: an index into solid, dashed, dotted, dash-dot), its kept epoch
    marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(parameters), figsize=(16, 4.2))
    for ax, parameter in zip(axes, parameters):
        for label, rows, colour, style, best in series:
            epochs = [row["epoch"] for row in rows]
            values = [val_mae(row, parameter) for row in rows]
            colour = plt.cm.tab10(colour % 10)
            ax.plot(epochs, values, ("-", "--", ":", "-.")[style % 4], color=colour,
                    linewidth=1.2, label=label)
            if best and best <= len(values):
                ax.plot([best], [values[best - 1]], "o", color=colour, markersize=3.5)
        ax.set_yscale("log")
        ax.set_title(f"validation MAE of {parameter}", fontsize=10)
        ax.set_xlabel("epoch")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=6.5)
    fig.suptitle(title, fontsize=10)
    with files.glyphs_quiet():  # (a file name's characters no font has)
        fig.tight_layout()
    save_figure(fig, path, dpi=80)


def run_label(config):
    """The run in words (``config``: a ``RunConfig``): variant, backbone,
    dataset file, split, and the training options that differ from the
    defaults (learning rate, target scaling, alpha rate)."""
    released = RELEASED if config.as_released else ""
    options = ""
    training = config.training
    if training.learning_rate is not None:
        options += f", lr {training.learning_rate:g}"
    if training.target_scaling != "none":
        options += f", targets scaled by {training.target_scaling}"
    rate = config.model.alpha_rate
    if rate is not None and rate != ALPHA_RATE:
        options += f", alpha rate {rate:g}"
    return (f"{config.variant}{released}, {config.model.backbone}, "
            f"{os.path.basename(config.data.path)}, split {training.split}{options}")
