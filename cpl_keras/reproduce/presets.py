"""The reproduction's settings: the named presets (``PRESETS``), the Table 1
versions (``TABLE1``) and the folders a preset writes to. The runs a setting
trains, and what a machine without a GPU is told about GPU-sized settings,
are ``cpl_keras.reproduce.plan``'s."""

from __future__ import annotations

import dataclasses
import os
import sys

from cpl_keras.models import variants as registry
from cpl_keras.models.options import ModelOptions
from cpl_keras.models.variants import MIN_IMAGE_SIZE, MTL_VARIANTS, TABLE_ORDER
from cpl_keras.training_options import TrainingOptions

PROG = "python -m cpl_keras.reproduce"

#: The run name stem of MTL-CPL-A as released (a ``seeded_variants`` entry).
RELEASED_RUN = "cpl-a-released"

#: The Table 1 versions a reproduction can make, by key: (protocol, split,
#: the setting holding its number of seeds). A preset's ``tables`` lists
#: those it makes (default: ``DEFAULT_TABLES``); Table 2 comes from the
#: ``cvgl`` runs.
TABLE1 = {
    "cvgl": ("cvgl", "paper", "seeds"),
    "cvgl_drive": ("cvgl", "drive", "seeds"),
    "random": ("random", "held-out-config", "random_seeds"),
}
DEFAULT_TABLES = ("cvgl", "random")
#: The preset's own counts: positive integers (epochs, batch size and
#: patience are checked by the training's rules, ``training_rules``).
POSITIVE = ("pairs", "random_pairs", "image_size", "crops", "chessboard_crops",
            "geometric_max", "seeds", "random_seeds", "workers")
#: Where a preset's cvgl pairs come from (``Preset.data``).
DATA_SOURCES = ("render", "release")
#: Smallest image side of the real sets (StereoBM's block of 15 and 16 disparities).
MIN_REAL_IMAGE_SIZE = 32

#: The real sets that ship with the package, each a Table 2 rig (a preset's
#: ``real_sets`` may name fewer: the presets whose runs are committed keep
#: the rigs they were evaluated on, so that a rerun restores them).
REAL_SETS = ("chessboard", "middlebury", "oakd")
#: Real-data roots reproduce passes on to ``cpl_keras.real.build all``.
REAL_ROOTS = ("kitti", "kitti_raw", "tsinghua", "cityscapes")
#: The tables' titles in REPORT.md.
TITLES = {"table1_cvgl": "Table 1, paper protocol (cvgl rigs, frame-level 70/30 split)",
          "table1_cvgl_drive": "Table 1, paper protocol, drive split (cvgl rigs, the end of "
                               "every rig's drive held out)",
          "table1_random": "Table 1, unseen rigs (random protocol, whole configurations held out)",
          "table2": "Table 2, real rigs (per rig and pooled; forward pass of the cvgl-trained "
                    "models)"}


