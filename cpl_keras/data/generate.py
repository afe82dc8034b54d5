"""Generate a synthetic CVGL-style stereo dataset (library function and CLI).

Usage::

    python -m cpl_keras.data.generate --protocol cvgl --pairs 10000 --out data/cvgl.h5
    python -m cpl_keras.data.generate --protocol random --pairs 64 --preview runs/sheet.png

Each pair is rendered and labelled by ``cpl_keras.data.pair`` (the paper's
13 targets, and what the release's labels need beside them). Pairs are
rendered in blocks by worker processes (``cpl_keras.data.blocks``) and
written in order through ``writer.StereoWriter`` (atomic: a killed run
leaves no file at the final path); pair i depends only on (seed, i), so the
bytes do not depend on the number of workers. An interrupted or crashed run
keeps ``<out>.partial`` with its complete blocks, and the same call
continues it from the first incomplete one (the same bytes as a run never
interrupted). Before any work, the file's size and the tables held in
memory are checked against what this machine has free (``check_room``).
The CLI prints a one-line ``summary_text``; ``--preview`` draws a contact
sheet of a few pairs (``cpl_keras.data.preview``).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

import numpy as np
from filelock import FileLock, Timeout

from cpl_keras import camera, cli, files
from cpl_keras.cli import check_interrupt, check_output_file, make_parent
from cpl_keras.data import pixels, protocols, scenes
from cpl_keras.data.blocks import iter_blocks
from cpl_keras.data.pair import EXTRA_UNITS, FLOAT_LABELS, INT_LABELS, LABEL_DESCRIPTIONS
from cpl_keras.data.storage import GENERATOR_VERSION  # noqa: F401  (the generator's own)
from cpl_keras.data.storage import DatasetError, StereoFile, min_bytes_per_pair
from cpl_keras.data.writer import StereoWriter

MIN_IMAGE_SIZE = 16
MAX_IMAGE_SIZE = 1024
#: Memory held from the start, per pair (the writer's record of written
#: pairs) and per rig of a protocol that draws one every few pairs (its
#: configuration, in the parent and in every worker, and the metadata's
#: JSON: measured about 7.6 KB at most in the parent): ``check_room``.
BYTES_PER_PAIR_HELD = 1
BYTES_PER_RIG_HELD = 8000


# ---------------------------------------------------------------------------
# The dataset
# ---------------------------------------------------------------------------
def _check_int(name, value, minimum, maximum=None):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum or (maximum is not None and value > maximum):
        bound = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"
        raise ValueError(f"{name} must be {bound}, got {value}")
    return int(value)


def check_output_path(out):
    """The output path as a string, or ValueError if it cannot be written
    (missing folders are fine: they are created when the file is written)."""
    return check_output_file(out)


def check_arguments(protocol, pairs, seed, image_size, workers):
    """``(pairs, seed, image_size, workers)`` checked (ValueError naming the bad one)."""
    protocols.check_protocol(protocol)
    pairs = _check_int("pairs", pairs, 1)
    seed = _check_int("seed", seed, 0, 2**63 - 1)
    image_size = _check_int("image_size", image_size, MIN_IMAGE_SIZE, MAX_IMAGE_SIZE)
    if workers is not None:
        workers = _check_int("workers", workers, 1)
    return pairs, seed, image_size, workers


def metadata(protocol, pairs, seed, image_size, command_line=None):
    """The dataset's metadata dict (JSON-able)."""
    return {
        "protocol": protocol, "seed": seed, "pairs": pairs, "image_size": image_size,
        "generator": "cpl_keras.data.generate", "generator_version": GENERATOR_VERSION,
        "towns": [scenes.make_town(i).describe() for i in range(len(scenes.TOWNS))],
        "ranges": protocols.ranges(protocol),
        "configurations": protocols.configurations(protocol, seed, pairs, image_size),
        "geometry": "x forward, y left, z up; label extrinsics = right camera pose in the left "
                    "camera frame, P_left = Ry(pitch) P_right + t (no relative yaw or roll); "
                    "pixel centres at integer (u, v)",
        "release_frame": "<name>_released: right-minus-left differences of the camera poses "
                         "in the vehicle frame, CARLA conventions (x forward, y right, z up, "
                         "pitch in degrees positive up); X, Y, Z as released at "
                         "(u_released, v_released) = (W/2, H/2)",
        "sky_distance_m": scenes.SKY_DISTANCE,
        "command_line": command_line,
    }


