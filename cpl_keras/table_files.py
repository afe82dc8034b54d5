"""Tables as predictions files: the results of Tables 1 and 2 that outlive the weights.

Every row of a table (a trained run, or a baseline: Average, the release's
buggy Average, Geometric) publishes what it predicted on the table's pairs
as one small ``.npz`` file (``np.load(path, allow_pickle=False)``; no object
arrays), and the tables are scored from those files alone: no weights, no
dataset. ``python -m cpl_keras.reproduce`` writes them next to each run's log
and curves (``<out>/runs/<protocol>_<name>[_on_<real set>]_predictions.npz``)
and makes its tables from them; ``--from-predictions DIR`` rebuilds every
table and REPORT.md from them.

The files' format (their arrays, their names) is
``cpl_keras.prediction_files``'s, which reads and writes them; this module
makes the files of a table's rows (``table1_files``, ``table2_files``) and
scores the tables from the files.

``tables_from_files(paths)`` groups the files by table and seed, scores each
group with the same code that scores a table in memory
(``evaluation.table_from_rows``, ``evaluation.table2_from_rigs``), and
aggregates a table made over several seeds into mean and spread
(``evaluation.aggregate_seeds``).
"""

from __future__ import annotations

import json
import os

from cpl_keras import evaluation, report, runs
from cpl_keras.data.storage import StereoFile
from cpl_keras.prediction_files import SUFFIX, PredictionsError, RowFile, load, row_arrays
from cpl_keras.table_rows import Rig

#: File name slug and variant of the baseline rows.
BASELINES = {"Average": "average", "Average (release bug)": "average-release",
             "Geometric": "geometric"}


def file_name(prefix, slug, data_stem=None):
    """``<prefix>_<slug>[_on_<data_stem>]_predictions.npz``."""
    return f"{prefix}_{slug}" + (f"_on_{data_stem}" if data_stem else "") + SUFFIX


def row_slug(row, source, suffix=""):
    """A row's file-name slug: the name of its run directory ``source``, or
    the baseline's slug with ``suffix`` (the seed's suffix, for tables over
    several seeds)."""
    if row in BASELINES:
        return BASELINES[row] + suffix
    return os.path.basename(os.path.normpath(source))



def _dataset_facts(path):
    with StereoFile(path) as f:
        version = f.metadata.get("generator_version")
    return os.path.basename(path), "" if version is None else str(version)


def _row_file(row, raw, *, where, configs, reference, **facts):
    """The ``RowFile`` of the row named ``row`` (its ``Row`` ``raw``): its
    run's variant, split and seed (a baseline: its reference run's split and
    seed), its dataset file's facts, its paths relative to ``where`` (the
    tables' folder); ``facts``: the file's other fields."""
    config = configs.get(os.path.abspath(raw.source)) if row not in BASELINES else None
    identity = config or configs[os.path.abspath(reference)]  # (split and seed)
    data_path = facts.pop("data_path")
    dataset, version = _dataset_facts(data_path)
    return RowFile(
        row=row, variant=BASELINES.get(row) or config.variant,
        source=report.portable_paths({"source": raw.source}, where)["source"],
        dataset=dataset, generator_version=version, dataset_path=runs.relative(data_path, where),
        split="" if identity.training.split is None else str(identity.training.split),
        seed=int(identity.training.seed or 0), context=report.portable_paths(facts.pop("context"), where),
        raw=raw, **facts)


def _run_configs(run_dirs):
    """``{run directory: its RunConfig}`` (the evaluated runs: each has one)."""
    return {os.path.abspath(r): runs.read_run_config(r) for r in run_dirs}


