"""Predictions files: what a model or a baseline predicted on a dataset's
pairs, in one format, read and written here alone.

Every file is a small ``.npz`` (``np.load(path, allow_pickle=False)``; no
object arrays) of numpy arrays. Two uses share the format:

* a run's **stored outputs** (``<run_dir>/predictions/<dataset>.npz``,
  ``write_run_outputs``; ``cpl_keras.runs`` names the files): the core
  arrays ``outputs``, ``pred``, ``indices`` and ``dataset``, so that a run is
  evaluated without its weights;
* a **published table row** (``<out>/runs/<protocol>_<name>[_on_<real
  set>]_predictions.npz``, ``write_files``; ``cpl_keras.table_files`` makes
  them from a table's rows and scores tables from them): the core arrays and the row's
  truth and identity, so that a table is rebuilt from the files alone.

A table row's file holds the fields of ``RowFile`` (a record of one; the
arrays in the order ``row_arrays`` writes them), and its row's own arrays
(n = pairs of the row, one line per pair; a run's stored outputs hold
``outputs``, ``pred``, ``indices`` and ``dataset`` of these):
``outputs`` (13,) str, the output names in the release's order (fx fy u0
v0 baseline disparity tx ty tz pitch X Y Z); ``pred`` (n, 13) float32;
``truth`` (n, 13) float64, the targets the row is scored against (the
release's for an as-released row); ``defined`` (n, 13) bool, where the
truth exists (real sets without ground-truth disparity leave disparity, X,
Y, Z out); ``indices`` (n,) int64, the pairs in the dataset file;
``as_released`` bool; and for the Geometric row ``failure_flags`` (k,) str
and ``failures`` (n, k) bool (its stage failures), ``prior_names`` /
``prior_values`` (its fallbacks), ``degenerate`` (columns undefined on a
rectified rig). Besides, ``format`` and ``format_version``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
import zipfile

import numpy as np

from cpl_keras.baselines.geometric import FAILURE_FLAGS
from cpl_keras.camera import TARGETS
from cpl_keras.cli import one_line
from cpl_keras.files import atomic_path
from cpl_keras.runs import RunError
from cpl_keras.table_rows import Row, RowError

#: File name suffix of a predictions file.
SUFFIX = "_predictions.npz"
FORMAT = "cpl_keras.predictions"
FORMAT_VERSION = 1
#: Arrays every table row's file has, and their dimensions (n = pairs, 13 = outputs).
SHAPES = {"pred": ("n", 13), "truth": ("n", 13), "defined": ("n", 13), "indices": ("n",),
          "outputs": (13,)}
STRINGS = ("format", "name", "row", "variant", "source", "dataset", "generator_version",
           "dataset_path", "split", "subset", "table", "rig", "context", "key")
NUMBERS = ("format_version", "seed", "table_number", "rig_index", "as_released")
class PredictionsError(RunError):
    """A predictions file is missing, unreadable or inconsistent (one line)."""


# ---------------------------------------------------------------------------
# A run's stored outputs (the core arrays)
# ---------------------------------------------------------------------------
def write_run_outputs(path, data_path, indices, outputs, names):
    """Store a run's ``outputs`` (name -> (n,) array) on pairs ``indices`` of
    ``data_path`` at ``path``: ``indices`` (int64), ``pred`` (n, 13
    float32), ``outputs`` (the names), ``dataset`` (the file's name).
    Atomic. Returns ``path``."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    pred = np.stack([np.asarray(outputs[n], np.float32).reshape(-1) for n in names], axis=1)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, indices=np.asarray(indices, np.int64), pred=pred,
                     outputs=np.array(list(names)),
                     dataset=np.array(os.path.basename(os.fspath(data_path))))
    return path


def read_run_outputs(path, indices, names):
    """The outputs stored at ``path`` on pairs ``indices`` (name -> float64
    array), or None when there is no such file. PredictionsError when it is
    unreadable or lacks some of the pairs."""
    if not os.path.isfile(path):
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            stored, pred = data["indices"], data["pred"]
            outputs = [str(n) for n in data["outputs"]]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as problem:
        raise PredictionsError(f"cannot read {path}: {one_line(problem)}") from None
    if outputs != list(names) or pred.shape != (len(stored), len(names)):
        raise PredictionsError(f"{path}: outputs {outputs} are not {list(names)}")
    where = {int(i): k for k, i in enumerate(stored)}
    missing = [int(i) for i in indices if int(i) not in where]
    if missing:
        raise PredictionsError(f"{path} has no predictions for {len(missing)} of the pairs "
                               f"asked (first: {missing[0]})")
    rows = np.array([where[int(i)] for i in indices], np.int64)
    return {name: pred[rows, k].astype(np.float64) for k, name in enumerate(names)}


