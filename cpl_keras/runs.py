"""The run directory, in one place: its files, their reading and writing.

A run directory (written by ``cpl_keras.training``)::

    config.json        everything needed to rebuild and reproduce the run
    model.keras        the best model (loads with safe_mode=True)
    best.weights.h5    its weights
    log.csv            one row per epoch, continuous across resumes; epoch 1 is the first
    curves.png         training curves
    train_stats.json   training-set statistics (the Average baseline)
    split.npz          train, val, test index arrays
    predictions/       the best model's outputs on datasets, one .npz each
                       (``evaluation.store_predictions``, in
                       ``cpl_keras.prediction_files``' format): they outlive the weights
    backup/            resume state: state.json, checkpoints, the lock

A *published* run directory is the same less the weights (model.keras,
best.weights.h5, backup/): what the reproduction commits and restores on
another machine. It evaluates from ``predictions/`` alone
(``cpl_keras.published``).

Training writes it through this module; every reader takes config.json
through ``load_run`` (a ``Run``, its ``config`` a ``RunConfig``) or
``read_run_config`` (older layouts too: ``normalise_config``), the model
through ``load_model``; every problem is a one-line ``RunError``. Its files
are written atomically (``cpl_keras.files``).
"""

from __future__ import annotations

import csv
import dataclasses
import os
import zipfile
from typing import Any

from cpl_keras import files
from cpl_keras.baselines.average import load_statistics
from cpl_keras.cli import one_line
from cpl_keras.datasets import load_split
from cpl_keras.errors import Error
from cpl_keras.models.options import ModelOptions
from cpl_keras.models.variants import VARIANT_ROWS
from cpl_keras.training_options import TrainingOptions

CONFIG = "config.json"
MODEL = "model.keras"
BEST_WEIGHTS = "best.weights.h5"
LOG = "log.csv"
CURVES = "curves.png"
STATS = "train_stats.json"
SPLIT = "split.npz"
BACKUP = "backup"
STATE = os.path.join(BACKUP, "state.json")
LOCK = os.path.join(BACKUP, "lock")
#: The files a finished run must have to be evaluated.
PREDICTIONS = "predictions"
#: The files every run directory has (a published one has no model.keras
#: but stored predictions instead).
REQUIRED = (CONFIG, STATS, SPLIT)
#: What a published run directory keeps (no weights).
PUBLISHED = (CONFIG, STATS, SPLIT, LOG, CURVES, PREDICTIONS)
#: Suffix of a table row of a run trained with ``as_released``.
RELEASED = " (as released)"


class RunError(Error):
    """A run directory cannot be read (one-line message)."""


def relative(path, start):
    """``path`` relative to the directory ``start`` (for files that are
    committed or moved: no machine's absolute paths in them)."""
    try:
        return os.path.relpath(os.path.abspath(path), os.path.abspath(start))
    except ValueError:  # another drive (Windows)
        return os.path.abspath(path)


# ---------------------------------------------------------------------------
# config.json
# ---------------------------------------------------------------------------
def normalise_config(config):
    """``config`` with each fact once and where it is now: the top-level
    ``as_released`` of the older layout moved into ``build``, the
    optimiser's ``weight_decay`` and ``clip_norm`` out of it (once model
    options), a build of before the disparity ceiling given its None, and a
    run of before ``bn_statistics`` and ``monitor`` given what it ran with
    (a new dict; the argument is kept)."""
    config = dict(config)
    build = dict(config.get("build") or {})
    if "as_released" in config:
        build.setdefault("as_released", bool(config.pop("as_released")))
    for key in ("weight_decay", "clip_norm"):
        if key in build:
            config.setdefault(key, build.pop(key))
    # (runs from before the disparity head's ceiling: the head's old bound)
    build.setdefault("disparity_ceiling", None)
    config["build"] = build
    # (runs from before the fixed BatchNorm statistics, the NMAE monitor and the
    # weights' moving average: the per-epoch draw, the validation loss, the weights)
    config.setdefault("bn_statistics", "epoch")
    config.setdefault("monitor", "loss")
    config.setdefault("weight_ema", 0.0)
    return config