def table1_files(context, rows, *, out_dir, prefix, stem, key, suffix=""):
    """``{file name: arrays}`` for the rows (name -> ``Row``) of
    ``evaluation.table_rows``."""
    configs = _run_configs(context["runs"])
    subset = "test" if context["data_description"].startswith("test split") else "all"
    files = {}
    for row, raw in rows.items():
        name = file_name(prefix, row_slug(row, raw.source, suffix))
        files[name] = row_arrays(_row_file(
            row, raw, where=out_dir, configs=configs, reference=context["runs"][0],
            name=name[: -len(SUFFIX)], data_path=context["data"], subset=subset, table=stem,
            table_number=context["table"], context=context, key=key))
    return files


def table2_files(run_list, rigs, *, out_dir, prefix, stem, key, suffix=""):
    """``{file name: arrays}`` for the ``Rig`` records of ``evaluation.table2_rigs``."""
    configs = _run_configs(run_list)
    files = {}
    for index, rig in enumerate(rigs):
        context = dict(rig.context(), runs=list(run_list))
        data_stem = os.path.splitext(os.path.basename(rig.data))[0]
        for row, raw in rig.rows.items():
            name = file_name(prefix, row_slug(row, raw.source, suffix), data_stem)
            files[name] = row_arrays(_row_file(
                row, raw, where=out_dir, configs=configs, reference=run_list[0],
                name=name[: -len(SUFFIX)], data_path=rig.data, subset="all",
                table=stem, table_number=2, context=context, key=key, rig=rig.rig,
                rig_index=index))
    return files


# ---------------------------------------------------------------------------
# Tables from files
# ---------------------------------------------------------------------------
def _one_table(stem, items):
    """The table ``stem`` of one seed from its files."""
    rows_seen = {}
    for item in items:
        where = (item.rig_index, item.row)
        if where in rows_seen:
            raise PredictionsError(f"{item.path} and {rows_seen[where]} are both row "
                                   f"{item.row} of {stem}" + (f" on {item.rig}"
                                                              if item.rig else ""))
        rows_seen[where] = item.path
    if any(item.rig_index >= 0 for item in items):          # Table 2: per rig, pooled
        run_lists = {json.dumps(item.context["runs"]) for item in items}
        if len(run_lists) > 1:
            raise PredictionsError(f"the files of {stem} name different runs: {items[0].path}")
        facts, rows = {}, {}
        for item in sorted(items, key=lambda i: i.rig_index):
            context = {k: v for k, v in item.context.items() if k != "runs"}
            if facts.setdefault(item.rig_index, context) != context:
                raise PredictionsError(f"{item.path}: its rig does not match the other "
                                       f"files of {stem} on {item.rig}")
            rows.setdefault(item.rig_index, {})[item.row] = item.raw
        rigs = [_rig(facts[index], rows[index], stem) for index in facts]
        return evaluation.table2_from_rigs(items[0].context["runs"], rigs)
    contexts = {json.dumps(item.context, sort_keys=True) for item in items}
    if len(contexts) > 1:
        raise PredictionsError(f"the files of {stem} disagree on its data or runs "
                               f"({items[0].path})")
    return evaluation.table_from_rows(items[0].context, {item.row: item.raw for item in items})


def _rig(context, rows, stem):
    """The ``Rig`` of a rig's files: its facts (their ``context``) and rows."""
    if sorted(context) != sorted(Rig.CONTEXT):
        raise PredictionsError(f"the files of {stem} on {context.get('rig')} hold no rig's "
                               f"facts ({', '.join(Rig.CONTEXT)})")
    return Rig(**context, rows=rows)


def tables_from_files(paths):
    """``{stem: table}`` from predictions files (every file is read and checked
    first): each table scored per seed, and a table over several seeds
    aggregated into mean and spread. PredictionsError on a bad file."""
    items = [load(path) for path in paths]
    if not items:
        raise PredictionsError("no predictions files given")
    groups = {}
    for item in items:
        groups.setdefault(item.table, {}).setdefault(item.seed, []).append(item)
    tables = {}
    for stem, by_seed in groups.items():
        seeds = sorted(by_seed)
        tables[stem] = evaluation.aggregate_seeds(
            [_one_table(stem, by_seed[seed]) for seed in seeds], seeds)
    return tables
