"""Training one of the paper's networks on a stereo dataset file.

``train(data, variant=..., run_dir=...)`` validates everything first (the
file, its labels and images, the arguments, the model itself), then creates
the run directory::

    run_dir/config.json        everything needed to rebuild and reproduce the run
    run_dir/model.keras        the best model (loads with safe_mode=True)
    run_dir/best.weights.h5    its weights
    run_dir/log.csv            one row per epoch, continuous across resumes
    run_dir/curves.png         training curves
    run_dir/train_stats.json   training-set statistics (the Average baseline)
    run_dir/split.npz          train, val, test index arrays
    run_dir/backup/            resume state (checkpoint of the last epoch)

Training follows the paper: Adam (lr 1e-3, Deep-Homo 1.5e-3), batch 16, up
to 200 epochs, early stopping on the validation loss with patience 5,
restoring the best weights.

Faults. After every epoch the model and optimizer state are checkpointed
atomically (new files first, then one ``os.replace`` of ``state.json`` that
names them), together with the early-stopping state and the log. A run
killed at any moment and started again with the same arguments resumes after
its last completed epoch; the epoch order of the data depends only on
(seed, epoch), so it ends with the same epoch count as an uninterrupted run.
A non-finite training loss stops the run and keeps the best weights so far.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import shutil
import sys
import time

import numpy as np

from cpl_keras.baselines.average import save_statistics, training_statistics
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.datasets import SPLITS, load_split, make_split, save_split, targets_from_labels

#: config.json keys that must match for a run directory to be resumed.
RESUME_KEYS = (
    "variant", "build", "data", "split", "seed", "batch_size", "learning_rate", "epochs",
    "as_released", "data_parallel", "patience", "test_fraction", "val_fraction",
    "bn_recompute_batches", "target_scaling",
)
#: Per-output MAE as the paper sums it ("none"), or each divided by the
#: target's training standard deviation ("std": standardised targets).
TARGET_SCALINGS = ("none", "std")
#: Training batches over which BatchNorm's moving statistics are recomputed
#: before every validation (0: keep Keras's moving averages, the default as
#: released).
BN_RECOMPUTE_BATCHES = 16


def cache_dir():
    """The project's cache directory: ``$CPL_KERAS_CACHE`` or ``~/.cache/cpl_keras``."""
    return os.environ.get("CPL_KERAS_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "cpl_keras"
    )


def enable_compile_cache():
    """Keep compiled training steps on disk (JAX), so a resumed or repeated run,
    or another run of the same model shape, skips most of XLA's compile time.

    ``$JAX_COMPILATION_CACHE_DIR`` wins when set; otherwise ``<cache_dir>/xla``.
    Returns the directory, or None on other backends.
    """
    if _backend() != "jax":
        return None
    import jax

    path = os.environ.get("JAX_COMPILATION_CACHE_DIR") or os.path.join(cache_dir(), "xla")
    jax.config.update("jax_compilation_cache_dir", path)
    return path


class TrainingError(ValueError):
    """A bad argument or run directory (one-line message)."""