def write_config(run_dir, config):
    """Write ``run_dir``'s config.json from a ``RunConfig`` (or a dict of it)."""
    if isinstance(config, RunConfig):
        config = config.to_dict()
    files.write_json(os.path.join(run_dir, CONFIG), normalise_config(config))


@dataclasses.dataclass(frozen=True, kw_only=True)
class RunConfig:
    """config.json, typed: three records (``model``, a ``ModelOptions``
    resolved for its variant; ``training``, a ``TrainingOptions``, defaults
    filled in; ``data``, ``DataFacts``), where it ran and how it ended.
    ``training.plan_run`` makes it, training fills in the outcome
    (``dataclasses.replace``) and writes it (``write_config``); every reader
    takes it through ``read_run_config`` / ``load_run``. On disk it stays
    flat (``to_dict``, ``from_dict``): the variant, ``build``, the data's and
    the training record's keys side by side; keys of an older layout it
    lacks are None here (or the record's default), keys not named here stay
    in ``other``."""

    model: ModelOptions
    training: TrainingOptions
    data: DataFacts
    # Data parallelism: devices, processes, and the batch over them.
    num_devices: int | None = None
    num_processes: int | None = None
    device_batch_size: int | None = None
    # The command line, the run directory, the Keras backend.
    command: str | None = None
    run_dir: str | None = None
    keras_backend: str | None = None
    # The machines it trained on, in order (``backend.machine``); a resume elsewhere adds one.
    machines: list | None = None
    # The model built: its optimizer's learning rate and its parameter count.
    learning_rate_used: float | None = None
    num_parameters: int | None = None
    # How it ended (None while it runs): epochs, the kept one and its validation loss,
    # time, status ("running", "finished", "failed"), why it stopped, the kept epoch's
    # monitored score, MTL-CPL-A's final alphas.
    epochs_run: int | None = None
    best_epoch: int | None = None
    best_val_loss: float | None = None
    wall_time_s: float | None = None
    status: str | None = None
    stopped: str | None = None
    best_score: float | None = None
    adaptive_weights: dict | None = None
    other: dict = dataclasses.field(default_factory=dict)

    #: Fields written once set, and fields written once the run has ended.
    LATE = ("machines", "learning_rate_used", "num_parameters")
    FINAL = ("best_score", "adaptive_weights")
    RECORDS = ("model", "training", "data")

    @property
    def variant(self):
        """The variant trained (the model record's)."""
        return self.model.variant

    @property
    def build(self):
        """config.json's ``build``: the model record (``to_config``, the
        variant left above it) with the images' size and the seed beside it,
        ``models.build_from_config``'s argument."""
        build = {key: value for key, value in self.model.to_config().items()
                 if key != "variant"}
        return dict(build, image_size=self.data.image_size, seed=self.training.seed)

    def to_dict(self):
        """config.json's dict: the variant, ``build``, the data's facts, the
        training record, the other fields in order (``LATE`` ones once set,
        ``FINAL`` ones once the run has ended), then ``other``."""
        ended = self.status in ("finished", "failed")
        out = {"variant": self.variant, "build": self.build, **self.data.to_config(),
               **self.training.to_config()}
        out.update({field.name: getattr(self, field.name)
                    for field in dataclasses.fields(self)
                    if field.name not in self.RECORDS + ("other",)
                    and not (field.name in self.LATE and getattr(self, field.name) is None)
                    and not (field.name in self.FINAL and not ended)})
        return dict(out, **self.other)

    @classmethod
    def from_dict(cls, config, where="config.json"):
        """The record of a config.json dict (normalised first); RunError,
        naming ``where``, when a key every run has is missing or a setting is bad."""
        config = normalise_config(config)
        for key in ("variant", "build", "data"):
            if key not in config:
                raise RunError(f"{where} has no '{key}'")
        if config["variant"] not in VARIANT_ROWS:
            raise RunError(f"{where}: unknown variant {config['variant']!r}")
        build = dict(config["build"])
        try:
            model = ModelOptions.from_config(build).for_variant(config["variant"])
            training = TrainingOptions.from_config(
                {key: value for key, value in config.items() if value is not None})
        except Error as error:  # (OptionsError, TrainingError)
            raise RunError(f"{where}: {error}") from None
        data = DataFacts.from_config(config, build.get("image_size"))
        named = {f.name for f in dataclasses.fields(cls)} - {"other"} - set(cls.RECORDS)
        known = (named | {"variant", "build"} | set(DataFacts.KEYS)
                 | set(TrainingOptions.recorded_fields()))
        return cls(model=model, training=training, data=data,
                   **{k: v for k, v in config.items() if k in named},
                   other={k: v for k, v in config.items() if k not in known})

    @property
    def as_released(self):
        """Whether the run was trained as released."""
        return self.model.as_released

    @property
    def row(self):
        """The table row of the run: its variant's row, marked when trained
        as released."""
        return VARIANT_ROWS[self.variant] + (RELEASED if self.as_released else "")


