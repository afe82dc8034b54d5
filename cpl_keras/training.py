"""Training one of the paper's networks on a stereo dataset file.

``train(data, variant=..., run_dir=...)`` validates everything first (the
file, its labels and images, the arguments, the model itself), then creates
the run directory (its files: ``cpl_keras.runs``).

Training follows the paper: Adam (lr 1e-3, Deep-Homo 1.5e-3), batch 16, up
to 200 epochs, early stopping on the validation loss with patience 5,
restoring the best weights.

Faults. After every epoch the model and optimizer state are checkpointed
atomically (new files first, then one ``os.replace`` of ``state.json`` that
names them), together with the early-stopping state and the log. A run
killed at any moment and started again with the same arguments resumes after
its last completed epoch; the epoch order of the data depends only on
(seed, epoch), so it ends with the same epoch count as an uninterrupted run.
A second process training into the same run directory (say, the same
command run again after a kill that missed) waits until the first one ends,
then resumes from where it left off (or finds the run finished).
The callback that checkpoints is ``cpl_keras.checkpointing.RunState``.
A non-finite training loss stops the run and keeps the best weights so far.
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import shutil
import sys

import numpy as np

from cpl_keras import models, runs
from cpl_keras.baselines.average import save_statistics, training_statistics
from cpl_keras.camera import FLOORS, RELEASED_FLOORS
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.datasets import SPLITS, load_split, make_split, save_split, targets_from_labels
from cpl_keras.errors import Error
from cpl_keras.models import BACKBONES, variants
from cpl_keras.models.variants import DISENTANGLE

#: config.json keys that must match for a run directory to be resumed.
RESUME_KEYS = (
    "variant", "build", "data", "split", "seed", "batch_size", "learning_rate", "epochs",
    "data_parallel", "patience", "test_fraction", "val_fraction",
    "bn_recompute_batches", "target_scaling",
)
#: Per-output MAE as the paper sums it ("none"), or each divided by the
#: target's training standard deviation ("std": standardised targets).
TARGET_SCALINGS = ("none", "std")
#: Training batches over which BatchNorm's moving statistics are recomputed
#: before every validation (0: keep Keras's moving averages, the default as
#: released).
BN_RECOMPUTE_BATCHES = 16
#: The CPL disparity head's ceiling, ``disparity_ceiling="auto"``: this many
#: times the largest disparity label of the training split
#: (``layers.PositiveDisparity`` says why).
DISPARITY_CEILING_FACTOR = 2.0


class TrainingError(Error):
    """A bad argument or run directory (one-line message)."""


# ---------------------------------------------------------------------------
# Planning: validate everything before anything is written
# ---------------------------------------------------------------------------
def _check_arguments(*, variant, backbone, split, epochs, batch_size, workers, patience, seed,
                     as_released, bn_recompute_batches, disentangle, target_scaling,
                     learning_rate, alpha_rate, time_budget_s, disparity_ceiling):
    """``plan_run``'s checks of its arguments (TrainingError, one line);
    returns the variant's spec and the BatchNorm recompute batches."""
    try:
        spec = variants.get(variant)
    except ValueError as error:
        raise TrainingError(str(error)) from None
    if backbone not in BACKBONES:
        raise TrainingError(f"unknown backbone {backbone!r}; choose one of {', '.join(BACKBONES)}")
    if split not in SPLITS:
        raise TrainingError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    for name, value in (("epochs", epochs), ("batch size", batch_size), ("workers", workers)):
        if not (isinstance(value, (int, np.integer)) and value >= 1):
            raise TrainingError(f"{name} must be a positive integer, got {value!r}")
    for name, value in (("patience", patience), ("seed", seed)):
        if isinstance(value, bool) or not (isinstance(value, (int, np.integer)) and value >= 0):
            raise TrainingError(f"{name} must be a non-negative integer, got {value!r}")
    if bn_recompute_batches is None:
        bn_recompute_batches = 0 if as_released else BN_RECOMPUTE_BATCHES
    if isinstance(bn_recompute_batches, bool) or not (
        isinstance(bn_recompute_batches, (int, np.integer)) and bn_recompute_batches >= 0
    ):
        raise TrainingError(
            f"BatchNorm recompute batches must be a non-negative integer, got {bn_recompute_batches!r}"
        )

    if disentangle not in DISENTANGLE:
        raise TrainingError(
            f"unknown disentangle {disentangle!r}; choose one of {', '.join(DISENTANGLE)}"
        )
    if target_scaling not in TARGET_SCALINGS:
        raise TrainingError(
            f"unknown target scaling {target_scaling!r}; choose one of {', '.join(TARGET_SCALINGS)}"
        )
    if target_scaling != "none" and spec.loss_mode(as_released) != "mae":
        raise TrainingError(
            "target scaling applies to the per-output MAE loss (MTL-Baseline, or CPL as "
            f"released), not to {variant}"
        )
    if learning_rate is not None and not (
        isinstance(learning_rate, (int, float)) and math.isfinite(learning_rate) and learning_rate > 0
    ):
        raise TrainingError(f"learning rate must be a positive number, got {learning_rate!r}")
    if alpha_rate is not None and (isinstance(alpha_rate, bool) or not (
        isinstance(alpha_rate, (int, float)) and math.isfinite(alpha_rate) and alpha_rate > 0
    )):
        raise TrainingError(f"alpha rate must be a positive number, got {alpha_rate!r}")
    if disparity_ceiling not in (None, "auto") and (
        isinstance(disparity_ceiling, bool)
        or not isinstance(disparity_ceiling, (int, float, np.floating))
        or not math.isfinite(disparity_ceiling) or disparity_ceiling <= FLOORS["disparity"]
    ):
        raise TrainingError(f"disparity ceiling must be 'auto', None or a number of pixels "
                            f"above {FLOORS['disparity']:g}, got {disparity_ceiling!r}")

    if time_budget_s is not None and (isinstance(time_budget_s, bool) or not (
        isinstance(time_budget_s, (int, float)) and math.isfinite(time_budget_s)
        and time_budget_s > 0
    )):
        raise TrainingError(f"time budget must be a positive number of seconds, "
                            f"got {time_budget_s!r}")
    return spec, bn_recompute_batches


