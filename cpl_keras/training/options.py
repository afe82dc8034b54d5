"""``TrainingOptions``: how a run trains, in one frozen record checked once.

The model's own knobs are ``models.options.ModelOptions``; this record holds
the rest of a run's settings (the schedule, the split, validation, early
stopping). ``planning.plan_run`` takes both; ``split_fields`` sorts keyword
arguments into the two by name, so ``train(data, variant=..., run_dir=...,
epochs=..., head_norm=True)`` reads as one call. Its checks raise
``TrainingError`` (one line); the defaults that depend on ``as_released``
(BatchNorm statistics, monitor, averaged weights) are None here and filled
in by planning (``planning._validation_settings``).
"""

from __future__ import annotations

import dataclasses
import math
import numbers

from cpl_keras import backend
from cpl_keras.datasets import SPLITS
from cpl_keras.errors import Error
from cpl_keras.models.options import ModelOptions, check_momentum
from cpl_keras.training.augment import AUGMENTATIONS

#: Per-output MAE as the paper sums it ("none"), or each divided by the
#: target's training standard deviation ("std": standardised targets).
TARGET_SCALINGS = ("none", "std")
#: Where BatchNorm's statistics come from before every validation
#: (``planning``'s notes).
BN_STATISTICS = ("fixed", "epoch")
#: What early stopping and the kept epoch follow (``planning``'s notes).
MONITORS = ("nmae", "loss")


class TrainingError(Error):
    """A bad argument or run directory (one-line message)."""


@dataclasses.dataclass(frozen=True)
class TrainingOptions:
    """A run's settings beside its model's (every default is the paper's:
    up to 200 epochs, batch 16, patience 5, the paper's split)."""

    epochs: int = 200
    batch_size: int = 16
    learning_rate: float | None = None
    image_size: int | None = None
    split: str = "paper"
    seed: int = 0
    data_parallel: bool = False
    patience: int = 5
    test_fraction: float = 0.3
    val_fraction: float = 0.1
    workers: int = 1
    bn_recompute_batches: int | None = None
    bn_statistics: str | None = None
    monitor: str | None = None
    target_scaling: str = "none"
    time_budget_s: float | None = None
    augment: str | None = None
    weight_ema: float | None = None

    def __post_init__(self):
        _choice("split", self.split, SPLITS)
        for name in ("epochs", "batch_size", "workers"):
            value = getattr(self, name)
            if not (_integer(value) and value >= 1):
                raise TrainingError(f"{name.replace('_', ' ')} must be a positive integer, "
                                    f"got {value!r}")
        for name in ("patience", "seed"):
            value = getattr(self, name)
            if not (_integer(value) and value >= 0):
                raise TrainingError(f"{name} must be a non-negative integer, got {value!r}")
        if self.learning_rate is not None and not (_real(self.learning_rate)
                                                   and self.learning_rate > 0):
            raise TrainingError(f"learning rate must be a positive number, "
                                f"got {self.learning_rate!r}")
        if self.time_budget_s is not None and not (_real(self.time_budget_s)
                                                   and self.time_budget_s > 0):
            raise TrainingError(f"time budget must be a positive number of seconds, "
                                f"got {self.time_budget_s!r}")
        if self.bn_statistics is not None:
            _choice("BatchNorm statistics", self.bn_statistics, BN_STATISTICS)
        if self.monitor is not None:
            _choice("monitor", self.monitor, MONITORS)
        if self.weight_ema is not None:
            check_momentum(self.weight_ema, TrainingError)
        if self.bn_recompute_batches is not None and not (
                _integer(self.bn_recompute_batches) and self.bn_recompute_batches >= 0):
            raise TrainingError(f"BatchNorm recompute batches must be a non-negative integer, "
                                f"got {self.bn_recompute_batches!r}")
        _choice("target scaling", self.target_scaling, TARGET_SCALINGS)
        if self.augment is not None:
            _choice("augmentation", self.augment, AUGMENTATIONS)


def split_fields(fields):
    """``(model fields, training fields)`` of keyword arguments, by the
    records' field names (TrainingError naming an unknown one)."""
    model_names = {field.name for field in dataclasses.fields(ModelOptions)}
    training_names = {field.name for field in dataclasses.fields(TrainingOptions)}
    unknown = sorted(set(fields) - model_names - training_names)
    if unknown:
        raise TrainingError(f"unknown training option {unknown[0]!r}")
    return ({k: v for k, v in fields.items() if k in model_names},
            {k: v for k, v in fields.items() if k in training_names})


def check_steps_per_execution(steps):
    """TrainingError (one line) unless ``steps``, the training steps per
    compiled call (Keras's ``steps_per_execution``), is a positive integer
    that Keras's backend runs: 1 under PyTorch, where Keras refuses more only
    at the first ``fit``, with the run directory made."""
    if not (_integer(steps) and steps >= 1):
        raise TrainingError(f"steps per execution must be a positive integer, got {steps!r}")
    if steps > 1 and backend.keras_backend() == "torch":
        raise TrainingError(f"steps per execution must be 1 under PyTorch (KERAS_BACKEND=torch), "
                            f"got {steps}: Keras runs one step per call there")


def _choice(what, value, choices):
    if value not in choices:
        raise TrainingError(f"unknown {what} {value!r}; choose one of {', '.join(choices)}")


def _integer(value):
    return not isinstance(value, bool) and isinstance(value, numbers.Integral)


def _real(value):
    return (not isinstance(value, bool) and isinstance(value, numbers.Real)
            and math.isfinite(value))