@dataclasses.dataclass(frozen=True, kw_only=True)
class DataFacts:
    """What a run trains on: the dataset file (config.json's ``data``), its
    pairs, protocol, real training rigs (Table 2 never scores the run on
    them), images' size ([height, width]) and the split's parts' pairs."""

    path: str
    num_pairs: int | None = None
    protocol: str | None = None
    training_rigs: list = dataclasses.field(default_factory=list)
    image_size: list | None = None
    num_train: int | None = None
    num_val: int | None = None
    num_test: int | None = None

    #: config.json's keys (the image size is written in ``build``).
    KEYS = ("data", "num_pairs", "protocol", "training_rigs", "num_train", "num_val", "num_test")

    def to_config(self):
        return {key: getattr(self, "path" if key == "data" else key) for key in self.KEYS}

    @classmethod
    def from_config(cls, config, image_size=None):
        given = {key: config[key] for key in cls.KEYS if config.get(key) is not None}
        return cls(path=given.pop("data"), image_size=image_size, **given)


def read_run_config(run_dir):
    """The run's config.json as a ``RunConfig``, or None when it has none.
    RunError when it is unreadable or holds no run (``RunConfig.from_dict``)."""
    path = os.path.join(run_dir, CONFIG)
    try:
        config = files.read_json(path)
    except (OSError, ValueError) as error:  # JSONDecodeError is a ValueError
        raise RunError(f"cannot read {path}: {error}") from None
    if config is None:
        return None
    if not isinstance(config, dict):
        raise RunError(f"{path} holds no run (not a JSON object)")
    return RunConfig.from_dict(config, path)


@dataclasses.dataclass(eq=False)
class Run:
    """A run directory as ``load_run`` reads it: where it is, its typed
    config, its training statistics (``train_stats.json``), its split
    (train, val, test index arrays) and where its weights are. ``model``
    holds the loaded model while evaluation uses it."""

    run_dir: str
    config: RunConfig
    stats: dict
    split: dict
    model_path: str
    model: Any = dataclasses.field(default=None, repr=False)

    @property
    def as_released(self):
        return self.config.as_released

    @property
    def row(self):
        return self.config.row


# ---------------------------------------------------------------------------
# log.csv
# ---------------------------------------------------------------------------
def log_file(run):
    """A run's log.csv: ``RUN/log.csv``, or ``RUN_log.csv`` beside a published
    run's folder (``published.publish_files``); RunError if neither exists."""
    for path in (os.path.join(run, LOG), run.rstrip("/") + "_" + LOG):
        if os.path.isfile(path):
            return path
    raise RunError(f"no log.csv for {run} (looked for RUN/log.csv and RUN_log.csv)")


