"""A run's resume state, ``backup/state.json``, as a record.

``TrainingState`` names every key the file holds; ``read_state`` and
``write_state`` are the one place the file is read and written (atomically,
``cpl_keras.files``). The checkpointing callback (``RunState``) keeps one
and rewrites the file after every epoch; the trainer reads it. Importing
this module imports no Keras.
"""

from __future__ import annotations

import dataclasses
import os

from cpl_keras import files, runs
from cpl_keras.training.planning import TrainingError


@dataclasses.dataclass(kw_only=True)
class TrainingState:
    """state.json, typed: one field per key, in the file's order.

    Epochs are Keras's indices (0 = the first; ``best_epoch`` and each
    row's ``epoch`` too); log.csv, curves.png, config.json and the console
    number them from 1. Mutable: the callback updates it as epochs end.
    ``to_dict()`` gives the file's dict, the keys in the order every version
    of the package has written them, so a file read and written back is
    the same byte for byte. A key missing from a file takes its default
    here (a fresh run's value); keys not named here (a file of another
    version) stay in ``other`` and are written back after the named ones."""

    # Epochs completed: the index of the next epoch to train.
    epoch: int = 0
    # The best monitored value so far (val_nmae or val_loss) and its epoch, or None.
    best: float | None = None
    best_epoch: int | None = None
    # Epochs since the last improvement (early stopping's counter).
    wait: int = 0
    # Why training ended before its epoch cap (early stopping, the time
    # budget, a non-finite loss), or None.
    stopped: str | None = None
    # The log of every epoch: ``epoch`` and each logged value (log.csv's rows).
    rows: list = dataclasses.field(default_factory=list)
    # The checkpoint files in backup/ (names without ``.weights.h5``): the
    # last epoch's (model and optimizer) and the best epoch's, or None.
    checkpoint: str | None = None
    best_weights: str | None = None
    # Seconds of training so far, over every start and resume of the run.
    wall_time_s: float = 0.0
    # Keys not named above, kept as read.
    other: dict = dataclasses.field(default_factory=dict)

    def to_dict(self):
        """state.json's dict: the named fields in order, then ``other``."""
        out = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)
               if field.name != "other"}
        return dict(out, **self.other)

    @classmethod
    def from_dict(cls, state, where="state.json"):
        """The record of a state.json dict; TrainingError, in one line naming
        ``where``, when it is not a JSON object or a named key holds a value
        of the wrong kind."""
        if not isinstance(state, dict):
            raise TrainingError(f"{where} is not a training state: a JSON object expected, "
                                f"got {type(state).__name__}")
        for key, value in state.items():
            problem = _problem(key, value)
            if problem:
                raise TrainingError(f"{where}: '{key}' must be {problem}, got {value!r:.60}")
        named = {f.name for f in dataclasses.fields(cls)} - {"other"}
        return cls(**{k: v for k, v in state.items() if k in named},
                   other={k: v for k, v in state.items() if k not in named})


#: What each named key of state.json holds: the kinds of value allowed, and
#: their words in an error.
_KINDS = {
    "epoch": ((int,), "a whole number >= 0"),
    "best": ((int, float, type(None)), "a number or null"),
    "best_epoch": ((int, type(None)), "a whole number >= 0 or null"),
    "wait": ((int,), "a whole number >= 0"),
    "stopped": ((str, type(None)), "a text or null"),
    "rows": ((list,), "a list of objects, each with a whole-number 'epoch' >= 0"),
    "checkpoint": ((str, type(None)), "a file name or null"),
    "best_weights": ((str, type(None)), "a file name or null"),
    "wall_time_s": ((int, float), "a number"),
}


def _problem(key, value):
    """What ``value`` of state.json's ``key`` should be, if it is not (else None)."""
    if key not in _KINDS:
        return None
    kinds, words = _KINDS[key]
    if isinstance(value, bool) or not isinstance(value, kinds):
        return words
    if key in ("epoch", "best_epoch", "wait") and value is not None and value < 0:
        return words
    if key == "rows" and any(not isinstance(row, dict) or _problem("epoch", row.get("epoch"))
                             for row in value):
        return words
    return None


def state_path(run_dir):
    """Where ``run_dir`` keeps its state.json."""
    return os.path.join(run_dir, runs.STATE)


def read_state(run_dir):
    """``run_dir``'s state.json as a ``TrainingState``; a fresh run's state
    when there is none. TrainingError in one line when it cannot be read or
    is malformed."""
    path = state_path(run_dir)
    try:
        state = files.read_json(path, default={})
    except (OSError, ValueError) as error:  # JSONDecodeError is a ValueError
        raise TrainingError(f"cannot read {path}: {error}") from None
    return TrainingState.from_dict(state, path)


def write_state(run_dir, state):
    """Write ``state`` (a ``TrainingState``) to ``run_dir``'s state.json, atomically."""
    files.write_json(state_path(run_dir), state.to_dict())
