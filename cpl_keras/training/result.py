"""How a training run ends: its final files, and what ``train`` returns.

``finish_run`` writes what a run leaves behind once training stops (the
best weights as model.keras, the final config.json, no epoch checkpoint
left in backup/); ``finished_run`` reads a run that has already ended back
without changing a file. Both give a ``TrainResult``; ``summary_line`` is
its one-line summary. Importing this module imports no Keras.
"""

from __future__ import annotations

import dataclasses
import os
import zipfile

from cpl_keras import backend, files, runs
from cpl_keras.training_options import TrainingError


@dataclasses.dataclass(frozen=True)
class TrainResult:
    """What ``train`` returns."""

    # config.json as the run left it: status, stopped, epochs_run, best_epoch
    # (1-based), best_val_loss, best_score, wall_time_s, ... (``runs.RunConfig``)
    config: runs.RunConfig
    # the trained model (best weights); None when not loaded (return_model=False)
    model: object = None
    # model.keras was written (an epoch completed)
    has_model: bool = False
    # the run had ended before this call: nothing was trained, no file changed
    finished_before: bool = False


def finished_run(run_dir, load_model=True):
    """The ``TrainResult`` of the run in ``run_dir`` if it has finished, read
    without changing a file (``finished_before``; ``model`` is model.keras,
    loaded, unless ``load_model`` is False); else None."""
    config = runs.read_run_config(run_dir) if os.path.isdir(run_dir) else None
    if config is None or config.status != "finished":
        return None
    check_saved_files(run_dir)
    path = os.path.join(run_dir, runs.MODEL)
    model = runs.load_model_file(path) if load_model and os.path.isfile(path) else None
    return TrainResult(config=dataclasses.replace(config, run_dir=run_dir), model=model,
                       has_model=os.path.isfile(path), finished_before=True)


def check_saved_files(run_dir):
    """TrainingError (one line, with the way out) when a finished run's
    model.keras or best.weights.h5 is there but damaged (truncated, not its
    format): such a run is not reported as finished. Reads the files'
    structure (the zip's directory and CRCs, the HDF5 superblock), no Keras."""
    import h5py

    model = os.path.join(run_dir, runs.MODEL)
    weights = os.path.join(run_dir, runs.BEST_WEIGHTS)
    problem = None
    if os.path.isfile(model):
        try:
            with zipfile.ZipFile(model) as archive:
                bad = archive.testzip()
            if bad is not None:
                problem = f"{model} is damaged ({bad} fails its CRC)"
        except (OSError, zipfile.BadZipFile, EOFError) as error:
            problem = f"{model} is damaged ({error})"
    if problem is None and os.path.isfile(weights):
        try:
            with h5py.File(weights, "r"):
                pass
        except OSError as error:
            first = (str(error).strip().splitlines() or ["unreadable"])[0]
            problem = f"{weights} is damaged ({first})"
    if problem is not None:
        raise TrainingError(f"the finished run's {problem}; delete the run directory to train "
                            f"it again, or use another --run-dir")


def finish_run(model, config, state, processes):
    """Best weights -> model.keras; final config.json; remove the checkpoint
    (in a group, process 0 writes; the others read best.weights.h5)."""
    from cpl_keras.training.checkpointing import publish_run_files

    run_dir = config.run_dir
    processes.write("best weights written", publish_run_files, run_dir, state)
    best = state.best_weights
    if best:
        # The file holds the optimizer's variables too: a run resumed after a
        # kill during this save has a fresh model whose optimizer must be
        # built first, or Keras skips them (with a warning) and model.keras
        # would lose its optimizer state.
        if not model.optimizer.built:
            model.optimizer.build(model.trainable_variables)
        model.load_weights(os.path.join(run_dir, runs.BEST_WEIGHTS))
    failed = (state.stopped or "").startswith("non-finite")
    config = dataclasses.replace(
        config, epochs_run=int(state.epoch),
        best_epoch=None if state.best_epoch is None else int(state.best_epoch) + 1,
        best_val_loss=_best_row(state).get("val_loss", state.best),
        best_score=state.best,
        wall_time_s=round(float(state.wall_time_s), 3),
        stopped=state.stopped,
        status="failed" if failed else "finished",
        adaptive_weights=model.adaptive_weights(),
    )
    processes.write("run finished", _write_final_files, model if best else None, config,
                    processes)
    return TrainResult(config=config, has_model=bool(best))


def _write_final_files(model, config, processes):
    """(The process that writes) model.keras of ``model`` (unless None), the
    final config.json, and no epoch checkpoint left in backup/."""
    run_dir = config.run_dir
    if model is not None:
        with files.atomic_path(os.path.join(run_dir, runs.MODEL)) as tmp, processes.alone():
            model.save(tmp)
    runs.write_config(run_dir, config)
    backup = os.path.join(run_dir, runs.BACKUP)
    for name in os.listdir(backup):
        if name.endswith(".weights.h5"):
            os.remove(os.path.join(backup, name))


def _best_row(state):
    """The log row of the kept epoch (empty when none)."""
    return next((row for row in state.rows if row["epoch"] == state.best_epoch), {})


def summary_line(result):
    """The one-line end-of-run summary of a ``TrainResult``."""
    config = result.config
    if config.best_epoch is None:
        return (f"no epoch completed ({config.stopped}); nothing saved as model.keras; "
                f"run directory: {config.run_dir}")
    score = ""
    if config.training.monitor == "nmae" and config.best_score is not None:
        score = f"val_nmae {config.best_score:.4g}, "
    under = backend_note(config)
    line = (f"best epoch {config.best_epoch} of {config.epochs_run}, "
            f"best val_loss {config.best_val_loss:.6g}, {score}"
            f"{under + ', ' if under else ''}run directory: {config.run_dir}")
    if config.status == "failed":
        line = f"stopped: {config.stopped}; kept the best weights: " + line
    return line


def run_backends(config):
    """The Keras backends the run of ``config`` trained under, in order: its
    machines' (``RunConfig.machines``, one more for a resume elsewhere), else
    its ``keras_backend``; empty where neither is recorded."""
    names = [m.get("keras_backend") for m in config.machines or () if isinstance(m, dict)]
    return list(dict.fromkeys(name for name in names or [config.keras_backend] if name))


def backend_note(config, resuming=False):
    """Where the run of ``config`` trained (in part) under a Keras backend
    other than this process's (read without importing Keras), the words
    that say so: "trained under jax, not torch" (a summary), or with
    ``resuming`` " (trained under jax until now)" (its resume's line, this
    process's backend added to its machines already); else ''."""
    names, current = run_backends(config), backend.keras_backend()
    others = [name for name in names if name != current]
    if not others:
        return ""
    if resuming:
        return f" (trained under {' and '.join(others)} until now)"
    return f"trained under {' and '.join(names)}" + ("" if current in names else f", not {current}")