@contextlib.contextmanager
def _exits_uninterrupted():
    """An ``ExitStack`` whose exits (the worker pool's end, the file's close)
    run with SIGINT ignored, from the moment its block ends: after a Ctrl-C,
    ``cli.run``'s watchdog delivers it again every ``interrupts.REDELIVER_S`` until
    the command has said it was interrupted, and one landing in an exit
    would cut it short. The handler is restored once they have run."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous is None:
        with contextlib.ExitStack() as stack:
            yield stack
        return
    try:
        with contextlib.ExitStack() as stack:
            try:
                yield stack
            finally:
                signal.signal(signal.SIGINT, signal.SIG_IGN)
    finally:
        signal.signal(signal.SIGINT, previous)


def check_room(out, protocol, pairs, image_size, workers, restart=False):
    """Raise ValueError (one line) when the dataset cannot fit: its file in
    the free disk space beside ``out`` (at ``storage.min_bytes_per_pair``,
    an estimate from below; a partial file there counted as written unless
    ``restart``), or
    what is held in memory from the start (``BYTES_PER_PAIR_HELD``, and
    ``BYTES_PER_RIG_HELD`` in the parent and each worker) in the free
    memory. Writes nothing."""
    per_pair = min_bytes_per_pair(image_size, len(FLOAT_LABELS) + len(INT_LABELS))
    partial = out + ".partial"
    written = os.path.getsize(partial) if os.path.isfile(partial) and not restart else 0
    rigs = protocols.num_configs(protocol, pairs)
    cli.check_room(f"{pairs} {protocol} pairs at {image_size} px (at least "
                   f"{cli.size_text(per_pair)} a pair on disk)", out,
                   disk=max(0, pairs * per_pair - written),
                   memory=pairs * BYTES_PER_PAIR_HELD + rigs * BYTES_PER_RIG_HELD * (1 + workers))


#: The settings that make a dataset what it is: a file of other values is
#: another dataset (``existing_dataset``).
DEFINING = ("protocol", "pairs", "seed", "image_size", "generator_version")


def _describe(meta):
    return (f"{meta.get('pairs')} {meta.get('protocol')} pairs at {meta.get('image_size')} px, "
            f"seed {meta.get('seed')}, generator {meta.get('generator_version')}")


def existing_dataset(out, meta, force=False):
    """Whether ``out`` already holds this dataset (same ``DEFINING`` values:
    it is left as it is). A file there of other settings, or one that is not
    a dataset, is refused (ValueError, one line naming both) unless
    ``force``, which replaces it."""
    if force or not os.path.exists(out):
        return False
    try:
        with StereoFile(out) as f:
            old = f.metadata
    except DatasetError as error:
        raise ValueError(f"{out} exists and is not a dataset this can replace ({error}); "
                         f"give --force to replace it, or another --out") from None
    if all(old.get(key) == meta.get(key) for key in DEFINING):
        return True
    raise ValueError(f"{out} holds another dataset ({_describe(old)}), not {_describe(meta)}; "
                     f"give --force to replace it, or another --out")


def generate_file(out, protocol, pairs, seed, image_size, workers, progress, command_line=None,
                  restart=False, log=None, force=False):
    """``generate_dataset`` with its checks first (arguments, the output path,
    a dataset already there: ``existing_dataset``, the disk and memory it
    needs), continuing ``out``'s interrupted ``.partial`` file unless
    ``restart``; returns the path written (or found)."""
    pairs, seed, image_size, workers = check_arguments(protocol, pairs, seed, image_size, workers)
    out = check_output_path(out)
    if workers is None:
        workers = os.cpu_count() or 1
    meta = metadata(protocol, pairs, seed, image_size, command_line)
    if log is None:
        log = (lambda line: print(line, file=sys.stderr)) if progress else (lambda line: None)
    if existing_dataset(out, meta, force):
        log(f"{out} already holds this dataset ({_describe(meta)}); left as it is")
        return out
    check_room(out, protocol, pairs, image_size, workers, restart)

    make_parent(out)
    writer = StereoWriter(out, pairs, image_size, metadata=meta,
                          label_descriptions=LABEL_DESCRIPTIONS, label_units=EXTRA_UNITS,
                          int_labels=INT_LABELS, resumable=True, restart=restart)
    with _exits_uninterrupted() as stack:
        stack.enter_context(writer)
        if writer.note:
            log(writer.note)
        first = writer.resumed_at
        if first:
            log(f"resuming {writer.tmp_path} at pair {first} of {pairs}")
        bar = cli.ProgressBar(pairs, f"{protocol}", progress, done=first)
        # (closing: a failed write ends the worker pool at once, not at exit)
        blocks = stack.enter_context(contextlib.closing(
            iter_blocks(protocol, seed, pairs, image_size, workers, first)))
        stack.callback(bar.close)
        for start, (left, right, labels) in blocks:
            writer.write(start, left, right, labels)
            bar.update(len(left))
            # a Ctrl-C that landed where an exception is swallowed (a callback
            # of h5py's, say) stops here, before the file is committed
            check_interrupt()
        check_interrupt()
    return out


def generate_dataset(out, *, protocol="cvgl", pairs, seed=0, image_size=112, workers=None,
                     progress=True, restart=False, log=None, force=False):
    """Render ``pairs`` stereo pairs and write them to the HDF5 file ``out``.

    ``protocol`` is one of ``PROTOCOLS``; ``workers=None`` uses every core.
    The file is written atomically (``writer.StereoWriter``); the same
    ``seed`` gives the same images and labels whatever ``workers`` is.
    An interruption or a crash keeps ``<out>.partial`` with the blocks
    written in full, and the next call for ``out`` continues it (``log``
    receives a line saying so; default: stderr when ``progress``). A
    partial file of other arguments is refused unless ``restart``, which
    starts again. A finished file already at ``out`` is left as it is when
    it holds this dataset, and refused when it holds another unless
    ``force`` (``existing_dataset``). Returns the path written. Raises
    ``ValueError`` (one line) on bad arguments, or when the file cannot fit
    (``check_room``).
    """
    return generate_file(out, protocol, pairs, seed, image_size, workers, progress,
                         restart=restart, log=log, force=force)


def dataset_name(protocol, pairs, seed, image_size, prefix=""):
    """The file name of a generated dataset,
    ``<prefix><protocol>_<pairs>_<size>px_s<seed>_v<generator version>.h5``.
    The generator's version is in the name, so a file of an older generator
    is never reused (it would be refused): a new one is made beside it."""
    return f"{prefix}{protocol}_{pairs}_{image_size}px_s{seed}_v{GENERATOR_VERSION}.h5"


def cached_dataset(folder, *, protocol, pairs, seed, image_size, prefix="", workers=None,
                   progress=True, log=None):
    """The dataset ``dataset_name(...)`` in ``folder``, generated first when it
    is not there (``log(line)`` says so; an interrupted one is continued from
    its ``.partial`` file). Every dataset the project makes for
    itself (the demonstration run, the reproduction, the learning curves)
    comes through here. Returns its path.

    The generation holds a lock (``<path>.lock``, released when its process
    ends however it ends, and removed once the file is made): another
    process that wants the same file waits for it (``log`` says so, once)
    and then takes the finished file, or makes it itself if the first
    process ended without it. Two demonstration
    runs started together on an empty cache used to make it both at once,
    and the second failed on HDF5's lock of the first's temporary file."""
    path = os.path.join(folder, dataset_name(protocol, pairs, seed, image_size, prefix))
    if os.path.exists(path):
        return path
    problem = files.cannot_write(folder)
    if problem:  # (the lock below cannot be made there: its wait never ended)
        raise OSError(f"cannot make {path}: no file can be made in {folder} ({problem})")
    os.makedirs(folder, exist_ok=True)
    lock = FileLock(path + ".lock")
    try:
        lock.acquire(timeout=0)
    except Timeout:
        if log:
            log(f"waiting for another process making {path}")
        lock.acquire()
    try:
        if not os.path.exists(path):
            if log:
                log(f"generating {pairs} {protocol} pairs at {image_size}px -> {path}")
            generate_dataset(path, protocol=protocol, pairs=pairs, seed=seed,
                             image_size=image_size, workers=workers, progress=progress,
                             log=log)
    finally:
        lock.release()
    if os.path.exists(path):  # (a failed generation leaves it for the others)
        with contextlib.suppress(OSError):
            os.remove(lock.lock_file)
    return path


# ---------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------
def label_summary(labels):
    """Figures about a dataset's label points (dict, JSON-able).

    ``pairs``; ``sky_at_release_pixel``: pairs whose release pixel (W/2, H/2)
    sees the sky; ``projection_fallback``: pairs where no drawn candidate was
    near enough and the nearest pixel was taken; ``beyond_max_distance``:
    label points at least ``pixels.MAX_LABEL_DISTANCE`` from the right
    camera (0 unless a whole image is sky or far); ``distance_median_m``,
    ``distance_max_m``: the label points' distances from the right camera.
    """
    lab = {k: np.asarray(labels[k], np.float64) for k in
           ("fx", "fy", "u0", "v0", "baseline", "disparity", "u", "v")}
    xyz = camera.image_to_camera(lab["fx"], lab["fy"], lab["u0"], lab["v0"], lab["baseline"],
                                 lab["disparity"], lab["u"], lab["v"])
    distance = np.sqrt(sum(np.square(c) for c in xyz))
    return {
        "pairs": int(len(distance)),
        "sky_at_release_pixel": int(np.sum(labels["sky_at_release_pixel"])),
        "projection_fallback": int(np.sum(labels["projection_fallback"])),
        "beyond_max_distance": int(np.sum(distance >= pixels.MAX_LABEL_DISTANCE)),
        "distance_median_m": float(np.median(distance)),
        "distance_max_m": float(distance.max()),
    }


def summary_text(path):
    """One line about the dataset file ``path`` (printed by the CLI)."""
    with StereoFile(path) as data:
        s = label_summary(data.labels)
        h, w, _ = data.image_shape
        protocol = data.metadata.get("protocol")
    n = s["pairs"]
    return (f"{n} {protocol} pairs at {w} px; label points {s['distance_median_m']:.1f} m "
            f"(median), {s['distance_max_m']:.1f} m (max) from the right camera, "
            f"{s['beyond_max_distance']} beyond {pixels.MAX_LABEL_DISTANCE:g} m, "
            f"{s['projection_fallback']} from the fallback (nearest pixel); the release's "
            f"pixel ({w / 2:g}, {h / 2:g}) sees the sky in {s['sky_at_release_pixel']} of {n} "
            f"pairs ({100.0 * s['sky_at_release_pixel'] / n:.1f} %)")


# ---------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------
PROG = "python -m cpl_keras.data.generate"


if __name__ == "__main__":  # the command line: cpl_keras/commands/generate.py
    import runpy

    runpy.run_module("cpl_keras.commands.generate", run_name="__main__")
