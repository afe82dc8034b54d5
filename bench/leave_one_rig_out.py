"""Real cameras, leave one rig out: train the models a recipe makes and score
each only on the real rigs it never saw, against the targets a person
calibrating their own rig needs (median relative error of fx and of fy at
most 0.15, the horizontal FoV within 5 degrees on at least half the pairs).

    python bench/leave_one_rig_out.py --synthetic data/wild.h5 --real-dir data/real \\
        --out paper_results/real-cameras --runs-dir runs/real-cameras \\
        [--with-real-crops] [--variant baseline] [--backbone small_resnet] \\
        [--epochs 60] [--augment photometric] [--time-budget 1500]

Without ``--with-real-crops`` one model trains on the synthetic set alone and
is scored on every real set of ``--real-dir``. With it, one model per real
rig trains on the synthetic set mixed (``cpl_keras.data.mix``) with the crops
of every OTHER real rig, and is scored on that rig only: a rig used in any
form in training is never a test rig (Table 2 refuses it anyway). The
training split is held-out-config, or with the real crops the paper's
frame-level split (held-out-config can put a whole real rig, one
configuration, into its test part, so that it is never trained on). Runs
resume where they stopped (the same command again); every finished model's
Table 2 goes to ``--out/<model>/`` (and its record on those rigs into its run
directory, ``real_cameras.json``, which calibrate reports), its log, curves
and config to ``--out/runs/``, and ``--out/summary.md`` collects the
field's metrics per rig with the targets. ``--out/summary.json`` holds
everything summary.md shows (``summary_markdown`` renders the page from it,
``regenerate`` again from the committed file).

fy is scored twice: the network's fy head (Table 2), and fy from square
pixels (``camera.square_pixel_fy``: fx and the crop's width and height, as
``calibrate --aspect square``, its default, reports it). The targets are
judged on the latter, what calibrate prints.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import os
import sys

from cpl_keras import files

os.environ.setdefault("KERAS_BACKEND", "jax")

#: What a calibrated real rig needs (issue targets): median relative focal
#: error of fx and fy, and the share of pairs with the hFoV within 5 degrees.
TARGETS = {"relative": 0.15, "fov_deg": 5, "fov_share": 0.5}
ROW = {"baseline": "MTL-Baseline", "cpl-u": "MTL-CPL-U", "cpl-a": "MTL-CPL-A"}


def real_sets(real_dir):
    """rig name -> path of every real set in ``real_dir``."""
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.evaluation.table2 import rig_name

    found = {}
    for path in sorted(glob.glob(os.path.join(real_dir, "*.h5"))):
        with StereoFile(path) as f:
            found[rig_name(f.metadata, path)] = path
    if not found:
        raise SystemExit(f"no real sets (*.h5) in {real_dir}; build them with "
                         f"python -m cpl_keras.real.build all --out-dir {real_dir}")
    return found


def plan(args, rigs):
    """``[(model name, training set, the rigs it is scored on)]``."""
    if not args.with_real_crops:
        return [("synthetic", args.synthetic, sorted(rigs))]
    from cpl_keras.data.mix import mix_datasets

    models = []
    for rig in sorted(rigs):
        if args.only and rig not in args.only:
            continue
        data = os.path.join(args.runs_dir, f"mix_without_{rig}.h5")
        if not os.path.exists(data):
            others = [rigs[r] for r in sorted(rigs) if r != rig]
            mix_datasets(data, [args.synthetic] + others)
        models.append((f"without-{rig}", data, [rig]))
    return models


def publish(run_dir, target, name):
    """The run's log, curves and config (no weights; the dataset and run
    directory without this machine's paths) as ``target/<name>_*``."""
    from cpl_keras import published, runs
    from cpl_keras.files import write_json

    published.publish_files(run_dir, target, name)
    config = runs.read_run_config(run_dir)
    portable = dataclasses.replace(
        config, data=dataclasses.replace(config.data, path=os.path.basename(config.data.path)),
        run_dir=name)
    write_json(os.path.join(target, f"{name}_config.json"), portable.to_dict())


