"""The reproduction's pipeline: datasets, runs (``jobs``), published
predictions, tables, REPORT.md (``page``); and the rebuild of the tables
and REPORT.md from the published predictions alone."""

from __future__ import annotations

import glob
import os
import platform
import time

from cpl_keras import cli, evaluation, prediction_files, published, report, runs, table_files
from cpl_keras.cache import enable_compile_cache
from cpl_keras.data.generate import cached_dataset
from cpl_keras.data.import_cvgl import import_release
from cpl_keras.data.storage import StereoFile
from cpl_keras.files import read_json, write_json
from cpl_keras.real import build
from cpl_keras.reproduce.jobs import train_all
from cpl_keras.reproduce.page import write_report
from cpl_keras.reproduce.plan import run_jobs
from cpl_keras.reproduce.presets import PROG, TABLE1, Settings, log
from cpl_keras.reproduce.record import (
    CHECKSUMS, SUMMARY, checksums, make_predictions, record_changed, recorded_checksums,
)

# ---------------------------------------------------------------------------
# Stage 1: data
# ---------------------------------------------------------------------------
def real_set_folder(config, data_dir, seed):
    """Where the real sets of these settings go (one file per rig)."""
    return os.path.join(data_dir, f"real_{config.image_size}px_mb{config.crops}_"
                                  f"cb{config.chessboard_crops}_s{seed}")


def release_datasets(release_dir, data_dir):
    """The authors' released files in ``release_dir`` imported once into
    ``data_dir`` (``cpl_keras.data.import_cvgl``; an import already there is
    reused): ``{"cvgl": path, "real": [paths]}``, the real sets those of its
    ``r`` and ``r_cs`` files that are there."""
    paths = {"cvgl": import_release(release_dir, os.path.join(data_dir, "cvgl_release.h5"),
                                    progress=False, log=log), "real": []}
    for suffix, name in (("r", "tsinghua_release"), ("r_cs", "cityscapes_release")):
        if os.path.exists(os.path.join(release_dir, f"li{suffix}.npy")):
            paths["real"].append(import_release(
                release_dir, os.path.join(data_dir, f"{name}.h5"), suffix, progress=False,
                log=log))
    return paths


def make_datasets(config, data_dir, seed, real_roots=None, release_dir=None):
    """Stage 1: the synthetic datasets (or the release's, imported from
    ``release_dir``: ``release_datasets``) and every real set (reused when
    present); ``{"cvgl": path, "random": path, "real": [paths]}``. Settings
    with no ``real_sets`` and no ``real_roots`` have none (and no Table 2)."""
    size = config.image_size
    paths = {"real": []}
    needed = {TABLE1[t][0] for t in config.tables}
    if config.data == "release":
        paths = release_datasets(release_dir, data_dir)
        needed = needed - {"cvgl"}
    for protocol, pairs in (("cvgl", config.pairs), ("random", config.random_pairs)):
        if protocol not in needed:
            continue
        paths[protocol] = cached_dataset(data_dir, protocol=protocol, pairs=pairs, seed=seed,
                                         image_size=size, workers=config.workers, log=log)
    if not (config.real_sets or any((real_roots or {}).values())):
        return paths                                    # no Table 2 beyond the release's
    # every real rig, through the one builder of ``python -m cpl_keras.real.build all``
    paths["real"] = paths["real"] + build.build_all(
        real_set_folder(config, data_dir, seed), roots=real_roots, stems=config.real_sets,
        crops_per_source={"middlebury": config.crops, "chessboard": config.chessboard_crops,
                          "oakd": config.chessboard_crops},
        report=log, image_size=size, seed=seed)
    return paths


