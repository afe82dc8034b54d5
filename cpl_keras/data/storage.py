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

A file whose ``schema_version`` is not ``SCHEMA_VERSION`` (another layout)
is refused in one line; one without the attribute (written before it, or
by hand) is read as version 1. Files made by ``cpl_keras.data.generate``
carry its ``generator_version`` in the metadata; ``StereoFile`` refuses one whose major version differs from the
installed generator's (the labels changed meaning), saying how to regenerate it.

Files are written by ``cpl_keras.data.writer.StereoWriter`` (atomically,
and resumably for the generator). ``StereoFile`` opens and validates a
file, reporting a problem as a one-line ``DatasetError`` that names it.
"""

from __future__ import annotations

import json
import os

import numpy as np

from cpl_keras.camera import TARGETS
from cpl_keras.errors import Error

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

    def _check_schema(self, f):
        """``DatasetError`` unless the file's ``schema_version`` is this
        reader's (a file without one is taken as version 1)."""
        version = f.attrs.get("schema_version", SCHEMA_VERSION)
        try:
            known = int(version) == SCHEMA_VERSION and float(version) == int(version)
        except (TypeError, ValueError):
            known = False
        if not known:
            said = version.decode(errors="replace") if isinstance(version, bytes) else version
            newer = isinstance(said, (int, np.integer)) and said > SCHEMA_VERSION
            raise DatasetError(
                f"{self.path}: dataset schema version {said!s:.40} is not this reader's "
                f"{SCHEMA_VERSION}" + ("; a newer cpl-keras wrote it: update cpl-keras to "
                                       "read it" if newer else " (not a layout it knows)"))

    def _validate(self, required_labels):
        h5py = _h5py()
        f = self._file
        self._check_schema(f)
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
        self._check_finished(f)
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
        # (a file imported from the authors' release stores some of them as
        # released only: <name>_released, cpl_keras.data.import_cvgl)
        missing = [name for name in required_labels
                   if name not in self.labels and f"{name}_released" not in self.labels]
        if missing:
            raise DatasetError(f"{self.path}: missing label(s) {', '.join(missing)}")
        try:
            self.metadata = json.loads(f.attrs.get("metadata_json", "{}"))
        except json.JSONDecodeError:
            raise DatasetError(f"{self.path}: metadata is not valid JSON") from None
        if not isinstance(self.metadata, dict):
            raise DatasetError(f"{self.path}: metadata is not a JSON object")
        check_generator_version(self.path, self.metadata)
        #: Whether the file holds the release's labels only where the project's
        #: are not derivable (``cpl_keras.data.import_cvgl``): as released only.
        self.as_released_only = bool(self.metadata.get("as_released_only", False))

    def _check_finished(self, f):
        """``DatasetError`` for the ``.partial`` file of a generation that has
        not finished (its ``pairs_complete`` short of its pairs): its other
        pairs are zeros, its labels there zeros too."""
        try:
            complete = int(f.attrs["pairs_complete"])
        except (KeyError, TypeError, ValueError):
            return  # (not a resumable writer's file)
        if complete >= self.num_pairs:
            return
        try:
            command = json.loads(f.attrs["metadata_json"]).get("command_line")
        except (KeyError, TypeError, ValueError, AttributeError):
            command = None
        finish = f"the command that made it ({command})" if command else "the call that made it"
        raise DatasetError(
            f"{self.path} is an unfinished dataset ({complete} of {self.num_pairs} pairs "
            f"written): finish it with {finish}, then use the file without .partial")

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