def _read_dataset(data, *, image_size, split, seed, test_fraction, val_fraction, as_released,
                  batch_size):
    """``plan_run``'s dataset: its facts, targets and split, checked against
    the arguments (DatasetError or TrainingError, one line)."""
    data = os.path.abspath(os.fspath(data))
    with StereoFile(data) as f:
        labels = f.labels
        height, width, _ = f.image_shape
        num_pairs = f.num_pairs
        protocol = f.metadata.get("protocol")
    if image_size is not None and (height, width) != (image_size, image_size):
        raise TrainingError(
            f"{data}: images are {height}x{width}, but --image-size is {image_size}"
        )
    try:
        targets = targets_from_labels(labels, as_released=as_released)
    except DatasetError as error:
        raise DatasetError(f"{data}: {error}") from None
    try:
        indices = make_split(labels, kind=split, seed=seed, test_fraction=test_fraction,
                             val_fraction=val_fraction, as_released=as_released)
    except DatasetError as error:
        raise DatasetError(f"{data}: {error}") from None
    except ValueError as error:
        raise TrainingError(str(error)) from None
    if len(indices["train"]) < 13:
        raise DatasetError(
            f"{data}: {len(indices['train'])} training pairs; need at least 13 "
            f"(use a larger dataset)"
        )
    if batch_size > len(indices["train"]):
        raise TrainingError(
            f"batch size {batch_size} is larger than the training split ({len(indices['train'])} "
            f"pairs of {data}); use --batch-size {len(indices['train'])} or less"
        )
    return {"data": data, "height": height, "width": width, "num_pairs": num_pairs,
            "protocol": protocol, "targets": targets, "indices": indices}