def read_log(path):
    """log.csv (the file, or a run directory holding it) as a list of dicts
    of floats, one per epoch, ``epoch`` 1-based (1 = the first epoch).

    Logs written before the epochs were numbered from 1 (Keras's CSVLogger
    convention: the first row is epoch 0) are recognised by their first row
    and renumbered, so both read alike."""
    if os.path.isdir(path):
        path = os.path.join(path, LOG)
    with open(path, newline="") as f:
        rows = [{k: float(v) for k, v in row.items() if v not in ("", None)}
                for row in csv.DictReader(f)]
    if rows and rows[0].get("epoch") == 0:  # the older, 0-based log
        for row in rows:
            row["epoch"] += 1
    return rows


# ---------------------------------------------------------------------------
# Reading a finished run
# ---------------------------------------------------------------------------
def load_run(run_dir):
    """The run directory as a ``Run``. RunError naming the first missing or
    malformed file."""
    run_dir = os.path.abspath(os.fspath(run_dir))
    if os.path.exists(run_dir) and not os.path.isdir(run_dir):
        raise RunError(f"not a run directory (a file, not a directory): {run_dir}")
    if not os.path.isdir(run_dir):
        raise RunError(f"run directory not found: {run_dir}")
    paths = {name: os.path.join(run_dir, name) for name in REQUIRED + (MODEL,)}
    for name, path in paths.items():
        if name == MODEL and stored_predictions(run_dir):
            continue  # a published run: its outputs are stored, not its weights
        if not os.path.isfile(path):
            what = "weights (model.keras)" if name == MODEL else name
            raise RunError(f"run directory {run_dir} has no {what}")
    config = read_run_config(run_dir)
    try:
        stats = load_statistics(paths[STATS])
    except (OSError, ValueError) as problem:
        raise RunError(f"cannot read {paths[STATS]}: {problem}") from None
    try:
        split = load_split(paths[SPLIT])
    except ValueError as problem:  # (DatasetError, naming the file)
        raise RunError(str(problem)) from None
    return Run(run_dir=run_dir, config=config, stats=stats, split=split,
               model_path=paths[MODEL])


# ---------------------------------------------------------------------------
# Stored predictions: a run's outputs that outlive its weights
# ---------------------------------------------------------------------------
def predictions_path(run_dir, data_path):
    """``<run_dir>/predictions/<dataset file name>.npz``."""
    name = os.path.splitext(os.path.basename(os.fspath(data_path)))[0]
    return os.path.join(run_dir, PREDICTIONS, name + ".npz")


def stored_predictions(run_dir):
    """The stored predictions files of a run directory (sorted paths)."""
    folder = os.path.join(run_dir, PREDICTIONS)
    if not os.path.isdir(folder):
        return []
    return sorted(os.path.join(folder, f) for f in os.listdir(folder) if f.endswith(".npz"))


def load_model(run):
    """The run's best model (``load_model_file``); RunError when it has none
    or it is damaged."""
    if not os.path.exists(run.model_path):
        raise RunError(f"run directory {run.run_dir} has no weights (model.keras): a "
                       f"published run holds only its stored predictions")
    return load_model_file(run.model_path)


def load_model_file(path):
    """A saved model (``keras.saving.load_model(..., safe_mode=True)``, the
    package's custom layers registered); RunError when it is damaged."""
    import keras

    import cpl_keras.models.factory  # noqa: F401  (registers the custom layers)
    from cpl_keras.layers import placeholder_arithmetic_quiet

    if os.path.isfile(path) and not zipfile.is_zipfile(path):
        # (Keras reports a damaged archive as "File not found")
        raise RunError(f"cannot load {path}: the file is truncated or corrupt (not a complete "
                       ".keras archive)")
    try:
        with placeholder_arithmetic_quiet():  # (Keras's NumPy backend's shape inference)
            return keras.saving.load_model(path, safe_mode=True)
    except Exception as problem:  # corrupt archives raise many kinds of errors
        detail = one_line(problem)
        if os.path.isfile(path) and (isinstance(problem, (zipfile.BadZipFile, EOFError))
                                     or "not found" in detail.lower()):
            # a member of the archive is damaged (Keras says "File not found")
            detail = f"the file is truncated or corrupt ({detail})"
        raise RunError(f"cannot load {path}: {detail}") from None