# ---------------------------------------------------------------------------
# Planning: validate everything before anything is written
# ---------------------------------------------------------------------------
def plan_run(data, *, variant, run_dir, epochs=200, batch_size=16, learning_rate=None,
             image_size=None, backbone="inception_v3", split="paper", as_released=False,
             seed=0, data_parallel=False, patience=5, test_fraction=0.3, val_fraction=0.1,
             workers=1, disentangle="exact", bounded_pitch_head=None,
             bn_recompute_batches=None, target_scaling="none", command=None):
    """Check the dataset and the arguments; return the run's plan (a dict).

    Raises ``DatasetError`` or ``TrainingError`` with a one-line message.
    Writes nothing.
    """
    from cpl_keras.models import BACKBONES, VARIANTS

    if variant not in VARIANTS:
        raise TrainingError(f"unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    if backbone not in BACKBONES:
        raise TrainingError(f"unknown backbone {backbone!r}; choose one of {', '.join(BACKBONES)}")
    if split not in SPLITS:
        raise TrainingError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    for name, value in (("epochs", epochs), ("batch size", batch_size), ("workers", workers)):
        if not (isinstance(value, (int, np.integer)) and value >= 1):
            raise TrainingError(f"{name} must be a positive integer, got {value!r}")
    if not (isinstance(patience, (int, np.integer)) and patience >= 0):
        raise TrainingError(f"patience must be a non-negative integer, got {patience!r}")
    if bn_recompute_batches is None:
        bn_recompute_batches = 0 if as_released else BN_RECOMPUTE_BATCHES
    if isinstance(bn_recompute_batches, bool) or not (
        isinstance(bn_recompute_batches, (int, np.integer)) and bn_recompute_batches >= 0
    ):
        raise TrainingError(
            f"BatchNorm recompute batches must be a non-negative integer, got {bn_recompute_batches!r}"
        )
    from cpl_keras.models.factory import DISENTANGLE

    if disentangle not in DISENTANGLE:
        raise TrainingError(
            f"unknown disentangle {disentangle!r}; choose one of {', '.join(DISENTANGLE)}"
        )
    if target_scaling not in TARGET_SCALINGS:
        raise TrainingError(
            f"unknown target scaling {target_scaling!r}; choose one of {', '.join(TARGET_SCALINGS)}"
        )
    if target_scaling != "none" and not (variant == "baseline" or (
            as_released and variant in ("cpl-u", "cpl-a"))):
        raise TrainingError(
            "target scaling applies to the per-output MAE loss (MTL-Baseline, or CPL as "
            f"released), not to {variant}"
        )
    if learning_rate is not None and not (
        isinstance(learning_rate, (int, float)) and math.isfinite(learning_rate) and learning_rate > 0
    ):
        raise TrainingError(f"learning rate must be a positive number, got {learning_rate!r}")

    data = os.path.abspath(os.fspath(data))
    with StereoFile(data) as f:
        labels = f.labels
        height, width, _ = f.image_shape
        num_pairs = f.num_pairs
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

    devices = _device_count() if data_parallel else 1
    run_batch = -(-batch_size // devices) * devices
    from cpl_keras.camera import FLOORS, RELEASED_FLOORS

    build = {
        "backbone": backbone, "image_size": [height, width], "as_released": bool(as_released),
        "floors": dict(RELEASED_FLOORS if as_released else FLOORS),
        "bounded_pitch_head": (not as_released) if bounded_pitch_head is None
        else bool(bounded_pitch_head),
        "disentangle": disentangle, "seed": int(seed),
    }
    run_dir = os.path.abspath(os.fspath(run_dir))
    config = {
        "variant": variant,
        "build": build,
        "data": data,
        "num_pairs": num_pairs,
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
        "as_released": bool(as_released),
        "data_parallel": bool(data_parallel),
        "num_devices": devices,
        "device_batch_size": run_batch,
        "command": command,
        "run_dir": run_dir,
        "keras_backend": _backend(),
    }
    _check_run_dir(run_dir, config)
    return {"config": config, "targets": targets, "split": indices, "workers": int(workers)}


def _backend():
    import keras

    return keras.backend.backend()


def _device_count():
    import keras

    return len(keras.distribution.list_devices())


def _check_run_dir(run_dir, config):
    """A run directory is new, empty, or holds the same run (to resume)."""
    if not os.path.exists(run_dir):
        return
    if not os.path.isdir(run_dir):
        raise TrainingError(f"run directory is not a directory: {run_dir}")
    path = os.path.join(run_dir, "config.json")
    if not os.path.exists(path):
        if os.listdir(run_dir):
            raise TrainingError(f"run directory {run_dir} is not empty and holds no run")
        return
    try:
        with open(path) as f:
            old = json.load(f)
    except (OSError, json.JSONDecodeError):
        raise TrainingError(f"{path} is unreadable; use another --run-dir") from None
    for key in RESUME_KEYS:
        if old.get(key) != config.get(key):
            raise TrainingError(
                f"run directory {run_dir} holds a different run ({key}: "
                f"{old.get(key)!r} there, {config.get(key)!r} now); use another --run-dir"
            )


# ---------------------------------------------------------------------------
# Checkpointing, early stopping, NaN guard: one callback, one state file
# ---------------------------------------------------------------------------
def _atomic_json(path, payload):
    tmp = path + ".partial"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=2)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _read_json(path, default=None):
    if not os.path.exists(path):
        return default
    with open(path) as f:
        return json.load(f)


def _make_run_callback():
    import keras

    from cpl_keras.models.batchnorm import recompute_batchnorm_statistics

    class RunState(keras.callbacks.Callback):
        """Checkpoints every epoch and does early stopping, crash-safely.

        State (``backup/state.json``): completed epochs, the early-stopping
        counters, the per-epoch logs and the names of the checkpoint files.
        Checkpoint files are written under fresh names and only then named
        by a new ``state.json`` (``os.replace``), so a kill at any moment
        leaves the previous epoch's state intact.
        """

        def __init__(self, run_dir, patience, sequence, bn_recompute_batches=0):
            super().__init__()
            self.run_dir = run_dir
            self.bn_recompute_batches = int(bn_recompute_batches)
            self.backup = os.path.join(run_dir, "backup")
            self.state_path = os.path.join(self.backup, "state.json")
            self.patience = patience
            self.sequence = sequence
            self.state = _read_json(self.state_path) or {
                "epoch": 0, "best": None, "best_epoch": None, "wait": 0, "stopped": None,
                "rows": [], "checkpoint": None, "best_weights": None, "wall_time_s": 0.0,
            }
            self.nan = None
            self._epoch_start = None

        # -- resume -------------------------------------------------------
        def restore(self, model):
            """Load the last checkpoint into ``model`` (weights + optimizer)."""
            ckpt = self.state.get("checkpoint")
            if ckpt is None:
                return 0
            # The weights file holds the optimizer's variables too; build the
            # optimizer first so they are loaded rather than skipped.
            if not model.optimizer.built:
                model.optimizer.build(model.trainable_variables)
            model.load_weights(os.path.join(self.backup, ckpt + ".weights.h5"))
            return int(self.state["epoch"])

        # -- keras hooks ---------------------------------------------------
        def on_train_begin(self, logs=None):
            if self.state["epoch"] == 0 and self.state["checkpoint"] is None:
                # Eq. 9's weights start balanced on the first training batch
                # (a resumed run has them in its checkpoint).
                x, y = self.sequence[0]
                self.model.initialise_adaptive_weights(x, y)

        def on_test_begin(self, logs=None):
            # Validation (and so the checkpoints and the saved model) runs in
            # inference mode: give it BatchNorm statistics of these weights.
            if self.bn_recompute_batches:
                count = min(self.bn_recompute_batches, len(self.sequence))
                recompute_batchnorm_statistics(
                    self.model, (self.sequence[i] for i in range(count))
                )

        def on_epoch_begin(self, epoch, logs=None):
            self._epoch_start = time.perf_counter()
            # Keras calls the dataset's on_epoch_end an extra time around its
            # first peek at the data, so the epoch is set here, explicitly:
            # the order of epoch e is then the same in a resumed run.
            self.sequence.set_epoch(epoch)

        def on_train_batch_end(self, batch, logs=None):
            loss = (logs or {}).get("loss")
            if loss is not None and not math.isfinite(float(np.asarray(loss))):
                self.nan = {"epoch": self.state["epoch"], "batch": int(batch)}
                self.model.stop_training = True

        def on_epoch_end(self, epoch, logs=None):
            if self.nan is not None:
                self.state["stopped"] = (
                    f"non-finite training loss at epoch {self.nan['epoch'] + 1}, "
                    f"batch {self.nan['batch'] + 1}"
                )
                self._commit(checkpoint=False)
                return
            logs = {k: float(np.asarray(v)) for k, v in (logs or {}).items()}
            state = self.state
            val = logs.get("val_loss", logs.get("loss"))
            improved = val is not None and math.isfinite(val) and (
                state["best"] is None or val < state["best"]
            )
            best_name = None
            if improved:
                state["best"], state["best_epoch"], state["wait"] = val, epoch, 0
                best_name = f"best-{epoch:04d}"
                self.model.save_weights(os.path.join(self.backup, best_name + ".weights.h5"))
            else:
                state["wait"] += 1
                if state["wait"] >= self.patience and epoch > 0:
                    state["stopped"] = (
                        f"early stopping: no improvement of val_loss for {self.patience} epochs"
                    )
                    self.model.stop_training = True
            alphas = self.model.adaptive_weights() or {}
            logs.update({f"alpha_{name}": value for name, value in alphas.items()})
            state["wall_time_s"] += time.perf_counter() - (self._epoch_start or time.perf_counter())
            # the run's training time so far and the machine's load, per epoch
            logs.update(wall_time_s=round(state["wall_time_s"], 3),
                        load_average=round(os.getloadavg()[0], 2))
            state["rows"].append({"epoch": epoch, **logs})
            state["epoch"] = epoch + 1
            self._commit(checkpoint=True, best_name=best_name)

        # -- helpers -------------------------------------------------------
        def _commit(self, checkpoint, best_name=None):
            os.makedirs(self.backup, exist_ok=True)
            old = (self.state.get("checkpoint"), self.state.get("best_weights"))
            if checkpoint:
                name = f"epoch-{self.state['epoch']:04d}"
                # Model and optimizer variables (Keras saves both).
                self.model.save_weights(os.path.join(self.backup, name + ".weights.h5"))
                self.state["checkpoint"] = name
            if best_name is not None:
                self.state["best_weights"] = best_name
            _atomic_json(self.state_path, self.state)
            for stale in old:
                if stale is not None and stale not in (self.state["checkpoint"],
                                                       self.state["best_weights"]):
                    path = os.path.join(self.backup, stale + ".weights.h5")
                    if os.path.exists(path):
                        os.remove(path)
            publish_run_files(self.run_dir, self.state)

    return RunState


def publish_run_files(run_dir, state):
    """Bring best.weights.h5, log.csv and curves.png in line with ``state``."""
    backup = os.path.join(run_dir, "backup")
    source = os.path.join(backup, f"{state.get('best_weights')}.weights.h5")
    if state.get("best_weights") and os.path.exists(source):
        # (After a finished run the backup copy is gone; best.weights.h5 stays.)
        tmp = os.path.join(run_dir, "best.partial.weights.h5")
        shutil.copyfile(source, tmp)
        os.replace(tmp, os.path.join(run_dir, "best.weights.h5"))
    write_log(os.path.join(run_dir, "log.csv"), state.get("rows", []))
    if state.get("rows"):
        plot_curves(os.path.join(run_dir, "curves.png"), state["rows"], state.get("best_epoch"))


def write_log(path, rows):
    """One CSV row per epoch (columns: epoch, then the sorted log keys)."""
    keys = sorted({k for row in rows for k in row if k != "epoch"})
    tmp = path + ".partial"
    with open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["epoch"] + keys)
        for row in rows:
            writer.writerow([row["epoch"]] + [repr(row[k]) if k in row else "" for k in keys])
    os.replace(tmp, path)


