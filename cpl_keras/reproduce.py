"""Regenerate every result of ``paper_results/`` with one command.

    python -m cpl_keras.reproduce                     # the paper's scale (a GPU job)
    python -m cpl_keras.reproduce --preset paper      # the same, into paper_results/paper/
    python -m cpl_keras.reproduce --preset paper-gpu  # CPL-A vs Baseline in 10 min of a GPU
    python -m cpl_keras.reproduce --preset cpu --jobs 2   # compact towers, 3 seeds, ~1.5 h on 2 cores
    python -m cpl_keras.reproduce --quick             # the same pipeline in minutes
    python -m cpl_keras.reproduce --pairs 2000 --epochs 4   # a chosen scale
    python -m cpl_keras.reproduce --from-predictions DIR    # tables again, from DIR alone

(``python evaluate.py --reproduce ...`` is the same command.)

The pipeline, every stage resumable (datasets, finished runs and published
predictions newer than their runs are reused; killed training runs resume
from their last epoch):

1. data: a ``cvgl``-protocol dataset (the paper's 50 rigs), a ``random``-
   protocol dataset (realistic rigs) and every real rig
   (``cpl_keras.real.build all``: the shipped OpenCV chessboard rig and
   Middlebury, KITTI / Tsinghua-Daimler / Cityscapes where their roots are
   given);
2. training: the preset's variants on each protocol (``cvgl`` with the
   paper's frame-level 70/30 split, ``random`` with whole configurations held
   out), plus MTL-CPL-A as released on cvgl where the preset has it; the
   preset's ``seeded_variants`` are trained for each of its seeds (a seed
   changes the split and the initial weights), the other runs once, on the
   first seed (``cpu``: the three MTL variants on 3 seeds, Deep-Homo and
   MTL-CPL-A as released on one);
3. predictions: every row of every table (each run, and the Average, the
   release's Average and the Geometric baselines) on its pairs, published as
   ``<out>/runs/*_predictions.npz`` (``cpl_keras.predictions``): Table 1 on
   each protocol's test split, Table 2 as a forward pass of the cvgl-trained
   models on every real rig;
4. tables, made from those files alone: Table 1 per protocol, Table 2 per rig
   and pooled (``cpl_keras.real.table2``); a table over several seeds gives
   every cell as mean ± spread, a row trained on one seed only its value;
5. ``REPORT.md``: settings, dataset sizes, seeds, epochs actually run, wall
   times, the machine, the tables, the plots and the comparison with the
   paper; ``reproduce.json`` holds the same facts, so that
   ``--from-predictions`` rebuilds the tables and REPORT.md without weights
   or datasets.
"""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import time

os.environ.setdefault("KERAS_BACKEND", "jax")

from cpl_keras import cli, runs  # noqa: E402
from cpl_keras.models.variants import TABLE_ORDER  # noqa: E402

PROG = "python -m cpl_keras.reproduce"

#: The MTL variants (the paper's three networks with two towers).
MTL_VARIANTS = ("cpl-u", "baseline", "cpl-a")

#: The run name stem of MTL-CPL-A as released (a ``seeded_variants`` entry).
RELEASED_RUN = "cpl-a-released"

#: Named scales. ``pairs`` / ``random_pairs``: pairs of the cvgl / random
#: datasets; ``seeds`` / ``random_seeds``: seeds per protocol (each its own
#: split and initial weights); ``variants``: trained on each protocol;
#: ``released``: also MTL-CPL-A as released on cvgl; ``seeded_variants``: the
#: runs trained on every seed (variants, and ``RELEASED_RUN``; None: all of
#: them), the others are trained once, on the first seed; ``crops``:
#: Middlebury crops; ``chessboard_crops``: crops per chessboard pair;
#: ``geometric_max``: pairs of each table (or real set) the Geometric
#: baseline runs on (None: all); ``workers``: data generation processes
#: (None: every core).
PRESETS = {
    # The paper's scale: CVGL's 123,017 pairs, up to 200 epochs, InceptionV3 at
    # 112 (the scale without --preset, into paper_results/paper/).
    "paper": {"pairs": 123017, "random_pairs": 123017, "epochs": 200, "image_size": 112,
              "backbone": "inception_v3", "crops": 500, "chessboard_crops": 20,
              "geometric_max": None, "batch_size": 16, "patience": 5, "seeds": 1,
              "random_seeds": 1, "variants": TABLE_ORDER, "released": True,
              "seeded_variants": None, "workers": None},
    # Ten minutes of one GPU machine (the device's per-command limit): the
    # deciding pair, MTL-CPL-A then MTL-Baseline, with the paper's towers on
    # 20,000 cvgl pairs rendered on that machine's CPU cores; each run ends at
    # early stopping or at its time budget, whichever comes first; Table 2
    # from both. bench/paper_gpu.sh runs it there and packs what comes back;
    # its --dry-run checks the same plan on a CPU at tiny scale.
    "paper-gpu": {"pairs": 20000, "random_pairs": 20000, "epochs": 200, "image_size": 112,
                  "backbone": "inception_v3", "crops": 500, "chessboard_crops": 20,
                  "geometric_max": 200, "batch_size": 16, "patience": 5, "seeds": 1,
                  "random_seeds": 1, "variants": ("cpl-a", "baseline"), "released": False,
                  "seeded_variants": None, "workers": None, "tables": ("cvgl",),
                  "run_budget_s": 150},
    # Sized for a 2-core CPU: 1 h 24 min measured with --jobs 2 (docs/evaluation.md):
    # every row of the tables, the MTL variants on cvgl over 3 seeds, Deep-Homo
    # and MTL-CPL-A as released on the first seed only; 1,000 pairs per
    # protocol, since a Deep-Homo training step costs 15-18 small_resnet ones.
    "cpu": {"pairs": 1000, "random_pairs": 1000, "epochs": 60, "image_size": 112,
            "backbone": "small_resnet", "crops": 500, "chessboard_crops": 20,
            "geometric_max": 200, "batch_size": 16, "patience": 5, "seeds": 3,
            "random_seeds": 1, "variants": TABLE_ORDER, "released": True,
            "seeded_variants": MTL_VARIANTS, "workers": None,
            "real_sets": ("chessboard", "middlebury")},
    # Tiny settings that run the paper-gpu pipeline end to end in minutes (CI).
    "quick": {"pairs": 150, "random_pairs": 150, "epochs": 1, "image_size": 32,
              "backbone": "small", "crops": 24, "chessboard_crops": 1, "geometric_max": 20,
              "batch_size": 16, "patience": 5, "seeds": 1, "random_seeds": 1,
              "variants": TABLE_ORDER, "released": True, "seeded_variants": None,
              "workers": None},
    # Does MTL-CPL-A beat MTL-Baseline? The three MTL variants on 8,000 cvgl
    # pairs, 3 seeds each, on the paper's frame-level split and on the drive
    # split (no test frame next to a training frame), every run to early
    # stopping; Table 2 from the paper-split runs. Many hours on 2 cores:
    # each finished run is published at once and a rerun skips it
    # (docs/evaluation.md#presets). The runs of a seed train in the order
    # CPL-A, Baseline, CPL-U, so the comparison that decides comes first.
    "cpu-8000": {"pairs": 8000, "random_pairs": 1000, "epochs": 100, "image_size": 112,
                 "backbone": "small_resnet", "crops": 500, "chessboard_crops": 20,
                 "geometric_max": None, "batch_size": 16, "patience": 5, "seeds": 3,
                 "random_seeds": 1, "variants": ("cpl-a", "baseline", "cpl-u"),
                 "released": False, "seeded_variants": None, "workers": None,
                 "tables": ("cvgl", "cvgl_drive"), "real_sets": ("chessboard", "middlebury")},
}
#: The Table 1 versions a reproduction can make, by key: (protocol, split,
#: the setting holding its number of seeds). A preset's ``tables`` lists
#: those it makes (default: ``DEFAULT_TABLES``); Table 2 comes from the
#: ``cvgl`` runs.
TABLE1 = {
    "cvgl": ("cvgl", "paper", "seeds"),
    "cvgl_drive": ("cvgl", "drive", "seeds"),
    "random": ("random", "held-out-config", "random_seeds"),
}
DEFAULT_TABLES = ("cvgl", "random")
#: The scale without --preset: the paper's, generating data on every core.
PAPER_SCALE = PRESETS["paper"]
QUICK = PRESETS["quick"]
#: Settings that are counts: positive integers (patience may be 0).
POSITIVE = ("pairs", "random_pairs", "epochs", "image_size", "crops", "chessboard_crops",
            "geometric_max", "batch_size", "seeds", "random_seeds", "workers")
