"""Stage 3 of the reproduction: the published predictions of every table,
group by group (one table of one seed), reused or computed and written;
and the record's checksums of them.

``reproduce.json`` keeps each published predictions file's checksum
(``CHECKSUMS``: the sha256 of its arrays, ``prediction_files.checksum``).
A run of the reproduction over its published folder reuses a group's files
only when they still hold what the record was made from; one changed since
(by hand) is named in one line and its group computed again (a file whose
arrays then differ goes beside the record, into ``rerun/``:
``prediction_files.write_group``). ``record_changed`` tells whether what
was written changes the record at all: when it does not, the reproduction
writes none of its pages."""

from __future__ import annotations

import json
import os

from cpl_keras import evaluation, prediction_files, runs, table_files
from cpl_keras.data.storage import StereoFile
from cpl_keras.files import read_json
from cpl_keras.reproduce.presets import log

#: The reproduction's summary, beside REPORT.md.
SUMMARY = "reproduce.json"
#: The summary's key of the published predictions' checksums
#: (``{path relative to the folder: sha256 of its arrays}``).
CHECKSUMS = "predictions_sha256"


def checksums(paths, out_dir):
    """``{path relative to out_dir: its arrays' sha256}`` of the predictions
    files ``paths``, as the summary records them."""
    return {runs.relative(p, out_dir): prediction_files.checksum(p) for p in paths}


def recorded_checksums(out_dir):
    """The checksums ``out_dir``'s summary recorded, or None (no summary, an
    unreadable one, or one written before they were recorded)."""
    try:
        summary = read_json(os.path.join(out_dir, SUMMARY))
    except (OSError, ValueError):
        return None
    found = summary.get(CHECKSUMS) if isinstance(summary, dict) else None
    return found if isinstance(found, dict) else None


def changed_since_recorded(paths, out_dir, recorded):
    """The files of ``paths`` (relative to ``out_dir``) of which the record
    ``recorded`` (``recorded_checksums``) has a checksum, and that no longer
    hold what it was made from."""
    found = []
    for path in paths:
        name = runs.relative(path, out_dir)
        if name in (recorded or {}) and prediction_files.checksum(path) != recorded[name]:
            found.append(name)
    return found


def record_changed(files, written, out_dir, recorded):
    """Whether the reproduction's predictions files ``files``, of which it
    wrote ``written`` into the folder, change the record ``recorded``
    (``recorded_checksums``): other files than it lists, or a file written
    that is not the one recorded (a record of before its checksums: any
    file written). Files changed since by hand, and left as they are, do
    not."""
    if recorded is None:
        return bool(written)
    if {runs.relative(p, out_dir) for p in files} != set(recorded):
        return True
    return any(recorded.get(name) != digest
               for name, digest in checksums(written, out_dir).items())


def _reusable(expected, key, run_dirs, out_dir, recorded, stem):
    """Whether the group's files ``expected`` are reused: all there, made
    from the same runs, data and settings (``key``) after the runs' models
    were written (or the runs restored from their published records: no
    weights, their outputs are the stored ones, and the published files are
    the record), and holding what the record was made from (each file
    changed since is said in one line)."""
    changed = changed_since_recorded([p for p in expected if os.path.exists(p)], out_dir,
                                     recorded)
    for name in changed:
        log(f"{name}: changed since {SUMMARY} recorded it (its arrays' sha256 differs from "
            f"the recorded one); {stem} computed again")
    models = [os.path.join(r, runs.MODEL) for r in run_dirs]
    restored = not any(os.path.exists(m) for m in models)
    return not changed and all(os.path.exists(p) for p in expected) and \
        all(prediction_files.read_key(p) == key for p in expected) and (restored or (
            all(os.path.exists(m) for m in models) and
            min(os.path.getmtime(p) for p in expected)
            >= max(os.path.getmtime(m) for m in models)))


