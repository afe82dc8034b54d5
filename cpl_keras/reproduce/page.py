"""Stage 5 of the reproduction: its page, REPORT.md, written from
``reproduce.json`` and the tables (and again by a rebuild)."""

from __future__ import annotations

import os

from cpl_keras import files, report, runs
from cpl_keras.models.variants import VARIANT_ROWS
from cpl_keras.report.curves import plot_mae_curves
from cpl_keras.reproduce.plan import run_stems
from cpl_keras.reproduce.presets import DEFAULT_TABLES, RELEASED_RUN, TABLE1, TITLES
from cpl_keras.runs import RELEASED

# ---------------------------------------------------------------------------
# Stage 5: REPORT.md (from reproduce.json and the tables)
# ---------------------------------------------------------------------------
def _stem_row(stem):
    """The table row of a run name stem (``cpl-a-released``: MTL-CPL-A (as released))."""
    if stem == RELEASED_RUN:
        return VARIANT_ROWS["cpl-a"] + RELEASED
    return VARIANT_ROWS.get(stem, stem)


def _budget_text(config):
    budget = config.run_budget_s
    return "" if budget is None else (f", or at a budget of {budget:g} s of training per run "
                                      f"(whichever ends it first)")


def scale_text(config):
    """The settings' paragraph of REPORT.md (``config``: a ``Settings``)."""
    preset = config.preset
    if config.quick:
        scale = "quick (tiny settings, a smoke test of the pipeline)"
    elif preset:
        scale = f"preset `{preset}`, as set below"
    else:
        scale = "as set below"
    counts = {t: getattr(config, TABLE1[t][2]) for t in config.tables}
    if config.tables != DEFAULT_TABLES:
        seeds = (f" Seeds per table: {', '.join(f'{t} {n}' for t, n in counts.items())} "
                 f"(each seed its own initial weights and, on the paper split, its own split; "
                 f"a table over several seeds gives mean ± spread)."
                 if max(counts.values()) > 1 else "")
    else:
        seeds = (f" Seeds per protocol: cvgl {config.seeds}, random {config.random_seeds} "
                 f"(each seed its own split and initial weights; a table over several seeds "
                 f"gives mean ± spread)." if max(config.seeds, config.random_seeds) > 1
                 else "")
    seeded = config.seeded_variants
    if seeds and seeded is not None:
        once = [stem for stem in run_stems(config) if stem not in seeded]
        if once:
            seeds += (f" Trained on every seed: {', '.join(_stem_row(s) for s in seeded)}; "
                      f"on the first seed only: {', '.join(_stem_row(s) for s in once)} (their "
                      f"rows are one run's values, without spread).")
    return (f"Scale: {scale}. Backbone `{config.backbone}`, {config.image_size}x"
            f"{config.image_size} images, batch {config.batch_size}, Adam (lr 1e-3, "
            f"Deep-Homo 1.5e-3), up to {config.epochs} epochs with early stopping "
            f"(patience {config.patience}, best weights restored){_budget_text(config)}."
            f"{seeds} {_inputs_text(config)}")


def _inputs_text(config):
    """What the runs trained on and from, against the paper's inputs."""
    towers = (f"the towers start from `{config.backbone_weights}` weights, as the paper's "
              f"from ImageNet's" if config.backbone_weights else
              "here the towers start from random weights (none can be downloaded)")
    if config.data == "release":
        return (f"Data: the authors' released files, imported, every run trained and scored "
                f"as released (the only labels the release gives for the disparity and X, Y, "
                f"Z; docs/data.md); the split `{config.split or 'paper'}`; {towers}.")
    return (f"The paper trained up to 200 epochs on 123,017 pairs from ImageNet weights; "
            f"{towers}.")


#: The parameters of the learning-curve figures (validation MAE per epoch).
CURVE_PARAMETERS = ("fx", "baseline", "disparity", "pitch")


def plot_protocol_curves(out_dir, runs_list):
    """``curves_<protocol>.png`` in ``out_dir``: the validation MAE of
    ``CURVE_PARAMETERS`` per epoch, every run of the protocol, from the
    published logs (``runs/<name>_log.csv``; so a rebuild draws them alike):
    a colour per variant, a line style per seed. Returns ``[(protocol, file
    name)]``."""
    figures = []
    for protocol in dict.fromkeys(s["protocol"] for s in runs_list):
        logged = []
        for s in runs_list:
            path = os.path.join(out_dir, "runs", f"{s['name']}_log.csv")
            if s["protocol"] == protocol and os.path.isfile(path):
                logged.append((s, runs.read_log(path)))
        if not logged:
            continue
        stems = list(dict.fromkeys(_run_stem(s) for s, _ in logged))
        seeds = sorted({s.get("seed") or 0 for s, _ in logged})
        series = [(_stem_row(_run_stem(s)) + (f", seed {s['seed']}" if len(seeds) > 1 else ""),
                   rows, stems.index(_run_stem(s)), seeds.index(s.get("seed") or 0),
                   s.get("best_epoch")) for s, rows in logged]
        name = f"curves_{protocol}.png"
        plot_mae_curves(os.path.join(out_dir, name), series, CURVE_PARAMETERS,
                        TITLES.get(f"table1_{protocol}", protocol))
        figures.append((protocol, name))
    return figures


