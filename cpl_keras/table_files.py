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

import numpy as np

from cpl_keras import evaluation, report, runs
from cpl_keras.baselines.geometric import FAILURE_FLAGS
from cpl_keras.camera import TARGETS
from cpl_keras.data.storage import StereoFile
from cpl_keras.prediction_files import (
    BASELINES, FORMAT, FORMAT_VERSION, SUFFIX, PredictionsError, file_name, load, row_slug,
)


def _dataset_facts(path):
    with StereoFile(path) as f:
        version = f.metadata.get("generator_version")
    return os.path.basename(path), "" if version is None else str(version)


def _arrays(row, raw, *, name, out_dir, run_configs, reference, data_path, subset, table,
            table_number, context, key, rig="", rig_index=-1):
    """The arrays of one row's file."""
    n = len(raw["indices"])
    defined = raw.get("defined") or {k: np.ones(n, bool) for k in TARGETS}
    config = run_configs.get(os.path.abspath(raw["source"])) if row not in BASELINES else None
    identity = config or run_configs[os.path.abspath(reference)]  # (split and seed)
    dataset, version = _dataset_facts(data_path)
    arrays = {
        "format": np.array(FORMAT), "format_version": np.array(FORMAT_VERSION, np.int64),
        "outputs": np.array(TARGETS),
        "pred": np.stack([np.asarray(raw["pred"][k], np.float32) for k in TARGETS], axis=1)
        .reshape(n, len(TARGETS)),
        "truth": np.stack([np.asarray(raw["truth"][k], np.float64) for k in TARGETS], axis=1)
        .reshape(n, len(TARGETS)),
        "defined": np.stack([np.asarray(defined[k], bool) for k in TARGETS], axis=1)
        .reshape(n, len(TARGETS)),
        "indices": np.asarray(raw["indices"], np.int64),
        "name": np.array(name), "row": np.array(row),
        "variant": np.array(BASELINES.get(row) or config.variant),
        "source": np.array(report.portable_paths({"source": raw["source"]}, out_dir)["source"]),
        "as_released": np.array(bool(raw["as_released"])),
        "dataset": np.array(dataset), "generator_version": np.array(version),
        "dataset_path": np.array(runs.relative(data_path, out_dir)),
        "split": np.array("" if identity.split is None else str(identity.split)),
        "subset": np.array(subset), "seed": np.array(int(identity.seed or 0), np.int64),
        "table": np.array(table), "table_number": np.array(int(table_number), np.int64),
        "rig": np.array(rig), "rig_index": np.array(int(rig_index), np.int64),
        "context": np.array(json.dumps(report.portable_paths(context, out_dir), sort_keys=True)),
        "key": np.array(key),
    }
    if row == "Geometric":
        arrays["failure_flags"] = np.array(FAILURE_FLAGS)
        arrays["failures"] = np.array([[bool(s[f]) for f in FAILURE_FLAGS]
                                       for s in raw["statuses"]], bool).reshape(n, len(FAILURE_FLAGS))
        arrays["prior_names"] = np.array(list(raw["priors"]), dtype=str)
        arrays["prior_values"] = np.array(list(raw["priors"].values()), np.float64)
        arrays["degenerate"] = np.array(list(raw.get("degenerate", [])), dtype=str)
    return arrays


def _run_configs(run_dirs):
    """``{run directory: its RunConfig}`` (the evaluated runs: each has one)."""
    return {os.path.abspath(r): runs.read_run_config(r) for r in run_dirs}


def table1_files(context, rows, *, out_dir, prefix, stem, key, suffix=""):
    """``{file name: arrays}`` for the raw rows of ``evaluation.table_rows``."""
    configs = _run_configs(context["runs"])
    subset = "test" if context["data_description"].startswith("test split") else "all"
    files = {}
    for row, raw in rows.items():
        name = file_name(prefix, row_slug(row, raw["source"], suffix))
        files[name] = _arrays(
            row, raw, name=name[: -len(SUFFIX)], out_dir=out_dir, run_configs=configs,
            reference=context["runs"][0], data_path=context["data"], subset=subset, table=stem,
            table_number=context["table"], context=context, key=key)
    return files


def table2_files(run_list, rigs, *, out_dir, prefix, stem, key, suffix=""):
    """``{file name: arrays}`` for the raw rigs of ``evaluation.table2_rigs``."""
    configs = _run_configs(run_list)
    files = {}
    for index, rig in enumerate(rigs):
        context = {k: rig[k] for k in ("rig", "data", "data_description", "rectified", "width",
                                       "data_source", "num_pairs")}
        context["runs"] = list(run_list)
        data_stem = os.path.splitext(os.path.basename(rig["data"]))[0]
        for row, raw in rig["rows"].items():
            name = file_name(prefix, row_slug(row, raw["source"], suffix), data_stem)
            files[name] = _arrays(
                row, raw, name=name[: -len(SUFFIX)], out_dir=out_dir, run_configs=configs,
                reference=run_list[0], data_path=rig["data"], subset="all", table=stem,
                table_number=2, context=context, key=key, rig=rig["rig"], rig_index=index)
    return files


# ---------------------------------------------------------------------------
# Tables from files
# ---------------------------------------------------------------------------
def _one_table(stem, items):
    """The table ``stem`` of one seed from its files."""
    rows_seen = {}
    for item in items:
        where = (item["rig_index"], item["row"])
        if where in rows_seen:
            raise PredictionsError(f"{item['path']} and {rows_seen[where]} are both row "
                                   f"{item['row']} of {stem}" + (f" on {item['rig']}"
                                                                 if item["rig"] else ""))
        rows_seen[where] = item["path"]
    if any(item["rig_index"] >= 0 for item in items):          # Table 2: per rig, pooled

        run_lists = {json.dumps(item["context"]["runs"]) for item in items}
        if len(run_lists) > 1:
            raise PredictionsError(f"the files of {stem} name different runs: {items[0]['path']}")
        rigs = {}
        for item in sorted(items, key=lambda i: i["rig_index"]):
            context = item["context"]
            rig = rigs.setdefault(item["rig_index"], dict(
                {k: v for k, v in context.items() if k != "runs"}, rows={}))
            if {k: v for k, v in context.items() if k != "runs"} != \
                    {k: v for k, v in rig.items() if k != "rows"}:
                raise PredictionsError(f"{item['path']}: its rig does not match the other "
                                       f"files of {stem} on {item['rig']}")
            rig["rows"][item["row"]] = item["raw"]
        return evaluation.table2_from_rigs(items[0]["context"]["runs"], list(rigs.values()))
    contexts = {json.dumps(item["context"], sort_keys=True) for item in items}
    if len(contexts) > 1:
        raise PredictionsError(f"the files of {stem} disagree on its data or runs "
                               f"({items[0]['path']})")
    return evaluation.table_from_rows(items[0]["context"],
                                      {item["row"]: item["raw"] for item in items})


def tables_from_files(paths):
    """``{stem: table}`` from predictions files (every file is read and checked
    first): each table scored per seed, and a table over several seeds
    aggregated into mean and spread. PredictionsError on a bad file."""
    items = [load(path) for path in paths]
    if not items:
        raise PredictionsError("no predictions files given")
    groups = {}
    for item in items:
        groups.setdefault(item["table"], {}).setdefault(item["seed"], []).append(item)
    tables = {}
    for stem, by_seed in groups.items():
        seeds = sorted(by_seed)
        tables[stem] = evaluation.aggregate_seeds(
            [_one_table(stem, by_seed[seed]) for seed in seeds], seeds)
    return tables