@dataclasses.dataclass(frozen=True)
class Preset:
    """A scale of the reproduction, checked when made (ValueError, one line).

    ``pairs`` / ``random_pairs``: pairs of the cvgl / random datasets;
    ``seeds`` / ``random_seeds``: seeds per protocol (each its own split and
    initial weights); ``variants``: trained on each protocol; ``released``:
    also MTL-CPL-A as released on cvgl; ``seeded_variants``: the runs trained
    on every seed (variants, and ``RELEASED_RUN``; None: all of them), the
    others are trained once, on the first seed; ``crops``: Middlebury crops;
    ``chessboard_crops``: crops per chessboard pair; ``geometric_max``: pairs
    of each table (or real set) the Geometric baseline runs on (None: all);
    ``workers``: data generation processes (None: every core); ``tables``:
    the Table 1 versions made (``TABLE1``); ``run_budget_s``: seconds of
    training per run (None: no limit); ``real_sets``: the Table 2 rigs
    (empty, and no real roots given: no Table 2);
    ``first_variants``: trained on every seed of a table before the other
    variants start; ``disparity_ceiling``: the CPL disparity head's,
    ``bn_statistics`` and ``monitor``: the BatchNorm statistics of
    validation and what early stopping follows; ``weight_ema``: the
    momentum of the averaged weights validated, kept and saved, 0 off
    (``training.train``'s arguments; None: its defaults).
    ``data``: ``"render"`` (the project's rendered pairs) or ``"release"``
    (the authors' released files, imported from ``--release-dir``: every
    run then trains and is scored as released, the only labels the release
    gives for the disparity and X, Y, Z); ``split``: the cvgl table's split
    (None: ``TABLE1``'s); ``backbone_weights``: the towers' initial weights
    ("imagenet" or a file; None: random), for the variants with towers.
    """

    pairs: int
    random_pairs: int
    epochs: int
    image_size: int
    backbone: str
    crops: int
    chessboard_crops: int
    geometric_max: int | None
    batch_size: int
    patience: int
    seeds: int
    random_seeds: int
    variants: tuple
    released: bool
    seeded_variants: tuple | None
    workers: int | None
    tables: tuple = DEFAULT_TABLES
    run_budget_s: float | None = None
    real_sets: tuple = REAL_SETS
    first_variants: tuple = ()
    disparity_ceiling: str | float | None = "auto"
    bn_statistics: str | None = None
    monitor: str | None = None
    weight_ema: float | None = None
    data: str = "render"
    split: str | None = None
    backbone_weights: str | None = None

    def __post_init__(self):
        for key in ("variants", "tables", "real_sets", "first_variants"):
            object.__setattr__(self, key, tuple(getattr(self, key)))
        if self.backbone_weights == "none":   # (--backbone-weights none: random towers)
            object.__setattr__(self, "backbone_weights", None)
        if self.seeded_variants is not None:
            object.__setattr__(self, "seeded_variants", tuple(self.seeded_variants))
        unknown = [s for s in self.real_sets if s not in REAL_SETS]
        if unknown:
            raise ValueError(f"unknown real set {unknown[0]!r}; choose from "
                             f"{', '.join(REAL_SETS)}")
        for key in POSITIVE:
            value = getattr(self, key)
            if value is None and key in ("geometric_max", "workers"):
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{key.replace('_', '-')} must be positive, got {value}")
        training_rules(self)
        if self.data not in DATA_SOURCES:
            raise ValueError(f"unknown data {self.data!r}; choose one of "
                             f"{', '.join(DATA_SOURCES)}")
        unknown = [t for t in self.tables if t not in TABLE1]
        if unknown or not self.tables:
            raise ValueError(f"unknown table {unknown[0] if unknown else '(none)'!r}; choose "
                             f"from {', '.join(TABLE1)}")
        for variant in self.first_variants:
            if variant not in self.variants:
                raise ValueError(f"first variant {variant!r} is not trained by these settings "
                                 f"({', '.join(self.variants)})")
        if self.seeded_variants is not None:
            trained = self.variants + ((RELEASED_RUN,) if self.released else ())
            for stem in self.seeded_variants:
                if stem not in trained:
                    raise ValueError(f"seeded variant {stem!r} is not trained by these "
                                     f"settings ({', '.join(trained)})")
        least = max([MIN_REAL_IMAGE_SIZE, MIN_IMAGE_SIZE.get(self.backbone, 1)]
                    + [registry.get(v).min_image_size or 1 for v in self.variants])
        if self.image_size < least:
            raise ValueError(f"image-size must be at least {least} (the {self.backbone} "
                             f"backbone and the real sets), got {self.image_size}")


def training_rules(preset):
    """Check a preset's training and model settings by the rules every run
    is checked by (``TrainingOptions``, ``ModelOptions``: the same rules as
    ``train.py`` and ``plan_run``, written once), before anything trains."""
    TrainingOptions(epochs=preset.epochs, batch_size=preset.batch_size,
                    patience=preset.patience, time_budget_s=preset.run_budget_s,
                    bn_statistics=preset.bn_statistics, monitor=preset.monitor,
                    weight_ema=preset.weight_ema, split=preset.split or "paper")
    for variant in preset.variants:
        options = ModelOptions(backbone=preset.backbone, disparity_ceiling=preset.disparity_ceiling,
                               backbone_weights=towers_weights(preset, variant))
        options.for_variant(variant)


