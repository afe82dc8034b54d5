"""The project's stereo dataset file: one HDF5 file per dataset.

Layout (``SCHEMA_VERSION`` 1)::

    /left, /right        uint8 (N, H, W, 3), RGB, one chunk per sample, gzip
    /labels/<name>       float32 (N,) for every name in REQUIRED_LABELS (and
                         any extra ones), attrs: unit, description
    /labels/config_id    int32 (N,)  rig configuration
    /labels/town_id      int32 (N,)  scene / town
    /labels/frame_index  int32 (N,)  frame along the drive
    /labels/<flag>       int32 (N,)  other integer labels named by the writer's
                         ``int_labels`` (e.g. the generator's sky_at_release_pixel)
    root attrs           schema_version, num_pairs, image_height, image_width,
                         and the generator's metadata (``metadata_json``);
                         a resumable writer's files also ``pairs_complete``

Files made by ``cpl_keras.data.generate`` carry its ``generator_version`` in
the metadata; ``StereoFile`` refuses one whose major version differs from the
installed generator's (the labels changed meaning), saying how to regenerate it.

Writes go to ``<path>.partial`` and are renamed to ``path`` only when the
writer closes without error, so an interrupted write never leaves a file
that looks complete. A resumable writer (the generator's) keeps the
``.partial`` file of an interrupted or crashed write, with the number of
leading pairs written in full (``pairs_complete``, flushed after each
block), and the next writer of the same path and settings continues it.
``StereoFile`` opens and validates a file, reporting a problem as a
one-line ``DatasetError`` that names it.
"""

from __future__ import annotations

import contextlib
import json
import os

import numpy as np

from cpl_keras.camera import TARGETS, UNITS
from cpl_keras.errors import Error
from cpl_keras.files import _unfinished, abandon, commit, write_failed

SCHEMA_VERSION = 1

#: Labels every dataset must carry: the 13 targets, the projection pixel and
#: the release's disparity.
REQUIRED_LABELS = TARGETS + ("u", "v", "disparity_released")
#: Integer bookkeeping labels.
INDEX_LABELS = ("config_id", "town_id", "frame_index")
#: The smallest share of its raw bytes that gzip leaves of a rendered or
#: real image (measured: 44-47 % at 112 px, 28-33 % at 512 px), with the
#: chunk index's bytes of a pair: ``min_bytes_per_pair``.
GZIP_FLOOR = 0.25
INDEX_BYTES_PER_PAIR = 100
#: The settings a resumed file must share with its writer's metadata, said
#: by name when they differ (every other metadata key must match too, but
#: ``command_line``, which may differ).
RESUME_KEYS = ("protocol", "pairs", "seed", "image_size", "generator_version")


class DatasetError(Error):
    """A dataset file is missing, unreadable or malformed (one-line message)."""


def _h5py():
    import h5py

    return h5py


def min_bytes_per_pair(image_size, labels):
    """The fewest bytes a pair of ``image_size`` (side, or (h, w)) with
    ``labels`` labels can take in a file: its two images gzip-compressed to
    ``GZIP_FLOOR`` of their raw size, float32/int32 labels and the chunk
    index. An estimate of a file's size from below: a file that needs more
    than the free space at this rate cannot fit."""
    h, w = (image_size, image_size) if np.isscalar(image_size) else image_size
    return 2 * h * w * 3 * GZIP_FLOOR + 4 * labels + INDEX_BYTES_PER_PAIR


