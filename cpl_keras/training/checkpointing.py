"""Checkpointing, early stopping and the NaN guard of a training run.

``RunState`` is the one Keras callback of a run: after every epoch it
checkpoints the model and optimizer state crash-safely, keeps the
early-stopping counters and the per-epoch log, and stops on a non-finite
training loss. ``publish_run_files`` brings the run directory's
best.weights.h5, log.csv and curves.png in line with its state.
"""

from __future__ import annotations

import csv
import math
import os
import shutil
import time

import keras
import numpy as np

from cpl_keras import cli, files, runs
from cpl_keras.models.batchnorm import recompute_batchnorm_statistics
from cpl_keras.report.curves import plot_curves, run_label
from cpl_keras.training.planning import TrainingError
from cpl_keras.training.processes import SingleProcess
from cpl_keras.training.state import read_state, write_state


class RunState(keras.callbacks.Callback):
    """Checkpoints every epoch and does early stopping, crash-safely.

    State (``backup/state.json``, ``self.state``: a ``TrainingState``,
    ``training.state``): completed epochs, the early-stopping counters, the
    per-epoch logs and the names of the checkpoint files. Checkpoint files
    are written under fresh names and only then named by a new
    ``state.json`` (``os.replace``), so a kill at any moment leaves the
    previous epoch's state intact. Inside the state, epochs are Keras's
    indices (0 = the first); log.csv, curves.png, config.json and the
    console number them from 1.
    """

    def __init__(self, run_dir, patience, sequence, bn_recompute_batches=0,
                 time_budget_s=None, bn_sequence=None, nmae_scale=None, weight_ema=False,
                 processes=None, probe=None):
        super().__init__()
        # ``probe()`` -> more of the epoch's log, at the weights as trained
        # (the loss terms' gradients, ``--term-gradients``), or None
        self.probe = probe
        self.run_dir = run_dir
        # the processes that train the run (``training.processes``): this one
        # writes the run directory if ``processes.writes`` (in a group,
        # process 0 does; the others keep the same state in memory and
        # follow its decision to stop)
        self.processes = SingleProcess() if processes is None else processes
        # wall-clock seconds of training the run may take (None: no limit)
        self.time_budget_s = time_budget_s
        self.bn_recompute_batches = int(bn_recompute_batches)
        # The BatchNorm statistics before every validation: over every batch
        # of ``bn_sequence`` (the same training pairs every epoch, population
        # variance), or, without it, over the first ``bn_recompute_batches``
        # batches of the epoch's order (average batch variance).
        self.bn_sequence = bn_sequence
        # What early stopping and the kept epoch follow: with ``nmae_scale``
        # (name -> the training split's mean |y| of each camera parameter)
        # the sum of the validation NMAEs (``nmae_scores``), else val_loss.
        self.nmae_scale = nmae_scale
        # With the optimizer's moving average of the weights (``use_ema``):
        # validation, the best checkpoint and so the saved model use the
        # averaged weights, swapped in for validation (BatchNorm statistics
        # recomputed for them) and out again before the epoch's checkpoint,
        # which keeps the weights as trained and the average among the
        # optimizer's variables, so a resumed run goes on exactly.
        self.weight_ema = weight_ema
        self._averaged_in = False
        self.backup = os.path.join(run_dir, runs.BACKUP)
        self.patience = patience
        self.sequence = sequence
        self.state = read_state(run_dir)
        self.nan = None
        self._epoch_start = None

    # -- resume -------------------------------------------------------
    def restore(self, model):
        """Load the last checkpoint into ``model`` (weights + optimizer)."""
        ckpt = self.state.checkpoint
        if ckpt is None:
            return 0
        load_checkpoint(model, self.run_dir, ckpt)
        # log.csv again from the state (atomically): a run begun by older code
        # has a 0-based log, renumbered from 1 here, before training goes on
        if self.processes.writes:
            write_log(os.path.join(self.run_dir, runs.LOG), self.state.rows)
        return int(self.state.epoch)

    # -- keras hooks ---------------------------------------------------
    def on_train_begin(self, logs=None):
        if self.state.epoch == 0 and self.state.checkpoint is None:
            # Eq. 9's weights start balanced on the first training batch
            # (a resumed run has them in its checkpoint).
            # (the whole first batch: in a process group each process holds a part)
            self.model.initialise_adaptive_weights(self.sequence.batch_targets(0))

    def on_test_begin(self, logs=None):
        if self.weight_ema and not self._averaged_in:
            self._swap_averaged_weights()
        # Validation (and so the checkpoints and the saved model) runs in
        # inference mode: give it BatchNorm statistics of these weights.
        if self.bn_sequence is not None:
            recompute_batchnorm_statistics(
                self.model, (self.bn_sequence[i] for i in range(len(self.bn_sequence))),
                population=True, global_batch=self.processes.global_batch,
            )
        elif self.bn_recompute_batches:
            count = min(self.bn_recompute_batches, len(self.sequence))
            recompute_batchnorm_statistics(
                self.model, (self.sequence[i] for i in range(count)),
                global_batch=self.processes.global_batch,
            )

    def on_epoch_begin(self, epoch, logs=None):
        self._epoch_start = time.perf_counter()
        # Keras calls the dataset's on_epoch_end an extra time around its
        # first peek at the data, so the epoch is set here, explicitly:
        # the order of epoch e is then the same in a resumed run.
        self.sequence.set_epoch(epoch)

    def on_train_batch_begin(self, batch, logs=None):
        cli.check_interrupt()

    def on_test_batch_end(self, batch, logs=None):
        cli.check_interrupt()

    def on_train_batch_end(self, batch, logs=None):
        cli.check_interrupt()  # Ctrl-C: stop now, with the last epoch's checkpoint
        loss = (logs or {}).get("loss")
        if loss is not None and not math.isfinite(float(np.asarray(loss))):
            self.nan = {"epoch": self.state.epoch, "batch": int(batch)}
            self.model.stop_training = True

    def _swap_averaged_weights(self):
        """Exchange the model's trainable weights with the optimizer's moving
        average of them (in place: no variable is created)."""
        optimizer = self.model.optimizer
        for variable, average in zip(optimizer._trainable_variables,
                                     optimizer._model_variables_moving_average):
            trained = np.array(keras.ops.convert_to_numpy(variable))
            variable.assign(average)
            average.assign(trained)
        self._averaged_in = not self._averaged_in

    def _weights_as_trained(self):
        """The trained weights back in the model after validation (for the
        epoch's checkpoint and the next epoch)."""
        if self._averaged_in:
            self._swap_averaged_weights()

    def on_epoch_end(self, epoch, logs=None):
        keras_logs = logs
        if self.nan is not None:
            self._weights_as_trained()
            self.state.stopped = (
                f"non-finite training loss at epoch {self.nan['epoch'] + 1}, "
                f"batch {self.nan['batch'] + 1}"
            )
            if self.processes.writes:
                self._commit(checkpoint=False)
            return
        logs = {k: float(np.asarray(v)) for k, v in (logs or {}).items()}
        state = self.state
        val = self._monitored(logs, keras_logs)
        improved = val is not None and math.isfinite(val) and (
            state.best is None or val < state.best
        )
        best_name = None
        if improved:
            state.best, state.best_epoch, state.wait = val, epoch, 0
            best_name = f"best-{epoch:04d}"
            if self.processes.writes:
                with self.processes.alone():
                    save_weights(self.model, os.path.join(self.backup, best_name + ".weights.h5"))
        self._weights_as_trained()
        if self.probe is not None:
            logs.update(self.probe())
        if not improved:
            state.wait += 1
            if state.wait >= self.patience and epoch > 0:
                monitored = "val_nmae" if self.nmae_scale is not None else "val_loss"
                state.stopped = (
                    f"early stopping: no improvement of {monitored} for {self.patience} epochs"
                )
        alphas = self.model.adaptive_weights() or {}
        logs.update({f"alpha_{name}": value for name, value in alphas.items()})
        took = time.perf_counter() - (self._epoch_start or time.perf_counter())
        state.wall_time_s += took
        if (state.stopped is None and self.time_budget_s is not None
                and state.wall_time_s + took > self.time_budget_s):
            # another epoch as long as this one would overrun the budget
            state.stopped = (f"time budget: another epoch would end after "
                             f"{self.time_budget_s:g} s of training")
        # (in a group, process 0's clock decides the time budget for all)
        state.stopped = self.processes.decide("stop", state.stopped)
        self.model.stop_training = state.stopped is not None
        # the run's training time so far and the machine's load, per epoch
        logs.update(wall_time_s=round(state.wall_time_s, 3),
                    load_average=round(os.getloadavg()[0], 2))
        state.rows.append({"epoch": epoch, **logs})
        state.epoch = epoch + 1
        if self.processes.writes:
            self._commit(checkpoint=True, best_name=best_name)
        else:
            state.checkpoint = f"epoch-{state.epoch:04d}"
            state.best_weights = best_name or state.best_weights

    # -- helpers -------------------------------------------------------
    def _monitored(self, logs, keras_logs):
        """The epoch's value that early stopping follows: with ``nmae_scale``
        the validation NMAE (its terms added to ``logs`` and, for the epoch
        line, a later callback, to Keras's ``keras_logs``), else val_loss."""
        if self.nmae_scale is None:
            return logs.get("val_loss", logs.get("loss"))
        scores = nmae_scores(logs, self.nmae_scale)
        logs.update(scores)
        if keras_logs is not None:
            keras_logs.update(scores)
        return logs.get("val_nmae", logs.get("val_loss", logs.get("loss")))

    def _commit(self, checkpoint, best_name=None):
        os.makedirs(self.backup, exist_ok=True)
        state = self.state
        old = (state.checkpoint, state.best_weights)
        if checkpoint:
            name = f"epoch-{state.epoch:04d}"
            # Model and optimizer variables (Keras saves both).
            with self.processes.alone():
                save_weights(self.model, os.path.join(self.backup, name + ".weights.h5"))
            state.checkpoint = name
        if best_name is not None:
            state.best_weights = best_name
        write_state(self.run_dir, state)
        for stale in old:
            if stale is not None and stale not in (state.checkpoint, state.best_weights):
                path = os.path.join(self.backup, stale + ".weights.h5")
                if os.path.exists(path):
                    os.remove(path)
        publish_run_files(self.run_dir, state)


