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
import os


from cpl_keras import runs
from cpl_keras.backend import keras_backend
from cpl_keras.data.mix import training_rigs
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.datasets import make_split, targets_from_labels
from cpl_keras.models import pretrained
from cpl_keras.models.options import ModelOptions, OptionsError
from cpl_keras.training_options import (  # noqa: F401
    BN_STATISTICS, MONITORS, TARGET_SCALINGS, TrainingError, TrainingOptions, split_fields,
)

#: (``BN_STATISTICS``: where BatchNorm's statistics come from before every
#: validation, with ``bn_recompute_batches`` > 0; 0 keeps Keras's moving
#: averages, as released: "fixed", the same training pairs every epoch (the
#: first of a permutation of the training split seeded by the run's seed),
#: the variance that of all of them together (population); "epoch", the
#: first batches of each epoch's shuffled order, the variance averaged over
#: batches (this project's default before; paper_results/faithful-2000
#: measured its draw swinging the validation loss 16-43 with the same
#: weights).)
#: Training batches of that recompute, by ``bn_statistics``: 64 batches of 16
#: are 1,024 pairs (Wu & Johnson 2021 use 10^3-10^4 samples), capped at the
#: training split.
BN_RECOMPUTE_BATCHES = {"fixed": 64, "epoch": 16}
#: (``MONITORS``: what early stopping and the kept epoch follow: "nmae", the
#: sum over the ten camera parameters of the validation MAE divided by the
#: training split's mean |y| (``checkpointing.nmae_scores``: weights that do
#: not move, every variant on the same scale); "loss", the validation loss
#: (the paper's; for MTL-CPL-A it is weighted by that epoch's alpha_i, a
#: moving objective).)
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


def _validation_settings(as_released, training):
    """``training`` (a ``TrainingOptions``) with what validation runs and
    early stopping follows filled in where None (as released: the
    release's), and the names of those left at their defaults (a run
    directory resumes with its own: ``_check_run_dir``)."""
    given = dict(bn_statistics=training.bn_statistics, monitor=training.monitor,
                 weight_ema=training.weight_ema,
                 bn_recompute_batches=training.bn_recompute_batches)
    defaulted = tuple(key for key, value in given.items() if value is None)
    bn_statistics = training.bn_statistics or ("epoch" if as_released else "fixed")
    weight_ema = training.weight_ema
    if weight_ema is None:
        weight_ema = 0.0 if as_released else WEIGHT_EMA
    monitor = training.monitor or ("loss" if as_released else "nmae")
    batches = training.bn_recompute_batches
    if batches is None:
        batches = 0 if as_released else BN_RECOMPUTE_BATCHES[bn_statistics]
    return dataclasses.replace(
        training, bn_recompute_batches=int(batches), bn_statistics=bn_statistics,
        monitor=monitor, weight_ema=float(weight_ema)), defaulted


def _check_variant(variant, model, training):
    """The rules between the variant and the two records (TrainingError, one
    line); returns the model options for it (``ModelOptions.for_variant``)."""
    try:
        options = model.for_variant(variant)
    except ValueError as error:  # (an unknown variant, OptionsError)
        raise TrainingError(str(error)) from None
    if options.backbone_weights is not None:  # (a file by its absolute path, as the data)
        options = options.replace(backbone_weights=pretrained.named(options.backbone_weights))
    if training.target_scaling != "none" and not options.spec.training_loss(
            model.as_released).per_output:
        raise TrainingError(
            "target scaling applies to the per-output MAE loss (MTL-Baseline, or CPL as "
            f"released), not to {variant}"
        )
    return options


