"""Regenerate every result of ``paper_results/`` with one command.

    python -m cpl_keras.reproduce            # the paper's scale (a GPU job)
    python -m cpl_keras.reproduce --quick    # the same pipeline in minutes
    python -m cpl_keras.reproduce --pairs 2000 --epochs 4   # a chosen scale

(``python evaluate.py --reproduce ...`` is the same command.)

The pipeline, every stage resumable (datasets, finished runs and tables
newer than their runs are reused; killed training runs resume from their
last epoch):

1. data: a ``cvgl``-protocol dataset (the paper's 50 rigs), a ``random``-
   protocol dataset (realistic rigs) and the real Middlebury crops set;
2. training: Deep-Homo, MTL-CPL-U, MTL-Baseline and MTL-CPL-A on each
   protocol (``cvgl`` with the paper's frame-level 70/30 split, ``random``
   with whole configurations held out), plus MTL-CPL-A as released on cvgl;
3. tables: Table 1 for each protocol (with the Average, the release's
   Average and the Geometric rows), Table 2 (forward pass of the cvgl-trained
   models on the real set);
4. ``REPORT.md``: settings, dataset sizes, seeds, epochs actually run, wall
   times, the machine, the tables, the plots and the comparison with the
   paper.
"""

from __future__ import annotations

import os
import platform
import shutil
import sys
import time

os.environ.setdefault("KERAS_BACKEND", "jax")

from cpl_keras import cli, runs  # noqa: E402
from cpl_keras.models.variants import TABLE_ORDER  # noqa: E402

PROG = "python -m cpl_keras.reproduce"

#: The paper's scale: CVGL's 123,017 pairs, 200 epochs, InceptionV3 at 112.
PAPER_SCALE = {"pairs": 123017, "random_pairs": 123017, "epochs": 200, "image_size": 112,
               "backbone": "inception_v3", "crops": 500, "geometric_max": None,
               "batch_size": 16, "patience": 5}
#: Tiny settings that run the same pipeline end to end in minutes (CI).
QUICK = {"pairs": 150, "random_pairs": 150, "epochs": 1, "image_size": 32,
         "backbone": "small", "crops": 24, "geometric_max": 20, "batch_size": 16, "patience": 5}

#: (protocol, split, variants trained on it, with the as-released CPL-A where set)
PROTOCOLS = (
    ("cvgl", "paper", TABLE_ORDER, True),
    ("random", "held-out-config", TABLE_ORDER, False),
)


def settings(quick=False, **overrides):
    """The run settings: the paper's scale or QUICK, with ``overrides`` applied."""
    chosen = dict(QUICK if quick else PAPER_SCALE)
    for key, value in overrides.items():
        if value is None:
            continue
        if key not in chosen:
            raise ValueError(f"unknown setting {key!r}")
        if key in ("pairs", "random_pairs", "epochs", "crops", "batch_size", "patience",
                   "geometric_max", "image_size") and int(value) < 1:
            raise ValueError(f"{key.replace('_', '-')} must be positive, got {value}")
        chosen[key] = value
    chosen["quick"] = bool(quick)
    return chosen


def _log(message):
    print(f"[reproduce] {message}", file=sys.stderr, flush=True)


def make_datasets(config, data_dir, seed):
    """Stage 1: the synthetic datasets and the real set (reused when present)."""
    from cpl_keras.data.generate import GENERATOR_VERSION, generate_dataset
    from cpl_keras.real.middlebury import build_middlebury

    size = config["image_size"]
    paths = {}
    for protocol, pairs in (("cvgl", config["pairs"]), ("random", config["random_pairs"])):
        # the format version in the name: a file of an older generator is
        # never reused (it would be refused), a new one is made beside it
        path = os.path.join(data_dir, f"{protocol}_{pairs}_{size}px_s{seed}_v{GENERATOR_VERSION}.h5")
        if not os.path.exists(path):
            _log(f"generating {pairs} {protocol} pairs at {size}px -> {path}")
            generate_dataset(path, protocol=protocol, pairs=pairs, seed=seed, image_size=size,
                             progress=True)
        paths[protocol] = path
    path = os.path.join(data_dir, f"middlebury_{config['crops']}_{size}px_s{seed}.h5")
    if not os.path.exists(path):
        _log(f"building {config['crops']} Middlebury crops at {size}px -> {path}")
        build_middlebury(path, crops=config["crops"], image_size=size, seed=seed)
    paths["real"] = path
    return paths