class StereoWriter:
    """Writes a dataset of ``num_pairs`` stereo pairs, atomically.

    Use as a context manager; ``write(start, left, right, labels)`` stores a
    block of pairs at ``start``. Labels are float32 except ``INDEX_LABELS`` and
    the names in ``int_labels`` (int32); ``label_units`` adds units to
    ``camera.UNITS``. On a clean exit the file is renamed into
    place; on an exception the partial file is deleted.

    ``resumable``: the partial file of an exception other than a failed
    write (a Ctrl-C, a crash of the caller) is closed and kept when it
    holds a complete pair. On entry, a partial file with the same metadata
    (every key but ``command_line``) and shape is continued: ``resumed_at``
    is then the number of leading pairs it holds in full, which the caller
    need not write again. One of other settings is refused with a
    ``DatasetError`` unless ``restart``, which discards it; one that cannot
    be read is started again, and ``note`` says so.
    """

    def __init__(self, path, num_pairs, image_size, metadata=None, label_descriptions=None,
                 compression="gzip", compression_opts=1, label_units=None, int_labels=(),
                 resumable=False, restart=False):
        num_pairs = int(num_pairs)
        if num_pairs <= 0:
            raise DatasetError(f"number of pairs must be positive, got {num_pairs}")
        h, w = (image_size, image_size) if np.isscalar(image_size) else image_size
        self.path = os.fspath(path)
        self.tmp_path = self.path + ".partial"
        self.num_pairs = num_pairs
        self.shape = (int(h), int(w), 3)
        self.metadata = dict(metadata or {})
        self.descriptions = dict(label_descriptions or {})
        self.units = {**UNITS, **dict(label_units or {})}
        self.int_labels = set(INDEX_LABELS) | set(int_labels)
        self.resumable, self.restart = bool(resumable), bool(restart)
        self.resumed_at, self.note = 0, None
        self._compression = compression
        self._compression_opts = compression_opts
        self._file = None
        self._written = np.zeros(num_pairs, dtype=bool)
        self._complete = 0  # (leading pairs written in full)

    def __enter__(self):
        h5py = _h5py()
        directory = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(directory):
            raise DatasetError(f"output directory does not exist: {directory}")
        if self.resumable and os.path.exists(self.tmp_path) and self._resume(h5py):
            return self
        if not self.resumable:
            _unfinished.add(self.tmp_path)  # (removed by a Ctrl-C's exit too)
        try:
            self._file = h5py.File(self.tmp_path, "w")
        except OSError as error:
            self._discard()
            raise DatasetError(write_failed(self.path, error)) from None
        f = self._file
        n, (h, w, c) = self.num_pairs, self.shape
        # (held for the file's life: a handle that HDF5 closes on its own,
        # after a failed write, prints an ignored exception)
        self._sets = {side: f.create_dataset(
            side, shape=(n, h, w, c), dtype="uint8", chunks=(1, h, w, c),
            compression=self._compression, compression_opts=self._compression_opts,
        ) for side in ("left", "right")}
        self._labels = f.create_group("labels")
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["num_pairs"] = n
        f.attrs["image_height"] = h
        f.attrs["image_width"] = w
        f.attrs["metadata_json"] = json.dumps(self.metadata, sort_keys=True)
        if self.resumable:
            f.attrs["pairs_complete"] = np.int64(0)
        return self

    def _resume(self, h5py):
        """Open the partial file of an earlier writer to continue it; False
        when it is to be started again instead (``restart``, no complete
        pair in it, or unreadable: ``note``)."""
        complete = None
        if not self.restart:
            try:
                with h5py.File(self.tmp_path, "r") as f:
                    complete = self._check_partial(f)
            except OSError as error:
                if "unable to lock file" in str(error):  # (another writer holds it)
                    raise DatasetError(f"{self.tmp_path} is being written by another "
                                       "process") from None
                complete = None
            if complete is None:
                self.note = (f"{self.tmp_path} cannot be read (an interrupted write); "
                             "starting again from the first pair")
        if not complete:
            try:
                os.remove(self.tmp_path)
            except OSError as error:
                raise DatasetError(write_failed(self.path, error)) from None
            return False
        try:
            self._file = f = h5py.File(self.tmp_path, "r+")
        except OSError as error:
            raise DatasetError(write_failed(self.path, error)) from None
        self._labels = f["labels"]
        self._sets = {"left": f["left"], "right": f["right"],
                      **{name: self._labels[name] for name in self._labels}}
        self._written[:complete] = True
        self._complete = self.resumed_at = complete
        return True

    def _check_partial(self, f):
        """The pairs complete in the open partial file ``f`` (0: none), None
        when it is not whole; ``DatasetError`` when it was written with other
        settings (``RESUME_KEYS`` named)."""
        n = self.num_pairs
        try:
            complete = int(f.attrs["pairs_complete"])
            metadata = json.loads(f.attrs["metadata_json"])
            sets = [f["left"], f["right"]] + list(f["labels"].values())
            whole = (0 <= complete <= n and isinstance(metadata, dict)
                     and f["left"].shape == f["right"].shape == (n,) + self.shape
                     and all(s.shape[0] == n for s in sets)
                     and all(f[side].id.get_num_chunks() >= complete
                             for side in ("left", "right")))
        except (AttributeError, KeyError, OSError, RuntimeError, TypeError, ValueError):
            return None
        if not whole:
            return None
        if complete == 0:
            return 0
        ours = json.loads(json.dumps(self.metadata, sort_keys=True))  # (as stored)
        ours = {k: v for k, v in ours.items() if k != "command_line"}
        theirs = {k: v for k, v in metadata.items() if k != "command_line"}
        if ours != theirs:
            named = [f"{k.replace('_', ' ')} {theirs.get(k)}, not {ours.get(k)}"
                     for k in RESUME_KEYS if theirs.get(k) != ours.get(k)]
            raise DatasetError(
                f"{self.tmp_path} holds an interrupted run of other settings "
                f"({', '.join(named) or 'its metadata differs'}); delete it, or start again "
                "with --restart")
        return complete

    def write(self, start, left, right, labels):
        """Store pairs ``start .. start + len(left)`` with their labels."""
        f = self._file
        left = np.asarray(left)
        right = np.asarray(right)
        stop = start + len(left)
        if left.shape[1:] != self.shape or right.shape != left.shape:
            raise DatasetError(
                f"images must have shape (n, {self.shape[0]}, {self.shape[1]}, 3), "
                f"got {left.shape} and {right.shape}"
            )
        try:
            self._sets["left"][start:stop] = left.astype(np.uint8, copy=False)
            self._sets["right"][start:stop] = right.astype(np.uint8, copy=False)
            for name, values in labels.items():
                values = np.asarray(values)
                if name not in self._sets:
                    dtype = "int32" if name in self.int_labels else "float32"
                    ds = self._labels.create_dataset(name, shape=(self.num_pairs,), dtype=dtype)
                    if name in self.units:
                        ds.attrs["unit"] = self.units[name]
                    if name in self.descriptions:
                        ds.attrs["description"] = self.descriptions[name]
                    self._sets[name] = ds
                self._sets[name][start:stop] = values
            f.flush()  # (a full disk shows at this block, not at the end)
            self._written[start:stop] = True
            if self.resumable:
                self._record_complete()
        except (OSError, RuntimeError) as error:
            self._abandon()
            raise DatasetError(write_failed(self.path, error)) from None

    def _record_complete(self):
        """Record in the file how many leading pairs are written in full
        (once their bytes are flushed: a kill between the two leaves the
        count behind, never ahead)."""
        rest = self._written[self._complete:]
        complete = self._complete + (len(rest) if rest.all() else int(rest.argmin()))
        if complete != self._complete:
            self._complete = complete
            self._file.attrs.modify("pairs_complete", np.int64(complete))
            self._file.flush()

    def __exit__(self, exc_type, exc, tb):
        f = self._file
        if f is None:  # (abandoned after a failed write)
            return False
        try:
            self._sets = self._labels = None
            f.close()  # (HDF5 writes its cached chunks and metadata here)
            self._file = None
        except Exception as error:  # a full disk, say: the file is not whole
            self._abandon()
            if exc_type is None:
                raise DatasetError(write_failed(self.path, error)) from None
            return False
        if exc_type is not None:
            if not (self.resumable and self._complete > 0):
                self._discard()  # (else kept, closed, for the next writer to continue)
            return False
        if not self._written.all():
            missing = int((~self._written).sum())
            self._discard()
            raise DatasetError(f"{missing} of {self.num_pairs} pairs were never written")
        try:
            commit(self.tmp_path, self.path)
        except OSError as error:
            self._discard()
            raise DatasetError(write_failed(self.path, error)) from None
        finally:
            _unfinished.discard(self.tmp_path)
        return False

    def _abandon(self):
        """After a failed write: the temporary file removed, its HDF5 handles
        kept open for the rest of the process (closing them would write
        again, print an ignored exception for each, and crash libhdf5 at
        exit), and the process marked to end without the interpreter's
        teardown (``files.abandon``)."""
        abandon(self._file, self._sets, self._labels)
        self._file = None
        self._discard()

    def _discard(self):
        """Remove the temporary file (nothing appears under the final name)."""
        _unfinished.discard(self.tmp_path)
        with contextlib.suppress(OSError):
            os.remove(self.tmp_path)