def load_checkpoint(model, run_dir, name):
    """Load the checkpoint ``name`` of ``run_dir``'s backup/ into ``model``:
    its weights and its optimizer's state (TrainingError, one line, when the
    file is missing, truncated or another model's)."""
    backup = os.path.join(run_dir, runs.BACKUP)
    # The weights file holds the optimizer's variables too; build the
    # optimizer first so they are loaded rather than skipped.
    if not model.optimizer.built:
        model.optimizer.build(model.trainable_variables)
    path = os.path.join(backup, name + ".weights.h5")
    try:
        model.load_weights(path)
    except (OSError, ValueError) as error:  # (missing, truncated, another model's)
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise TrainingError(
            f"cannot resume from the checkpoint {path} ({first}); delete "
            f"{backup} to start the run again from epoch 1, or use another "
            f"--run-dir") from None


def save_weights(model, path):
    """``model.save_weights(path)``, atomically (``files.atomic_path``): a
    failure (a full disk) leaves no file and raises ``TrainingError`` in one
    line (``files.write_failed``)."""
    try:
        with files.atomic_path(path) as tmp, files.library_write(path):
            model.save_weights(tmp)
    except (OSError, RuntimeError) as error:
        raise TrainingError(files.write_failed(path, error)) from None


def nmae_scores(logs, scale):
    """The validation NMAEs of an epoch's ``logs``: ``val_nmae_<name>``, the
    validation MAE of each camera parameter divided by ``scale[name]`` (the
    training split's mean |y|, fixed for the run), and ``val_nmae``, their
    sum: the tables' measure, on one scale for every variant and with no
    weight that moves (MTL-CPL-A's val_loss is weighted by that epoch's
    alpha_i). Each term is logged, so a swing names its cause."""
    scores = {}
    for name, value in scale.items():
        # (the per-output MAE loss of MTL-Baseline is logged as its _loss;
        # with target scaling, the unscaled MAE is its _mae metric)
        mae = logs.get(f"val_{name}_mae", logs.get(f"val_{name}_loss"))
        if mae is not None:
            scores[f"val_nmae_{name}"] = float(mae) / float(value)
    if scores:
        scores["val_nmae"] = float(sum(scores.values()))
    return scores


