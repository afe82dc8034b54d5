"""Import the authors' released CVGL data into the project's dataset format.

Usage::

    python -m cpl_keras.data.import_cvgl RELEASE_DIR --out data/cvgl_release.h5
    python -m cpl_keras.data.import_cvgl RELEASE_DIR --suffix r --out data/tdcb_release.h5

``RELEASE_DIR`` is either of the release's layouts (``release_files``: the
folder of 15 flat ``.npy`` files, or the raw episodes' root; detected). The
file written keeps the release's row order (raw episodes have none: their
frames are shuffled once with ``--seed``, as the release shuffled its rows
before saving them, unseeded), its images in RGB (the release's CVGL
images are BGR), and **the release's 13 labels unchanged** as
``<target>_released`` (``fx_released`` .. ``Z_released``; pitch in degrees
as released, the disparity StereoBM's mean), with the release's
projection pixel as ``u_released``, ``v_released``.

The project's own labels are derived where the release determines them
exactly (``DERIVED``): on the CVGL data the intrinsics and the right
camera's pose in the fixed left camera's frame (pitch, tx, ty, tz,
baseline = tx; ``protocols.cvgl_relative_pose``, the generator's own
conversion) and the rig of each pair (``config_id``). The release cannot
give the true disparity at a projection pixel, the point X, Y, Z it
projects to, nor that pixel (``UNDERIVED``): a file so imported trains and
is scored **as released** only (``train.py --as-released``; Table 1 then
scores all 13 columns against the release's labels); a run without it is
refused in one line. The real sets' files (``--suffix r`` or ``r_cs``) keep
full-resolution intrinsics for 112-pixel images, so none of their labels
is the project's: they are scored as released only too. The file's
metadata says all this (``labels_note``).

Images are read and written in blocks: memory does not grow with
the data (``bench/bench_import.py`` measures it). An interrupted import
keeps ``OUT.partial`` and the same command continues it; an ``--out``
that holds this import is left as it is, any other file there refused.
"""

from __future__ import annotations

import os
import sys

import numpy as np

from cpl_keras import camera, cli
from cpl_keras.data import protocols, release_files
from cpl_keras.data.pair import released_disparity
from cpl_keras.data.release_files import (
    BGR, IMAGE_SIZE, LABEL_FILES, RELEASE_PIXEL, TARGET_OF_FILE, ReleaseError,
)
from cpl_keras.data.storage import DatasetError, StereoFile, min_bytes_per_pair
from cpl_keras.data.writer import StereoWriter

PROG = "python -m cpl_keras.data.import_cvgl"
#: The importer's version (the meaning of the labels it writes).
IMPORTER_VERSION = "1.0"
#: Pairs read and written at a time.
BLOCK = 512
#: The project's labels each set derives from the release's, and those it cannot.
DERIVED = {"": ("fx", "fy", "u0", "v0", "baseline", "tx", "ty", "tz", "pitch", "yaw", "roll",
                "config_id"),
           "r": (), "r_cs": ()}
UNDERIVED = {"": ("disparity", "X", "Y", "Z", "u", "v"),
             "r": camera.TARGETS + ("u", "v"), "r_cs": camera.TARGETS + ("u", "v")}
#: Each set's name in the file's metadata (``source``; ``rig`` for the real ones).
SOURCES = {"": "cvgl-release", "r": "tsinghua-release", "r_cs": "cityscapes-release"}
UNITS = {"fx_released": "px", "fy_released": "px", "u0_released": "px", "v0_released": "px",
         "baseline_released": "m", "disparity_released": "px", "tx_released": "m",
         "ty_released": "m", "tz_released": "m", "X_released": "m", "Y_released": "m",
         "Z_released": "m", "u_released": "px", "v_released": "px"}
INT_LABELS = ("config_id", "town_id", "frame_index")
#: The labels stored as float64: the release's, unchanged.
WIDE_LABELS = tuple(f"{name}_released" for name in camera.TARGETS + ("u", "v"))


def released_name(file):
    """The stored name of the release's label file ``file`` (``p`` -> ``pitch_released``)."""
    return f"{TARGET_OF_FILE[file]}_released"