# ---------------------------------------------------------------------------
# Published table rows
# ---------------------------------------------------------------------------
def write_files(folder, files):
    """Write ``{file name: arrays}`` into ``folder`` (created if missing), all
    files or none (``cpl_keras.files.atomic_path``); returns their paths. A
    file that already holds the same arrays is left as it is, byte for byte
    (an .npz's bytes carry the time it was written)."""
    return _write(folder, files)[0]


def _write(folder, files):
    """``write_files``, and the paths of the files it wrote."""
    os.makedirs(folder, exist_ok=True)
    paths = [os.path.join(folder, name) for name in files]
    changed = [(path, arrays) for path, arrays in zip(paths, files.values())
               if not same_arrays(path, arrays)]
    if not changed:
        return paths, []
    with atomic_path(*[path for path, _ in changed]) as tmps:
        tmps = tmps if isinstance(tmps, list) else [tmps]
        for tmp, (_, arrays) in zip(tmps, changed):
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
    return paths, [path for path, _ in changed]


def checksum(path):
    """The sha256 (hex) of what the .npz file ``path`` holds: each array's
    name, dtype, shape and values, in name order; not the zip's bytes, which
    carry the time it was written. None when it is missing or cannot be
    read. A published record keeps its files' (``reproduce.json``), so
    that a file changed since (by hand) is told from the one it was made
    from."""
    digest = hashlib.sha256()
    try:
        with np.load(path, allow_pickle=False) as f:
            for name in sorted(f.files):
                value = np.ascontiguousarray(f[name])
                digest.update(json.dumps([name, value.dtype.str, value.shape]).encode())
                digest.update(value.tobytes())
    except Exception:  # (a missing or damaged file is no file of the record)
        return None
    return digest.hexdigest()


#: The arrays of a predictions file that say where it was made (paths
#: relative to its folder), not what it holds.
LOCATION_KEYS = ("key", "source", "dataset_path", "context")


def same_arrays(path, arrays, ignore=()):
    """Whether the .npz file ``path`` holds exactly ``arrays`` (the same
    names, dtypes, shapes and values, NaN equal to NaN), leaving out the
    arrays named in ``ignore``; False when it is missing or cannot be read."""
    try:
        with np.load(path, allow_pickle=False) as f:
            if sorted(f.files) != sorted(arrays):
                return False
            for name, value in arrays.items():
                if name in ignore:
                    continue
                old, new = f[name], np.asarray(value)
                if old.dtype != new.dtype or old.shape != new.shape:
                    return False
                if not np.array_equal(old, new, equal_nan=new.dtype.kind in "fc"):
                    return False
    except Exception:  # (a missing or damaged file is written again)
        return False
    return True


#: Where a reproduction over a published folder writes the predictions
#: files whose arrays differ from the published ones (inside that folder).
RERUN = "rerun"


def write_group(folder, files, published=False, log=None, beside=None):
    """Write one group's predictions files (``{name: arrays}``) into
    ``folder`` (``write_files``: unchanged ones are left as
    they are). In a ``published`` record a file whose arrays differ from the
    published file's is written beside it, into ``<folder>/../rerun/runs/``,
    with one line saying how many values differ and by how much; the
    published file is left as it is (``log(line)``, default stderr); so is
    one that differs only by where it was made (``LOCATION_KEYS``). Returns
    the paths the tables read (the published ones) and those of the files
    written into ``folder``; ``beside`` (a list) gets the paths of those
    written beside it."""
    if not published:
        return _write(folder, files)
    log = log or (lambda line: print(line, file=sys.stderr, flush=True))
    paths, new, differ = [], {}, {}
    for name, arrays in files.items():
        path = os.path.join(folder, name)
        paths.append(path)
        if not os.path.exists(path):
            new[name] = arrays
        elif not same_arrays(path, arrays, ignore=LOCATION_KEYS):
            differ[name] = arrays
    written = _write(folder, new)[1]
    if differ:
        rerun = os.path.join(os.path.dirname(folder), RERUN, os.path.basename(folder))
        put = write_files(rerun, differ)
        if beside is not None:
            beside.extend(put)
        for name, arrays in differ.items():
            log(f"{name}: {_difference(os.path.join(folder, name), arrays)} from the "
                f"published file; written beside it in {rerun}, the published file left as "
                f"it is")
    return paths, written