def _run_name(run_summary):
    """The run's name without its table key (``cvgl_drive_cpl-u-s1``: ``cpl-u-s1``)."""
    name, key = run_summary["name"], run_summary["protocol"]
    return name[len(key) + 1:] if name.startswith(key + "_") else name.split("_", 1)[1]


def _run_stem(run_summary):
    """The name stem of a run's summary (``cvgl_cpl-u-s1``: ``cpl-u``)."""
    name = _run_name(run_summary)
    seed = run_summary.get("seed")
    return name[: -len(f"-s{seed}")] if seed is not None and name.endswith(f"-s{seed}") \
        else name


def write_report(out_dir, summary, tables, rebuilt_by=None):
    """Stage 5: REPORT.md from the reproduction's summary (``reproduce.json``,
    its settings a ``Settings``: ``pipeline.read_summary``) and its tables;
    ``rebuilt_by``: the command that rebuilt them from the published
    predictions."""
    config, info = summary["settings"], summary["machine"]
    lines = [files.generated_line(summary["command"]), "", "# Reproducing Tables 1 and 2", ""]
    lines += ["Everything on this page was produced by one command:", "", "```",
              summary["command"], "```", ""]
    if rebuilt_by:
        lines += ["The tables and this page were rebuilt from the published predictions "
                  "(`runs/*_predictions.npz`), without weights or datasets, by:", "", "```",
                  rebuilt_by, "```", ""]
    partial = summary.get("partial")
    if partial:
        seeds = "; ".join(f"{key}: seed{'s' if len(numbers) > 1 else ''} "
                          f"{', '.join(map(str, numbers))}"
                          for key, numbers in partial["seeds"].items())
        lines += [f"**Partial**: the tables of the seeds whose runs have all finished "
                  f"({seeds}), made without training; left out: "
                  f"{'; '.join(partial['left_out']) or 'nothing'}.", ""]
    runs_list = summary["runs"]
    lines += [scale_text(config), "",
              f"Machine: {info['platform']}, Python {info['python']}, {info['cpus']} CPUs, "
              f"Keras {info['keras']}, JAX {info['jax']}, devices {', '.join(info['devices'])}. "
              f"Training wall time, summed over the runs: "
              f"{sum(s['wall_time_s'] or 0 for s in runs_list) / 60:.1f} min; this invocation "
              f"(stages not reused from earlier ones): {info['wall_time_s'] / 60:.1f} min.", "",
              "## Data", ""]
    lines += [f"- {kind}: {line}" for kind, line in summary["datasets"].items()]
    lines += ["", "## Training runs", "",
              "| protocol | run | split | seed | epochs run | best epoch | best val loss | "
              "wall time (min) | stopped |",
              "|---|---|---|---|---|---|---|---|---|"]
    for s in runs_list:
        stopped = s["stopped"] or (f"epoch cap ({config.epochs})"
                                   if s["epochs_run"] == config.epochs else "")
        wall = "" if s["wall_time_s"] is None else f"{s['wall_time_s'] / 60:.1f}"
        loss = "" if s["best_val_loss"] is None else f"{s['best_val_loss']:.4g}"
        lines.append(f"| {s['protocol']} | {_run_name(s)} | {s['split']} | "
                     f"{s.get('seed', '')} | {s['epochs_run']} | {s['best_epoch']} | {loss} | "
                     f"{wall} | {stopped} |")
    lines += ["", "Training curves, per-epoch logs and each table row's published predictions "
              "(`*_predictions.npz`): [`runs/`](runs/).", ""]
    figures = plot_protocol_curves(out_dir, runs_list)
    if figures:
        lines += ["## Learning curves", "",
                  "Validation MAE per epoch of every run (from the published logs; one "
                  "colour per table row, one line style per seed; a dot marks the kept "
                  "epoch).", ""]
        lines += [f"![Learning curves, {protocol}]({name})" for protocol, name in figures]
        lines += [""]
    for stem, table in tables.items():
        body = report.markdown(table).split("\n")[1:]
        body = ["#" + line if line.startswith("#") else line for line in body]
        title = ("Table 1, the authors' released CVGL data (trained and scored as released)"
                 if stem == "table1_cvgl" and config.data == "release" else TITLES.get(stem, stem))
        lines += [f"## {title}", ""] + body
        plots = [f"![FOV-threshold curves, {stem}]({stem}_fov.png)"]
        if report.is_table2(table):
            plots.append(f"![Predicted against true field of view per rig, {stem}]"
                         f"({stem}_fov_scatter.png)")
        lines += plots + ["", f"Files: [`{stem}.md`]({stem}.md), [`{stem}.csv`]({stem}.csv), "
                              f"[`{stem}.json`]({stem}.json).", ""]
        differences = report.differences_beyond_spread(table.rows)
        if differences:
            lines += ["### Differences beyond the spread" + (" (pooled)" if report.is_table2(table)
                                                            else ""), "",
                      "NMAE = MAE / mean(|y|) of the rows trained on several seeds: `<` where "
                      "the first row's mean is lower by more than the two spreads added, "
                      "`>` where the second's is, `=` where the difference is within them.",
                      ""] + differences + [""]
    if summary.get("discussion"):
        lines += ["## Comparison with the paper", "", summary["discussion"].strip(), ""]
    files.write_text(os.path.join(out_dir, "REPORT.md"), "\n".join(lines) + "\n")