def labels_note(suffix):
    """What an imported file's labels are, in words (its metadata's ``labels_note``)."""
    underived = ", ".join(UNDERIVED[suffix])
    units = "pitch in degrees" if suffix == "" else "pitch in radians, intrinsics at full resolution"
    return (f"The release's 13 labels unchanged as <target>_released ({units}, disparity as "
            f"released). Not derivable from the release: {underived}. Train and score this file "
            "as released (train.py --as-released): the project's own labels are incomplete.")


def metadata(directory, layout, suffix, pairs, seed, command_line=None):
    """The imported file's metadata (JSON-able)."""
    meta = {"protocol": SOURCES[suffix], "source": SOURCES[suffix], "layout": layout,
            "suffix": suffix, "release_dir": os.path.abspath(directory), "pairs": int(pairs),
            "image_size": IMAGE_SIZE, "importer": "cpl_keras.data.import_cvgl",
            "importer_version": IMPORTER_VERSION, "derived_labels": list(DERIVED[suffix]),
            "underived_labels": list(UNDERIVED[suffix]), "as_released_only": True,
            "labels_note": labels_note(suffix), "command_line": command_line}
    if layout == "episodes":
        meta["shuffle_seed"] = int(seed)
    if suffix:
        meta.update(rig=SOURCES[suffix], rectified=True)
    return meta


def project_labels(released, suffix):
    """The project's labels that ``released`` (the release's labels of
    some rows, keyed by file name) determine exactly (``DERIVED``): the
    intrinsics, the right camera's pose in the left camera's frame and the
    rig id, computed once per distinct rig."""
    if suffix:
        return {}
    rigs = np.stack([released[k] for k in ("fx", "tx", "ty", "tz", "p")], axis=1)
    distinct, config_id = np.unique(rigs, axis=0, return_inverse=True)
    poses = np.array([_pose(*row[1:]) for row in distinct])      # (rigs, 6)
    per_pair = poses[config_id.reshape(-1)]
    out = {k: np.asarray(released[k], np.float64) for k in ("fx", "fy", "u0", "v0")}
    for i, name in enumerate(("pitch", "yaw", "roll", "tx", "ty", "tz")):
        out[name] = per_pair[:, i]
    out["baseline"] = out["tx"]
    out["config_id"] = config_id.reshape(-1).astype(np.int32)
    return out


def _pose(tx, ty, tz, p):
    pitch, yaw, roll, t = protocols.cvgl_relative_pose(
        *protocols.cvgl_carla_from_released(tx, ty, tz, p))
    return (pitch, yaw, roll, *(float(v) for v in t))


def stored_labels(released, suffix):
    """Every label the imported file stores for those rows."""
    n = len(released["fx"])
    out = {released_name(k): np.asarray(released[k], np.float64) for k in LABEL_FILES}
    out["u_released"] = out["v_released"] = np.full(n, RELEASE_PIXEL[suffix])
    return out


# ---------------------------------------------------------------------------
# The two layouts, block by block
# ---------------------------------------------------------------------------
def _flat_blocks(left, right, released, suffix, first, project):
    """``(start, left, right, labels)`` of the flat layout from row ``first``."""
    bgr = BGR[suffix]
    for start in range(first, len(left), BLOCK):
        stop = min(start + BLOCK, len(left))
        rows = {k: v[start:stop] for k, v in released.items()}
        labels = {**stored_labels(rows, suffix),
                  **{k: v[start:stop] for k, v in project.items()}}
        lb, rb = np.asarray(left[start:stop]), np.asarray(right[start:stop])
        if bgr:
            lb, rb = np.ascontiguousarray(lb[..., ::-1]), np.ascontiguousarray(rb[..., ::-1])
        yield start, lb, rb, labels


def _episode_release_labels(frames):
    """The release's labels of every frame (keyed by file name), its images
    read once each for StereoBM's mean, and the frames' bookkeeping labels."""
    rows = []
    for _, _, _, _, left_png, right_png, params in frames:
        left = release_files.read_frame_rgb(left_png)
        right = release_files.read_frame_rgb(right_png)
        rows.append(release_files.episode_labels(params, released_disparity(left, right)))
    released = {k: np.array([row[k] for row in rows], np.float64) for k in LABEL_FILES}
    towns = sorted({f[0] for f in frames})
    index = {"config_id": np.array([f[2] for f in frames], np.int32),
             "town_id": np.array([towns.index(f[0]) for f in frames], np.int32),
             "frame_index": np.array([f[3] for f in frames], np.int32)}
    return released, index