def train_all(config, paths, runs_dir, seed):
    """Stage 2: every model of every protocol; returns {protocol: [run dirs]}."""
    from cpl_keras import training

    trained = {}
    for protocol, split, variants, with_released in PROTOCOLS:
        jobs = [(v, False) for v in variants] + ([("cpl-a", True)] if with_released else [])
        trained[protocol] = []
        for variant, released in jobs:
            name = variant + ("-released" if released else "")
            run_dir = os.path.join(runs_dir, protocol, name)
            plan = dict(
                variant=variant, run_dir=run_dir, epochs=config["epochs"],
                batch_size=config["batch_size"], backbone=config["backbone"], split=split,
                as_released=released, seed=seed, patience=config["patience"],
            )
            # Refuses (TrainingError) a run directory that holds a run of other
            # settings, so a run made at another scale is never reused.
            training.plan_run(paths[protocol], **plan)
            if (runs.read_config(run_dir) or {}).get("status") == "finished":
                _log(f"{protocol}/{name}: finished run found, reused")
                trained[protocol].append(run_dir)
                continue
            _log(f"training {protocol}/{name} ({config['backbone']}, up to {config['epochs']} epochs)")
            summary = training.train(paths[protocol], verbose=2, **plan)
            _log(training.summary_line(summary))
            if summary["best_epoch"] is None:
                raise training.TrainingError(f"{run_dir}: no epoch completed ({summary['stopped']})")
            trained[protocol].append(run_dir)
    return trained


def make_tables(config, paths, trained, out_dir, command):
    """Stage 3: Table 1 per protocol and Table 2; returns {stem: table}, with
    paths relative to ``out_dir``."""
    from cpl_keras import evaluation, report

    tables = {}
    jobs = [("table1_cvgl", 1, trained["cvgl"], None),
            ("table1_random", 1, trained["random"], None),
            ("table2_middlebury", 2, trained["cvgl"], paths["real"])]
    for stem, number, run_dirs, data in jobs:
        cached = _cached_table(os.path.join(out_dir, f"{stem}.json"), run_dirs, data)
        if cached is not None:
            _log(f"{stem}: up to date with its runs, reused")
            tables[stem] = cached
            continue
        _log(f"evaluating {stem}")
        table = evaluation.make_table(number, run_dirs, data, geometric=True,
                                      geometric_max=config["geometric_max"], progress=_log)
        report.write_outputs(out_dir, stem, table, command)
        tables[stem] = report.portable(table, out_dir)
    return tables


def _cached_table(path, run_dirs, data):
    """A table written earlier from the same runs and data, if none changed since."""
    table = runs.read_json(path)
    if table is None:
        return None
    # the table's paths are relative to its folder (older tables: absolute)
    here = os.path.dirname(os.path.abspath(path))
    recorded = [os.path.normpath(os.path.join(here, r)) for r in table.get("runs", [])]
    if recorded != [os.path.abspath(r) for r in run_dirs]:
        return None
    if data is not None and os.path.normpath(os.path.join(here, table.get("data", ""))) != \
            os.path.abspath(data):
        return None
    models = [os.path.join(r, runs.MODEL) for r in run_dirs]
    if not all(os.path.exists(m) for m in models):
        return None
    if max(os.path.getmtime(m) for m in models) > os.path.getmtime(path):
        return None
    return table


def collect_run_files(trained, out_dir):
    """Copy each run's training log and curves into ``out_dir/runs``; the
    runs' summaries (run directories relative to ``out_dir``)."""
    target = os.path.join(out_dir, "runs")
    os.makedirs(target, exist_ok=True)
    summaries = []
    for protocol, run_dirs in trained.items():
        for run_dir in run_dirs:
            name = f"{protocol}_{os.path.basename(run_dir)}"
            for source, suffix in ((runs.LOG, "_log.csv"), (runs.CURVES, "_curves.png")):
                path = os.path.join(run_dir, source)
                if os.path.exists(path):
                    shutil.copyfile(path, os.path.join(target, name + suffix))
            run_config = runs.read_config(run_dir, {})
            summaries.append({"protocol": protocol, "name": name,
                              "run_dir": runs.relative(run_dir, out_dir),
                              "as_released": runs.config_as_released(run_config),
                              **{k: run_config.get(k) for k in (
                                  "variant", "split", "epochs", "epochs_run",
                                  "best_epoch", "best_val_loss", "wall_time_s", "stopped")}})
    return summaries


