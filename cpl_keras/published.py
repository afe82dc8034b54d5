"""A published run: a finished run directory less its weights (model.keras,
best.weights.h5, backup/), what the reproduction commits under
paper_results/ and restores on another machine. It evaluates from its
stored predictions alone (``runs.PUBLISHED`` names its files).

``publish_run_dir`` writes one, ``restore_run_dir`` makes a run directory of
it again, ``is_published`` tells one; ``publish_files`` copies a run's log
and curves beside it. Each config.json goes through ``runs.RunConfig``, and
every folder is written under a temporary name and then renamed.
"""

from __future__ import annotations

import dataclasses
import os
import shutil

from cpl_keras import files
from cpl_keras.runs import (
    CONFIG, CURVES, LOG, PUBLISHED, RunError, read_run_config, stored_predictions, write_config,
)


def publish_files(run_dir, target_dir, name):
    """Copy a run's log.csv and curves.png to ``target_dir/<name>_log.csv``
    and ``<name>_curves.png`` (atomically; a missing file is skipped): the
    small results that are published, unlike the weights."""
    os.makedirs(target_dir, exist_ok=True)
    for source, suffix in ((LOG, "_log.csv"), (CURVES, "_curves.png")):
        path = os.path.join(run_dir, source)
        if os.path.exists(path):
            with files.atomic_path(os.path.join(target_dir, name + suffix)) as tmp:
                shutil.copyfile(path, tmp)


def publish_run_dir(run_dir, target):
    """Copy the published part of a finished run directory (``PUBLISHED``:
    no weights) to the folder ``target``, replacing what it held; its
    config.json names the dataset file and the run directory without a
    machine's paths. File times are kept (a table made from the stored
    predictions is newer than them). Returns ``target``."""
    config = read_run_config(run_dir)
    if config is None or config.status != "finished":
        raise RunError(f"{run_dir} holds no finished run to publish")
    if not stored_predictions(run_dir):
        raise RunError(f"{run_dir} has no stored predictions to publish")
    staging = target.rstrip(os.sep) + ".partial"
    shutil.rmtree(staging, ignore_errors=True)
    os.makedirs(staging)
    for name in PUBLISHED:
        source = os.path.join(run_dir, name)
        if os.path.isdir(source):
            shutil.copytree(source, os.path.join(staging, name), copy_function=shutil.copy2)
        elif os.path.isfile(source) and name != CONFIG:
            shutil.copy2(source, os.path.join(staging, name))
    write_config(staging, dataclasses.replace(
        config, data=dataclasses.replace(config.data, path=os.path.basename(config.data.path)),
        run_dir=os.path.basename(os.path.normpath(run_dir))))
    shutil.copystat(os.path.join(run_dir, CONFIG), os.path.join(staging, CONFIG))
    if os.path.isdir(target):
        shutil.rmtree(target)
    os.replace(staging, target)
    files.sync_folder(os.path.dirname(os.path.abspath(target)))
    return target


def is_published(folder):
    """True when ``folder`` holds a published run (``publish_run_dir``)."""
    try:
        config = read_run_config(folder) if os.path.isdir(folder) else None
    except RunError:
        return False
    return config is not None and config.status == "finished" and bool(stored_predictions(folder))


def restore_run_dir(folder, run_dir, data_path):
    """Make ``run_dir`` (absent or empty) a published run again from
    ``folder``: the files of ``publish_run_dir``, its config.json pointing at
    ``data_path`` (the same dataset file name, RunError otherwise) and at
    ``run_dir``. It evaluates from its stored predictions; it cannot resume
    (no weights, and it is finished)."""
    config = read_run_config(folder)
    if config is None:
        raise RunError(f"{folder} holds no published run (no {CONFIG})")
    if os.path.basename(os.fspath(data_path)) != config.data.path:
        raise RunError(f"{folder} was trained on {config.data.path}, not on "
                       f"{os.path.basename(os.fspath(data_path))}")
    if os.path.exists(run_dir) and os.listdir(run_dir):
        raise RunError(f"cannot restore into {run_dir}: it is not empty")
    staging = run_dir.rstrip(os.sep) + ".partial"
    shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(folder, staging, copy_function=shutil.copy2)
    write_config(staging, dataclasses.replace(
        config, data=dataclasses.replace(config.data, path=os.path.abspath(os.fspath(data_path))),
        run_dir=os.path.abspath(run_dir),
        other=dict(config.other, restored_from=folder)))
    shutil.copystat(os.path.join(folder, CONFIG), os.path.join(staging, CONFIG))
    if os.path.isdir(run_dir):
        os.rmdir(run_dir)
    os.makedirs(os.path.dirname(os.path.abspath(run_dir)), exist_ok=True)
    os.replace(staging, run_dir)
    files.sync_folder(os.path.dirname(os.path.abspath(run_dir)))
    return run_dir
