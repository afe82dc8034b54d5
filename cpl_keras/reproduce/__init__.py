"""Regenerate every result of ``paper_results/`` with one command.

    python -m cpl_keras.reproduce                     # the paper's scale (a GPU job)
    python -m cpl_keras.reproduce --preset paper      # the same, into paper_results/paper/
    python -m cpl_keras.reproduce --preset paper-gpu  # CPL-A vs Baseline in 10 min of a GPU
    python -m cpl_keras.reproduce --preset cpu --jobs 2   # compact towers, 3 seeds, ~1.5 h on 2 cores
    python -m cpl_keras.reproduce --quick             # the same pipeline in minutes
    python -m cpl_keras.reproduce --pairs 2000 --epochs 4   # a chosen scale
    python -m cpl_keras.reproduce --from-predictions DIR    # tables again, from DIR alone

(``cpl-reproduce ...`` is the same command, installed.)

The pipeline, every stage resumable (datasets, finished runs and published
predictions newer than their runs, holding what the record was made from,
are reused; killed training runs resume from their last epoch):

1. data: a ``cvgl``-protocol dataset (the paper's 50 rigs), a ``random``-
   protocol dataset (realistic rigs) and every real rig
   (``cpl_keras.real.build all``: the shipped OpenCV chessboard rig and
   Middlebury, KITTI / Tsinghua-Daimler / Cityscapes where their roots are
   given);
2. training: the preset's variants on each protocol (``cvgl`` with the
   paper's frame-level 70/30 split, ``random`` with whole configurations held
   out), plus MTL-CPL-A as released on cvgl where the preset has it; the
   preset's ``seeded_variants`` are trained for each of its seeds (a seed
   changes the split and the initial weights), the other runs once, on the
   first seed (``cpu``: the three MTL variants on 3 seeds, Deep-Homo and
   MTL-CPL-A as released on one);
3. predictions: every row of every table (each run, and the Average, the
   release's Average and the Geometric baselines) on its pairs, published as
   ``<out>/runs/*_predictions.npz`` (``cpl_keras.table_files``): Table 1 on
   each protocol's test split, Table 2 as a forward pass of the cvgl-trained
   models on every real rig;
4. tables, made from those files alone: Table 1 per protocol, Table 2 per rig
   and pooled (``cpl_keras.evaluation.table2``); a table over several seeds gives
   every cell as mean ± spread, a row trained on one seed only its value;
5. ``REPORT.md``: settings, dataset sizes, seeds, epochs actually run, wall
   times, the machine, the tables, the plots and the comparison with the
   paper; ``reproduce.json`` holds the same facts, so that
   ``--from-predictions`` rebuilds the tables and REPORT.md without weights
   or datasets.

The package: ``presets`` (the settings), ``plan`` (the runs they make, and
their cost on a CPU), ``jobs``
(training each run and publishing it; with ``--jobs`` in processes of their
own, ``cpl_keras.training.parallel``), ``record`` (stage 3: the
published predictions, reused or computed again, and their checksums in
``reproduce.json``), ``pipeline`` (the stages and the rebuild), ``page``
(REPORT.md); its command line is ``cpl_keras.commands.reproduce``.
"""

from __future__ import annotations

from cpl_keras.models.variants import SLOW_VARIANTS
from cpl_keras.reproduce.jobs import publish_run, published_record, train_all
from cpl_keras.reproduce.page import scale_text, write_report
from cpl_keras.reproduce.pipeline import (
    SUMMARY, make_datasets, read_summary, rebuild, rebuild_command, reproduce,
)
from cpl_keras.reproduce.plan import (
    GPU_SIZED_PAIRS, Job, cpu_cost, gpu_sized, has_accelerator, run_jobs, run_stems,
)
from cpl_keras.reproduce.presets import (
    DEFAULT_TABLES, MTL_VARIANTS, PAPER_SCALE, PRESETS, PROG, QUICK, Preset, REAL_ROOTS,
    REAL_SETS, RELEASED_RUN, TABLE1, Settings, default_folders, settings,
)

__all__ = [
    "DEFAULT_TABLES", "GPU_SIZED_PAIRS", "MTL_VARIANTS", "PAPER_SCALE", "PRESETS", "PROG",
    "Job", "Preset", "QUICK", "REAL_ROOTS", "REAL_SETS", "RELEASED_RUN", "SLOW_VARIANTS", "SUMMARY",
    "Settings", "TABLE1",
    "cpu_cost", "default_folders", "gpu_sized", "has_accelerator",
    "make_datasets", "publish_run", "published_record", "read_summary", "rebuild",
    "rebuild_command", "reproduce", "run_jobs", "run_stems",
    "scale_text", "settings", "train_all", "write_report",
]