def machine():
    import jax
    import keras

    return {"platform": platform.platform(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "keras": keras.__version__, "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()]}


def _dataset_line(path):
    from cpl_keras.data.storage import StereoFile

    with StereoFile(path) as f:
        meta = f.metadata
        configs = len(set(f.labels["config_id"].tolist())) if "config_id" in f.labels else "n/a"
        return (f"`{os.path.basename(path)}`: {f.num_pairs} pairs, "
                f"{f.image_shape[1]}x{f.image_shape[0]} px, {configs} configurations, "
                f"source {meta.get('source', meta.get('protocol'))}, seed {meta.get('seed')}")


def write_report(out_dir, config, paths, summaries, tables, info, command, discussion=None):
    """Stage 4: REPORT.md from the measured figures (and an optional discussion)."""
    from cpl_keras import report

    lines = ["# Reproducing Tables 1 and 2", ""]
    scale = "quick (tiny settings, a smoke test of the pipeline)" if config["quick"] else "as set below"
    lines += ["Everything on this page was produced by one command:", "", "```", command, "```", "",
              f"Scale: {scale}. Backbone `{config['backbone']}`, {config['image_size']}x"
              f"{config['image_size']} images, batch {config['batch_size']}, Adam (lr 1e-3, "
              f"Deep-Homo 1.5e-3), up to {config['epochs']} epochs with early stopping "
              f"(patience {config['patience']}, best weights restored). The paper trained up to "
              f"200 epochs on 123,017 pairs from ImageNet weights; here the towers start from "
              f"random weights (none can be downloaded).", "",
              f"Machine: {info['platform']}, Python {info['python']}, {info['cpus']} CPUs, "
              f"Keras {info['keras']}, JAX {info['jax']}, devices {', '.join(info['devices'])}. "
              f"Training wall time, summed over the runs: "
              f"{sum(s['wall_time_s'] or 0 for s in summaries) / 60:.1f} min; this invocation "
              f"(stages not reused from earlier ones): {info['wall_time_s'] / 60:.1f} min.", "",
              "## Data", ""]
    lines += [f"- {kind}: {_dataset_line(path)}" for kind, path in paths.items()]
    lines += ["", "## Training runs", "",
              "| protocol | run | split | epochs run | best epoch | best val loss | wall time (min) | stopped |",
              "|---|---|---|---|---|---|---|---|"]
    for s in summaries:
        wall = "" if s["wall_time_s"] is None else f"{s['wall_time_s'] / 60:.1f}"
        loss = "" if s["best_val_loss"] is None else f"{s['best_val_loss']:.4g}"
        lines.append(f"| {s['protocol']} | {s['name'].split('_', 1)[1]} | {s['split']} | "
                     f"{s['epochs_run']} | {s['best_epoch']} | {loss} | {wall} | {s['stopped'] or ''} |")
    lines += ["", "Training curves and per-epoch logs: [`runs/`](runs/).", ""]
    titles = {"table1_cvgl": "Table 1, paper protocol (cvgl rigs, frame-level 70/30 split)",
              "table1_random": "Table 1, unseen rigs (random protocol, whole configurations held out)",
              "table2_middlebury": "Table 2, real data (Middlebury crops, forward pass only)"}
    for stem, table in tables.items():
        body = report.markdown(table).split("\n")
        body = ["###" + line[2:] if line.startswith("## ") else line for line in body[1:]]
        lines += [f"## {titles[stem]}", ""] + body
        lines += [f"![FOV-threshold curves, {stem}]({stem}_fov.png)", "",
                  f"Files: [`{stem}.md`]({stem}.md), [`{stem}.csv`]({stem}.csv), "
                  f"[`{stem}.json`]({stem}.json).", ""]
    if discussion:
        lines += ["## Comparison with the paper", "", discussion.strip(), ""]
    runs.write_text(os.path.join(out_dir, "REPORT.md"), "\n".join(lines) + "\n")


def reproduce(*, out_dir, data_dir, runs_dir, config, seed=0, command="", discussion_file=None):
    """Run the whole pipeline; returns the path of REPORT.md."""
    for directory in (out_dir, data_dir, runs_dir):
        os.makedirs(directory, exist_ok=True)
    start = time.time()
    from cpl_keras.cache import enable_compile_cache

    enable_compile_cache()
    paths = make_datasets(config, data_dir, seed)
    trained = train_all(config, paths, runs_dir, seed)
    tables = make_tables(config, paths, trained, out_dir, command)
    summaries = collect_run_files(trained, out_dir)
    info = dict(machine(), wall_time_s=time.time() - start)
    discussion = None
    if discussion_file and os.path.exists(discussion_file):
        with open(discussion_file) as f:
            discussion = f.read()
    runs.write_json(os.path.join(out_dir, "reproduce.json"), {
        "command": command, "settings": config, "seed": seed,
        "data": {kind: runs.relative(path, out_dir) for kind, path in paths.items()},
        "runs": summaries, "machine": info})
    write_report(out_dir, config, paths, summaries, tables, info, command, discussion)
    return os.path.join(out_dir, "REPORT.md")


# ---------------------------------------------------------------------------
# Command line (also evaluate.py --reproduce)
# ---------------------------------------------------------------------------
def add_arguments(parser):
    """The reproduction's options, as an argument group of ``parser``."""
    from cpl_keras.models.backbones import BACKBONES

    group = parser.add_argument_group("reproduce (cpl_keras/reproduce.py)")
    group.add_argument("--quick", action="store_true", help="tiny settings (minutes)")
    group.add_argument("--pairs", type=int, help="cvgl-protocol pairs (paper: 123017)")
    group.add_argument("--random-pairs", type=int, help="random-protocol pairs")
    group.add_argument("--epochs", type=int, help="maximum epochs per run (paper: 200)")
    group.add_argument("--patience", type=int, help="early stopping patience (paper: 5)")
    group.add_argument("--backbone", choices=BACKBONES)
    group.add_argument("--image-size", type=int)
    group.add_argument("--crops", type=int, help="Middlebury crops for Table 2")
    group.add_argument("--seed", type=int, default=0)
    group.add_argument("--data-dir", help="where the datasets go (default data/reproduce)")
    group.add_argument("--runs-dir", help="where the runs go (default runs/reproduce)")
    group.add_argument("--discussion", help="Markdown file appended to REPORT.md as the "
                       "comparison with the paper (default paper_results/discussion.md "
                       "when writing to paper_results/)")
    return group


def resolve_defaults(args):
    """Fill in the output, data and runs folders (and the discussion file)."""
    from cpl_keras.evaluation import PAPER_DIR

    quick = "quick" if args.quick else "reproduce"
    args.out = args.out or (os.path.join("runs", "quick", "paper_results") if args.quick
                            else PAPER_DIR)
    args.data_dir = args.data_dir or os.path.join("data", quick)
    args.runs_dir = args.runs_dir or os.path.join("runs", quick)
    if args.discussion is None and os.path.abspath(args.out) == os.path.abspath(PAPER_DIR):
        args.discussion = os.path.join(PAPER_DIR, "discussion.md")
    return args


def run(args, command, prog=PROG):
    """Run the reproduction for parsed ``args``; the exit status."""
    from cpl_keras.data.storage import DatasetError

    try:
        config = settings(
            args.quick, pairs=args.pairs, random_pairs=args.random_pairs, epochs=args.epochs,
            patience=args.patience, backbone=args.backbone, image_size=args.image_size,
            crops=args.crops, geometric_max=args.geometric_max,
        )
        with cli.interruptible():
            report = reproduce(
                out_dir=args.out, data_dir=args.data_dir, runs_dir=args.runs_dir, config=config,
                seed=args.seed, command=command, discussion_file=args.discussion,
            )
    except KeyboardInterrupt:  # every stage is resumable: the same command goes on
        return cli.interrupted(prog, resume=command)
    except (ValueError, DatasetError, OSError) as error:  # EvaluationError is a ValueError
        return cli.fail(prog, error)
    print(f"report written to {report}")
    return 0


def main(argv=None):
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--out", help="output directory (default: paper_results/; with "
                        "--quick: runs/quick/paper_results)")
    parser.add_argument("--geometric-max", type=int,
                        help="run the Geometric baseline on the first N evaluation pairs only")
    add_arguments(parser)
    args = resolve_defaults(parser.parse_args(argv))
    if args.geometric_max is not None and args.geometric_max < 1:
        parser.error(f"--geometric-max must be positive, got {args.geometric_max}")
    return run(args, cli.command_line(PROG, argv), PROG)


if __name__ == "__main__":
    sys.exit(main())