def towers_weights(preset, variant):
    """The initial weights of ``variant``'s towers under ``preset``: its
    ``backbone_weights``, or None for a variant without towers (Deep-Homo)."""
    return None if registry.get(variant).builder == "deep_homo" else preset.backbone_weights


#: The named scales (``--preset``), each a ``Preset``.
PRESETS = {
    # The paper's scale: CVGL's 123,017 pairs, up to 200 epochs, InceptionV3 at
    # 112 (the scale without --preset, into paper_results/paper/).
    "paper": Preset(pairs=123017, random_pairs=123017, epochs=200, image_size=112,
                    backbone="inception_v3", crops=500, chessboard_crops=20,
                    geometric_max=None, batch_size=16, patience=5, seeds=1,
                    random_seeds=1, variants=TABLE_ORDER, released=True,
                    seeded_variants=None, workers=None),
    # Ten minutes of one GPU machine (the device's per-command limit): the
    # deciding pair, MTL-CPL-A then MTL-Baseline, with the paper's towers on
    # 20,000 cvgl pairs rendered on that machine's CPU cores; each run ends at
    # early stopping or at its time budget, whichever comes first; Table 2
    # from both. bench/paper_gpu.sh runs it there and packs what comes back;
    # its --dry-run checks the same plan on a CPU at tiny scale.
    "paper-gpu": Preset(pairs=20000, random_pairs=20000, epochs=200, image_size=112,
                        backbone="inception_v3", crops=500, chessboard_crops=20,
                        geometric_max=200, batch_size=16, patience=5, seeds=1,
                        random_seeds=1, variants=("cpl-a", "baseline"), released=False,
                        seeded_variants=None, workers=None, tables=("cvgl",),
                        run_budget_s=150),
    # Sized for a 2-core CPU: 1 h 24 min measured with --jobs 2 (paper_results/cpu/README.md):
    # every row of the tables, the MTL variants on cvgl over 3 seeds, Deep-Homo
    # and MTL-CPL-A as released on the first seed only; 1,000 pairs per
    # protocol, since a Deep-Homo training step costs 15-18 small_resnet ones.
    "cpu": Preset(pairs=1000, random_pairs=1000, epochs=60, image_size=112,
                  backbone="small_resnet", crops=500, chessboard_crops=20,
                  geometric_max=200, batch_size=16, patience=5, seeds=3,
                  random_seeds=1, variants=TABLE_ORDER, released=True,
                  seeded_variants=MTL_VARIANTS, workers=None,
                  real_sets=("chessboard", "middlebury"),
                  # (its published runs validated as before the fixed
                  # BatchNorm statistics, the NMAE monitor and the average)
                  bn_statistics="epoch", monitor="loss", weight_ema=0.0),
    # Tiny settings that run the paper-gpu pipeline end to end in minutes (CI).
    "quick": Preset(pairs=150, random_pairs=150, epochs=1, image_size=32,
                    backbone="small", crops=24, chessboard_crops=1, geometric_max=20,
                    batch_size=16, patience=5, seeds=1, random_seeds=1,
                    variants=TABLE_ORDER, released=True, seeded_variants=None,
                    workers=None),
    # Does MTL-CPL-A beat MTL-Baseline? The three MTL variants on 8,000 cvgl
    # pairs, 3 seeds each, on the paper's frame-level split and on the drive
    # split (no test frame next to a training frame), every run to early
    # stopping; Table 2 from the paper-split runs. Many hours on 2 cores:
    # each finished run is published at once and a rerun skips it
    # (docs/evaluation.md#presets). CPL-A and Baseline train on every seed
    # before CPL-U (``first_variants``), so the comparison that decides lands
    # first.
    "cpu-8000": Preset(pairs=8000, random_pairs=1000, epochs=100, image_size=112,
                       backbone="small_resnet", crops=500, chessboard_crops=20,
                       geometric_max=None, batch_size=16, patience=5, seeds=3,
                       random_seeds=1, variants=("cpl-a", "baseline", "cpl-u"),
                       released=False, seeded_variants=None, workers=None,
                       tables=("cvgl", "cvgl_drive"),
                       real_sets=("chessboard", "middlebury"),
                       first_variants=("cpl-a", "baseline"),
                       # (its first runs were trained before the disparity
                       # head's ceiling; all 18 keep the bound they had, and
                       # the validation of before the fixed BatchNorm
                       # statistics, the NMAE monitor and the average)
                       disparity_ceiling=None, bn_statistics="epoch", monitor="loss",
                       weight_ema=0.0),
    # The paper's towers decide the paper's claim: InceptionV3 MTL-CPL-A and
    # MTL-Baseline on the same 2,000 cvgl pairs (1,260 training), 3 seeds,
    # paper split, every run to early stopping with the project's defaults of
    # before the averaged weights (fixed BatchNorm statistics, the NMAE
    # monitor; weight_ema 0, which its published runs were trained with).
    # About 1-2 h a run on 2 cores (12 samples/s, 2-5 min an epoch): each
    # finished run is published at once and a rerun goes on from there,
    # rerun after rerun.
    "inception-2000": Preset(pairs=2000, random_pairs=1000, epochs=200, image_size=112,
                             backbone="inception_v3", crops=500, chessboard_crops=20,
                             geometric_max=200, batch_size=16, patience=5, seeds=3,
                             random_seeds=1, variants=("cpl-a", "baseline"), released=False,
                             seeded_variants=None, workers=None, tables=("cvgl",),
                             real_sets=("chessboard", "middlebury"),
                             first_variants=("cpl-a", "baseline"), weight_ema=0.0),
    # The compact towers on the same data, seeds and settings (about ten
    # minutes a run), so that the tower's effect is seen at equal data.
    "compact-2000": Preset(pairs=2000, random_pairs=1000, epochs=200, image_size=112,
                           backbone="small_resnet", crops=500, chessboard_crops=20,
                           geometric_max=200, batch_size=16, patience=5, seeds=3,
                           random_seeds=1, variants=("cpl-a", "baseline", "cpl-u"),
                           released=False, seeded_variants=None, workers=None,
                           tables=("cvgl",), real_sets=("chessboard", "middlebury"),
                           first_variants=("cpl-a", "baseline"), weight_ema=0.0),
}
# The paper's experiment on the paper's own inputs, for whoever has them and
# a GPU (docs/evaluation.md#the-papers-own-data): the authors' released CVGL
# files imported (--release-dir; their r and r_cs files too when there),
# the four networks of Table 1 trained as the paper did (InceptionV3 towers
# from ImageNet weights, batch 16, Adam 1e-3, up to 200 epochs, patience 5)
# on the split as released, and as released (the release's labels are the
# only ones it gives for the disparity and X, Y, Z); Table 2 from the
# release's real files and --tsinghua's folder. About 43 ms a step on one
# H200 (369 samples/s measured, paper_results/notes/gpu-h200.md): about
# 4 min an epoch of 86,111 training pairs.
PRESETS["paper-release"] = dataclasses.replace(
    PRESETS["paper"], variants=("baseline", "cpl-u", "cpl-a", "deep-homo"), released=False,
    tables=("cvgl",), real_sets=(), data="release", split="released",
    backbone_weights="imagenet")
