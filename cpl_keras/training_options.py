"""``TrainingOptions``: how a run trains, in one frozen record checked once.

The model's own knobs are ``models.options.ModelOptions``; this record holds
the rest of a run's settings (the schedule, the split, the optimiser,
validation, early stopping). ``planning.plan_run`` takes both;
``split_fields`` sorts keyword arguments into the two by name, so
``train(data, variant=..., run_dir=..., epochs=..., head_norm=True)`` reads
as one call. Its checks raise ``TrainingError`` (one line); the defaults
that depend on ``as_released`` (BatchNorm statistics, monitor, averaged
weights) are None here and filled in by planning
(``planning._validation_settings``).

A run's config.json holds the record flat, one key per field
(``to_config``, ``from_config``), but for the fields marked
``RECORDED: False`` (arguments of one command, not settings of the run); a
run directory resumes only with the same record, but for the fields marked
``RESUMES_CHANGED`` (a time budget may be given anew). A new training
switch is one field here (with its check in ``__post_init__``), one
argparse line in ``cpl_keras/commands/train.py`` and its use
(docs/layout.md).
"""

from __future__ import annotations

import dataclasses
import math
import numbers

from cpl_keras import backend
from cpl_keras.datasets import SPLITS
from cpl_keras.errors import Error
from cpl_keras.models.options import ModelOptions, check_momentum

#: The augmentations ``StereoSequence`` (``training.augment``) and
#: ``train.py --augment`` offer.
AUGMENTATIONS = ("photometric",)
#: Per-output MAE as the paper sums it ("none"), or each divided by the
#: target's training standard deviation ("std": standardised targets).
TARGET_SCALINGS = ("none", "std")
#: Where BatchNorm's statistics come from before every validation
#: (``planning``'s notes).
BN_STATISTICS = ("fixed", "epoch")
#: What early stopping and the kept epoch follow (``planning``'s notes).
MONITORS = ("nmae", "loss")


#: The named recipes (``--recipe``): each is a set of field values of the
#: two records (``split_fields`` sorts them). "paper" changes nothing;
#: "sound" is the training recipe of the fair comparison
#: (paper_results/fair-fight/protocol.md), the same for every variant.
RECIPES = {
    "paper": {},
    "sound": {"head_activation": "leaky_relu_0.01", "head_norm": True,
              "disparity_head": "softplus", "clip_norm": 1.0},
}
#: Field metadata: an argument of one command, not recorded in config.json.
NOT_RECORDED = {"recorded": False}
#: Field metadata: may differ when a run directory is resumed.
RESUMES_CHANGED = {"resumes_changed": True}


class TrainingError(Error):
    """A bad argument or run directory (one-line message)."""


@dataclasses.dataclass(frozen=True)
class TrainingOptions:
    """A run's settings beside its model's (every default is the paper's:
    up to 200 epochs, batch 16, patience 5, the paper's split, Adam at the
    variant's learning rate).

    split, test_fraction, val_fraction: the split (``datasets.SPLITS``) and
    its shares. seed: the split's, the initial weights' and the batches'
    order's. batch_size, learning_rate (None: the variant's), epochs,
    patience: the schedule. weight_decay: decoupled weight decay (AdamW; 0
    is off, the paper's Adam; never on Eq. 9's weights). clip_norm: the
    global gradient-norm clip (None: off, the paper's). bn_recompute_batches,
    bn_statistics, monitor, weight_ema: validation (``planning``'s notes;
    None: the default, as released the release's). target_scaling: the
    per-output MAE's scaling. time_budget_s: seconds of training the run may
    take. augment: the training batches' augmentation. data_parallel: over
    every device Keras sees. image_size: the images' size the command
    expects (checked against the dataset file; the run records the file's).
    workers: loader threads.
    """

    split: str = "paper"
    test_fraction: float = 0.3
    val_fraction: float = 0.1
    seed: int = 0
    batch_size: int = 16
    learning_rate: float | None = None
    epochs: int = 200
    patience: int = 5
    weight_decay: float = 0.0
    clip_norm: float | None = None
    bn_recompute_batches: int | None = None
    bn_statistics: str | None = None
    monitor: str | None = None
    weight_ema: float | None = None
    target_scaling: str = "none"
    time_budget_s: float | None = dataclasses.field(default=None, metadata=RESUMES_CHANGED)
    augment: str | None = None
    data_parallel: bool = False
    image_size: int | None = dataclasses.field(default=None, metadata=NOT_RECORDED)
    workers: int = dataclasses.field(default=1, metadata=NOT_RECORDED)

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
        if not (_real(self.weight_decay) and self.weight_decay >= 0):
            raise TrainingError(f"weight decay must be a number >= 0, got {self.weight_decay!r}")
        if self.clip_norm is not None and not (_real(self.clip_norm) and self.clip_norm > 0):
            raise TrainingError(f"clip norm must be a positive number, got {self.clip_norm!r}")

    # -- config.json -------------------------------------------------------
    @classmethod
    def recorded_fields(cls):
        """The names of the fields config.json holds, in order."""
        return tuple(field.name for field in dataclasses.fields(cls)
                     if field.metadata.get("recorded", True))

    def to_config(self):
        """config.json's keys of this record (``recorded_fields``)."""
        return {name: getattr(self, name) for name in self.recorded_fields()}

    @classmethod
    def from_config(cls, config):
        """The record of config.json's keys (a run's dict; other keys are
        left to the caller, a key it lacks keeps its default)."""
        return cls(**{name: config[name] for name in cls.recorded_fields() if name in config})

    def differences(self, other):
        """``(name, this value, other's)`` of each recorded field that
        differs from ``other``'s and must not when a run is resumed."""
        return [(field.name, getattr(self, field.name), getattr(other, field.name))
                for field in dataclasses.fields(self)
                if field.metadata.get("recorded", True)
                and not field.metadata.get("resumes_changed", False)
                and getattr(self, field.name) != getattr(other, field.name)]


def recipe(name):
    """The field values of the named recipe (``RECIPES``; TrainingError)."""
    if name not in RECIPES:
        raise TrainingError(f"unknown recipe {name!r}; choose one of {', '.join(RECIPES)}")
    return dict(RECIPES[name])


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