def _read_dataset(data, *, image_size, split, seed, test_fraction, val_fraction, as_released,
                  batch_size):
    """``plan_run``'s dataset: its ``facts`` (a ``runs.DataFacts``),
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
    facts = runs.DataFacts(path=data, num_pairs=num_pairs, protocol=protocol,
                           training_rigs=rigs, image_size=[height, width],
                           **{f"num_{part}": len(indices[part])
                              for part in ("train", "val", "test")})
    return {"facts": facts, "targets": targets, "split": indices}


def plan_run(data, *, variant, run_dir, model=None, training=None, command=None, processes=1,
             **fields):
    """Check the dataset and the settings; return the run's plan (a
    ``RunPlan``: its ``config`` is what config.json will hold).

    ``model``: a ``ModelOptions`` (the network's knobs); ``training``: a
    ``TrainingOptions`` (the rest of the run's settings); ``fields``: fields
    of either, by name, replacing theirs (``plan_run(data, variant="cpl-a",
    run_dir=..., epochs=50, head_norm=True)``). The defaults are the paper's
    (Adam at the variant's learning rate, batch 16, up to 200 epochs,
    patience 5, InceptionV3 towers, the paper's split). The model options'
    "auto" fields are read off the training split (the disparity head's
    ceiling, ``DISPARITY_CEILING_FACTOR`` times the largest training label;
    the softplus head's start; the range weights' scales), and a run
    directory resumes with its own. ``training.time_budget_s``: seconds of
    training (summed over resumes) the run may take; after an epoch, when
    another as long would overrun them, the run ends as finished with
    ``stopped`` saying so, keeping its best epoch. The validation settings
    left None get the defaults of ``_validation_settings`` (as released, the
    release's). ``command``: the command line recorded. Raises
    ``DatasetError`` or ``TrainingError`` with a one-line message.
    ``processes``: how many processes train the run together (the group
    ``training.train`` joined). Writes nothing.
    """
    model_fields, training_fields = split_fields(fields)
    try:
        model = (model or ModelOptions()).replace(**model_fields)
    except OptionsError as error:
        raise TrainingError(str(error)) from None
    training = dataclasses.replace(training or TrainingOptions(), **training_fields)
    options = _check_variant(variant, model, training)
    training, defaulted = _validation_settings(model.as_released, training)
    dataset = _read_dataset(data, image_size=training.image_size, split=training.split,
                            seed=training.seed, test_fraction=training.test_fraction,
                            val_fraction=training.val_fraction, as_released=model.as_released,
                            batch_size=training.batch_size)
    devices = _devices(training.data_parallel, processes)
    train_labels = {name: values[dataset["split"]["train"]]
                    for name, values in dataset["targets"].items()}
    options = options.for_training_set(train_labels, DISPARITY_CEILING_FACTOR)
    config = runs.RunConfig(
        model=options, training=_recorded(training), data=dataset["facts"],
        num_devices=devices, num_processes=processes,
        device_batch_size=-(-training.batch_size // devices) * devices, command=command,
        run_dir=os.path.abspath(os.fspath(run_dir)), keras_backend=keras_backend())
    automatic = tuple(name for name in AUTOMATIC if getattr(model, name) == "auto")
    config = _check_run_dir(config, keep_model=automatic + WEIGHTS_CHECKSUM, keep=defaulted)
    config = _with_weights_checksum(config)
    return RunPlan(config=config, targets=dataset["targets"], split=dataset["split"],
                   workers=int(training.workers))


def _recorded(training):
    """``training`` as a run records it: the arguments of one command
    (``TrainingOptions``' fields not recorded) at their defaults, the
    numbers as config.json holds them."""
    unrecorded = {field.name: field.default for field in dataclasses.fields(training)
                  if not field.metadata.get("recorded", True)}
    numbers = {name: float(getattr(training, name)) for name in ("learning_rate",
                                                                "time_budget_s", "clip_norm")
               if getattr(training, name) is not None}
    numbers.update({name: int(getattr(training, name))
                    for name in ("seed", "batch_size", "epochs", "patience")})
    return dataclasses.replace(training, **unrecorded, **numbers,
                               weight_decay=float(training.weight_decay),
                               data_parallel=bool(training.data_parallel))


#: The model options read off the training split when "auto": a run
#: directory resumes with its own values of these (runs of before one of
#: them: their own, or none).
AUTOMATIC = ("disparity_ceiling", "disparity_start", "range_scales")
#: The towers' weights file's checksum, read off the file when a run begins
#: (``_with_weights_checksum``): a run resumed with the same file keeps its
#: own, and the file is not read again.
WEIGHTS_CHECKSUM = ("backbone_weights_sha256",)


def _with_weights_checksum(config):
    """``config`` with the sha256 of its towers' weights file in its model
    record (with ``backbone_weights``): a new run's read off the file
    ("imagenet": Keras's, downloaded into its cache when not there), a
    resumed run's its own. TrainingError (one line naming the file) when it
    cannot be read."""
    model = config.model
    if model.backbone_weights is None or model.backbone_weights_sha256:
        return config
    try:
        path = pretrained.weights_file(model.backbone_weights)
        digest = pretrained.checksum(path)
    except (OSError, pretrained.WeightsError) as error:
        raise TrainingError(str(error)) from None
    return dataclasses.replace(config, model=model.replace(backbone_weights_sha256=digest))


def _devices(data_parallel, processes):
    """The devices a run trains on: every device Keras sees with
    ``data_parallel`` (else 1), over ``processes`` processes, each of which
    must hold as many devices."""
    devices = _device_count() if data_parallel else 1
    if devices % processes:
        raise TrainingError(f"{devices} devices do not split evenly over {processes} "
                            f"processes; give every process as many devices")
    return devices


def _device_count():
    import keras

    return len(keras.distribution.list_devices())


def _check_run_dir(config, keep_model=(), keep=()):
    """``config`` (a ``RunConfig``) for its run directory, which must be new,
    empty, or hold the same run (to resume). A run is resumed with its own
    value of each model option of ``keep_model`` (those read off the
    training labels, given as "auto", and the towers' weights file's
    checksum where the file is the same; a run of before the disparity
    ceiling: None), and with its own value of each training option of
    ``keep`` (settings left at their defaults, whose defaults have changed
    since: the BatchNorm statistics, the monitor and the weights' moving
    average)."""
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
    same_weights = old.model.backbone_weights == config.model.backbone_weights
    kept = {name: getattr(old.model, name) for name in keep_model
            if same_weights or name not in WEIGHTS_CHECKSUM}
    config = dataclasses.replace(config, model=config.model.replace(**kept))
    config = dataclasses.replace(config, training=dataclasses.replace(
        config.training, **{key: getattr(old.training, key) for key in keep
                            if getattr(old.training, key) is not None}))
    _check_same_run(old, config)
    return config


def resume_differences(old, config):
    """``(setting, value there, value now)`` of each setting of ``config``
    that differs from ``old``'s, the run in its run directory: a run
    directory resumes only with the same variant, model record (config.json's
    ``build``), dataset file and training record (but for what may change,
    ``TrainingOptions.differences``)."""
    found = [(key, getattr(old, key), getattr(config, key))
             for key in ("variant", "build") if getattr(old, key) != getattr(config, key)]
    if old.data.path != config.data.path:
        found.append(("data", old.data.path, config.data.path))
    return found + old.training.differences(config.training)


def _check_same_run(old, config, begun=""):
    """TrainingError (one line, naming the first setting that differs, its
    value there first) unless ``old``, the run in ``config``'s run
    directory, is the run ``config`` plans."""
    for key, there, now in resume_differences(old, config)[:1]:
        raise TrainingError(
            f"run directory {config.run_dir} holds a different run{begun} ({key}: "
            f"{there!r} there, {now!r} now); use another --run-dir"
        )


def check_run_dir_again(config):
    """The run directory of ``config`` (a ``RunPlan``'s) read again: another
    process may have begun a run there since it was planned (two commands
    started at once on one directory). The trainer asks before it reports a
    run finished, while it waits for the directory's lock and under it, so
    the check and the run's first write are one step. TrainingError (one
    line, naming the other run's setting that differs) unless that run is
    this one; returns whether a run is there (its config.json written; a
    failed run counts, replaced as ``plan_run`` says)."""
    try:
        old = runs.read_run_config(config.run_dir) if os.path.isdir(config.run_dir) else None
    except runs.RunError as error:
        raise TrainingError(f"run directory {config.run_dir} holds a different run or an "
                            f"unreadable one ({error}); use another --run-dir") from None
    if old is not None and old.status != "failed":
        _check_same_run(old, config, ", begun by another process since this one planned")
    return old is not None