def _has_hdf5_signature(path):
    """Whether ``path`` starts like an HDF5 file (its signature at byte 0, or
    at 512, 1024, ... after a user block)."""
    signature = b"\x89HDF\r\n\x1a\n"
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as f:
            offset = 0
            while offset + len(signature) <= size:
                f.seek(offset)
                if f.read(len(signature)) == signature:
                    return True
                offset = 512 if offset == 0 else offset * 2
    except OSError:
        pass
    return False


GENERATOR = "cpl_keras.data.generate"
#: The data generator's format version (its labels' meaning): a file made by
#: another major version is refused (``check_generator_version``). Kept with
#: the storage format; ``cpl_keras.data.generate`` writes it into every file.
GENERATOR_VERSION = "3.0"


def _major(version):
    try:
        return int(str(version).split(".")[0])
    except ValueError:
        return None


def check_generator_version(path, metadata):
    """Raise ``DatasetError`` (one line) if ``metadata`` says the file was made
    by another major version of the data generator than the installed one.
    Files from other writers (real data, tests) are not checked."""
    if metadata.get("generator") != GENERATOR:
        return
    version = metadata.get("generator_version")
    found, current = _major(version), _major(GENERATOR_VERSION)
    if found == current:
        return
    command = (f"python -m cpl_keras.data.generate --protocol {metadata.get('protocol', 'cvgl')} "
               f"--pairs {metadata.get('pairs', 'N')} --seed {metadata.get('seed', 0)} "
               f"--image-size {metadata.get('image_size', 112)} --out {path}")
    age = "a newer" if found is not None and found > current else "an older"
    raise DatasetError(
        f"{path}: dataset format {version} is {age} format than this generator's "
        f"{GENERATOR_VERSION} (its labels differ); regenerate it: {command}")