# ---------------------------------------------------------------------------
# Stage 4: tables (from the published predictions alone)
# ---------------------------------------------------------------------------
def make_tables(prediction_files, out_dir, command):
    """Every table from the predictions files; each written as Markdown, CSV,
    JSON and plots into ``out_dir``. Returns ``{stem: table}``."""
    tables = table_files.tables_from_files(prediction_files)
    for stem, table in tables.items():
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
                published.publish_files(run_dir, target, name)
                run_config = runs.read_run_config(run_dir)
                summaries.append({"protocol": protocol, "name": name,
                                  "run_dir": runs.relative(run_dir, out_dir),
                                  "as_released": run_config.as_released,
                                  "variant": run_config.variant,
                                  **{k: getattr(run_config.training, k)
                                     for k in ("split", "seed", "epochs")},
                                  **{k: getattr(run_config, k) for k in (
                                      "epochs_run", "best_epoch", "best_val_loss",
                                      "wall_time_s", "stopped")}})
    return summaries


def machine():
    import jax
    import keras

    return {"platform": platform.platform(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "keras": keras.__version__, "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()]}


def _dataset_line(path):
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


#: Where ``partial`` reproductions write their tables, inside the output folder.
PARTIAL = "partial"


def complete_seeds(config, trained, seed):
    """``trained`` (``train_all``'s ``{table key: {seed: [run dirs]}}``) cut
    to the seeds whose runs have all finished, and a line for each seed left
    out ("cvgl seed 2 (not finished: baseline-s2)")."""
    expected = {}
    for job in run_jobs(config, seed):
        expected.setdefault((job.key, job.seed), []).append(job.name)
    kept, left_out = {}, []
    for (key, run_seed), names in expected.items():
        run_dirs = trained.get(key, {}).get(run_seed, [])
        done = {os.path.basename(run_dir) for run_dir in run_dirs}
        missing = [name for name in names if name not in done]
        if missing:
            left_out.append(f"{key} seed {run_seed} (not finished: {', '.join(missing)})")
        else:
            kept.setdefault(key, {})[run_seed] = run_dirs
    return kept, left_out


def reproduce(*, out_dir, data_dir, runs_dir, config, seed=0, command="", discussion_file=None,
              real_roots=None, jobs=1, partial=False, release_dir=None):
    """Run the whole pipeline of ``config`` (the ``Settings``); returns the
    path of REPORT.md. ``jobs``: training runs at a time (``train_all``);
    ``release_dir``: the authors' released files (``config.data`` "release").

    ``partial``: train nothing; write the tables and REPORT.md of the seeds
    whose runs have all finished (published or in ``runs_dir``) into
    ``out_dir/partial/``, a look at a reproduction still under way. Its
    REPORT.md names the seeds in and the runs not finished."""
    for directory in (out_dir, data_dir, runs_dir):
        os.makedirs(directory, exist_ok=True)
    start = time.time()

    enable_compile_cache()
    paths = make_datasets(config, data_dir, seed, real_roots, release_dir)
    records = _published_records(out_dir)
    trained = train_all(config, paths, runs_dir, seed, jobs, out_dir=out_dir, train=not partial)
    published_before = not partial and os.path.exists(os.path.join(out_dir, SUMMARY))
    partial_info = None
    if partial:
        trained, left_out = complete_seeds(config, trained, seed)
        if not trained:
            raise evaluation.EvaluationError(
                "no seed has all its runs finished yet: " + "; ".join(left_out))
        out_dir = os.path.join(out_dir, PARTIAL)
        os.makedirs(out_dir, exist_ok=True)
        partial_info = {"seeds": {key: sorted(by_seed) for key, by_seed in trained.items()},
                        "left_out": left_out}
    recorded, written, beside = recorded_checksums(out_dir), [], []
    files = make_predictions(config, paths, trained, out_dir, written, recorded, beside)
    if published_before and not record_changed(files, written, out_dir, recorded) and \
            _published_records(out_dir) == records:
        # nothing new: the record stays as published, byte for byte (its
        # summary would change only by this machine and this wall time)
        _left_as_published(out_dir, written, beside)
        return os.path.join(out_dir, "REPORT.md")
    tables = make_tables(files, out_dir, command)
    summaries = collect_run_files(trained, out_dir)
    info = dict(machine(), wall_time_s=time.time() - start)
    discussion = None
    if discussion_file and os.path.exists(discussion_file):
        with open(discussion_file) as f:
            discussion = f.read()
    roots = {k: runs.relative(v, out_dir) for k, v in (real_roots or {}).items() if v}
    summary = {
        "command": command, "settings": config.to_dict(),
        "seed": seed, "real_roots": roots,
        "data": dict({k: runs.relative(paths[k], out_dir) for k in ("cvgl", "random")
                      if k in paths},
                     real=[runs.relative(p, out_dir) for p in paths["real"]]),
        "datasets": dataset_lines(paths), "runs": summaries, "machine": info,
        "predictions": [runs.relative(p, out_dir) for p in files],
        CHECKSUMS: checksums(files, out_dir), "tables": list(tables),
        "discussion": discussion, "partial": partial_info}
    write_json(os.path.join(out_dir, SUMMARY), summary)
    write_report(out_dir, dict(summary, settings=config), tables)
    return os.path.join(out_dir, "REPORT.md")


def _left_as_published(out_dir, written, beside):
    """Say that the published record in ``out_dir`` is left as it is: the
    predictions files it lacked and ``written`` again as recorded, and where
    those computed again that differ from it went (``beside``)."""
    def files(paths):
        return f"{len(paths)} predictions file{'s' if len(paths) > 1 else ''}"

    said = [f"{out_dir}: the published record " + (
        "left as it is" if beside else "is up to date with its runs and data")]
    if written:
        said.append(f"{files(written)} it lacked written again as recorded")
    if beside:
        said.append(f"{len(beside)} computed again differ{'' if len(beside) > 1 else 's'} "
                    f"from it: beside it in {os.path.dirname(beside[0])}")
    log("; ".join(said) + ("; nothing else written" if written or beside else
                           "; nothing written"))


def _published_records(out_dir):
    """The published run records in ``out_dir/runs`` (their config.json's
    contents), to tell whether a reproduction published a run."""
    found = {}
    for path in sorted(glob.glob(os.path.join(out_dir, "runs", "*", runs.CONFIG))):
        with open(path, "rb") as f:
            found[path] = f.read()
    return found


# ---------------------------------------------------------------------------
# Rebuilding the tables and REPORT.md from the published predictions
# ---------------------------------------------------------------------------
#: The keys of the summary a rebuild needs.
SUMMARY_KEYS = ("command", "settings", "datasets", "runs", "machine", "predictions", "tables")


def read_summary(out_dir):
    """``out_dir/reproduce.json``, checked, its settings a ``Settings`` (those
    of an older file: the fields it has, the defaults for those added
    since); ValueError (one line) otherwise."""
    return _with_settings(_stored_summary(out_dir), out_dir)


def _with_settings(stored, out_dir):
    """The summary ``stored`` in ``out_dir`` with its settings as a ``Settings``."""
    try:
        return dict(stored, settings=Settings.from_dict(stored["settings"]))
    except (AttributeError, TypeError, ValueError) as error:
        raise ValueError(f"{os.path.join(out_dir, SUMMARY)}: settings: "
                         f"{cli.one_line(error)}") from None


def _stored_summary(out_dir):
    """``out_dir/reproduce.json`` as stored, with every key of ``SUMMARY_KEYS``."""
    path = os.path.join(out_dir, SUMMARY)
    if not os.path.isdir(out_dir):
        raise ValueError(f"not a folder: {out_dir}")
    try:
        summary = read_json(path)
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
    was spelt (``cpl-reproduce``, with ``--discussion``: that text
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
    stored = _stored_summary(out_dir)
    summary = _with_settings(stored, out_dir)
    if discussion_file is not None:
        with open(discussion_file) as f:
            stored["discussion"] = summary["discussion"] = f.read()
    files = [os.path.join(out_dir, p) for p in summary["predictions"]]
    tables = table_files.tables_from_files(files)
    if list(tables) != list(summary["tables"]):
        raise prediction_files.PredictionsError(
            f"the predictions make tables {list(tables)}, {SUMMARY} lists {summary['tables']}")
    make_tables(files, out_dir, summary["command"])
    if discussion_file is not None:  # (its settings as they were stored)
        write_json(os.path.join(out_dir, SUMMARY), stored)
    write_report(out_dir, summary, tables, rebuilt_by=command)
    return os.path.join(out_dir, "REPORT.md")