def publish_run_files(run_dir, state):
    """Bring best.weights.h5, log.csv and curves.png in line with ``state``
    (a ``TrainingState``)."""
    source = os.path.join(run_dir, runs.BACKUP, f"{state.best_weights}.weights.h5")
    if state.best_weights and os.path.exists(source):
        # (After a finished run the backup copy is gone; best.weights.h5 stays.)
        with files.atomic_path(os.path.join(run_dir, runs.BEST_WEIGHTS)) as tmp:
            shutil.copyfile(source, tmp)
    write_log(os.path.join(run_dir, runs.LOG), state.rows)
    if state.rows:
        config = runs.read_run_config(run_dir)
        plot_curves(os.path.join(run_dir, runs.CURVES), state.rows, state.best_epoch,
                    title=curves_title(config, state) if config else None)


def write_log(path, rows):
    """One CSV row per epoch (columns: epoch, then the sorted log keys).
    ``rows`` are the state's (``epoch``: Keras's 0-based index); the file
    numbers the epochs from 1, as the console and config.json do."""
    keys = sorted({k for row in rows for k in row if k != "epoch"})
    with files.atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["epoch"] + keys)
        for row in rows:
            writer.writerow([row["epoch"] + 1] + [repr(row[k]) if k in row else "" for k in keys])


def curves_title(config, state):
    """curves.png's title: the run (``config``, a ``RunConfig``: variant,
    backbone, dataset file, split), then its epochs so far, or how it ended
    (``state``: a ``TrainingState``)."""
    done = len(state.rows)
    stopped, cap = state.stopped, config.training.epochs
    if stopped:
        how = f"{'failed' if stopped.startswith('non-finite') else 'finished'}: {stopped}"
        status = f"{done} epoch{'s' * (done != 1)}, {how}"
    elif cap and done >= cap:
        status = f"{done} of {cap} epochs, finished"
    else:
        status = f"{done} of at most {cap} epochs so far"
    return f"{run_label(config)}\n{status}"