class StereoFile:
    """A validated, read-only view of a dataset file.

    Labels are loaded into memory (a few floats per pair); images are read on
    demand with ``read_pairs``, so memory does not grow with the dataset.
    """

    def __init__(self, path, required_labels=REQUIRED_LABELS):
        h5py = _h5py()
        self.path = os.fspath(path)
        if not os.path.exists(self.path):
            raise DatasetError(f"dataset not found: {self.path}")
        if not os.path.isfile(self.path):
            raise DatasetError(f"dataset is not a file: {self.path}")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as error:
            if _has_hdf5_signature(self.path):
                raise DatasetError(
                    f"HDF5 file is truncated or corrupt: {self.path} "
                    f"({' '.join(str(error).split())})") from None
            raise DatasetError(f"not an HDF5 file: {self.path}") from None
        try:
            self._validate(required_labels)
        except Exception:
            self._file.close()
            raise

    def _validate(self, required_labels):
        h5py = _h5py()
        f = self._file
        for side in ("left", "right"):
            if side not in f:
                raise DatasetError(f"{self.path}: missing image array '/{side}'")
            if not isinstance(f[side], h5py.Dataset):
                raise DatasetError(f"{self.path}: '/{side}' is not an array")
        left, right = f["left"], f["right"]
        if left.ndim != 4 or left.shape[-1] != 3 or left.dtype != np.uint8:
            raise DatasetError(
                f"{self.path}: '/left' must be uint8 (N, H, W, 3), got {left.dtype} {left.shape}"
            )
        if right.shape != left.shape or right.dtype != left.dtype:
            raise DatasetError(
                f"{self.path}: '/right' {right.shape} does not match '/left' {left.shape}"
            )
        self.num_pairs = int(left.shape[0])
        self.image_shape = tuple(int(s) for s in left.shape[1:])
        if self.num_pairs == 0:
            raise DatasetError(f"{self.path}: dataset holds no pairs")
        if "labels" not in f or not isinstance(f["labels"], h5py.Group):
            raise DatasetError(f"{self.path}: missing label group '/labels'")
        group = f["labels"]
        self.labels = {}
        for name in group:
            item = group[name]
            if not isinstance(item, h5py.Dataset) or item.dtype.kind not in "fiub":
                raise DatasetError(f"{self.path}: label '{name}' is not a numeric array")
            values = item[()]
            if values.shape != (self.num_pairs,):
                raise DatasetError(
                    f"{self.path}: label '{name}' has shape {values.shape}, "
                    f"expected ({self.num_pairs},)"
                )
            if not np.all(np.isfinite(values)):
                bad = int((~np.isfinite(values)).sum())
                raise DatasetError(f"{self.path}: label '{name}' has {bad} non-finite values")
            self.labels[name] = values
        missing = [name for name in required_labels if name not in self.labels]
        if missing:
            raise DatasetError(f"{self.path}: missing label(s) {', '.join(missing)}")
        try:
            self.metadata = json.loads(f.attrs.get("metadata_json", "{}"))
        except json.JSONDecodeError:
            raise DatasetError(f"{self.path}: metadata is not valid JSON") from None
        if not isinstance(self.metadata, dict):
            raise DatasetError(f"{self.path}: metadata is not a JSON object")
        check_generator_version(self.path, self.metadata)

    def read_pairs(self, indices):
        """Left and right images (uint8, (n, H, W, 3)) of ``indices``, in that order."""
        indices = np.asarray(indices, dtype=np.int64)
        if indices.size == 0:
            empty = np.zeros((0,) + self.image_shape, np.uint8)
            return empty, empty.copy()
        if indices.min() < 0 or indices.max() >= self.num_pairs:
            raise DatasetError(f"{self.path}: pair index out of range")
        order = np.argsort(indices, kind="stable")
        sorted_idx = indices[order]
        unique, inverse = np.unique(sorted_idx, return_inverse=True)
        out = []
        for side in ("left", "right"):
            block = self._file[side][unique]          # h5py needs increasing indices
            images = np.empty((len(indices),) + self.image_shape, np.uint8)
            images[order] = block[inverse]
            out.append(images)
        return out[0], out[1]

    def close(self):
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def __len__(self):
        return self.num_pairs
