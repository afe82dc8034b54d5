"""Planning a training run: everything is checked before anything is written.

``plan_run(data, variant=..., run_dir=...)`` checks the arguments, reads the
dataset file (its images, labels and split, against the arguments) and an
existing run directory (only the same run may be resumed in it), and
returns the run's plan (a ``RunPlan``): the config.json it will write (a
``runs.RunConfig``), the targets and the split. ``cpl_keras.training.train``
runs a plan. Problems are one-line ``TrainingError`` or ``DatasetError``;
nothing is written.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from cpl_keras import distributed, runs
from cpl_keras.backend import keras_backend
from cpl_keras.camera import FLOORS, RELEASED_FLOORS
from cpl_keras.data.mix import training_rigs
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.datasets import SPLITS, make_split, targets_from_labels
from cpl_keras.errors import Error
from cpl_keras.models import BACKBONES, variants
from cpl_keras.models.variants import ALPHA_RATE, DISENTANGLE, HEAD_ACTIVATIONS, POINT_ERRORS
from cpl_keras.training.augment import AUGMENTATIONS

#: config.json keys that must match for a run directory to be resumed.
RESUME_KEYS = (
    "variant", "build", "data", "split", "seed", "batch_size", "learning_rate", "epochs",
    "data_parallel", "patience", "test_fraction", "val_fraction",
    "bn_recompute_batches", "bn_statistics", "monitor", "target_scaling", "augment",
    "weight_ema",
)
#: Per-output MAE as the paper sums it ("none"), or each divided by the
#: target's training standard deviation ("std": standardised targets).
TARGET_SCALINGS = ("none", "std")
#: Where BatchNorm's statistics come from before every validation (with
#: ``bn_recompute_batches`` > 0; 0 keeps Keras's moving averages, as released):
#: "fixed", the same training pairs every epoch (the first of a permutation of
#: the training split seeded by the run's seed), the variance that of all of
#: them together (population); "epoch", the first batches of each epoch's
#: shuffled order, the variance averaged over batches (this project's default
#: before; paper_results/faithful-2000 measured its draw swinging the
#: validation loss 16-43 with the same weights).
BN_STATISTICS = ("fixed", "epoch")
#: Training batches of that recompute, by ``bn_statistics``: 64 batches of 16
#: are 1,024 pairs (Wu & Johnson 2021 use 10^3-10^4 samples), capped at the
#: training split.
BN_RECOMPUTE_BATCHES = {"fixed": 64, "epoch": 16}
#: What early stopping and the kept epoch follow: "nmae", the sum over the ten
#: camera parameters of the validation MAE divided by the training split's
#: mean |y| (``checkpointing.nmae_scores``: weights that do not move, every
#: variant on the same scale); "loss", the validation loss (the paper's; for
#: MTL-CPL-A it is weighted by that epoch's alpha_i, a moving objective).
MONITORS = ("nmae", "loss")
#: The momentum of the moving average of the weights that validation, the
#: kept epoch and the saved model use (``weight_ema=None``; 0 is off, the
#: paper's and the release's): the optimizer's exponential moving average,
#: about 100 steps, with the BatchNorm statistics recomputed for it.
#: paper_results/weight-ema measured it steadying the monitor and lowering
#: InceptionV3 MTL-CPL-A's test NMAE on every column in both seeds run.
WEIGHT_EMA = 0.99
#: The CPL disparity head's ceiling, ``disparity_ceiling="auto"``: this many
#: times the largest disparity label of the training split
#: (``layers.PositiveDisparity`` says why).
DISPARITY_CEILING_FACTOR = 2.0


class TrainingError(Error):
    """A bad argument or run directory (one-line message)."""


@dataclasses.dataclass(frozen=True)
class RunPlan:
    """A checked run, ready to train (``plan_run``; ``trainer.train`` runs it)."""

    # the settings, as config.json will hold them (the outcome fields None)
    config: runs.RunConfig
    # target name -> (num_pairs,) array: what each head is trained on
    targets: dict
    # "train", "val", "test" -> index arrays into the dataset file
    split: dict
    # loader threads per sequence of batches
    workers: int


def _check_choice(what, value, choices):
    """``value`` must be one of ``choices`` (TrainingError, one line, naming ``what``)."""
    if value not in choices:
        raise TrainingError(f"unknown {what} {value!r}; choose one of {', '.join(choices)}")


def _check_momentum(weight_ema):
    if isinstance(weight_ema, bool) or not (isinstance(weight_ema, (int, float, np.floating))
                                            and 0 <= weight_ema < 1):
        raise TrainingError(f"the weights' moving-average momentum must be in [0, 1), "
                            f"got {weight_ema!r}")


def _validation_settings(as_released, bn_recompute_batches, bn_statistics, monitor,
                         weight_ema):
    """What validation runs and early stopping follows, checked (TrainingError,
    one line), the defaults filled in (as released: the release's). Returns
    them as config.json's fields, and the names of those left at their
    defaults (a run directory resumes with its own: ``_check_run_dir``)."""
    given = dict(bn_statistics=bn_statistics, monitor=monitor, weight_ema=weight_ema,
                 bn_recompute_batches=bn_recompute_batches)
    defaulted = tuple(key for key, value in given.items() if value is None)
    if bn_statistics is None:
        bn_statistics = "epoch" if as_released else "fixed"
    _check_choice("BatchNorm statistics", bn_statistics, BN_STATISTICS)
    if weight_ema is None:
        weight_ema = 0.0 if as_released else WEIGHT_EMA
    _check_momentum(weight_ema)
    if monitor is None:
        monitor = "loss" if as_released else "nmae"
    _check_choice("monitor", monitor, MONITORS)
    if bn_recompute_batches is None:
        bn_recompute_batches = 0 if as_released else BN_RECOMPUTE_BATCHES[bn_statistics]
    if isinstance(bn_recompute_batches, bool) or not (
        isinstance(bn_recompute_batches, (int, np.integer)) and bn_recompute_batches >= 0
    ):
        raise TrainingError(
            f"BatchNorm recompute batches must be a non-negative integer, got {bn_recompute_batches!r}"
        )
    settings = dict(bn_recompute_batches=int(bn_recompute_batches), bn_statistics=bn_statistics,
                    monitor=monitor, weight_ema=float(weight_ema))
    return settings, defaulted


def _check_target_scaling(target_scaling, spec, variant, as_released):
    """``target_scaling`` must be known, and "none" unless the variant's
    training loss is the per-output MAE (TrainingError, one line)."""
    _check_choice("target scaling", target_scaling, TARGET_SCALINGS)
    if target_scaling != "none" and not spec.training_loss(as_released).per_output:
        raise TrainingError(
            "target scaling applies to the per-output MAE loss (MTL-Baseline, or CPL as "
            f"released), not to {variant}"
        )


def _check_optional_numbers(learning_rate, alpha_rate, disparity_ceiling, time_budget_s):
    """The settings that are a number or None (their defaults): each must be
    a finite number in its range (TrainingError, one line)."""
    if learning_rate is not None and not (
        isinstance(learning_rate, (int, float)) and math.isfinite(learning_rate) and learning_rate > 0
    ):
        raise TrainingError(f"learning rate must be a positive number, got {learning_rate!r}")
    if alpha_rate is not None and (isinstance(alpha_rate, bool) or not (
        isinstance(alpha_rate, (int, float)) and math.isfinite(alpha_rate) and alpha_rate >= 0
    )):
        raise TrainingError(f"alpha rate must be a number >= 0 (0: frozen), got {alpha_rate!r}")
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


def _check_arguments(*, variant, backbone, split, epochs, batch_size, workers, patience, seed,
                     as_released, bn_recompute_batches, bn_statistics, monitor, disentangle,
                     point_errors, exp_disparity_head, target_scaling, learning_rate, alpha_rate,
                     time_budget_s, disparity_ceiling, augment, weight_ema, head_activation="relu"):
    """``plan_run``'s checks of its arguments, in this order (TrainingError,
    one line); returns the variant's spec and ``_validation_settings``'s
    (config.json's BatchNorm, monitor and moving-average fields, defaults
    filled in; the names of those left at their defaults)."""
    try:
        spec = variants.get(variant)
    except ValueError as error:
        raise TrainingError(str(error)) from None
    _check_choice("backbone", backbone, BACKBONES)
    _check_choice("split", split, SPLITS)
    for name, value in (("epochs", epochs), ("batch size", batch_size), ("workers", workers)):
        if not (isinstance(value, (int, np.integer)) and value >= 1):
            raise TrainingError(f"{name} must be a positive integer, got {value!r}")
    for name, value in (("patience", patience), ("seed", seed)):
        if isinstance(value, bool) or not (isinstance(value, (int, np.integer)) and value >= 0):
            raise TrainingError(f"{name} must be a non-negative integer, got {value!r}")
    validation, defaulted = _validation_settings(
        as_released, bn_recompute_batches, bn_statistics, monitor, weight_ema)
    _check_choice("disentangle", disentangle, DISENTANGLE)
    _check_choice("point errors", point_errors, POINT_ERRORS)
    if point_errors != "metres" and not spec.training_loss(as_released).projection:
        raise TrainingError(f"point errors {point_errors!r} apply to the camera projection "
                            f"loss, which {variant} does not train with")
    if exp_disparity_head and spec.builder != "direct":
        raise TrainingError(f"an exp disparity head is MTL-Baseline's ablation; {variant} has "
                            f"its own disparity head")
    _check_choice("head activation", head_activation, HEAD_ACTIVATIONS)
    if head_activation != "relu" and spec.builder == "deep_homo":
        raise TrainingError(f"head activation {head_activation!r} applies to the regression "
                            f"heads; {variant} has its own")
    _check_target_scaling(target_scaling, spec, variant, as_released)
    _check_optional_numbers(learning_rate, alpha_rate, disparity_ceiling, time_budget_s)
    if augment is not None:
        _check_choice("augmentation", augment, AUGMENTATIONS)
    return spec, validation, defaulted


def _read_dataset(data, *, image_size, split, seed, test_fraction, val_fraction, as_released,
                  batch_size):
    """``plan_run``'s dataset: its facts (``fields``: config.json's data,
    num_pairs, protocol, training_rigs and split sizes), ``image_size``,
    ``targets`` and ``split``, checked against the arguments (DatasetError
    or TrainingError, one line)."""
    data = os.path.abspath(os.fspath(data))
    with StereoFile(data) as f:
        labels = f.labels
        height, width, _ = f.image_shape
        num_pairs = f.num_pairs
        protocol = f.metadata.get("protocol")
        rigs = training_rigs(f.metadata)
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
    fields = dict(data=data, num_pairs=num_pairs, protocol=protocol, training_rigs=rigs,
                  **{f"num_{part}": len(indices[part]) for part in ("train", "val", "test")})
    return {"fields": fields, "image_size": [height, width], "targets": targets, "split": indices}


def plan_run(data, *, variant, run_dir, epochs=200, batch_size=16, learning_rate=None,
             image_size=None, backbone="inception_v3", split="paper", as_released=False,
             seed=0, data_parallel=False, patience=5, test_fraction=0.3, val_fraction=0.1,
             workers=1, disentangle="exact", point_errors="metres", exp_disparity_head=False,
             head_activation="relu", bounded_pitch_head=None,
             positive_focal_head=None, alpha_rate=None, disparity_ceiling="auto",
             bn_recompute_batches=None, bn_statistics=None, monitor=None,
             target_scaling="none", time_budget_s=None, augment=None, weight_ema=None, command=None):
    """Check the dataset and the arguments; return the run's plan (a
    ``RunPlan``: its ``config`` is what config.json will hold).

    The defaults are the paper's (Adam at the variant's learning rate, batch
    16, up to 200 epochs, patience 5, InceptionV3 towers, the paper's split).
    ``time_budget_s``: seconds of training (summed over resumes) the run may
    take; after an epoch, when another as long would overrun them, the run
    ends as finished with ``stopped`` saying so, keeping its best epoch.
    ``disparity_ceiling``: the CPL disparity head's largest output in px
    (``"auto"``: ``DISPARITY_CEILING_FACTOR`` times the largest training
    label; None: ``layers.MAX_OUTPUT``, the bound of runs made before it).
    ``point_errors``: the CPL variants' point errors of Eq. 7, ``"metres"``
    (the paper's) or ``"relative"`` (``losses.POINT_ERRORS``; an ablation).
    ``exp_disparity_head``: MTL-Baseline with the CPL variants' disparity
    head, d = exp(z) up to its ceiling (an ablation).
    ``head_activation``: the regression heads' hidden activation, ``"relu"``
    (the release's) or a leaky ReLU (``variants.HEAD_ACTIVATIONS``; ablations).
    ``augment``: None, or ``"photometric"`` (``training.augment``; not the paper's).
    ``bn_statistics`` (``BN_STATISTICS``), ``bn_recompute_batches`` and
    ``monitor`` (``MONITORS``): the BatchNorm statistics validation runs
    with, and what early stopping follows (None: "fixed" over 64 batches and
    "nmae"; as released: Keras's moving averages and "loss"). ``weight_ema``:
    ``runs.RunConfig``'s (None: ``WEIGHT_EMA``; as released, 0). Raises
    ``DatasetError`` or ``TrainingError`` with a one-line message. Writes
    nothing.
    """
    spec, validation, defaulted = _check_arguments(
        variant=variant, backbone=backbone, split=split, epochs=epochs, batch_size=batch_size,
        workers=workers, patience=patience, seed=seed, as_released=as_released,
        bn_recompute_batches=bn_recompute_batches, bn_statistics=bn_statistics,
        monitor=monitor, disentangle=disentangle, point_errors=point_errors,
        exp_disparity_head=exp_disparity_head, head_activation=head_activation,
        target_scaling=target_scaling, learning_rate=learning_rate, alpha_rate=alpha_rate,
        time_budget_s=time_budget_s, disparity_ceiling=disparity_ceiling, augment=augment,
        weight_ema=weight_ema)
    dataset = _read_dataset(data, image_size=image_size, split=split, seed=seed,
                            test_fraction=test_fraction, val_fraction=val_fraction,
                            as_released=as_released, batch_size=batch_size)
    devices, processes = _devices_and_processes(data_parallel)
    build = _build_arguments(
        spec, dataset, backbone=backbone, as_released=as_released,
        bounded_pitch_head=bounded_pitch_head, positive_focal_head=positive_focal_head,
        disentangle=disentangle, seed=seed, alpha_rate=alpha_rate,
        disparity_ceiling=disparity_ceiling, point_errors=point_errors,
        exp_disparity_head=bool(exp_disparity_head), head_activation=head_activation)
    config = runs.RunConfig(
        variant=variant, build=build, **dataset["fields"], split=split,
        test_fraction=test_fraction, val_fraction=val_fraction, seed=int(seed),
        batch_size=int(batch_size),
        learning_rate=None if learning_rate is None else float(learning_rate),
        epochs=int(epochs), patience=int(patience), **validation, target_scaling=target_scaling,
        time_budget_s=None if time_budget_s is None else float(time_budget_s),
        augment=augment, data_parallel=bool(data_parallel), num_devices=devices,
        num_processes=processes, device_batch_size=-(-batch_size // devices) * devices,
        command=command,
        run_dir=os.path.abspath(os.fspath(run_dir)), keras_backend=keras_backend())
    config = _check_run_dir(config, keep_ceiling=disparity_ceiling == "auto", keep=defaulted)
    return RunPlan(config=config, targets=dataset["targets"], split=dataset["split"],
                   workers=int(workers))


def _devices_and_processes(data_parallel):
    """``(devices, processes)`` a run trains on: every device Keras sees with
    ``data_parallel`` (else 1), over the processes of the group joined by
    ``training.train`` (else 1); each process must hold as many devices."""
    devices = _device_count() if data_parallel else 1
    group = distributed.current()
    processes = 1 if group is None else group.num_processes
    if devices % processes:
        raise TrainingError(f"{devices} devices do not split evenly over {processes} "
                            f"processes; give every process as many devices")
    return devices, processes


def _build_arguments(spec, dataset, *, backbone, as_released, bounded_pitch_head,
                     positive_focal_head, disentangle, seed, alpha_rate, disparity_ceiling,
                     point_errors="metres", exp_disparity_head=False, head_activation="relu"):
    """config.json's ``build``: ``models.build_model``'s keyword arguments
    for ``dataset``'s images (``_read_dataset``; the heads as released when
    ``as_released``, unless set; the disparity head's ceiling; the adaptive
    weights' pace for MTL-CPL-A; the point errors where not in metres and
    MTL-Baseline's exp disparity head and the heads' activation where not the
    defaults, so that the runs made before those choices resume)."""
    build = {
        "backbone": backbone, "image_size": dataset["image_size"],
        "as_released": bool(as_released),
        "floors": dict(RELEASED_FLOORS if as_released else FLOORS),
        "bounded_pitch_head": (not as_released) if bounded_pitch_head is None
        else bool(bounded_pitch_head),
        "positive_focal_head": (not as_released) if positive_focal_head is None
        else bool(positive_focal_head),
        "disentangle": disentangle, "seed": int(seed),
        "disparity_ceiling": _disparity_ceiling(disparity_ceiling, spec, as_released, dataset,
                                                exp_disparity_head),
    }
    if spec.training_loss(as_released).adaptive:
        build["alpha_rate"] = float(ALPHA_RATE if alpha_rate is None else alpha_rate)
    if point_errors != "metres":
        build["point_errors"] = point_errors
    if exp_disparity_head:
        build["exp_disparity_head"] = True
    if head_activation != "relu":
        build["head_activation"] = head_activation
    return build


def _disparity_ceiling(setting, spec, as_released, dataset, exp_head=False):
    """The build's ``disparity_ceiling`` (px): None where the disparity head
    is not the positive one (the direct variants unless ``exp_head``, or as
    released), and with
    ``"auto"`` ``DISPARITY_CEILING_FACTOR`` times the largest training label
    of ``dataset`` (``_read_dataset``'s)."""
    if as_released or not (spec.training_loss(as_released).projection or exp_head):
        return None
    if setting == "auto":
        train_labels = dataset["targets"]["disparity"][dataset["split"]["train"]]
        return round(DISPARITY_CEILING_FACTOR * float(np.max(train_labels)), 3)
    return None if setting is None else float(setting)


def _device_count():
    import keras

    return len(keras.distribution.list_devices())


def _check_run_dir(config, keep_ceiling=False, keep=()):
    """``config`` (a ``RunConfig``) for its run directory, which must be new,
    empty, or hold the same run (to resume). With ``keep_ceiling``
    (``disparity_ceiling="auto"``) a run is resumed with its own disparity
    ceiling (a run of before the ceiling: None), and with its own value of
    each config key of ``keep`` (settings left at their defaults, whose
    defaults have changed since: the BatchNorm statistics, the monitor and
    the weights' moving average)."""
    run_dir = config.run_dir
    if not os.path.exists(run_dir):
        return config
    if not os.path.isdir(run_dir):
        raise TrainingError(f"run directory is not a directory: {run_dir}")
    try:
        old = runs.read_run_config(run_dir)
    except runs.RunError as error:  # (unreadable, or not a run of this package)
        raise TrainingError(f"run directory {run_dir} holds a different run or an unreadable "
                            f"one ({error}); use another --run-dir") from None
    if old is None:
        backup = os.path.join(run_dir, runs.BACKUP)
        # (a process killed between creating the directory and its config.json
        # leaves an empty backup/ with the lock: still an empty run directory)
        started = os.listdir(run_dir) == [runs.BACKUP] and set(os.listdir(backup)) <= {"lock"}
        if os.listdir(run_dir) and not started:
            raise TrainingError(f"run directory {run_dir} is not empty and holds no run")
        return config
    if old.status == "failed":
        return config  # (replaced by the next run: ``_replace_failed_run``)
    if keep_ceiling:
        config = dataclasses.replace(config, build=dict(
            config.build, disparity_ceiling=old.build["disparity_ceiling"]))
    config = dataclasses.replace(config, **{key: getattr(old, key) for key in keep
                                            if getattr(old, key) is not None})
    for key in RESUME_KEYS:
        if getattr(old, key) != getattr(config, key):
            raise TrainingError(
                f"run directory {run_dir} holds a different run ({key}: "
                f"{getattr(old, key)!r} there, {getattr(config, key)!r} now); use another "
                f"--run-dir"
            )
    return config

