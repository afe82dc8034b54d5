"""Collapsed heads: on how many test pairs does a regression head put out
one and the same value, and how much of its error is there?

    D=data/reproduce-inception-2000-ema/cvgl_2000_112px_s0_v3.0.h5
    R=paper_results/inception-2000-ema/runs
    python analyses/collapsed_heads.py --data $D \\
        --run "MTL-CPL-A, seed 0=$R/cvgl_cpl-a-s0,$R/cvgl_baseline-s0" \\
        --run "MTL-Baseline, seed 0=$R/cvgl_baseline-s0" --out runs/collapsed.md

Every head is Dense(120, relu) -> Dense(84, relu) -> Dense(1)
(``layers.regression_head``). On a pair where every unit of its first layer
is at zero, the head's output is that of its biases alone: the same value
for every such pair, and no gradient reaches the head's first layer or the
towers from that pair through it. A head that has collapsed so on part of
the pairs shows in its stored predictions as one value shared by many test
pairs, which a working head (a camera parameter is the same only within one
rig) does not put out.

Each ``--run NAME=RUN[,REFERENCE]`` is one run directory (published or not,
read through its stored predictions where it has them), on the test split
of ``--data``, and optionally a run to compare with on the same pairs
(``--reference-name`` says what it is). Per run and column: the share of
test pairs on the run's most common output value (equal to 1e-6 of it);
where that share reaches ``--min-share``, the value, the truth of those
pairs, the share of the column's absolute error that falls on them, and the
MAE of the run and of the reference on them and on the other pairs.

With ``--units`` (only for runs whose ``model.keras`` is at hand; published
runs carry no weights), a forward pass also measures it in the heads: per
head, the share of test pairs with every unit of the first layer at zero,
and how many of its 120 units are above zero for any test pair.

``regenerate`` rebuilds a committed page from its JSON and the command on
its first line (no dataset or weights needed).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: Two outputs are one value when they differ by less than this (relative).
SAME = 1e-6


def run_spec(text):
    """``NAME=RUN[,REFERENCE]`` -> ``(name, run, reference or None)``."""
    name, sep, paths = text.partition("=")
    parts = paths.split(",")
    if not sep or not name or len(parts) not in (1, 2) or not all(parts):
        raise argparse.ArgumentTypeError(f"expected NAME=RUN[,REFERENCE], got {text!r}")
    return name, parts[0], parts[1] if len(parts) == 2 else None


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="the runs' dataset (.h5)")
    parser.add_argument("--run", action="append", required=True, type=run_spec,
                        metavar="NAME=RUN[,REFERENCE]", help="one run (repeatable)")
    parser.add_argument("--reference-name", default="MTL-Baseline",
                        help="what the REFERENCE runs are (the page's words)")
    parser.add_argument("--min-share", type=float, default=0.05,
                        help="the share of test pairs on one value that the page details")
    parser.add_argument("--units", action="store_true",
                        help="also count the heads' first-layer units at zero (needs model.keras)")
    parser.add_argument("--out", required=True, help="the Markdown page to write (.md)")
    args = parser.parse_args(argv)
    if not args.out.endswith(".md"):
        parser.error(f"--out must end in .md, got {args.out}")
    if not 0 < args.min_share <= 1:
        parser.error(f"--min-share must be in (0, 1], got {args.min_share}")
    return args


def modal_value(values):
    """``(value, mask)``: the value most outputs share (to ``SAME``, relative)
    and which outputs share it; the first such value where several tie."""
    values = np.asarray(values, np.float64)
    best, best_count = values[:1], 0
    for value in np.unique(values):
        count = int(np.sum(np.abs(values - value) <= SAME * max(abs(value), 1e-12)))
        if count > best_count:
            best, best_count = value, count
    value = float(np.asarray(best).reshape(-1)[0]) if len(values) else float("nan")
    return value, np.abs(values - value) <= SAME * max(abs(value), 1e-12)


def _slope(truth, pred):
    """Least-squares slope of ``pred`` on ``truth`` (1: follows the truth, 0:
    flat); ``None`` where the truth does not vary."""
    if np.ptp(truth) == 0:
        return None
    return float(np.polyfit(truth, pred, 1)[0])


def collapse(raw, reference=None):
    """Per column: the share of pairs on the modal output and, for the
    pairs on it, what they cost (``None`` where no pair shares a value)."""
    from cpl_keras.evaluation.verdicts import COLUMN_PARAMETER

    out = {}
    for column, name in COLUMN_PARAMETER.items():
        truth = np.asarray(raw["truth"][name], np.float64)
        pred = np.asarray(raw["pred"][name], np.float64)
        value, on = modal_value(pred)
        error = np.abs(pred - truth)
        cell = {"share": float(on.mean()), "pairs": int(on.sum()), "value": value}
        if on.sum() > 1 and (~on).any():
            low, high = float(truth[on].min()), float(truth[on].max())
            others = truth[~on]
            cell.update(truth_min=low, truth_max=high,
                        others_min=float(others.min()), others_max=float(others.max()),
                        others_inside=int(np.sum((others >= low) & (others <= high))),
                        error_share=float(error[on].sum() / error.sum()) if error.sum() else None,
                        mae_on=float(error[on].mean()), mae_off=float(error[~on].mean()))
            if reference is not None:
                ref = np.abs(np.asarray(reference["pred"][name], np.float64) - truth)
                ref_pred = np.asarray(reference["pred"][name], np.float64)
                cell.update(reference_on=float(ref[on].mean()),
                            reference_off=float(ref[~on].mean()),
                            reference_slope_on=_slope(truth[on], ref_pred[on]))
        out[column] = cell if on.sum() > 1 else {"share": 0.0, "pairs": 0, "value": None}
    return out


def first_layer_units(run_dir, data_path, batch_size=50):
    """Per head: the share of test pairs with every first-layer unit at zero
    and the units above zero for any of them (a forward pass of model.keras)."""
    import keras

    from cpl_keras.camera import PARAMETERS
    from cpl_keras.evaluation.pairs import evaluation_indices, open_dataset
    from cpl_keras.runs import load_run
    from cpl_keras.saving import load_model

    run = load_run(run_dir)
    path = os.path.join(run_dir, "model.keras")
    if not os.path.isfile(path):
        from cpl_keras.evaluation import EvaluationError

        raise EvaluationError(f"{run_dir}: no model.keras (--units needs the run's weights)")
    model = load_model(path)
    heads = [name for name in PARAMETERS if f"{name}_dense_120" in [x.name for x in model.layers]]
    probe = keras.Model(model.inputs, [model.get_layer(f"{h}_dense_120").output for h in heads])
    with open_dataset(data_path) as data:
        indices, _ = evaluation_indices(run, data_path, data.num_pairs)
        parts = []
        for start in range(0, len(indices), batch_size):
            left, right = data.read_pairs(indices[start:start + batch_size])
            parts.append([np.asarray(a) for a in probe.predict_on_batch(
                {"left_image": left.astype(np.float32), "right_image": right.astype(np.float32)})])
    acts = [np.concatenate([p[i] for p in parts]) for i in range(len(heads))]
    return {h: {"pairs_all_zero": float(np.mean(a.max(axis=1) <= 0)),
                "units_active": int(np.sum((a > 0).any(axis=0))), "units": int(a.shape[1])}
            for h, a in zip(heads, acts)}


def analyse(args):
    from cpl_keras.evaluation.forward_pass import paired_outputs

    result = {}
    for name, run_dir, reference_dir in args.run:
        raw, config = paired_outputs(run_dir, args.data)
        reference = paired_outputs(reference_dir, args.data)[0] if reference_dir else None
        if reference is not None and not np.array_equal(reference["indices"], raw["indices"]):
            from cpl_keras.evaluation import EvaluationError

            raise EvaluationError(f"{reference_dir}: its test pairs are not those of {run_dir}")
        result[name] = {"run": os.path.relpath(os.path.abspath(run_dir), REPO),
                        "reference": reference_dir and os.path.relpath(
                            os.path.abspath(reference_dir), REPO),
                        "seed": config.training.seed, "test_pairs": len(raw["indices"]),
                        "epochs_run": config.epochs_run, "best_epoch": config.best_epoch,
                        "columns": collapse(raw, reference)}
        if args.units:
            result[name]["units"] = first_layer_units(run_dir, args.data)
    return result


def _number(value, digits=3):
    return "-" if value is None else f"{value:.{digits}f}"


def markdown(result, args, command):
    """The page of ``result`` (``analyse``'s, or its JSON) written by ``command``."""
    from cpl_keras import files
    from cpl_keras.evaluation.verdicts import COLUMNS

    lines = [files.generated_line(command), "",
             "# Collapsed heads: test pairs on one output value", "", "```", command, "```",
             "", "Share of the test pairs on the run's most common output value, per column "
             "(a working head's outputs differ from pair to pair):", "",
             "| run | seed, test pairs | epochs (kept) | " + " | ".join(COLUMNS) + " |",
             "|---|---|---" + "|---" * len(COLUMNS) + "|"]
    for name, r in result.items():
        lines.append(f"| {name} | {r['seed']}, {r['test_pairs']} | {r['epochs_run']} "
                     f"({r['best_epoch']}) | " + " | ".join(
                         _number(r["columns"][c]["share"], 2) for c in COLUMNS) + " |")
    ref = args.reference_name
    lines += ["", f"Where the share is {args.min_share:g} or more: the value, the truth on "
              "those pairs and on the others (with how many of the others lie inside the "
              "first range: few where the head is dead on one end of the column's range), "
              "the share of the column's absolute error on them, and the MAE on them and on "
              f"the other pairs (the run's, then {ref}'s on the same pairs, with the slope of "
              f"{ref}'s output on the truth over the pairs on one value: 1 follows the truth, "
              "0 is flat):",
              "", "| run | column | pairs | value | truth on them | truth on the others "
              "(inside) | share of the error "
              f"| MAE on them / others | {ref}'s MAE on them / others |",
              "|---|---|---|---|---|---|---|---|---|"]
    for name, r in result.items():
        for column in COLUMNS:
            c = r["columns"][column]
            if c["share"] < args.min_share or "mae_on" not in c:
                continue
            reference = (f"{c['reference_on']:.4f} / {c['reference_off']:.4f} "
                         f"({_number(c['reference_slope_on'], 2)})"
                         if "reference_on" in c else "-")
            lines.append(f"| {name} | {column} | {c['pairs']} | {c['value']:.4f} | "
                         f"{c['truth_min']:.3f} to {c['truth_max']:.3f} | "
                         f"{c['others_min']:.3f} to {c['others_max']:.3f} ({c['others_inside']}) | "
                         f"{_number(c['error_share'], 2)} | {c['mae_on']:.4f} / "
                         f"{c['mae_off']:.4f} | {reference} |")
    return "\n".join(lines + units_lines(result)) + "\n"


def units_lines(result):
    rows = {name: r["units"] for name, r in result.items() if "units" in r}
    if not rows:
        return []
    heads = list(next(iter(rows.values())))
    lines = ["", "In the heads (a forward pass of each run's model.keras over its test "
             "pairs): the share of pairs with every unit of the head's first layer at zero "
             "(at or below zero for a leaky ReLU), and the units above zero for any test "
             "pair, of 120:", "",
             "| run | " + " | ".join(heads) + " |", "|---" + "|---" * len(heads) + "|"]
    for name, units in rows.items():
        lines.append(f"| {name} | " + " | ".join(
            f"{units[h]['pairs_all_zero']:.2f}, {units[h]['units_active']}" if h in units
            else "-" for h in heads) + " |")
    return lines


def command_line(args):
    runs = [f'--run "{n}={r}' + (f',{ref}"' if ref else '"') for n, r, ref in args.run]
    return " ".join(["python analyses/collapsed_heads.py", f"--data {args.data}"] + runs
                    + ([f'--reference-name "{args.reference_name}"']
                       if args.reference_name != "MTL-Baseline" else [])
                    + ([f"--min-share {args.min_share:g}"] if args.min_share != 0.05 else [])
                    + (["--units"] if args.units else []) + [f"--out {args.out}"])


def regenerate(page_path):
    """The committed page ``page_path`` as this script writes it, from its
    JSON beside it and the command on its first line (its options)."""
    from cpl_keras import files

    command, payload = files.page_source(page_path)
    args = parse_args(shlex.split(command)[2:])
    return markdown(payload, args, command)


def main(argv=None):
    from cpl_keras import files

    args = parse_args(argv)
    result = analyse(args)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    files.write_page(args.out, markdown(result, args, command_line(args)), result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    from cpl_keras import cli

    cli.run(main, "analyses/collapsed_heads.py")