def _episode_blocks(frames, released, project, first):
    for start in range(first, len(frames), BLOCK):
        stop = min(start + BLOCK, len(frames))
        part = frames[start:stop]
        left = np.stack([release_files.read_frame_rgb(f[4]) for f in part])
        right = np.stack([release_files.read_frame_rgb(f[5]) for f in part])
        rows = {k: v[start:stop] for k, v in released.items()}
        yield start, left, right, {**stored_labels(rows, ""),
                                   **{k: v[start:stop] for k, v in project.items()}}


def read_release(directory, suffix="", seed=0):
    """``(layout, n, blocks)``: the release at ``directory`` read and checked
    in full before anything is written; ``blocks(first)`` yields its rows
    from ``first`` on, in the imported file's order."""
    layout = release_files.detect_layout(directory, suffix)
    if layout == "flat":
        left, right, released = release_files.read_flat(directory, suffix)
        project = project_labels(released, suffix)
        return layout, len(left), lambda first: _flat_blocks(
            left, right, released, suffix, first, project)
    frames = release_files.find_episodes(directory)
    order = np.random.default_rng(seed).permutation(len(frames))
    frames = [frames[i] for i in order]
    released, index = _episode_release_labels(frames)
    project = {**project_labels(released, ""), **index}   # (the episodes name their rigs)
    return layout, len(frames), lambda first: _episode_blocks(frames, released, project, first)


def existing_import(out, meta):
    """Whether ``out`` already holds this import (left as it is); a file of
    anything else there is refused (ValueError, one line)."""
    if not os.path.exists(out):
        return False
    keys = ("source", "layout", "release_dir", "pairs", "importer_version", "shuffle_seed")
    try:
        with StereoFile(out) as f:
            same = all(f.metadata.get(k) == meta.get(k) for k in keys)
    except DatasetError as error:
        raise ValueError(f"{out} exists and is not a dataset ({error}); choose another "
                         "--out") from None
    if same:
        return True
    raise ValueError(f"{out} exists and holds another dataset; choose another --out "
                     "(or delete it)")


def import_release(directory, out, suffix="", seed=0, progress=True, command_line=None,
                   log=None):
    """Import the release at ``directory`` into the dataset file ``out``;
    returns ``out``. Bad input raises a one-line ``ReleaseError`` before
    anything is written; an interrupted import keeps ``out.partial`` for the
    same call to continue."""
    if suffix not in release_files.SUFFIXES:
        raise ReleaseError(f"unknown suffix {suffix!r}; choose one of "
                           f"{', '.join(repr(s) for s in release_files.SUFFIXES)}")
    out = cli.check_output_file(out)
    log = log or (lambda line: print(line, file=sys.stderr, flush=True))
    layout, n, blocks = read_release(directory, suffix, seed)
    meta = metadata(directory, layout, suffix, n, seed, command_line)
    if existing_import(out, meta):
        log(f"{out} already holds this import ({n} pairs of {directory}); left as it is")
        return out
    cli.check_room(f"{n} pairs at {IMAGE_SIZE} px", out,
                   disk=n * min_bytes_per_pair(IMAGE_SIZE, 2 * len(LABEL_FILES)))
    cli.make_parent(out)
    writer = StereoWriter(out, n, IMAGE_SIZE, metadata=meta, label_units=UNITS,
                          int_labels=INT_LABELS, resumable=True, wide_labels=WIDE_LABELS,
                          label_descriptions={"u_released": "the release's projection pixel"})
    with writer:
        first = writer.resumed_at
        if first:
            log(f"resuming {writer.tmp_path} at pair {first} of {n}")
        bar = cli.ProgressBar(n, SOURCES[suffix], progress, done=first)
        try:
            for start, left, right, labels in blocks(first):
                writer.write(start, left, right, labels)
                bar.update(len(left))
                cli.check_interrupt()
        finally:
            bar.close()
    return out


if __name__ == "__main__":  # the command line: cpl_keras/commands/import_cvgl.py
    import runpy

    runpy.run_module("cpl_keras.commands.import_cvgl", run_name="__main__")