def plot_curves(path, rows, best_epoch=None):
    """Training and validation loss per epoch (log scale when positive), and
    the adaptive weights alpha_i of Eq. 9 beside them when the run has them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
        ax.axvline(best_epoch + 1, color="grey", linestyle="--", label=f"best (epoch {best_epoch + 1})")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss")
    ax.legend()
    ax.grid(True, alpha=0.3)
    if alpha_keys:
        ax = axes[0, 1]
        for key in alpha_keys:
            ax.plot(epochs, [row.get(key, np.nan) for row in rows], label=key[len("alpha_"):])
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.set_ylabel("alpha_i (Eq. 9)")
        ax.legend(fontsize=7, ncol=2)
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    tmp = path + ".partial.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)


# ---------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------
def train(data, *, variant, run_dir, epochs=200, batch_size=16, learning_rate=None,
          image_size=None, backbone="inception_v3", split="paper", as_released=False, seed=0,
          data_parallel=False, patience=5, test_fraction=0.3, val_fraction=0.1, workers=1,
          steps_per_execution=1, disentangle="exact", bounded_pitch_head=None,
          bn_recompute_batches=None, target_scaling="none", verbose=1, command=None):
    """Train ``variant`` on the dataset file ``data``; returns the summary dict.

    Everything is validated before the run directory is created (see
    ``plan_run``). An existing run directory holding the same run is resumed.
    The summary has ``best_epoch`` (1-based), ``best_val_loss``,
    ``epochs_run``, ``run_dir``, ``status``, ``stopped`` (why training
    ended early, or None) and ``model`` (the trained model, best weights).
    """
    plan = plan_run(
        data, variant=variant, run_dir=run_dir, epochs=epochs, batch_size=batch_size,
        learning_rate=learning_rate, image_size=image_size, backbone=backbone, split=split,
        as_released=as_released, seed=seed, data_parallel=data_parallel, patience=patience,
        test_fraction=test_fraction, val_fraction=val_fraction, workers=workers,
        disentangle=disentangle, bounded_pitch_head=bounded_pitch_head,
        bn_recompute_batches=bn_recompute_batches, target_scaling=target_scaling,
        command=command,
    )
    import keras

    scope = contextlib.nullcontext()
    if data_parallel:
        devices = keras.distribution.list_devices()
        scope = keras.distribution.DataParallel(devices=devices).scope()
    with scope:
        return _run(plan, learning_rate, steps_per_execution, verbose)


def _run(plan, learning_rate, steps_per_execution, verbose):
    import keras

    from cpl_keras.datasets import StereoSequence
    from cpl_keras.models import build_model, compile_model

    config = plan["config"]
    variant = config["variant"]
    try:
        model = build_model(variant, **config["build"])
        compile_model(model, learning_rate=learning_rate, steps_per_execution=steps_per_execution,
                      target_scale=_target_scale(plan) if config["target_scaling"] == "std" else None)
    except ValueError as error:
        raise TrainingError(f"cannot build {variant}: {error}") from None
    config["learning_rate_used"] = float(
        f"{float(keras.ops.convert_to_numpy(model.optimizer.learning_rate)):.7g}"
    )
    config["num_parameters"] = int(model.count_params())

    # Nothing has been written so far; from here on the run directory exists.
    run_dir = config["run_dir"]
    os.makedirs(os.path.join(run_dir, "backup"), exist_ok=True)
    lock = _lock_run_dir(run_dir)  # held until this process ends
    previous = _read_json(os.path.join(run_dir, "config.json"), {})
    for key in ("epochs_run", "best_epoch", "best_val_loss", "wall_time_s", "status", "stopped"):
        config[key] = previous.get(key)
    config["status"] = "running"
    _atomic_json(os.path.join(run_dir, "config.json"), config)
    split_path = os.path.join(run_dir, "split.npz")
    if os.path.exists(split_path):
        old = load_split(split_path)
        if any(not np.array_equal(old[k], plan["split"][k]) for k in old):
            raise TrainingError(f"{split_path} differs from this run's split; use another --run-dir")
    else:
        save_split(split_path + ".partial.npz", plan["split"])
        os.replace(split_path + ".partial.npz", split_path)
    # The release's Average bug depends on the order of the training set: its
    # frames were shuffled, so sample i is the i-th of a shuffled order.
    train_order = np.random.default_rng(config["seed"]).permutation(plan["split"]["train"])
    # ... and it averaged the release's labels (its frame, degrees, StereoBM).
    with StereoFile(config["data"]) as data_file:
        release_targets = targets_from_labels(data_file.labels, as_released=True)
    stats = training_statistics(plan["targets"], train_order, release_targets=release_targets)
    save_statistics(os.path.join(run_dir, "train_stats.json"), stats)

    multiple = config["num_devices"]
    common = dict(targets=plan["targets"], batch_size=config["device_batch_size"],
                  multiple_of=multiple, workers=plan["workers"])
    train_seq = StereoSequence(config["data"], plan["split"]["train"], shuffle=True,
                               seed=config["seed"], **common)
    val_seq = StereoSequence(config["data"], plan["split"]["val"], shuffle=False, **common)

    RunState = _make_run_callback()
    run_state = RunState(run_dir, config["patience"], train_seq, config["bn_recompute_batches"])
    state = run_state.state
    done = state.get("stopped") is not None or state["epoch"] >= config["epochs"]
    if not done:
        initial_epoch = run_state.restore(model)
        if initial_epoch:
            print(f"Resuming {run_dir} after epoch {initial_epoch}", file=sys.stderr)
        train_seq.set_epoch(initial_epoch)
        # shuffle=False: the sequence shuffles itself, seeded per epoch; Keras's
        # own shuffle of the batch order uses Python's unseeded global RNG.
        model.fit(train_seq, validation_data=val_seq, epochs=config["epochs"],
                  initial_epoch=initial_epoch, callbacks=[run_state], shuffle=False,
                  verbose=verbose)
    train_seq.close()
    val_seq.close()
    summary = _finish(model, run_dir, config, run_state.state)
    summary["model"] = model
    lock.close()
    return summary


def _lock_run_dir(run_dir):
    """An exclusive lock on ``run_dir/backup/lock``: a second process training
    into the same run directory (say, after a kill that missed the first)
    stops with one line instead of both writing its checkpoints. The lock
    ends with the process, however it ends."""
    import fcntl

    handle = open(os.path.join(run_dir, "backup", "lock"), "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        raise TrainingError(
            f"run directory {run_dir} is in use by another training process"
        ) from None
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
    publish_run_files(run_dir, state)
    best = state.get("best_weights")
    if best:
        model.load_weights(os.path.join(run_dir, "best.weights.h5"))
        tmp = os.path.join(run_dir, "model.partial.keras")
        model.save(tmp)
        os.replace(tmp, os.path.join(run_dir, "model.keras"))
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
    _atomic_json(os.path.join(run_dir, "config.json"), config)
    for name in os.listdir(os.path.join(run_dir, "backup")):
        if name.endswith(".weights.h5"):
            os.remove(os.path.join(run_dir, "backup", name))
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