# The same runs with every default of training, the averaged weights
# (weight_ema 0.99) included: paper_results/weight-ema measured them helping
# InceptionV3 MTL-CPL-A on every column. Runs stop later with them (an
# InceptionV3 run 1-2.5 h on 2 cores, a compact one 20-40 min); the compact
# towers' MTL-CPL-A and MTL-Baseline only. The InceptionV3 runs make Table 1
# alone: three of them were trained (paper_results/weight-ema) before the
# preset existed and published without predictions on the real sets.
PRESETS["inception-2000-ema"] = dataclasses.replace(PRESETS["inception-2000"], weight_ema=None,
                                                    real_sets=())
PRESETS["compact-2000-ema"] = dataclasses.replace(PRESETS["compact-2000"], weight_ema=None,
                                                  variants=("cpl-a", "baseline"))
#: The scale without --preset: the paper's, generating data on every core.
PAPER_SCALE = PRESETS["paper"]
QUICK = PRESETS["quick"]


@dataclasses.dataclass(frozen=True)
class Settings(Preset):
    """The settings of one reproduction: a ``Preset``'s fields (checked as
    there) and which preset they came from. ``to_dict`` / ``from_dict``:
    their form in ``reproduce.json`` (``pipeline.SUMMARY``)."""

    preset: str | None = None  #: the preset's name (``PRESETS``; None: the paper's scale)
    quick: bool = False        #: the quick preset (``--quick``)

    def __post_init__(self):
        if self.preset is not None and self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of "
                             f"{', '.join(PRESETS)}")
        if self.quick is not (self.preset == "quick"):
            raise ValueError(f"quick must be {self.preset == 'quick'} with preset "
                             f"{self.preset!r}, got {self.quick!r}")
        super().__post_init__()

    def to_dict(self):
        """The JSON form: every field in order (the ``Preset``'s, then
        ``preset`` and ``quick``), tuples as lists."""
        return {key: list(value) if isinstance(value, tuple) else value
                for key, value in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, config):
        """The settings of a ``to_dict`` form, also of an older one without
        the fields added since (their defaults). ValueError (one line) on an
        unknown or missing setting, or a bad value."""
        names = [field.name for field in dataclasses.fields(cls)]
        unknown = [key for key in config if key not in names]
        if unknown:
            raise ValueError(f"unknown setting {unknown[0]!r}")
        required = [field.name for field in dataclasses.fields(cls)
                    if field.default is dataclasses.MISSING]
        missing = [key for key in required if key not in config]
        if missing:
            raise ValueError(f"setting {missing[0]!r} missing")
        # (settings of before the averaged weights: trained without them)
        return cls(**{"weight_ema": 0.0, **config})


