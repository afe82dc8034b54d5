"""What training prints while it runs: one short line per epoch.

Keras's own progress bar prints every logged metric on every line (14 to 30
of them here, 350 to 700 characters), which wraps into a wall of text in a
terminal. ``EpochLines`` prints the loss, the validation loss (or the
monitored ``val_nmae``) and the
validation MAE of three key parameters (fx, baseline as ``b``, pitch), one
line per epoch of at most ``WIDTH`` characters; ``log.csv`` keeps every
metric. On a terminal a progress bar with the running loss is redrawn in
place during the epoch; written to a file or a pipe, only the epoch lines
appear (no carriage returns in a log file).
"""

from __future__ import annotations

import math
import shutil
import sys
import time

import keras
import numpy as np

#: The parameters whose validation MAE the epoch line shows, and their short names.
KEY_MAES = (("fx", "fx"), ("baseline", "b"), ("pitch", "pitch"))
#: The longest line printed (characters).
WIDTH = 100


def number(value):
    """``value`` in at most 9 characters, 4 significant digits: 187.2,
    0.04512, 12345, 1.23e+06, nan."""
    value = float(value)
    if not math.isfinite(value):
        return str(value)
    size = abs(value)
    if size == 0:
        return "0"
    if 1e-3 <= size < 1e5:
        return f"{value:.{max(0, 3 - math.floor(math.log10(size)))}f}"
    return f"{value:.3g}"


def val_mae(logs, name):
    """The validation MAE of output ``name`` in Keras's logs (the ``_mae``
    metric, or the ``_loss`` of the per-output MAE loss), or None."""
    for key in (f"val_{name}_mae", f"val_{name}_loss"):
        if key in logs:
            return logs[key]
    return None


def epoch_line(epoch, epochs, logs, seconds, best=False):
    """The line of a finished epoch (``epoch`` 1-based)."""
    parts = [f"epoch {epoch}/{epochs}", _duration(seconds)]
    # (the monitored sum of validation NMAEs in place of the validation
    # loss, when the run follows it: log.csv has both)
    for key in ("loss", "val_nmae" if "val_nmae" in logs else "val_loss"):
        if key in logs:
            parts.append(f"{key} {number(logs[key])}")
    maes = [f"{short} {number(v)}" for name, short in KEY_MAES
            if (v := val_mae(logs, name)) is not None]
    if maes:
        parts.append("val MAE " + " ".join(maes))
    if best:
        parts.append("best")
    return "  ".join(parts)[:WIDTH]


def _duration(seconds):
    seconds = int(round(seconds))
    if seconds < 100:
        return f"{seconds}s"
    if seconds < 6000:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m"


class EpochLines(keras.callbacks.Callback):
    """Prints ``epoch_line`` after every epoch (and, on a terminal, a progress
    bar during it). ``run_state``: the run's ``RunState``, listed before this
    callback, whose state marks the best epoch so far."""

    def __init__(self, epochs, run_state=None, stream=None, live=None):
        super().__init__()
        self.epochs = epochs
        self.run_state = run_state
        self.stream = stream or sys.stdout
        self.live = self.stream.isatty() if live is None else live
        self._start = self._drawn = 0.0
        self._shown = 0  # characters of the bar on the screen
        self._epoch = 0

    def _write(self, text, end=""):
        if self.live:
            if not end:  # a bar that wrapped could not be redrawn in place
                text = text[:min(WIDTH, shutil.get_terminal_size((WIDTH, 24)).columns - 1)]
            # back to the line's start, blanks over what is left of the bar
            text = "\r" + text + " " * max(0, self._shown - len(text))
            self._shown = 0 if end else len(text) - 1
        self.stream.write(text + end)
        self.stream.flush()

    def on_epoch_begin(self, epoch, logs=None):
        self._epoch, self._start, self._drawn = epoch, time.perf_counter(), 0.0

    def on_train_batch_end(self, batch, logs=None):
        now = time.perf_counter()
        if not self.live or now - self._drawn < 0.25:
            return
        self._drawn = now
        steps = (self.params or {}).get("steps") or 0
        done = batch + 1
        text = f"epoch {self._epoch + 1}/{self.epochs} "
        if steps:
            filled = int(20 * min(done, steps) / steps)
            left = (now - self._start) / done * max(0, steps - done)
            text += f"[{'=' * filled}{'.' * (20 - filled)}] {done}/{steps} {_duration(left)} left"
        else:
            text += f"{done} batches"
        loss = (logs or {}).get("loss")
        if loss is not None:
            text += f"  loss {number(loss)}"
        self._write(text)

    def on_test_begin(self, logs=None):
        if self.live:
            self._write(f"epoch {self._epoch + 1}/{self.epochs} validating")

    def on_epoch_end(self, epoch, logs=None):
        state = getattr(self.run_state, "state", None)
        best = state is not None and state.best_epoch == epoch
        logs = {k: float(np.asarray(v)) for k, v in (logs or {}).items()}
        self._write(epoch_line(epoch + 1, self.epochs, logs,
                               time.perf_counter() - self._start, best=best), end="\n")