def _difference(path, arrays):
    """How the predictions ``arrays`` differ from the file ``path``'s, in words."""
    try:
        with np.load(path, allow_pickle=False) as old:
            was = old["pred"].astype(np.float64) if "pred" in old.files else None
    except Exception:  # (a damaged published file)
        return "its arrays differ (the published file cannot be read)"
    if "pred" in arrays and was is not None and was.shape == np.shape(arrays["pred"]):
        new = np.asarray(arrays["pred"], np.float64)
        differ = ~((new == was) | (np.isnan(new) & np.isnan(was)))
        if differ.any():
            largest = float(np.nanmax(np.abs(new - was)[differ]))
            return (f"{int(differ.sum())} of {differ.size} predicted values differ (by up "
                    f"to {largest:.4g})")
    return "its arrays differ"



def _scalar(arrays, key, path, kind):
    value = arrays[key]
    if value.shape != ():
        raise PredictionsError(f"{path}: '{key}' is not a single value")
    if kind is str:
        if value.dtype.kind != "U":
            raise PredictionsError(f"{path}: '{key}' is not a string")
        return str(value)
    if value.dtype.kind not in "biu":
        raise PredictionsError(f"{path}: '{key}' is not an integer")
    return int(value)


def read_key(path):
    """The ``key`` stored in a predictions file (None when it cannot be read)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            return str(f["key"])
    except Exception:  # a stale or damaged file is recomputed, never trusted
        return None


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)
class RowFile:
    """One table row's predictions file as a record: the arrays of the module
    doc (``row_arrays`` writes them, ``load`` reads them back), the row's
    own arrays as a ``table_rows.Row`` (``raw``; its ``source`` is the
    file's)."""

    # the file's name stem (cvgl_cpl-a), the table row (MTL-CPL-A), the variant
    # (cpl-a, or average, average-release, geometric)
    name: str
    row: str
    variant: str
    # the run directory relative to the tables' folder (a baseline: what it is
    # computed from)
    source: str
    # the dataset file's name, its generator version (empty for real sets), its
    # path relative to the tables' folder
    dataset: str
    generator_version: str
    dataset_path: str
    # the run's split (paper, held-out-config), the pairs used (test: its test
    # split; all: every pair of a real set), its seed (a baseline: its reference run's)
    split: str
    subset: str
    seed: int
    # the table's file stem (table1_cvgl, table2), its number, the real set's rig
    # and its position among the table's real sets ("", -1 for Table 1)
    table: str
    table_number: int
    rig: str = ""
    rig_index: int = -1
    # the table's fields as it records them (JSON in the file), and what the file
    # was computed from (runs, data, Geometric settings: JSON), to tell when it is stale
    context: dict
    key: str
    raw: Row
    # where it was read from (None for a file not yet written)
    path: str | None = None


def row_arrays(item):
    """The arrays of the ``RowFile`` ``item``'s file, in the file's order."""
    raw, n = item.raw, item.raw.num_pairs
    defined = raw.defined or {k: np.ones(n, bool) for k in TARGETS}
    columns = lambda values, kind: np.stack(  # noqa: E731
        [np.asarray(values[k], kind) for k in TARGETS], axis=1).reshape(n, len(TARGETS))
    arrays = {
        "format": np.array(FORMAT), "format_version": np.array(FORMAT_VERSION, np.int64),
        "outputs": np.array(TARGETS), "pred": columns(raw.pred, np.float32),
        "truth": columns(raw.truth, np.float64), "defined": columns(defined, bool),
        "indices": np.asarray(raw.indices, np.int64),
        "name": np.array(item.name), "row": np.array(item.row),
        "variant": np.array(item.variant), "source": np.array(item.source),
        "as_released": np.array(bool(raw.as_released)),
        "dataset": np.array(item.dataset), "generator_version": np.array(item.generator_version),
        "dataset_path": np.array(item.dataset_path), "split": np.array(item.split),
        "subset": np.array(item.subset), "seed": np.array(int(item.seed), np.int64),
        "table": np.array(item.table), "table_number": np.array(int(item.table_number), np.int64),
        "rig": np.array(item.rig), "rig_index": np.array(int(item.rig_index), np.int64),
        "context": np.array(json.dumps(item.context, sort_keys=True)), "key": np.array(item.key),
    }
    if item.row == "Geometric":
        arrays["failure_flags"] = np.array(FAILURE_FLAGS)
        arrays["failures"] = np.array([[bool(s[f]) for f in FAILURE_FLAGS]
                                       for s in raw.statuses], bool).reshape(n, len(FAILURE_FLAGS))
        arrays["prior_names"] = np.array(list(raw.priors), dtype=str)
        arrays["prior_values"] = np.array(list(raw.priors.values()), np.float64)
        arrays["degenerate"] = np.array(list(raw.degenerate or []), dtype=str)
    return arrays


def _read(path):
    """The arrays of the predictions file ``path``, its identity checked
    (``{name: scalar}``). PredictionsError when it is no such file."""
    if not os.path.isfile(path):
        raise PredictionsError(f"predictions file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as error:
        raise PredictionsError(f"{path}: not a readable predictions file "
                               f"({type(error).__name__}: {one_line(error)})") from None
    missing = [k for k in STRINGS + NUMBERS + tuple(SHAPES) if k not in arrays]
    if missing:
        raise PredictionsError(f"{path}: not a predictions file (no {', '.join(missing)})")
    item = {k: _scalar(arrays, k, path, str) for k in STRINGS}
    item.update({k: _scalar(arrays, k, path, int) for k in NUMBERS})
    if item["format"] != FORMAT or item["format_version"] != FORMAT_VERSION:
        raise PredictionsError(f"{path}: format {item['format']} {item['format_version']}, "
                               f"expected {FORMAT} {FORMAT_VERSION}")
    if [str(x) for x in arrays["outputs"]] != list(TARGETS):
        raise PredictionsError(f"{path}: outputs {list(arrays['outputs'])} are not "
                               f"{list(TARGETS)}")
    n = len(arrays["indices"])
    for key, shape in SHAPES.items():
        expected = tuple(n if d == "n" else d for d in shape)
        if arrays[key].shape != expected:
            raise PredictionsError(f"{path}: '{key}' has shape {arrays[key].shape}, expected "
                                   f"{expected}")
    if arrays["pred"].dtype != np.float32 or arrays["truth"].dtype.kind != "f" \
            or arrays["defined"].dtype != bool or arrays["indices"].dtype.kind not in "iu":
        raise PredictionsError(f"{path}: wrong array types (pred float32, truth float, "
                               f"defined bool, indices integer)")
    try:
        item["context"] = json.loads(item["context"])
    except ValueError as error:
        raise PredictionsError(f"{path}: 'context' is not JSON ({error})") from None
    return arrays, item


def load(path):
    """A predictions file as a ``RowFile``: its identity (``name``, ``row``,
    ``seed``, ``table``, ``table_number``, ``rig``, ``rig_index``, ...), its
    ``context`` (dict) and ``raw``, the row as the table code scores it.
    PredictionsError (one line, naming the file) if it is missing, unreadable
    or inconsistent."""
    path = os.fspath(path)
    arrays, item = _read(path)
    n = len(arrays["indices"])
    column = lambda key, kind: {k: arrays[key][:, i].astype(kind)  # noqa: E731
                                for i, k in enumerate(TARGETS)}
    raw = {"source": item["source"], "as_released": bool(item["as_released"]),
           "indices": arrays["indices"].astype(np.int64), "truth": column("truth", np.float64),
           "pred": column("pred", np.float64), "defined": column("defined", bool)}
    if item["row"] == "Geometric":
        for key in ("failure_flags", "failures", "prior_names", "prior_values", "degenerate"):
            if key not in arrays:
                raise PredictionsError(f"{path}: a Geometric row without '{key}'")
        flags = [str(f) for f in arrays["failure_flags"]]
        if arrays["failures"].shape != (n, len(flags)):
            raise PredictionsError(f"{path}: 'failures' has shape {arrays['failures'].shape}")
        raw["statuses"] = [dict(zip(flags, map(bool, line))) for line in arrays["failures"]]
        raw["priors"] = {str(k): float(v) for k, v in zip(arrays["prior_names"],
                                                          arrays["prior_values"])}
        raw["degenerate"] = [str(k) for k in arrays["degenerate"]]
    fields = {k: v for k, v in item.items()
              if k not in ("format", "format_version", "as_released")}
    try:
        return RowFile(**fields, raw=Row(**raw), path=path)
    except RowError as error:
        raise PredictionsError(f"{path}: {error}") from None