#: Smallest image side of the real sets (StereoBM's block of 15 and 16 disparities).
MIN_REAL_IMAGE_SIZE = 32

#: The real sets that ship with the package, each a Table 2 rig (a preset's
#: ``real_sets`` may name fewer: the presets whose runs are committed keep
#: the rigs they were evaluated on, so that a rerun restores them).
REAL_SETS = ("chessboard", "middlebury", "oakd")
#: Real-data roots reproduce passes on to ``cpl_keras.real.build all``.
REAL_ROOTS = ("kitti", "kitti_raw", "tsinghua", "cityscapes")
#: The tables' titles in REPORT.md.
TITLES = {"table1_cvgl": "Table 1, paper protocol (cvgl rigs, frame-level 70/30 split)",
          "table1_cvgl_drive": "Table 1, paper protocol, drive split (cvgl rigs, the end of "
                               "every rig's drive held out)",
          "table1_random": "Table 1, unseen rigs (random protocol, whole configurations held out)",
          "table2": "Table 2, real rigs (per rig and pooled; forward pass of the cvgl-trained "
                    "models)"}


def settings(quick=False, preset=None, **overrides):
    """The run settings: a preset (``PRESETS``; default ``PAPER_SCALE``,
    ``quick=True`` is ``preset="quick"``) with ``overrides`` applied (None:
    keep the preset's). ValueError (one line) on a bad value."""
    if quick and preset not in (None, "quick"):
        raise ValueError(f"--quick is --preset quick; it cannot go with --preset {preset}")
    name = "quick" if quick else preset
    if name is not None and name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    chosen = dict(PRESETS[name] if name else PAPER_SCALE)
    chosen.setdefault("tables", DEFAULT_TABLES)
    chosen.setdefault("run_budget_s", None)
    chosen.setdefault("real_sets", REAL_SETS)
    chosen["real_sets"] = tuple(chosen["real_sets"])
    unknown = [s for s in chosen["real_sets"] if s not in REAL_SETS]
    if unknown:
        raise ValueError(f"unknown real set {unknown[0]!r}; choose from {', '.join(REAL_SETS)}")
    for key, value in overrides.items():
        if value is None:
            continue
        if key not in chosen:
            raise ValueError(f"unknown setting {key!r}")
        chosen[key] = value
    for key in POSITIVE + ("patience",):
        value = chosen[key]
        if value is None and key in ("geometric_max", "workers"):
            continue
        least = 0 if key == "patience" else 1
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            what = "non-negative" if least == 0 else "positive"
            raise ValueError(f"{key.replace('_', '-')} must be {what}, got {value}")
    budget = chosen["run_budget_s"]
    if budget is not None and (isinstance(budget, bool) or not isinstance(budget, (int, float))
                               or not math.isfinite(budget) or budget <= 0):
        raise ValueError(f"run-budget must be a positive number of seconds, got {budget}")
    from cpl_keras.models import variants as registry
    from cpl_keras.models.variants import BACKBONES, MIN_IMAGE_SIZE

    if chosen["backbone"] not in BACKBONES:
        raise ValueError(f"unknown backbone {chosen['backbone']!r}; choose one of "
                         f"{', '.join(BACKBONES)}")
    chosen["variants"] = tuple(chosen["variants"])
    chosen["tables"] = tuple(chosen["tables"])
    unknown = [t for t in chosen["tables"] if t not in TABLE1]
    if unknown or not chosen["tables"]:
        raise ValueError(f"unknown table {unknown[0] if unknown else '(none)'!r}; choose from "
                         f"{', '.join(TABLE1)}")
    for variant in chosen["variants"]:
        registry.get(variant)
    if chosen["seeded_variants"] is not None:
        chosen["seeded_variants"] = tuple(chosen["seeded_variants"])
        trained = run_stems(chosen)
        for stem in chosen["seeded_variants"]:
            if stem not in trained:
                raise ValueError(f"seeded variant {stem!r} is not trained by these settings "
                                 f"({', '.join(trained)})")
    least = max([MIN_REAL_IMAGE_SIZE, MIN_IMAGE_SIZE.get(chosen["backbone"], 1)]
                + [registry.get(v).min_image_size or 1 for v in chosen["variants"]])
    if chosen["image_size"] < least:
        raise ValueError(f"image-size must be at least {least} (the {chosen['backbone']} "
                         f"backbone and the real sets), got {chosen['image_size']}")
    chosen["preset"] = name
    chosen["quick"] = name == "quick"
    return chosen