def settings(quick=False, preset=None, **overrides):
    """The run settings (``Settings``): a preset (``PRESETS``; default
    ``PAPER_SCALE``, ``quick=True`` is ``preset="quick"``) with ``overrides``
    applied (None: keep the preset's). ValueError (one line) on a bad value."""
    if quick and preset not in (None, "quick"):
        raise ValueError(f"--quick is --preset quick; it cannot go with --preset {preset}")
    name = "quick" if quick else preset
    chosen = PRESETS.get(name, PAPER_SCALE)  # (an unknown name: Settings refuses it)
    fields = {field.name: getattr(chosen, field.name) for field in dataclasses.fields(Preset)}
    for key in overrides:
        if key not in fields:
            raise ValueError(f"unknown setting {key!r}")
    fields.update({k: v for k, v in overrides.items() if v is not None})
    return Settings(**fields, preset=name, quick=name == "quick")


def log(message):
    print(f"[reproduce] {message}", file=sys.stderr, flush=True)


#: The reproduction's default output folder: ``paper_results/`` of the
#: current directory (from the repository's root, the committed folder),
#: never a folder of the installed package.
RESULTS_DIR = "paper_results"


def default_folders(preset):
    """``(out, data_dir, runs_dir)`` of a preset, each relative to the current
    directory (None: the paper's scale into paper_results/)."""
    if preset == "quick":
        return os.path.join("runs", "quick", "paper_results"), os.path.join("data", "quick"), \
            os.path.join("runs", "quick")
    if preset is None:
        return RESULTS_DIR, os.path.join("data", "reproduce"), os.path.join("runs", "reproduce")
    return (os.path.join(RESULTS_DIR, preset), os.path.join("data", f"reproduce-{preset}"),
            os.path.join("runs", f"reproduce-{preset}"))


