"""Training one of the paper's networks on a stereo dataset file.

``train(data, variant=..., run_dir=...)`` validates everything first (the
file, its labels and images, the arguments: ``cpl_keras.training.planning``; the
model itself), then creates the run directory (its files:
``cpl_keras.runs``).

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
then resumes from where it left off (or finds the run finished); one on
another run there (two commands started at once) is refused in one line.
The callback that checkpoints is ``cpl_keras.training.checkpointing.RunState``;
the final model and config.json, and a finished run read back, are
``cpl_keras.training.result``'s.
A non-finite training loss stops the run and keeps the best weights so far.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import os
import shutil
import sys
import time

import numpy as np

from cpl_keras import backend, files, models, runs
from cpl_keras.baselines.average import save_statistics, training_statistics
from cpl_keras.camera import PARAMETERS
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.models import variants
from cpl_keras.datasets import load_split, save_split, targets_from_labels
from cpl_keras.training.gradients import TermGradients
from cpl_keras.training.head_units import HeadUnits
from cpl_keras.training.planning import (
    TrainingError, check_run_dir_again, plan_run,
)
from cpl_keras.training_options import check_steps_per_execution
from cpl_keras.training.processes import join_processes
from cpl_keras.training.result import backend_note, finish_run, finished_run
from cpl_keras.training.state import read_state

# ---------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------
def train(data, *, steps_per_execution=1, verbose=1, return_model=True, term_gradients=False,
          head_units=False, **options):
    """Train a variant on the dataset file ``data``; returns a ``TrainResult``.

    ``options`` are ``planning.plan_run``'s keyword arguments (``variant``
    and ``run_dir`` required; the records ``model`` and ``training``, or
    any of their fields by name: ``epochs``, ``batch_size``, ``backbone``,
    ``split``, ``seed``, ``as_released``, ``head_norm``, ... with the
    paper's defaults): everything is validated before the run directory is
    created. An existing run directory holding the same run is resumed.
    The result holds the run's final ``config`` (``best_epoch``, 1-based,
    ``best_val_loss``, ``epochs_run``, ``run_dir``, ``status``, ``stopped``:
    why training ended early, or None) and ``model`` (the trained model,
    best weights). A run that has already ended is left untouched
    (``finished_before``; its model.keras keeps its optimizer state); with
    ``return_model=False`` it is read without importing Keras and the
    result's ``model`` is None (train.py: a finished run's command returns
    at once).
    ``steps_per_execution``: training steps per compiled call (Keras's).
    ``term_gradients``: log, every epoch, the gradient that each loss term
    sends into the towers' shared features (``grad_<target>`` columns of
    log.csv; ``training.gradients``; not with data parallelism). A
    diagnostic: it changes nothing of the training.
    ``head_units``: log, every epoch, each regression head's live units on
    the same probe pairs (``dead_<head>``, ``units_<head>``;
    ``training.head_units``): when a head dies. A diagnostic too.
    ``verbose``: 0 prints nothing, 1 one short line per epoch (every metric
    is in log.csv) and a progress bar when stdout is a terminal, 2 the
    epoch lines only.
    """
    check_steps_per_execution(steps_per_execution)  # (before any file: 1 under PyTorch)
    # (the group is joined before any device is counted)
    processes = join_processes(options.get("data_parallel", getattr(
        options.get("training"), "data_parallel", False)))
    plan = plan_run(data, processes=processes.count, **options)
    _check_probes(plan.config.variant, term_gradients, head_units)
    check_run_dir_again(plan.config)  # (a finished run begun there since: this one's?)
    finished = finished_run(plan.config.run_dir, return_model)
    processes.agree("the run", group_fingerprint, plan, finished)
    if finished is not None:
        return finished
    import keras

    if processes.writes:
        _replace_failed_run(plan.config.run_dir)
    scope = contextlib.nullcontext()
    if plan.config.training.data_parallel:
        devices = keras.distribution.list_devices()
        # (across processes each one reads its own part of every batch:
        # StereoSequence's ``process``; Keras shards only tf.data itself)
        scope = keras.distribution.DataParallel(
            devices=devices, auto_shard_dataset=processes.part is None).scope()
    with scope, processes.failures():
        probes = tuple(name for name, on in (("term_gradients", term_gradients),
                                             ("head_units", head_units)) if on)
        return _run(plan, processes, steps_per_execution, verbose, probes)


def group_fingerprint(plan, finished):
    """What every process of a group must agree on before training: the
    settings, the dataset's labels and split, the step counts of an epoch,
    and where the run stands (a run directory that one process sees and
    another does not shows here)."""
    config = plan.config
    batch, data = config.device_batch_size, config.data
    digest = hashlib.sha256()
    for name in sorted(plan.targets):
        digest.update(np.asarray(plan.targets[name], np.float32).tobytes())
    for part in ("train", "val", "test"):
        digest.update(np.asarray(plan.split[part], np.int64).tobytes())
    state = read_state(config.run_dir)
    return {
        "training steps per epoch": -(-data.num_train // batch),
        "validation steps": -(-data.num_val // batch),
        "devices": config.num_devices,
        "variant": config.variant, "build": config.build, **config.training.to_config(),
        "dataset pairs": data.num_pairs,
        "labels and split (sha256)": digest.hexdigest()[:16],
        "run status": "finished" if finished is not None else getattr(
            runs.read_run_config(config.run_dir), "status", None) or "new",
        "epochs completed": int(state.epoch),
    }


def _failed_run(run_dir):
    """The config of the run in ``run_dir`` if it failed (a non-finite loss), else None."""
    config = runs.read_run_config(run_dir) if os.path.isdir(run_dir) else None
    return config if config is not None and config.status == "failed" else None


def _replace_failed_run(run_dir):
    """A failed run is not resumed: the next run into its directory, with
    these settings or others, starts afresh in its place (said on stderr)."""
    failed = _failed_run(run_dir)
    if failed is None:
        return
    print(f"Replacing the failed run in {run_dir} ({failed.stopped})", file=sys.stderr,
          flush=True)
    shutil.rmtree(run_dir)


def _run(plan, processes, steps_per_execution, verbose, probes=()):
    import keras

    config = plan.config
    # (a resumed run's weights come from its checkpoint: the towers' initial
    # weights file, ``backbone_weights``, is not read again)
    resumed = read_state(config.run_dir).checkpoint is not None
    try:
        model = models.build_from_config(config.variant, config.build,
                                         read_backbone_weights=not resumed)
        models.compile_model(model, config.training, steps_per_execution=steps_per_execution,
                             target_scale=_target_scale(plan)
                             if config.training.target_scaling == "std" else None)
    except ValueError as error:
        raise TrainingError(f"cannot build {config.variant}: {error}") from None
    config = dataclasses.replace(
        config, num_parameters=int(model.count_params()), learning_rate_used=float(
            f"{float(keras.ops.convert_to_numpy(model.optimizer.learning_rate)):.7g}"))

    # Nothing has been written so far; from here on the run directory exists
    # (written by process 0 alone when several train together). The lock is
    # released however training ends (a Ctrl-C in a notebook, then train() again).
    with _lock_run_dir(config) if processes.writes else contextlib.nullcontext():
        return _run_locked(plan, model, config, processes, verbose, probes)


def _run_locked(plan, model, config, processes, verbose, probes=()):
    from cpl_keras.training.sequence import StereoSequence

    run_dir = config.run_dir
    written = processes.write("run directory ready", _open_run_dir, plan, config, run_dir)
    finished = finished_run(run_dir)  # (by the process this one waited for)
    if finished is not None:
        return finished
    config = written or config  # (the config.json written; the other processes keep theirs)
    training, data = config.training, config.data.path
    common = dict(targets=plan.targets, batch_size=config.device_batch_size,
                  multiple_of=config.num_devices, workers=plan.workers, part=processes.part)
    train_seq = StereoSequence(data, plan.split["train"], shuffle=True,
                               seed=training.seed, augment=training.augment, **common)
    val_seq = StereoSequence(data, plan.split["val"], shuffle=False, **common)

    bn_seq = None
    if training.bn_statistics == "fixed" and training.bn_recompute_batches:
        bn_seq = StereoSequence(data, batchnorm_pairs(plan), shuffle=False, **common)

    from cpl_keras.training.checkpointing import RunState
    from cpl_keras.training.progress import EpochLines

    run_state = RunState(run_dir, training.patience, train_seq, training.bn_recompute_batches,
                         time_budget_s=training.time_budget_s, bn_sequence=bn_seq,
                         nmae_scale=nmae_scale(plan) if training.monitor == "nmae" else None,
                         weight_ema=training.weight_ema > 0, processes=processes,
                         probe=_probe(model, probes, StereoSequence(
                             data, plan.split["train"][:PROBE_PAIRS], shuffle=False,
                             **dict(common, workers=1, multiple_of=1)))
                         if probes and not training.data_parallel else None)
    state = run_state.state
    done = state.stopped is not None or state.epoch >= training.epochs
    try:
        if not done:
            initial_epoch = run_state.restore(model)
            if initial_epoch:
                print(f"Resuming {run_dir} after epoch {initial_epoch}"
                      f"{backend_note(config, resuming=True)}", file=sys.stderr)
            train_seq.set_epoch(initial_epoch)
            # shuffle=False: the sequence shuffles itself, seeded per epoch; Keras's
            # own shuffle of the batch order uses Python's unseeded global RNG.
            callbacks = [run_state]
            if verbose and processes.writes:  # (Keras's bar: all 14-30 metrics a line)
                callbacks.append(EpochLines(training.epochs, run_state,
                                            live=None if verbose == 1 else False))
            model.fit(train_seq, validation_data=val_seq, epochs=training.epochs,
                      initial_epoch=initial_epoch, callbacks=callbacks, shuffle=False,
                      verbose=0)
    finally:  # (also on Ctrl-C: no reading threads left behind)
        for sequence in (train_seq, val_seq, bn_seq):
            if sequence is not None:
                sequence.close()
    return dataclasses.replace(finish_run(model, config, run_state.state, processes), model=model)


#: Training pairs (the first of the split, the same every epoch) on which
#: ``term_gradients`` measures each loss term's gradient and ``head_units``
#: counts each head's live units.
PROBE_PAIRS = 64


def _check_probes(variant, term_gradients, head_units):
    """Refuse, before anything is written, a diagnostic that ``variant``
    has nothing to measure for (Deep-Homo: one loss term, no regression heads)."""
    if variants.get(variant).builder == "deep_homo":
        for flag, on in (("term gradients", term_gradients), ("head units", head_units)):
            if on:
                raise TrainingError(f"{flag} measure the regression heads and loss terms; "
                                    f"{variant} has neither")


def _probe(model, probes, sequence):
    """``probe()`` -> the epoch's diagnostics named in ``probes`` on the
    pairs of ``sequence`` (read once, then closed): each loss term's gradient
    norm at the shared features (``training.gradients``), each head's live
    units (``training.head_units``)."""
    batches = [sequence[i] for i in range(len(sequence))]
    sequence.close()
    x = {name: np.concatenate([b[0][name] for b in batches]) for name in batches[0][0]}
    y = {name: np.concatenate([b[1][name] for b in batches]) for name in batches[0][1]}
    measures = []
    if "term_gradients" in probes:
        gradients = TermGradients(model)
        measures.append(lambda: gradients(x, y))
    if "head_units" in probes:
        units = HeadUnits(model)
        measures.append(lambda: units(x))
    return lambda: {k: v for measure in measures for k, v in measure().items()}


def _open_run_dir(plan, config, run_dir):
    """(The process that writes) ``_write_run_files``, unless the run has
    finished meanwhile (by the process whose lock this one waited for:
    ``_lock_run_dir``); returns the config as written, or ``config``."""
    if finished_run(run_dir, load_model=False) is not None:
        return config
    return _write_run_files(plan, config, run_dir)


def _write_run_files(plan, config, run_dir):
    """config.json (status "running", this machine added to ``machines``),
    split.npz and train_stats.json: what a run directory holds from its start. Returns ``config`` as written (a
    resumed run keeps its outcome so far)."""
    split_path = os.path.join(run_dir, runs.SPLIT)
    if os.path.exists(split_path):  # (checked before anything is written: a refusal writes nothing)
        try:
            old = load_split(split_path)
        except DatasetError as problem:
            raise TrainingError(f"{problem}: delete it (the run writes it again from its "
                                f"seed) or use another --run-dir") from None
        if any(not np.array_equal(old[k], plan.split[k]) for k in old):
            raise TrainingError(f"{split_path} differs from this run's split; use another --run-dir")
    previous = runs.read_run_config(run_dir)  # (a run to resume: checked by plan_run)
    machines = list(getattr(previous, "machines", None) or [])
    if not machines or machines[-1] != backend.machine():
        machines.append(backend.machine())
    config = dataclasses.replace(config, status="running", machines=machines, **{
        key: getattr(previous, key, None) for key in ("epochs_run", "best_epoch",
                                                      "best_val_loss", "wall_time_s", "stopped")})
    runs.write_config(run_dir, config)
    if not os.path.exists(split_path):
        with files.atomic_path(split_path) as tmp:
            save_split(tmp, plan.split)
    # The release's Average bug depends on the order of the training set: its
    # frames were shuffled, so sample i is the i-th of a shuffled order.
    train_order = np.random.default_rng(config.training.seed).permutation(plan.split["train"])
    # ... and it averaged the release's labels (its frame, degrees, StereoBM).
    with StereoFile(config.data.path) as data_file:
        release_targets = targets_from_labels(data_file.labels, as_released=True)
    stats = training_statistics(plan.targets, train_order, release_targets=release_targets)
    save_statistics(os.path.join(run_dir, runs.STATS), stats)
    return config


def _lock_run_dir(config):
    """An exclusive lock on the run directory's ``backup/lock``: one process
    at a time trains into it, and the check of its settings
    (``check_run_dir_again``) and its first write are one step. A second
    process on the same run (the same command run again after a kill that
    missed the first) waits until the first ends, then carries on from the
    state it left, ending as an uninterrupted run would; one on another run
    (two commands started at once) is refused in one line once the holder's
    config.json is there (written just after it locks), without waiting.
    The lock ends with the run (the caller closes the handle) or the process."""
    os.makedirs(os.path.join(config.run_dir, runs.BACKUP), exist_ok=True)
    handle = open(os.path.join(config.run_dir, runs.LOCK), "a+")
    try:
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if check_run_dir_again(config):  # (the holder's run is this one)
                    print(f"Waiting for the training process that is using {config.run_dir}",
                          file=sys.stderr, flush=True)
                    fcntl.flock(handle, fcntl.LOCK_EX)
                    break
            time.sleep(0.05)
        check_run_dir_again(config)
    except BaseException:
        handle.close()
        raise
    return handle


def batchnorm_pairs(plan):
    """The training pairs BatchNorm's statistics are recomputed over with
    ``bn_statistics="fixed"``: ``bn_recompute_batches`` whole batches (at
    most the training split's whole batches) from a permutation of the
    training split seeded by the run's seed; the same every epoch and on
    resume.

    The pairs stay in that shuffled order: each batch is a random mix, as
    training's are. In file order a batch holds neighbouring frames of one
    drive, and the deeper layers' statistics of such batches, normalised
    batch by batch, are not those of training: on the InceptionV3 MTL-CPL-A
    run of paper_results/faithful-2000-steady they gave a validation loss of
    46.5 where the shuffled order gave 10.1 with the same weights."""
    config = plan.config
    train = np.asarray(plan.split["train"])
    batch = config.device_batch_size
    count = min(config.training.bn_recompute_batches, max(len(train) // batch, 1)) * batch
    return np.random.default_rng([config.training.seed, 1024]).permutation(train)[:count]


def nmae_scale(plan):
    """The training split's mean |y| of each camera parameter: the NMAE
    monitor's fixed normalisers (1 where a parameter is 0 throughout)."""
    train = plan.split["train"]
    scale = {}
    for name in PARAMETERS:
        mean = float(np.mean(np.abs(np.asarray(plan.targets[name], np.float64)[train])))
        scale[name] = mean if mean > 1e-9 else 1.0
    return scale


def _target_scale(plan):
    """Training standard deviation of every target (1 for a constant one,
    such as the cvgl protocol's u0 and v0)."""
    train = plan.split["train"]
    scale = {}
    for name, values in plan.targets.items():
        std = float(np.std(np.asarray(values, np.float64)[train]))
        scale[name] = std if std > 1e-6 else 1.0
    return scale