def square_pixel_fy_error(run_dir, path):
    """Median relative error of fy from square pixels on every pair of the
    real set ``path``: ``camera.square_pixel_fy`` of the run's fx and each
    crop's width and height (labels ``crop_width``, ``crop_height``)."""
    import numpy as np

    from cpl_keras import evaluation
    from cpl_keras.camera import square_pixel_fy
    from cpl_keras.runs import load_run

    run = load_run(run_dir)
    try:
        with evaluation.open_dataset(path) as data:
            size_h, size_w = data.image_shape[:2]
            labels = data.labels
            fx = evaluation.run_predictions(run, data, np.arange(data.num_pairs))["fx"]
    finally:
        evaluation.forget_model(run)
    fy = square_pixel_fy(fx, labels["crop_width"], labels["crop_height"], size_w, size_h)
    return float(np.median(np.abs(fy / labels["fy"] - 1.0)))


def own_test_rows(name, run_dir):
    """The model's scores on its own test split, per source of its training
    file (the rendered pairs, each trained-on rig's held-out crops): median
    relative error of fx and of the fy head, one dict per source."""
    import numpy as np

    from cpl_keras import evaluation
    from cpl_keras.datasets import load_split
    from cpl_keras.runs import load_run

    run = load_run(run_dir)
    test = load_split(os.path.join(run_dir, "split.npz"))["test"]
    try:
        with evaluation.open_dataset(run.config.data.path) as data:
            labels, meta = data.labels, data.metadata
            pred = evaluation.run_predictions(run, data, test)
    finally:
        evaluation.forget_model(run)
    source = labels["source_index"][test] if "source_index" in labels else np.zeros(len(test), int)
    names = [r.get("rig") or "rendered" for r in meta.get("sources", [{}])]
    rows = []
    for k, source_name in enumerate(names):
        mask = source == k
        if not mask.any():
            continue
        fx, fy = (float(np.median(np.abs(pred[n][mask] / labels[n][test][mask] - 1.0)))
                  for n in ("fx", "fy"))
        rows.append({"model": name, "source": source_name, "test_pairs": int(mask.sum()),
                     "fx_relative_median": fx, "fy_head_relative_median": fy})
    return rows


def summary_rows(name, table, row, square_fy):
    """One dict per rig of a model's Table 2: its field metrics and the
    Average row's, fy from square pixels (``square_fy``: rig -> median
    relative error), and which targets are met (fy: square pixels)."""
    rows = []
    for rig, part in table.rigs.items():
        model, average = part.rows[row], part.rows["Average"]
        field = {k: float(model["field"][k]) for k in
                 ("relative_fx_median", "relative_fy_median", "hfov_error_deg_median")}
        within = float(model["fov_within_deg"][str(TARGETS["fov_deg"])]) / 100
        fy_square = float(square_fy[rig])
        rows.append({
            "rig": rig, "model": name, "pairs": int(model["num_pairs"]),
            "fx_relative_median": field["relative_fx_median"],
            "fx_relative_median_average": float(average["field"]["relative_fx_median"]),
            "fy_square_pixels_relative_median": fy_square,
            "fy_head_relative_median": field["relative_fy_median"],
            "fy_head_relative_median_average": float(average["field"]["relative_fy_median"]),
            "hfov_error_deg_median": field["hfov_error_deg_median"],
            "hfov_within_share": within,
            "targets_met": {"fx": bool(field["relative_fx_median"] <= TARGETS["relative"]),
                            "fy_square_pixels": bool(fy_square <= TARGETS["relative"]),
                            "hfov": bool(within >= TARGETS["fov_share"])}})
    return rows


def summary_markdown(summary):
    """summary.md from summary.json's dict (``summary``: ``command``,
    ``targets``, ``held_out``, ``own_test``), its generated line first."""
    targets = summary["targets"]
    lines = [files.generated_line(summary["command"]), "",
             "# Real rigs held out from training", "",
             f"Targets: median relative error of fx and of fy at most {targets['relative']}, "
             f"hFoV within {targets['fov_deg']} deg on at least "
             f"{100 * targets['fov_share']:.0f} % of the pairs; fy judged from square pixels "
             "(fx and the crop's sides, as calibrate reports it).", "",
             "| rig | model | pairs | fx rel. error (Average) | fy rel. error, square pixels | "
             "fy rel. error, fy head (Average) | hFoV error, deg | hFoV within 5 deg | "
             "targets met |", "|---|---|---|---|---|---|---|---|---|"]
    for r in summary["held_out"]:
        lines.append(
            f"| {r['rig']} | {r['model']} | {r['pairs']} | {r['fx_relative_median']:.3f} "
            f"({r['fx_relative_median_average']:.3f}) | "
            f"{r['fy_square_pixels_relative_median']:.3f} | "
            f"{r['fy_head_relative_median']:.3f} ({r['fy_head_relative_median_average']:.3f}) | "
            f"{r['hfov_error_deg_median']:.1f} | {100 * r['hfov_within_share']:.0f} % | "
            f"{'yes' if all(r['targets_met'].values()) else 'no'} |")
    lines += ["", "On each model's own test split (pairs of its training file it did not train "
              "on, per source):", "",
              "| model | source | test pairs | fx rel. error | fy rel. error (fy head) |",
              "|---|---|---|---|---|"]
    lines += [f"| {r['model']} | {r['source']} | {r['test_pairs']} | "
              f"{r['fx_relative_median']:.3f} | {r['fy_head_relative_median']:.3f} |"
              for r in summary["own_test"]]
    return "\n".join(lines) + "\n"