def _log(message):
    print(f"[reproduce] {message}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------
# Stage 1: data
# ---------------------------------------------------------------------------
def real_set_folder(config, data_dir, seed):
    """Where the real sets of these settings go (one file per rig)."""
    return os.path.join(data_dir, f"real_{config['image_size']}px_mb{config['crops']}_"
                                  f"cb{config['chessboard_crops']}_s{seed}")


def make_datasets(config, data_dir, seed, real_roots=None):
    """Stage 1: the synthetic datasets and every real set (reused when
    present); ``{"cvgl": path, "random": path, "real": [paths]}``."""
    from cpl_keras.data.generate import GENERATOR_VERSION, generate_dataset
    from cpl_keras.real import build

    size = config["image_size"]
    paths = {}
    needed = {TABLE1[t][0] for t in config.get("tables", DEFAULT_TABLES)}
    for protocol, pairs in (("cvgl", config["pairs"]), ("random", config["random_pairs"])):
        if protocol not in needed:
            continue
        # the format version in the name: a file of an older generator is
        # never reused (it would be refused), a new one is made beside it
        path = os.path.join(data_dir, f"{protocol}_{pairs}_{size}px_s{seed}_v{GENERATOR_VERSION}.h5")
        if not os.path.exists(path):
            _log(f"generating {pairs} {protocol} pairs at {size}px -> {path}")
            generate_dataset(path, protocol=protocol, pairs=pairs, seed=seed, image_size=size,
                             workers=config["workers"], progress=True)
        paths[protocol] = path
    # every real rig, through the one builder of ``python -m cpl_keras.real.build all``
    args = build.parse_args(["all", "--out-dir", real_set_folder(config, data_dir, seed),
                             "--image-size", str(size), "--seed", str(seed)])
    for name in REAL_ROOTS:
        setattr(args, name, (real_roots or {}).get(name))
    paths["real"] = build.build_all(
        args, report=_log, stems=config["real_sets"],
        crops={"middlebury": config["crops"], "chessboard": config["chessboard_crops"],
               "oakd": config["chessboard_crops"]})
    return paths


# ---------------------------------------------------------------------------
# Stage 2: training
# ---------------------------------------------------------------------------
def run_stems(config, protocol="cvgl"):
    """The runs of the settings on ``protocol``, by name stem (the variant, or
    ``RELEASED_RUN``)."""
    stems = list(config["variants"])
    if protocol == "cvgl" and config["released"]:
        stems.append(RELEASED_RUN)
    return tuple(stems)


def run_jobs(config, seed):
    """Every training run of the settings: ``(table key, protocol, split, run
    seed, variant, as released, run name)``. The runs of ``seeded_variants``
    (None: all) are trained on every seed of a table, the others on its first
    seed only; a table trained over several seeds names its runs
    ``<stem>-s<seed>`` (``cpl-u-s1``, ``deep-homo-s0``, ``cpl-a-released-s0``)."""
    seeded = config.get("seeded_variants")
    jobs = []
    for key in config.get("tables", DEFAULT_TABLES):
        protocol, split, seeds_key = TABLE1[key]
        count = config[seeds_key]
        for run_seed in range(seed, seed + count):
            for stem in run_stems(config, protocol):
                if run_seed != seed and seeded is not None and stem not in seeded:
                    continue
                released = stem == RELEASED_RUN
                variant = "cpl-a" if released else stem
                name = stem + (f"-s{run_seed}" if count > 1 else "")
                jobs.append((key, protocol, split, run_seed, variant, released, name))
    return jobs


def train_all(config, paths, runs_dir, seed, jobs=1, out_dir=None):
    """Stage 2: every run; returns ``{table key: {seed: [run dirs]}}``.
    ``jobs`` > 1 trains that many runs at a time, each in its own process
    (``train_parallel``); the runs are the same either way.

    With ``out_dir``, each run is published the moment it ends
    (``publish_run``: its stored predictions, log, curves, config and split
    in ``out_dir/runs/<key>_<name>/``, no weights), and a run whose
    published record is there but whose run directory is not (another
    machine, a later session) is restored from it instead of trained again.
    """
    from cpl_keras import training

    trained, pending = {}, []
    for key, protocol, split, run_seed, variant, released, name in run_jobs(config, seed):
        run_dir = os.path.join(runs_dir, key, name)
        plan = dict(
            variant=variant, run_dir=run_dir, epochs=config["epochs"],
            batch_size=config["batch_size"], backbone=config["backbone"], split=split,
            as_released=released, seed=run_seed, patience=config["patience"],
            time_budget_s=config.get("run_budget_s"),
        )
        record = published_record(out_dir, key, name) if out_dir else None
        finished = (runs.read_config(run_dir) or {}).get("status") == "finished"
        if not finished and record and runs.is_published(record) and \
                not (os.path.isdir(run_dir) and os.listdir(run_dir)):
            runs.restore_run_dir(record, run_dir, paths[protocol])
            _log(f"{key}/{name}: restored from its published record {record} (no weights)")
            finished = True
        # Refuses (TrainingError) a run directory that holds a run of other
        # settings, so a run made at another scale is never reused.
        training.plan_run(paths[protocol], **plan)
        trained.setdefault(key, {}).setdefault(run_seed, []).append(run_dir)
        if finished:
            _log(f"{key}/{name}: finished run found, reused")
            if record and not runs.is_published(record):
                publish_run(run_dir, record, _real_paths(key, paths))
            continue
        pending.append((f"{key}/{name}", paths[protocol], plan,
                        (record, _real_paths(key, paths)) if record else None))
    if jobs > 1 and len(pending) > 1:
        train_parallel(pending, jobs, config["backbone"], config["epochs"])
        return trained
    for label, data, plan, publish in pending:
        _log(f"training {label} ({config['backbone']}, up to {config['epochs']} epochs)")
        summary = training.train(data, verbose=2, **plan)
        _log(training.summary_line(summary))
        if summary["best_epoch"] is None:
            raise training.TrainingError(f"{plan['run_dir']}: no epoch completed "
                                         f"({summary['stopped']})")
        if publish:
            publish_run(plan["run_dir"], *publish)
    return trained


def published_record(out_dir, key, name):
    """Where run ``name`` of table ``key`` is published: ``out_dir/runs/<key>_<name>``."""
    return os.path.join(out_dir, "runs", f"{key}_{name}")


def _real_paths(key, paths):
    """The real sets a run of table ``key`` is evaluated on (Table 2: the cvgl runs)."""
    return list(paths.get("real") or []) if key == "cvgl" else []


def publish_run(run_dir, record, real_paths):
    """Publish a finished run at once: its outputs on its test split and on
    ``real_paths`` stored in the run directory (``evaluation.store_predictions``),
    then its published part copied to ``record`` (``runs.publish_run_dir``)
    and its log and curves beside it (``runs.publish_files``)."""
    from cpl_keras import evaluation

    evaluation.store_predictions(run_dir, real_paths)
    runs.publish_run_dir(run_dir, record)
    runs.publish_files(run_dir, os.path.dirname(record), os.path.basename(record))
    _log(f"published {record}")


#: Variants whose training step costs many MTL steps (Deep-Homo: 15-18x a
#: small_resnet step, bench/bench_variants.py); ``train_parallel`` starts them
#: first, so that the short runs fill the other process meanwhile.
SLOW_VARIANTS = ("deep-homo",)


def _exit_with_parent(parent, every=2.0):
    """End this process (status 143, as by SIGTERM) once ``parent`` is gone:
    a reproduction killed outright leaves no training behind."""
    import threading

    def watch():
        while os.getppid() == parent:
            time.sleep(every)
        os._exit(143)

    threading.Thread(target=watch, daemon=True, name="exit-with-parent").start()


def _train_job(data, plan, parent):
    """A training run in a process of its own (``train_parallel``): quiet; the
    exit status says how it ended (0 trained, 1 no epoch completed, 2 an
    error, printed on one line, 130 interrupted, 143 its parent gone; a
    killed run resumes from its last completed epoch)."""
    from cpl_keras import training
    from cpl_keras.cache import enable_compile_cache
    from cpl_keras.data.storage import DatasetError

    _exit_with_parent(parent)
    enable_compile_cache()
    try:
        with cli.interruptible():
            summary = training.train(data, verbose=0, **plan)
    except KeyboardInterrupt:  # the last completed epoch is checkpointed
        sys.exit(130)
    except (training.TrainingError, DatasetError, OSError) as error:
        print(f"{PROG}: error: {plan['run_dir']}: {error}", file=sys.stderr)
        sys.exit(2)
    _log(training.summary_line(summary))
    sys.exit(0 if summary["best_epoch"] is not None else 1)


def train_parallel(pending, jobs, backbone, epochs):
    """Train ``pending`` runs (``(label, data, plan[, publish])``: ``publish``
    is None or ``publish_run``'s record and real sets, used when the run
    ends) ``jobs`` at a time,
    each in a fresh process (spawned: JAX does not survive a fork); the slow
    variants first. Ctrl-C (or SIGINT to this process) interrupts every
    running run, which resumes from its last epoch next time; a run that
    fails stops the others and raises ``TrainingError``."""
    import multiprocessing
    import multiprocessing.connection
    import signal

    from cpl_keras import training

    context = multiprocessing.get_context("spawn")
    pending = [tuple(job) + (None,) * (4 - len(job)) for job in pending]
    queue = sorted(pending, key=lambda job: job[2]["variant"] not in SLOW_VARIANTS)
    running = {}
    failure = None
    try:
        while (queue and failure is None) or running:
            while queue and failure is None and len(running) < jobs:
                label, data, plan, publish = queue.pop(0)
                _log(f"training {label} ({backbone}, up to {epochs} epochs; "
                     f"{jobs} runs at a time)")
                process = context.Process(target=_train_job, args=(data, plan, os.getpid()),
                                          name=label)
                process.start()
                running[process.sentinel] = (label, plan, process, publish)
            ready = multiprocessing.connection.wait(list(running), timeout=5)
            for sentinel in ready:
                label, plan, process, publish = running.pop(sentinel)
                process.join()
                if process.exitcode == 0 and publish:
                    publish_run(plan["run_dir"], *publish)
                if process.exitcode != 0 and failure is None:
                    failure = (f"{plan['run_dir']}: training ended with exit status "
                               f"{process.exitcode}")
                    for _, _, other, _ in running.values():
                        other.terminate()  # SIGTERM: resumes from its last epoch
    except KeyboardInterrupt:
        for _, _, process, _ in running.values():
            if process.is_alive():
                os.kill(process.pid, signal.SIGINT)
        for _, _, process, _ in running.values():
            process.join(timeout=60)
            if process.is_alive():
                process.terminate()
        raise
    if failure is not None:
        raise training.TrainingError(failure)


# ---------------------------------------------------------------------------
# Stage 3: published predictions
# ---------------------------------------------------------------------------
def _group_predictions(number, stem, prefix, run_dirs, data, config, out_dir, suffix):
    """The predictions files of one table of one seed: reused when they were
    made from the same runs, data and settings after the runs' models were
    written, else computed and written (all files or none)."""
    from cpl_keras import evaluation, predictions

    folder = os.path.join(out_dir, "runs")
    key = json.dumps({"table": stem, "runs": [runs.relative(r, out_dir) for r in run_dirs],
                      "data": [runs.relative(p, out_dir) for p in data] if data else None,
                      "geometric_max": config["geometric_max"],
                      "format": predictions.FORMAT_VERSION}, sort_keys=True)
    rows = ["Average", "Average (release bug)"] + list(run_dirs) + ["Geometric"]
    stems = [None] if number == 1 else [os.path.splitext(os.path.basename(p))[0] for p in data]
    names = [predictions.file_name(prefix, predictions.row_slug(r, {"source": r}, suffix), s)
             for s in stems for r in rows]
    expected = [os.path.join(folder, name) for name in names]
    models = [os.path.join(r, runs.MODEL) for r in run_dirs]
    if all(os.path.exists(p) for p in expected + models) and \
            all(predictions.read_key(p) == key for p in expected) and \
            min(os.path.getmtime(p) for p in expected) >= max(os.path.getmtime(m) for m in models):
        _log(f"{stem} ({', '.join(os.path.basename(r) for r in run_dirs)}): published "
             f"predictions up to date with their runs, reused")
        return expected
    _log(f"evaluating {stem}: {', '.join(os.path.basename(r) for r in run_dirs)}")
    if number == 1:
        context, raw = evaluation.table_rows(1, run_dirs, geometric=True,
                                             geometric_max=config["geometric_max"], progress=_log)
        files = predictions.table1_files(context, raw, out_dir=out_dir, prefix=prefix, stem=stem,
                                         key=key, suffix=suffix)
    else:
        from cpl_keras.real import table2

        run_list, rigs = table2.table2_rigs(run_dirs, data, geometric=True,
                                            geometric_max=config["geometric_max"], progress=_log)
        files = predictions.table2_files(run_list, rigs, out_dir=out_dir, prefix=prefix,
                                         stem=stem, key=key, suffix=suffix)
    if sorted(files) != sorted(names):
        raise evaluation.EvaluationError(f"{stem}: predictions files {sorted(files)} are not "
                                         f"the expected {sorted(names)}")
    return predictions.write_files(folder, {name: files[name] for name in names})


def make_predictions(config, paths, trained, out_dir):
    """Stage 3: the predictions of every row of every table, for every seed;
    returns their paths (Table 1 per table key, then Table 2)."""
    groups = []
    for key, by_seed in trained.items():
        for run_seed, run_dirs in by_seed.items():
            groups.append((1, f"table1_{key}", key, run_dirs, None,
                           f"-s{run_seed}" if len(by_seed) > 1 else ""))
    cvgl = trained.get("cvgl", {})
    for run_seed, run_dirs in cvgl.items():
        groups.append((2, "table2", "cvgl", run_dirs, paths["real"],
                       f"-s{run_seed}" if len(cvgl) > 1 else ""))
    files = []
    for number, stem, prefix, run_dirs, data, suffix in groups:
        files += _group_predictions(number, stem, prefix, run_dirs, data, config, out_dir, suffix)
    return files


# ---------------------------------------------------------------------------
# Stage 4: tables (from the published predictions alone)
# ---------------------------------------------------------------------------
def make_tables(prediction_files, out_dir, command):
    """Every table from the predictions files; each written as Markdown, CSV,
    JSON and plots into ``out_dir``. Returns ``{stem: table}``."""
    from cpl_keras import predictions, report
    from cpl_keras.real import table2

    tables = predictions.tables_from_files(prediction_files)
    for stem, table in tables.items():
        if "rigs" in table:
            table2.write_table2(out_dir, stem, table, command)
        else:
            report.write_outputs(out_dir, stem, table, command)
    return tables


def collect_run_files(trained, out_dir):
    """Copy each run's training log and curves into ``out_dir/runs``; the
    runs' summaries (run directories relative to ``out_dir``)."""
    target = os.path.join(out_dir, "runs")
    os.makedirs(target, exist_ok=True)
    summaries = []
    for protocol, by_seed in trained.items():
        for run_dirs in by_seed.values():
            for run_dir in run_dirs:
                name = f"{protocol}_{os.path.basename(run_dir)}"
                runs.publish_files(run_dir, target, name)
                run_config = runs.read_config(run_dir, {})
                summaries.append({"protocol": protocol, "name": name,
                                  "run_dir": runs.relative(run_dir, out_dir),
                                  "as_released": runs.config_as_released(run_config),
                                  **{k: run_config.get(k) for k in (
                                      "variant", "split", "seed", "epochs", "epochs_run",
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


def dataset_lines(paths):
    """``{kind: line}`` describing every dataset (real sets: ``real``, one per file)."""
    lines = {k: _dataset_line(paths[k]) for k in ("cvgl", "random") if k in paths}
    for path in paths["real"]:
        lines[f"real ({os.path.splitext(os.path.basename(path))[0]})"] = _dataset_line(path)
    return lines


# ---------------------------------------------------------------------------
# Stage 5: REPORT.md (from reproduce.json and the tables)
# ---------------------------------------------------------------------------
def _stem_row(stem):
    """The table row of a run name stem (``cpl-a-released``: MTL-CPL-A (as released))."""
    from cpl_keras.models.variants import VARIANT_ROWS
    from cpl_keras.runs import RELEASED

    if stem == RELEASED_RUN:
        return VARIANT_ROWS["cpl-a"] + RELEASED
    return VARIANT_ROWS.get(stem, stem)


def _budget_text(config):
    budget = config.get("run_budget_s")
    return "" if budget is None else (f", or at a budget of {budget:g} s of training per run "
                                      f"(whichever ends it first)")


def _scale_text(config):
    preset = config.get("preset")
    if config.get("quick"):
        scale = "quick (tiny settings, a smoke test of the pipeline)"
    elif preset:
        scale = f"preset `{preset}`, as set below"
    else:
        scale = "as set below"
    counts = {TABLE1[t][2]: config[TABLE1[t][2]] for t in config.get("tables", DEFAULT_TABLES)}
    if tuple(config.get("tables", DEFAULT_TABLES)) != DEFAULT_TABLES:
        seeds = (f" Seeds per table: {', '.join(f'{t} {config[TABLE1[t][2]]}' for t in config['tables'])} "
                 f"(each seed its own initial weights and, on the paper split, its own split; "
                 f"a table over several seeds gives mean ± spread)."
                 if max(counts.values()) > 1 else "")
    else:
        seeds = (f" Seeds per protocol: cvgl {config['seeds']}, random {config['random_seeds']} "
                 f"(each seed its own split and initial weights; a table over several seeds "
                 f"gives mean ± spread)." if max(config["seeds"], config["random_seeds"]) > 1
                 else "")
    seeded = config.get("seeded_variants")
    if seeds and seeded is not None:
        once = [stem for stem in run_stems(config) if stem not in seeded]
        if once:
            seeds += (f" Trained on every seed: {', '.join(_stem_row(s) for s in seeded)}; "
                      f"on the first seed only: {', '.join(_stem_row(s) for s in once)} (their "
                      f"rows are one run's values, without spread).")
    return (f"Scale: {scale}. Backbone `{config['backbone']}`, {config['image_size']}x"
            f"{config['image_size']} images, batch {config['batch_size']}, Adam (lr 1e-3, "
            f"Deep-Homo 1.5e-3), up to {config['epochs']} epochs with early stopping "
            f"(patience {config['patience']}, best weights restored){_budget_text(config)}."
            f"{seeds} The paper trained "
            f"up to 200 epochs on 123,017 pairs from ImageNet weights; here the towers start "
            f"from random weights (none can be downloaded).")


#: The parameters of the learning-curve figures (validation MAE per epoch).
CURVE_PARAMETERS = ("fx", "baseline", "disparity", "pitch")


def plot_protocol_curves(out_dir, runs_list):
    """``curves_<protocol>.png`` in ``out_dir``: the validation MAE of
    ``CURVE_PARAMETERS`` per epoch, every run of the protocol, from the
    published logs (``runs/<name>_log.csv``; so a rebuild draws them alike).
    Returns ``[(protocol, file name)]``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cpl_keras.learning_curves import _val_mae

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
        fig, axes = plt.subplots(1, len(CURVE_PARAMETERS), figsize=(16, 4.2))
        for ax, parameter in zip(axes, CURVE_PARAMETERS):
            for s, rows in logged:
                epochs = [row["epoch"] for row in rows]
                values = [_val_mae(row, parameter) for row in rows]
                colour = plt.cm.tab10(stems.index(_run_stem(s)) % 10)
                style = ("-", "--", ":", "-.")[seeds.index(s.get("seed") or 0) % 4]
                label = _stem_row(_run_stem(s)) + (f", seed {s['seed']}" if len(seeds) > 1
                                                    else "")
                ax.plot(epochs, values, style, color=colour, linewidth=1.2, label=label)
                best = s.get("best_epoch")
                if best and best <= len(values):
                    ax.plot([best], [values[best - 1]], "o", color=colour, markersize=3.5)
            ax.set_yscale("log")
            ax.set_title(f"validation MAE of {parameter}", fontsize=10)
            ax.set_xlabel("epoch")
            ax.grid(True, alpha=0.3)
        axes[0].legend(fontsize=6.5)
        fig.suptitle(TITLES.get(f"table1_{protocol}", protocol), fontsize=10)
        fig.tight_layout()
        name = f"curves_{protocol}.png"
        runs.save_figure(fig, os.path.join(out_dir, name), dpi=80)
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
    """Stage 5: REPORT.md from the reproduction's summary (``reproduce.json``)
    and its tables; ``rebuilt_by``: the command that rebuilt them from the
    published predictions."""
    from cpl_keras import report
    from cpl_keras.real import table2

    config, info = summary["settings"], summary["machine"]
    lines = ["# Reproducing Tables 1 and 2", ""]
    lines += ["Everything on this page was produced by one command:", "", "```",
              summary["command"], "```", ""]
    if rebuilt_by:
        lines += ["The tables and this page were rebuilt from the published predictions "
                  "(`runs/*_predictions.npz`), without weights or datasets, by:", "", "```",
                  rebuilt_by, "```", ""]
    runs_list = summary["runs"]
    lines += [_scale_text(config), "",
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
        stopped = s["stopped"] or (f"epoch cap ({config['epochs']})"
                                   if s["epochs_run"] == config["epochs"] else "")
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
        render = table2.markdown if "rigs" in table else report.markdown
        body = render(table).split("\n")[1:]
        body = ["#" + line if line.startswith("#") else line for line in body]
        lines += [f"## {TITLES.get(stem, stem)}", ""] + body
        plots = [f"![FOV-threshold curves, {stem}]({stem}_fov.png)"]
        if "rigs" in table:
            plots.append(f"![Predicted against true field of view per rig, {stem}]"
                         f"({stem}_fov_scatter.png)")
        lines += plots + ["", f"Files: [`{stem}.md`]({stem}.md), [`{stem}.csv`]({stem}.csv), "
                              f"[`{stem}.json`]({stem}.json).", ""]
        differences = report.differences_beyond_spread(table)
        if differences:
            lines += ["### Differences beyond the spread" + (" (pooled)" if "rigs" in table
                                                            else ""), "",
                      "NMAE = MAE / mean(|y|) of the rows trained on several seeds: `<` where "
                      "the first row's mean is lower by more than the two spreads added, "
                      "`>` where the second's is, `=` where the difference is within them.",
                      ""] + differences + [""]
    if summary.get("discussion"):
        lines += ["## Comparison with the paper", "", summary["discussion"].strip(), ""]
    runs.write_text(os.path.join(out_dir, "REPORT.md"), "\n".join(lines) + "\n")


def reproduce(*, out_dir, data_dir, runs_dir, config, seed=0, command="", discussion_file=None,
              real_roots=None, jobs=1):
    """Run the whole pipeline; returns the path of REPORT.md. ``jobs``:
    training runs at a time (``train_all``)."""
    for directory in (out_dir, data_dir, runs_dir):
        os.makedirs(directory, exist_ok=True)
    start = time.time()
    from cpl_keras.cache import enable_compile_cache

    enable_compile_cache()
    paths = make_datasets(config, data_dir, seed, real_roots)
    trained = train_all(config, paths, runs_dir, seed, jobs, out_dir=out_dir)
    files = make_predictions(config, paths, trained, out_dir)
    tables = make_tables(files, out_dir, command)
    summaries = collect_run_files(trained, out_dir)
    info = dict(machine(), wall_time_s=time.time() - start)
    discussion = None
    if discussion_file and os.path.exists(discussion_file):
        with open(discussion_file) as f:
            discussion = f.read()
    roots = {k: runs.relative(v, out_dir) for k, v in (real_roots or {}).items() if v}
    summary = {
        "command": command, "settings": dict(config, variants=list(config["variants"])),
        "seed": seed, "real_roots": roots,
        "data": dict({k: runs.relative(paths[k], out_dir) for k in ("cvgl", "random")
                      if k in paths},
                     real=[runs.relative(p, out_dir) for p in paths["real"]]),
        "datasets": dataset_lines(paths), "runs": summaries, "machine": info,
        "predictions": [runs.relative(p, out_dir) for p in files], "tables": list(tables),
        "discussion": discussion}
    runs.write_json(os.path.join(out_dir, SUMMARY), summary)
    write_report(out_dir, summary, tables)
    return os.path.join(out_dir, "REPORT.md")


# ---------------------------------------------------------------------------
# Rebuilding the tables and REPORT.md from the published predictions
# ---------------------------------------------------------------------------
#: The reproduction's summary, beside REPORT.md.
SUMMARY = "reproduce.json"
#: The keys of the summary a rebuild needs.
SUMMARY_KEYS = ("command", "settings", "datasets", "runs", "machine", "predictions", "tables")


def read_summary(out_dir):
    """``out_dir/reproduce.json``, checked; ValueError (one line) otherwise."""
    path = os.path.join(out_dir, SUMMARY)
    if not os.path.isdir(out_dir):
        raise ValueError(f"not a folder: {out_dir}")
    try:
        summary = runs.read_json(path)
    except (OSError, ValueError) as error:
        raise ValueError(f"cannot read {path}: {cli.one_line(error)}") from None
    if summary is None:
        raise ValueError(f"{path} not found: not the output folder of a reproduction")
    missing = [k for k in SUMMARY_KEYS if not isinstance(summary, dict) or k not in summary]
    if missing:
        raise ValueError(f"{path} has no {', '.join(missing)} (written before predictions "
                         f"were published? run the reproduction again)")
    return summary


def rebuild_command(out_dir):
    """The command REPORT.md names as its rebuild: the same whichever way it
    was spelt (``evaluate.py --reproduce``, with ``--discussion``: that text
    is then in ``reproduce.json``), so that rebuilding a committed folder in
    place changes no byte of it."""
    path = os.path.relpath(out_dir)
    if path.startswith(os.pardir):
        path = os.path.abspath(out_dir)
    return f"{PROG} --from-predictions {path}"


def rebuild(out_dir, command="", discussion_file=None):
    """Every table and REPORT.md of the reproduction in ``out_dir`` again, from
    its published predictions and ``reproduce.json`` alone (no weights, no
    datasets). Every file is read and checked before anything is written.
    ``discussion_file``: a new comparison with the paper (Markdown), stored
    in ``reproduce.json`` in place of the old one (written after the tables
    were seen). Returns the path of REPORT.md."""
    from cpl_keras import predictions

    summary = read_summary(out_dir)
    if discussion_file is not None:
        with open(discussion_file) as f:
            summary["discussion"] = f.read()
    files = [os.path.join(out_dir, p) for p in summary["predictions"]]
    tables = predictions.tables_from_files(files)
    if list(tables) != list(summary["tables"]):
        raise predictions.PredictionsError(
            f"the predictions make tables {list(tables)}, {SUMMARY} lists {summary['tables']}")
    make_tables(files, out_dir, summary["command"])
    if discussion_file is not None:
        runs.write_json(os.path.join(out_dir, SUMMARY), summary)
    write_report(out_dir, summary, tables, rebuilt_by=command)
    return os.path.join(out_dir, "REPORT.md")


# ---------------------------------------------------------------------------
# Command line (also evaluate.py --reproduce)
# ---------------------------------------------------------------------------
#: Options that set the scale (not allowed with --from-predictions).
SCALE_OPTIONS = ("quick", "preset", "pairs", "random_pairs", "epochs", "patience", "backbone",
                 "image_size", "crops", "chessboard_crops", "seeds", "random_seeds", "workers",
                 "data_dir", "runs_dir", "geometric_max", "jobs", "run_budget",
                 "allow_cpu") + REAL_ROOTS


def add_arguments(parser):
    """The reproduction's options, as an argument group of ``parser``; every
    number is checked when parsed (``cli.positive_int``)."""
    from cpl_keras.models.variants import BACKBONES

    positive, non_negative = cli.positive_int, cli.non_negative_int
    group = parser.add_argument_group("reproduce (cpl_keras/reproduce.py)")
    group.add_argument("--preset", choices=tuple(PRESETS), help="a named scale: paper (the "
                       "paper's: 123,017 pairs, InceptionV3, every row; the default, into "
                       "paper_results/), paper-gpu (MTL-CPL-A and MTL-Baseline with InceptionV3 "
                       "towers on 20,000 pairs, sized for ten minutes of one GPU), cpu (compact "
                       "towers, 3 seeds, ~1.5 h on 2 cores with --jobs 2), cpu-8000 (MTL "
                       "variants on 8,000 cvgl pairs, 3 seeds, paper and drive splits; many "
                       "hours, resumable run by run), quick (= --quick); the flags below "
                       "override its values")
    group.add_argument("--quick", action="store_true", help="tiny settings (minutes)")
    group.add_argument("--pairs", type=positive, help="cvgl-protocol pairs (paper: 123017)")
    group.add_argument("--random-pairs", type=positive, help="random-protocol pairs")
    group.add_argument("--epochs", type=positive, help="maximum epochs per run (paper: 200)")
    group.add_argument("--patience", type=non_negative, help="early stopping patience (paper: 5)")
    group.add_argument("--backbone", choices=BACKBONES,
                       help="the towers (paper: inception_v3; cpu presets: small_resnet)")
    group.add_argument("--image-size", type=positive,
                       help="square image side of every dataset (paper: 112)")
    group.add_argument("--crops", type=positive, help="Middlebury crops for Table 2")
    group.add_argument("--chessboard-crops", type=positive,
                       help="crops per OpenCV chessboard pair for Table 2")
    group.add_argument("--seeds", type=positive, help="cvgl runs per variant, seeds "
                       "SEED, SEED+1, ... (each its own split and initial weights)")
    group.add_argument("--random-seeds", type=positive, help="random-protocol runs per variant")
    group.add_argument("--workers", type=positive, help="data generation processes "
                       "(default: every core)")
    group.add_argument("--run-budget", type=cli.positive_float, metavar="SECONDS",
                       help="seconds of training each run may take (train.py --time-budget; "
                       "paper-gpu: 150; default: no limit)")
    group.add_argument("--allow-cpu", action="store_true",
                       help="run settings sized for a GPU (InceptionV3 towers on "
                       f"{GPU_SIZED_PAIRS:,}+ pairs) on a machine without one")
    group.add_argument("--jobs", type=positive, help="training runs at a time, each in its own "
                       "process (default 1; 2 did about 1.4x the work per unit time on a "
                       "2-core CPU); the runs and the tables are the same")
    group.add_argument("--seed", type=non_negative, default=0,
                       help="seed of the datasets and the first run seed")
    group.add_argument("--kitti", help="Table 2: KITTI stereo 2015 root")
    group.add_argument("--kitti-raw", help="Table 2: KITTI raw root")
    group.add_argument("--tsinghua", help="Table 2: Tsinghua-Daimler Cyclist root")
    group.add_argument("--cityscapes", help="Table 2: Cityscapes root")
    group.add_argument("--data-dir", help="where the datasets go (default data/reproduce, "
                       "data/quick with --quick, data/reproduce-<preset> with --preset)")
    group.add_argument("--runs-dir", help="where the runs go (default runs/reproduce, "
                       "runs/quick, runs/reproduce-<preset>)")
    group.add_argument("--discussion", help="Markdown file appended to REPORT.md as the "
                       "comparison with the paper (default: discussion.md in the output "
                       "folder, if there is one); with --from-predictions it replaces the "
                       "stored one")
    group.add_argument("--from-predictions", metavar="DIR",
                       help="rebuild every table and REPORT.md in DIR (a reproduction's output "
                       "folder) from its published predictions alone: no weights, no datasets")
    return group


#: Settings sized for a GPU: InceptionV3 towers on this many pairs or more.
GPU_SIZED_PAIRS = 10000
#: The faithful model's training rate on a 2-core CPU (docs/performance.md).
CPU_SAMPLES_PER_S = 12


def gpu_sized(config):
    """Whether ``config`` trains InceptionV3 towers on GPU-sized data."""
    return config["backbone"] == "inception_v3" and config["pairs"] >= GPU_SIZED_PAIRS


def has_accelerator():
    """Whether JAX sees a GPU or TPU (imported here, after the arguments are checked)."""
    import jax

    return jax.default_backend() != "cpu"


def cpu_cost(config, seed=0):
    """The one line that refuses GPU-sized settings on a CPU, with their cost."""
    train = config["pairs"] * (1 - 0.3) * (1 - 0.1)
    epoch_h = train / CPU_SAMPLES_PER_S / 3600
    count = len(run_jobs(config, seed))
    return (f"these settings are sized for a GPU ({config['pairs']:,} pairs, InceptionV3 "
            f"towers, {count} runs) and JAX sees no GPU here: one epoch of one run would take "
            f"about {epoch_h:.1f} h on this CPU (~{CPU_SAMPLES_PER_S} samples/s); pass "
            f"--allow-cpu to go on, or use --preset cpu or cpu-8000")


def default_folders(preset):
    """``(out, data_dir, runs_dir)`` of a preset (None: the paper's scale into
    paper_results/)."""
    from cpl_keras.evaluation import PAPER_DIR

    if preset == "quick":
        return os.path.join("runs", "quick", "paper_results"), os.path.join("data", "quick"), \
            os.path.join("runs", "quick")
    if preset is None:
        return PAPER_DIR, os.path.join("data", "reproduce"), os.path.join("runs", "reproduce")
    return (os.path.join(PAPER_DIR, preset), os.path.join("data", f"reproduce-{preset}"),
            os.path.join("runs", f"reproduce-{preset}"))


def resolve_args(parser, args):
    """Check the reproduction's options (``parser.error``: one line, exit 2,
    before anything is written) and fill in the folders and the settings
    (``args.config``)."""
    if args.from_predictions is not None:
        given = [name for name in SCALE_OPTIONS if getattr(args, name, None) not in (None, False)]
        if given:
            parser.error(f"--from-predictions rebuilds the tables of DIR as they were made; "
                         f"drop --{given[0].replace('_', '-')}")
        if args.out is not None and os.path.abspath(args.out) != \
                os.path.abspath(args.from_predictions):
            parser.error("--from-predictions DIR writes into DIR; drop --out")
        if args.discussion is not None and not os.path.isfile(args.discussion):
            parser.error(f"--discussion: file not found: {args.discussion}")
        args.out = args.from_predictions
        args.config = None
        return args
    try:
        args.config = settings(
            args.quick, args.preset, pairs=args.pairs, random_pairs=args.random_pairs,
            epochs=args.epochs, patience=args.patience, backbone=args.backbone,
            image_size=args.image_size, crops=args.crops, chessboard_crops=args.chessboard_crops,
            geometric_max=args.geometric_max, seeds=args.seeds, random_seeds=args.random_seeds,
            workers=args.workers, run_budget_s=args.run_budget)
    except ValueError as error:
        parser.error(str(error))
    if gpu_sized(args.config) and not args.allow_cpu and not has_accelerator():
        parser.error(cpu_cost(args.config, args.seed))
    out, data_dir, runs_dir = default_folders(args.config["preset"])
    args.out = args.out or out
    args.data_dir = args.data_dir or data_dir
    args.runs_dir = args.runs_dir or runs_dir
    if args.discussion is None:
        args.discussion = os.path.join(args.out, "discussion.md")
    for name in REAL_ROOTS:
        root = getattr(args, name)
        if root is not None and not os.path.isdir(root):
            parser.error(f"--{name.replace('_', '-')}: dataset root not found: {root}")
    return args


def run(args, command, prog=PROG):
    """Run the reproduction (or the rebuild) for resolved ``args``; the exit status."""
    from cpl_keras.data.storage import DatasetError

    try:
        if args.from_predictions is not None:
            report = rebuild(args.out, rebuild_command(args.out), args.discussion)
        else:
            with cli.interruptible():
                report = reproduce(
                    out_dir=args.out, data_dir=args.data_dir, runs_dir=args.runs_dir,
                    config=args.config, seed=args.seed, command=command,
                    discussion_file=args.discussion,
                    real_roots={name: getattr(args, name) for name in REAL_ROOTS},
                    jobs=args.jobs or 1)
    except KeyboardInterrupt:  # every stage is resumable: the same command goes on
        return cli.interrupted(prog, resume=command)
    except (ValueError, DatasetError, OSError) as error:  # EvaluationError is a ValueError
        return cli.fail(prog, error)
    print(f"report written to {report}")
    return 0


def main(argv=None):
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--out", help="output directory (default: paper_results/; with "
                        "--quick: runs/quick/paper_results; with --preset P: "
                        "paper_results/P)")
    parser.add_argument("--geometric-max", type=cli.positive_int,
                        help="run the Geometric baseline on the first N evaluation pairs only")
    add_arguments(parser)
    args = resolve_args(parser, parser.parse_args(argv))
    return run(args, cli.command_line(PROG, argv), PROG)


if __name__ == "__main__":
    sys.exit(main())
