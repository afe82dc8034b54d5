"""Writing a dataset file (the schema of ``cpl_keras.data.storage``): ``StereoWriter``.

Writes go to ``<path>.partial`` and are renamed to ``path`` only when the
writer closes without error, so an interrupted write never leaves a file
that looks complete. A resumable writer (the generator's) keeps the
``.partial`` file of an interrupted or crashed write, with the number of
leading pairs written in full (``pairs_complete``, flushed after each
block), and the next writer of the same path and settings continues it.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys

import numpy as np

from cpl_keras.camera import UNITS
from cpl_keras.data.storage import INDEX_LABELS, SCHEMA_VERSION, DatasetError
from cpl_keras.files import abandon, commit, mark_unfinished, unmark_unfinished, write_failed

#: The settings a resumed file must share with its writer's metadata, said
#: by name when they differ (every other metadata key must match too, but
#: ``command_line``, which may differ).
RESUME_KEYS = ("protocol", "pairs", "seed", "image_size", "generator_version")


class StereoWriter:
    """Writes a dataset of ``num_pairs`` stereo pairs, atomically.

    Use as a context manager; ``write(start, left, right, labels)`` stores a
    block of pairs at ``start``. Labels are float32 except ``INDEX_LABELS`` and
    the names in ``int_labels`` (int32) and in ``wide_labels`` (float64: an
    imported release's labels, kept unchanged); ``label_units`` adds units to
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
                 resumable=False, restart=False, wide_labels=()):
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
        self.wide_labels = set(wide_labels)
        self.resumable, self.restart = bool(resumable), bool(restart)
        self.resumed_at, self.note = 0, None
        self._compression = compression
        self._compression_opts = compression_opts
        self._file = None
        self._written = np.zeros(num_pairs, dtype=bool)
        self._complete = 0  # (leading pairs written in full)

    def __enter__(self):
        import h5py

        directory = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(directory):
            raise DatasetError(f"output directory does not exist: {directory}")
        if self.resumable and os.path.exists(self.tmp_path) and self._resume(h5py):
            return self
        if not self.resumable:
            mark_unfinished(self.tmp_path)  # (removed by a Ctrl-C's exit too)
        try:
            self._file = h5py.File(self.tmp_path, "w")
        except BaseException as error:  # (a full disk; a Ctrl-C: nothing left)
            self._discard()
            if isinstance(error, OSError):
                raise DatasetError(write_failed(self.path, error)) from None
            raise
        try:
            self._lay_out(self._file)
        except BaseException:  # (a Ctrl-C, say: no half-made file is left)
            self.__exit__(*sys.exc_info())
            raise
        return self

    def _lay_out(self, f):
        """The new file's datasets and attributes (no pair written yet)."""
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
                    dtype = ("int32" if name in self.int_labels else
                             "float64" if name in self.wide_labels else "float32")
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
            unmark_unfinished(self.tmp_path)
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
        unmark_unfinished(self.tmp_path)
        with contextlib.suppress(OSError):
            os.remove(self.tmp_path)


def pairs_kept(partial_path):
    """The leading pairs that a resumable writer's ``partial_path`` holds
    written in full (its ``pairs_complete``): what the next writer continues
    from; 0 when there is no such file or it cannot be read (the next writer
    starts again)."""
    import h5py

    try:
        with h5py.File(partial_path, "r") as f:
            return max(0, int(f.attrs["pairs_complete"]))
    except (OSError, KeyError, TypeError, ValueError):
        return 0