def regenerate(page_path):
    """The text ``main`` wrote for the committed page ``page_path``: a
    summary.md from summary.json beside it, a model's table2.md from its
    table2.json (``report.regenerate``)."""
    if os.path.basename(page_path) != "summary.md":
        from cpl_keras import report

        return report.regenerate(page_path)
    with open(os.path.join(os.path.dirname(page_path), "summary.json")) as f:
        return summary_markdown(json.load(f))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--synthetic", required=True, help="the rendered training set (.h5)")
    parser.add_argument("--real-dir", required=True, help="folder of real sets (real.build all)")
    parser.add_argument("--out", required=True, help="folder for the tables and summary.md")
    parser.add_argument("--runs-dir", required=True, help="folder for the runs and mixed sets")
    parser.add_argument("--with-real-crops", action="store_true",
                        help="one model per rig, trained with the other rigs' crops")
    parser.add_argument("--only", nargs="+", metavar="RIG",
                        help="with --with-real-crops: train only the models that leave out "
                        "these rigs (the rest of a later run resumes them)")
    parser.add_argument("--variant", choices=sorted(ROW), default="baseline")
    parser.add_argument("--split", choices=("paper", "held-out-config"),
                        help="the training run's split (default held-out-config; with "
                        "--with-real-crops paper: a real rig can be one configuration, the "
                        "chessboard's 260 crops, which held-out-config would hold out whole)")
    parser.add_argument("--backbone", default="small_resnet")
    parser.add_argument("--epochs", type=int, default=60)
    parser.add_argument("--augment", default="photometric")
    parser.add_argument("--time-budget", type=float, help="seconds of training per model")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    from cpl_keras import evaluation, real_record, report
    from cpl_keras.training import train

    os.makedirs(args.runs_dir, exist_ok=True)
    rigs = real_sets(args.real_dir)
    command = "python bench/leave_one_rig_out.py " + " ".join(argv or sys.argv[1:])
    held_out, own = [], []
    for name, data, tested in plan(args, rigs):
        run_dir = os.path.join(args.runs_dir, name)
        split = args.split or ("paper" if args.with_real_crops else "held-out-config")
        result = train(data, variant=args.variant, run_dir=run_dir, backbone=args.backbone,
                       epochs=args.epochs, split=split, seed=args.seed,
                       augment=None if args.augment == "none" else args.augment,
                       time_budget_s=args.time_budget, verbose=2)
        if result.config.status != "finished":
            raise SystemExit(f"{run_dir}: {result.config.status} ({result.config.stopped})")
        publish(run_dir, os.path.join(args.out, "runs"), name)
        table = evaluation.make_table2([run_dir], [rigs[r] for r in tested], geometric=False)
        report.write_outputs(os.path.join(args.out, name), "table2", table, command)
        # the run's own record on the rigs it never saw, for calibrate to say
        real_record.write_record(run_dir, table, command=command)
        square_fy = {r: square_pixel_fy_error(run_dir, rigs[r]) for r in tested}
        held_out += summary_rows(name, table, ROW[args.variant], square_fy)
        own += own_test_rows(name, run_dir)
        print(f"{name}: scored on {', '.join(tested)}", flush=True)
    summary = {"command": command, "args": vars(args), "rigs": rigs, "targets": TARGETS,
               "held_out": held_out, "own_test": own}
    text = summary_markdown(summary)
    files.write_text(os.path.join(args.out, "summary.md"), text)  # (atomically)
    files.write_json(os.path.join(args.out, "summary.json"), summary, indent=1)
    print(text)
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/leave_one_rig_out.py')