def _group_predictions(number, stem, prefix, run_dirs, data, config, out_dir, suffix,
                       written=None, recorded=None, beside=None):
    """The predictions files of one table of one seed: reused when
    ``_reusable`` (``recorded``: the record's checksums), else computed and
    written (all files or none; a file whose arrays are unchanged is left as
    it is; in a published folder one whose arrays differ goes beside it,
    ``prediction_files.write_group``). ``written`` and ``beside`` (lists)
    get the paths written into the folder and beside it."""
    folder = os.path.join(out_dir, "runs")
    key = json.dumps({"table": stem, "runs": [runs.relative(r, out_dir) for r in run_dirs],
                      "data": [runs.relative(p, out_dir) for p in data] if data else None,
                      "geometric_max": config.geometric_max,
                      "format": prediction_files.FORMAT_VERSION}, sort_keys=True)
    def rows(released_only):   # (no Geometric row on a file of the release's labels only)
        return ["Average", "Average (release bug)"] + list(run_dirs) + (
            [] if released_only else ["Geometric"])

    rigs = [(None, rows(config.data == "release"))] if number == 1 else [
        (os.path.splitext(os.path.basename(p))[0], rows(_released_only(p))) for p in data]
    names = [table_files.file_name(prefix, table_files.row_slug(r, r, suffix), s)
             for s, rig_rows in rigs for r in rig_rows]
    expected = [os.path.join(folder, name) for name in names]
    if _reusable(expected, key, run_dirs, out_dir, recorded, stem):
        log(f"{stem} ({', '.join(os.path.basename(r) for r in run_dirs)}): published "
            f"predictions up to date with their runs, reused")
        return expected
    log(f"evaluating {stem}: {', '.join(os.path.basename(r) for r in run_dirs)}")
    if number == 1:
        context, raw = evaluation.table_rows(1, run_dirs, geometric=True,
                                             geometric_max=config.geometric_max, progress=log)
        files = table_files.table1_files(context, raw, out_dir=out_dir, prefix=prefix, stem=stem,
                                         key=key, suffix=suffix)
    else:
        run_list, rigs = evaluation.table2_rigs(run_dirs, data, geometric=True,
                                                geometric_max=config.geometric_max, progress=log)
        files = table_files.table2_files(run_list, rigs, out_dir=out_dir, prefix=prefix,
                                         stem=stem, key=key, suffix=suffix)
    if sorted(files) != sorted(names):
        raise evaluation.EvaluationError(f"{stem}: predictions files {sorted(files)} are not "
                                         f"the expected {sorted(names)}")
    paths, wrote = prediction_files.write_group(
        folder, {name: files[name] for name in names},
        published=os.path.exists(os.path.join(out_dir, SUMMARY)), log=log, beside=beside)
    if written is not None:
        written.extend(wrote)
    return paths


def _released_only(path):
    with StereoFile(path) as f:
        return f.as_released_only


def make_predictions(config, paths, trained, out_dir, written=None, recorded=None,
                     beside=None):
    """Stage 3: the predictions of every row of every table, for every seed;
    returns their paths (Table 1 per table key, then Table 2). ``recorded``:
    the record's checksums (``recorded_checksums``); ``written`` and
    ``beside`` (lists) get the paths of the files written into ``out_dir``'s
    runs/ and beside it (``_group_predictions``)."""
    groups = []
    for key, by_seed in trained.items():
        for run_seed, run_dirs in by_seed.items():
            groups.append((1, f"table1_{key}", key, run_dirs, None,
                           f"-s{run_seed}" if len(by_seed) > 1 else ""))
    cvgl = trained.get("cvgl", {}) if paths["real"] else {}     # no real sets: no Table 2
    for run_seed, run_dirs in cvgl.items():
        groups.append((2, "table2", "cvgl", run_dirs, paths["real"],
                       f"-s{run_seed}" if len(cvgl) > 1 else ""))
    files = []
    for number, stem, prefix, run_dirs, data, suffix in groups:
        files += _group_predictions(number, stem, prefix, run_dirs, data, config, out_dir, suffix,
                                    written, recorded, beside)
    return files