def plan_run(data, *, variant, run_dir, epochs=200, batch_size=16, learning_rate=None,
             image_size=None, backbone="inception_v3", split="paper", as_released=False,
             seed=0, data_parallel=False, patience=5, test_fraction=0.3, val_fraction=0.1,
             workers=1, disentangle="exact", bounded_pitch_head=None,
             positive_focal_head=None, alpha_rate=None, disparity_ceiling="auto",
             bn_recompute_batches=None, target_scaling="none", time_budget_s=None,
             command=None):
    """Check the dataset and the arguments; return the run's plan (a dict).

    Raises ``DatasetError`` or ``TrainingError`` with a one-line message.
    Writes nothing.
    """
    spec, bn_recompute_batches = _check_arguments(
        variant=variant, backbone=backbone, split=split, epochs=epochs, batch_size=batch_size,
        workers=workers, patience=patience, seed=seed, as_released=as_released,
        bn_recompute_batches=bn_recompute_batches, disentangle=disentangle,
        target_scaling=target_scaling, learning_rate=learning_rate, alpha_rate=alpha_rate,
        time_budget_s=time_budget_s, disparity_ceiling=disparity_ceiling)
    dataset = _read_dataset(data, image_size=image_size, split=split, seed=seed,
                            test_fraction=test_fraction, val_fraction=val_fraction,
                            as_released=as_released, batch_size=batch_size)
    data, height, width = dataset["data"], dataset["height"], dataset["width"]
    num_pairs, protocol = dataset["num_pairs"], dataset["protocol"]
    targets, indices = dataset["targets"], dataset["indices"]

    devices = _device_count() if data_parallel else 1
    run_batch = -(-batch_size // devices) * devices

    build = {
        "backbone": backbone, "image_size": [height, width], "as_released": bool(as_released),
        "floors": dict(RELEASED_FLOORS if as_released else FLOORS),
        "bounded_pitch_head": (not as_released) if bounded_pitch_head is None
        else bool(bounded_pitch_head),
        "positive_focal_head": (not as_released) if positive_focal_head is None
        else bool(positive_focal_head),
        "disentangle": disentangle, "seed": int(seed),
        "disparity_ceiling": _disparity_ceiling(disparity_ceiling, spec, as_released,
                                                targets["disparity"][indices["train"]]),
    }
    if spec.loss_mode(as_released) == "projection-adaptive":
        from cpl_keras.losses import ALPHA_RATE

        build["alpha_rate"] = float(ALPHA_RATE if alpha_rate is None else alpha_rate)
    run_dir = os.path.abspath(os.fspath(run_dir))
    config = {
        "variant": variant,
        "build": build,
        "data": data,
        "num_pairs": num_pairs,
        "protocol": protocol,
        "split": split,
        "test_fraction": test_fraction,
        "val_fraction": val_fraction,
        "num_train": len(indices["train"]),
        "num_val": len(indices["val"]),
        "num_test": len(indices["test"]),
        "seed": int(seed),
        "batch_size": int(batch_size),
        "learning_rate": None if learning_rate is None else float(learning_rate),
        "epochs": int(epochs),
        "patience": int(patience),
        "bn_recompute_batches": int(bn_recompute_batches),
        "target_scaling": target_scaling,
        "time_budget_s": None if time_budget_s is None else float(time_budget_s),
        "data_parallel": bool(data_parallel),
        "num_devices": devices,
        "device_batch_size": run_batch,
        "command": command,
        "run_dir": run_dir,
        "keras_backend": _backend(),
    }
    _check_run_dir(run_dir, config, keep_ceiling=disparity_ceiling == "auto")
    return {"config": config, "targets": targets, "split": indices, "workers": int(workers)}


def _disparity_ceiling(setting, spec, as_released, train_disparities):
    """The build's ``disparity_ceiling`` (px): None where the disparity head
    is not the positive one (the direct variants, or as released), and with
    ``"auto"`` ``DISPARITY_CEILING_FACTOR`` times the largest training label."""
    if as_released or not spec.loss_mode(as_released).startswith("projection"):
        return None
    if setting == "auto":
        return round(DISPARITY_CEILING_FACTOR * float(np.max(train_disparities)), 3)
    return None if setting is None else float(setting)


def _backend():
    import keras

    return keras.backend.backend()


def _device_count():
    import keras

    return len(keras.distribution.list_devices())


def _check_run_dir(run_dir, config, keep_ceiling=False):
    """A run directory is new, empty, or holds the same run (to resume).
    With ``keep_ceiling`` (``disparity_ceiling="auto"``) a run is resumed
    with its own disparity ceiling (a run of before the ceiling: None)."""
    if not os.path.exists(run_dir):
        return
    if not os.path.isdir(run_dir):
        raise TrainingError(f"run directory is not a directory: {run_dir}")
    try:
        old = runs.read_config(run_dir)
    except runs.RunError:
        path = os.path.join(run_dir, runs.CONFIG)
        raise TrainingError(f"{path} is unreadable; use another --run-dir") from None
    if old is None:
        backup = os.path.join(run_dir, runs.BACKUP)
        # (a process killed between creating the directory and its config.json
        # leaves an empty backup/ with the lock: still an empty run directory)
        started = os.listdir(run_dir) == [runs.BACKUP] and set(os.listdir(backup)) <= {"lock"}
        if os.listdir(run_dir) and not started:
            raise TrainingError(f"run directory {run_dir} is not empty and holds no run")
        return
    if old.get("status") == "failed":
        return  # (replaced by the next run: ``_replace_failed_run``)
    if keep_ceiling:
        config["build"]["disparity_ceiling"] = old["build"]["disparity_ceiling"]
    config = runs.normalise_config(config)
    for key in RESUME_KEYS:
        if old.get(key) != config.get(key):
            raise TrainingError(
                f"run directory {run_dir} holds a different run ({key}: "
                f"{old.get(key)!r} there, {config.get(key)!r} now); use another --run-dir"
            )


# ---------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------
def train(data, *, variant, run_dir, epochs=200, batch_size=16, learning_rate=None,
          image_size=None, backbone="inception_v3", split="paper", as_released=False, seed=0,
          data_parallel=False, patience=5, test_fraction=0.3, val_fraction=0.1, workers=1,
          steps_per_execution=1, disentangle="exact", bounded_pitch_head=None,
          positive_focal_head=None, alpha_rate=None, disparity_ceiling="auto",
          bn_recompute_batches=None, target_scaling="none", time_budget_s=None, verbose=1,
          command=None):
    """Train ``variant`` on the dataset file ``data``; returns the summary dict.

    Everything is validated before the run directory is created (see
    ``plan_run``). An existing run directory holding the same run is resumed.
    The summary has ``best_epoch`` (1-based), ``best_val_loss``,
    ``epochs_run``, ``run_dir``, ``status``, ``stopped`` (why training
    ended early, or None) and ``model`` (the trained model, best weights).
    A run that has already ended is left untouched (``finished_before``:
    True in its summary; its model.keras keeps its optimizer state).
    ``verbose``: 0 prints nothing, 1 one short line per epoch (the loss, the
    validation loss and key validation MAEs; every metric is in log.csv)
    and a progress bar during the epoch when stdout is a terminal, 2 the
    epoch lines only.
    ``time_budget_s``: seconds of training (summed over resumes) the run may
    take; after an epoch, when another as long would overrun them, the run
    ends as finished with ``stopped`` saying so, keeping its best epoch.
    ``disparity_ceiling``: the CPL disparity head's largest output in px
    (``"auto"``: ``DISPARITY_CEILING_FACTOR`` times the largest training
    label; None: ``layers.MAX_OUTPUT``, the bound of runs made before it).
    """
    if isinstance(steps_per_execution, bool) or not (
        isinstance(steps_per_execution, (int, np.integer)) and steps_per_execution >= 1
    ):
        raise TrainingError(
            f"steps per execution must be a positive integer, got {steps_per_execution!r}")
    plan = plan_run(
        data, variant=variant, run_dir=run_dir, epochs=epochs, batch_size=batch_size,
        learning_rate=learning_rate, image_size=image_size, backbone=backbone, split=split,
        as_released=as_released, seed=seed, data_parallel=data_parallel, patience=patience,
        test_fraction=test_fraction, val_fraction=val_fraction, workers=workers,
        disentangle=disentangle, bounded_pitch_head=bounded_pitch_head,
        positive_focal_head=positive_focal_head, alpha_rate=alpha_rate,
        disparity_ceiling=disparity_ceiling,
        bn_recompute_batches=bn_recompute_batches, target_scaling=target_scaling,
        time_budget_s=time_budget_s, command=command,
    )
    import keras

    finished = _finished_run(plan["config"]["run_dir"])
    if finished is not None:
        return finished
    _replace_failed_run(plan["config"]["run_dir"])
    scope = contextlib.nullcontext()
    if data_parallel:
        devices = keras.distribution.list_devices()
        scope = keras.distribution.DataParallel(devices=devices).scope()
    with scope:
        return _run(plan, learning_rate, steps_per_execution, verbose)


def _failed_run(run_dir):
    """The config of the run in ``run_dir`` if it failed (a non-finite loss), else None."""
    config = runs.read_config(run_dir, {}) if os.path.isdir(run_dir) else {}
    return config if config.get("status") == "failed" else None


def _replace_failed_run(run_dir):
    """A failed run is not resumed: the next run into its directory, with
    these settings or others, starts afresh in its place (said on stderr)."""
    failed = _failed_run(run_dir)
    if failed is None:
        return
    print(f"Replacing the failed run in {run_dir} ({failed.get('stopped')})", file=sys.stderr,
          flush=True)
    shutil.rmtree(run_dir)


def _finished_run(run_dir):
    """The summary of the run in ``run_dir`` if it has finished, read without
    changing a file; else None. ``finished_before`` is True in it;
    ``model`` is model.keras, loaded."""
    config = runs.read_config(run_dir, {}) if os.path.isdir(run_dir) else {}
    if config.get("status") != "finished":
        return None
    path = os.path.join(run_dir, runs.MODEL)
    model = None
    if os.path.isfile(path):
        import keras

        import cpl_keras.models.factory  # noqa: F401  (registers the custom layers)

        model = keras.saving.load_model(path, safe_mode=True)
    return {
        "run_dir": run_dir, "status": config["status"], "stopped": config.get("stopped"),
        "epochs_run": config.get("epochs_run"), "best_epoch": config.get("best_epoch"),
        "best_val_loss": config.get("best_val_loss"), "has_model": model is not None,
        "finished_before": True, "model": model,
    }


def _run(plan, learning_rate, steps_per_execution, verbose):
    import keras

    config = plan["config"]
    variant = config["variant"]
    try:
        model = models.build_model(variant, **config["build"])
        models.compile_model(model, learning_rate=learning_rate,
                             steps_per_execution=steps_per_execution,
                             target_scale=_target_scale(plan) if config["target_scaling"] == "std" else None)
    except ValueError as error:
        raise TrainingError(f"cannot build {variant}: {error}") from None
    config["learning_rate_used"] = float(
        f"{float(keras.ops.convert_to_numpy(model.optimizer.learning_rate)):.7g}"
    )
    config["num_parameters"] = int(model.count_params())

    # Nothing has been written so far; from here on the run directory exists.
    run_dir = config["run_dir"]
    os.makedirs(os.path.join(run_dir, runs.BACKUP), exist_ok=True)
    lock = _lock_run_dir(run_dir)
    try:  # (released however training ends: a Ctrl-C in a notebook, then train() again)
        return _run_locked(plan, model, config, run_dir, verbose)
    finally:
        lock.close()


def _run_locked(plan, model, config, run_dir, verbose):
    from cpl_keras.sequence import StereoSequence

    finished = _finished_run(run_dir)  # (by the process this one waited for)
    if finished is not None:
        return finished
    previous = runs.read_config(run_dir, {})
    for key in ("epochs_run", "best_epoch", "best_val_loss", "wall_time_s", "status", "stopped"):
        config[key] = previous.get(key)
    config["status"] = "running"
    runs.write_config(run_dir, config)
    split_path = os.path.join(run_dir, runs.SPLIT)
    if os.path.exists(split_path):
        old = load_split(split_path)
        if any(not np.array_equal(old[k], plan["split"][k]) for k in old):
            raise TrainingError(f"{split_path} differs from this run's split; use another --run-dir")
    else:
        with runs.atomic_path(split_path) as tmp:
            save_split(tmp, plan["split"])
    # The release's Average bug depends on the order of the training set: its
    # frames were shuffled, so sample i is the i-th of a shuffled order.
    train_order = np.random.default_rng(config["seed"]).permutation(plan["split"]["train"])
    # ... and it averaged the release's labels (its frame, degrees, StereoBM).
    with StereoFile(config["data"]) as data_file:
        release_targets = targets_from_labels(data_file.labels, as_released=True)
    stats = training_statistics(plan["targets"], train_order, release_targets=release_targets)
    save_statistics(os.path.join(run_dir, runs.STATS), stats)

    multiple = config["num_devices"]
    common = dict(targets=plan["targets"], batch_size=config["device_batch_size"],
                  multiple_of=multiple, workers=plan["workers"])
    train_seq = StereoSequence(config["data"], plan["split"]["train"], shuffle=True,
                               seed=config["seed"], **common)
    val_seq = StereoSequence(config["data"], plan["split"]["val"], shuffle=False, **common)

    from cpl_keras.checkpointing import RunState
    from cpl_keras.progress import EpochLines

    run_state = RunState(run_dir, config["patience"], train_seq, config["bn_recompute_batches"],
                         time_budget_s=config.get("time_budget_s"))
    state = run_state.state
    done = state.get("stopped") is not None or state["epoch"] >= config["epochs"]
    try:
        if not done:
            initial_epoch = run_state.restore(model)
            if initial_epoch:
                print(f"Resuming {run_dir} after epoch {initial_epoch}", file=sys.stderr)
            train_seq.set_epoch(initial_epoch)
            # shuffle=False: the sequence shuffles itself, seeded per epoch; Keras's
            # own shuffle of the batch order uses Python's unseeded global RNG.
            callbacks = [run_state]
            if verbose:  # (Keras's bar would print all 14-30 metrics on every line)
                callbacks.append(EpochLines(config["epochs"], run_state,
                                            live=None if verbose == 1 else False))
            model.fit(train_seq, validation_data=val_seq, epochs=config["epochs"],
                      initial_epoch=initial_epoch, callbacks=callbacks, shuffle=False,
                      verbose=0)
    finally:  # (also on Ctrl-C: no reading threads left behind)
        train_seq.close()
        val_seq.close()
    summary = _finish(model, run_dir, config, run_state.state)
    summary["model"] = model
    return summary


def _lock_run_dir(run_dir):
    """An exclusive lock on ``run_dir/backup/lock``, so that one process at a
    time trains into a run directory. A second process (say, the same command
    run again after a kill that missed the first) waits until the first ends
    and then carries on from the state it left: the run ends as an
    uninterrupted one would. The lock ends with the run, however it ends (the
    caller closes the handle), or with the process."""
    handle = open(os.path.join(run_dir, runs.LOCK), "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        print(f"Waiting for the training process that is using {run_dir}", file=sys.stderr,
              flush=True)
        fcntl.flock(handle, fcntl.LOCK_EX)
    return handle


def _target_scale(plan):
    """Training standard deviation of every target (1 for a constant one,
    such as the cvgl protocol's u0 and v0)."""
    train = plan["split"]["train"]
    scale = {}
    for name, values in plan["targets"].items():
        std = float(np.std(np.asarray(values, np.float64)[train]))
        scale[name] = std if std > 1e-6 else 1.0
    return scale


def _finish(model, run_dir, config, state):
    """Best weights -> model.keras; final config.json; remove the checkpoint."""
    from cpl_keras.checkpointing import publish_run_files

    publish_run_files(run_dir, state)
    best = state.get("best_weights")
    if best:
        # The file holds the optimizer's variables too: a run resumed after a
        # kill during this save has a fresh model whose optimizer must be
        # built first, or Keras skips them (with a warning) and model.keras
        # would lose its optimizer state.
        if not model.optimizer.built:
            model.optimizer.build(model.trainable_variables)
        model.load_weights(os.path.join(run_dir, runs.BEST_WEIGHTS))
        with runs.atomic_path(os.path.join(run_dir, runs.MODEL)) as tmp:
            model.save(tmp)
    nan = state.get("stopped") or ""
    failed = nan.startswith("non-finite")
    config.update(
        epochs_run=int(state["epoch"]),
        best_epoch=None if state.get("best_epoch") is None else int(state["best_epoch"]) + 1,
        best_val_loss=state.get("best"),
        wall_time_s=round(float(state.get("wall_time_s", 0.0)), 3),
        stopped=state.get("stopped"),
        status="failed" if failed else "finished",
        adaptive_weights=model.adaptive_weights(),
    )
    runs.write_config(run_dir, config)
    backup = os.path.join(run_dir, runs.BACKUP)
    for name in os.listdir(backup):
        if name.endswith(".weights.h5"):
            os.remove(os.path.join(backup, name))
    return {
        "run_dir": run_dir, "status": config["status"], "stopped": config["stopped"],
        "epochs_run": config["epochs_run"], "best_epoch": config["best_epoch"],
        "best_val_loss": config["best_val_loss"], "has_model": bool(best),
    }


def summary_line(summary):
    """The one-line end-of-run summary."""
    if summary["best_epoch"] is None:
        return (f"no epoch completed ({summary['stopped']}); nothing saved as model.keras; "
                f"run directory: {summary['run_dir']}")
    line = (f"best epoch {summary['best_epoch']} of {summary['epochs_run']}, "
            f"best val_loss {summary['best_val_loss']:.6g}, run directory: {summary['run_dir']}")
    if summary["status"] == "failed":
        line = f"stopped: {summary['stopped']}; kept the best weights: " + line
    return line
