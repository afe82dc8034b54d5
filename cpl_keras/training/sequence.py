"""The Keras side of the datasets: ``StereoSequence``, the batches a model
trains and evaluates on (a ``keras.utils.PyDataset``). Everything else about
the datasets (targets, splits, the file's labels) is in ``cpl_keras.datasets``,
which does not import Keras."""

from __future__ import annotations

import os
import threading

import keras
import numpy as np

from cpl_keras.camera import TARGETS
from cpl_keras.data.storage import StereoFile
from cpl_keras.datasets import targets_from_labels
from cpl_keras.training.augment import photometric
from cpl_keras.training_options import AUGMENTATIONS

#: A sequence keeps its images in memory ("auto") when they take at most this
#: many bytes (2 GiB: 27,000 pairs at 112x112).
IN_MEMORY_LIMIT = 2 * 1024**3
#: Pairs read at a time when the images are loaded into memory (a ``close``
#: stops the load between two blocks).
LOAD_BLOCK = 512


class StereoSequence(keras.utils.PyDataset):
    """Batches of stereo pairs and their 13 targets, read from an HDF5 file.

    Each item is ``({"left_image", "right_image"}, {target: (b, 1)})``,
    images float32 RGB 0..255 (the model scales its own inputs). The
    images are kept in memory or streamed batch by batch (``in_memory``).

    Args:
        path: the dataset file (``cpl_keras.data.storage`` schema).
        indices: the pairs this sequence serves (e.g. ``split["train"]``).
        targets: dict name -> (N,) float32 over the whole file, as from
            ``targets_from_labels``; ``None`` reads the stored targets.
        batch_size: pairs per batch.
        shuffle: reshuffle ``indices`` every epoch. The order of epoch
            ``e`` depends only on ``(seed, e)``, so a resumed run sees the
            same batches as an uninterrupted one (``set_epoch``).
        seed: seed of the shuffles.
        multiple_of: every batch size is made a multiple of this (the
            device count under data parallelism): the last batch is
            padded with pairs from the start of the epoch's order.
        workers, use_multiprocessing, max_queue_size: as for
            ``keras.utils.PyDataset``.
        in_memory: keep the images of ``indices`` in memory (uint8),
            read once in index order on first use (True), stream every
            batch from the file (False), or keep them when they take at
            most ``IN_MEMORY_LIMIT`` bytes ("auto", the default). Random
            batches of a gzip-compressed file read at about 190 pairs/s
            on one core, slower than the compact backbone trains; the
            batches are the same either way.
        part: None, or in a process group the function that takes this
            process's share of a batch (``training.processes.Group.part``,
            handed over by the trainer): every batch is then this process's
            part of the global batch of ``batch_size`` pairs (the
            ``process_id``-th of ``num_processes`` equal slices), from the
            same order on every process.
        augment: None (the images as stored) or ``"photometric"``
            (``cpl_keras.training.augment.photometric``, drawn from the seed, the
            epoch and the batch index: the same batch whenever it is
            served).
    """

    def __init__(self, path, indices, targets=None, batch_size=16, shuffle=False,
                 seed=0, multiple_of=1, workers=1, use_multiprocessing=False,
                 max_queue_size=10, in_memory="auto", augment=None, part=None):
        super().__init__(workers=workers, use_multiprocessing=use_multiprocessing,
                         max_queue_size=max_queue_size)
        self.path = os.path.abspath(os.fspath(path))
        self.indices = np.asarray(indices, dtype=np.int64)
        if self.indices.ndim != 1 or len(self.indices) == 0:
            raise ValueError("indices must be a non-empty 1-D array")
        multiple_of = int(multiple_of)
        batch_size = int(batch_size)
        if batch_size <= 0 or multiple_of <= 0:
            raise ValueError("batch_size and multiple_of must be positive")
        self.multiple_of = multiple_of
        self.batch_size = -(-batch_size // multiple_of) * multiple_of
        self.shuffle = bool(shuffle)
        self.seed = int(seed)
        self.epoch = 0
        self._file = None
        self._pid = None
        self._lock = threading.Lock()
        self._closed = False
        if targets is None:
            with StereoFile(self.path) as f:
                targets = targets_from_labels(f.labels)
        self.targets = {name: np.asarray(targets[name], np.float32) for name in TARGETS}
        size = len(self.targets[TARGETS[0]])
        if self.indices.min() < 0 or self.indices.max() >= size:
            raise ValueError("indices out of range of the targets")
        if in_memory not in (True, False, "auto"):
            raise ValueError(f"in_memory must be True, False or 'auto', got {in_memory!r}")
        self._unique = np.unique(self.indices)
        if in_memory == "auto":
            with StereoFile(self.path) as f:
                pair_bytes = 2 * int(np.prod(f.image_shape))
            in_memory = len(self._unique) * pair_bytes <= IN_MEMORY_LIMIT
        self.in_memory = bool(in_memory)
        self._images = None
        if augment is not None and augment not in AUGMENTATIONS:
            raise ValueError(f"augment must be None or one of {', '.join(AUGMENTATIONS)}, "
                             f"got {augment!r}")
        self.augment = augment
        if part is not None:
            part(np.arange(self.batch_size))  # (ValueError unless a batch splits evenly)
        self.part = part

    # -- keras.utils.PyDataset -------------------------------------------
    @property
    def num_batches(self):
        return -(-len(self.indices) // self.batch_size)

    def __len__(self):
        return self.num_batches

    def __getitem__(self, index):
        if not 0 <= index < self.num_batches:
            raise IndexError(f"batch {index} out of range")
        batch = self.batch_indices(index)
        if self.part is not None:
            batch = self.part(batch)
        if self.in_memory:
            left_all, right_all = self._cached_images()
            rows = np.searchsorted(self._unique, batch)
            left, right = left_all[rows], right_all[rows]
        else:
            left, right = self._stereo_file().read_pairs(batch)
        if self.augment == "photometric":
            left, right = photometric(left, right,
                                      np.random.default_rng([self.seed, self.epoch, index]))
        x = {"left_image": left.astype(np.float32), "right_image": right.astype(np.float32)}
        y = {name: values[batch][:, None] for name, values in self.targets.items()}
        return x, y

    def on_epoch_end(self):
        # Called after the epoch's worker threads have stopped; shuffling in
        # on_epoch_begin would race with the prefetching of the next epoch.
        # (Training sets the epoch explicitly with ``set_epoch``.)
        self.epoch += 1

    # -- helpers -----------------------------------------------------------
    def set_epoch(self, epoch):
        """Serve the order of epoch ``epoch`` next (used when resuming)."""
        self.epoch = int(epoch)

    def order(self, epoch=None):
        """The pair order of an epoch (the indices, shuffled if enabled)."""
        epoch = self.epoch if epoch is None else int(epoch)
        if not self.shuffle:
            return self.indices
        cached = getattr(self, "_order_cache", None)
        if cached is None or cached[0] != epoch:
            rng = np.random.default_rng([self.seed, epoch])
            cached = (epoch, self.indices[rng.permutation(len(self.indices))])
            self._order_cache = cached  # one permutation per epoch, not per batch
        return cached[1]

    def batch_targets(self, index):
        """The targets of the whole batch ``index`` (every process's part)."""
        batch = self.batch_indices(index)
        return {name: values[batch][:, None] for name, values in self.targets.items()}

    def batch_indices(self, index):
        """Pair indices of batch ``index`` of the current epoch."""
        order = self.order()
        batch = order[index * self.batch_size:(index + 1) * self.batch_size]
        short = (-len(batch)) % self.multiple_of
        if short:
            batch = np.concatenate([batch, np.resize(order, short)])
        return batch

    def _cached_images(self):
        """The images of every index of this sequence (uint8, in the order
        of ``np.unique(indices)``), read on first use in blocks of
        increasing indices (far faster than random batches). A ``close``
        stops the load at the next block."""
        with self._lock:
            if self._images is None:
                self._check_open()
                f = StereoFile(self.path)
                try:
                    shape = (len(self._unique),) + f.image_shape
                    left, right = np.empty(shape, np.uint8), np.empty(shape, np.uint8)
                    for start in range(0, len(self._unique), LOAD_BLOCK):
                        self._check_open()
                        block = self._unique[start:start + LOAD_BLOCK]
                        left[start:start + len(block)], right[start:start + len(block)] = \
                            f.read_pairs(block)
                finally:
                    f.close()
                self._images = (left, right)
            return self._images

    def _stereo_file(self):
        # One handle per process; h5py serialises access between threads.
        with self._lock:
            self._check_open()
            if self._file is None or self._pid != os.getpid():
                self._file = StereoFile(self.path)
                self._pid = os.getpid()
            return self._file

    def _check_open(self):
        if self._closed:
            raise ValueError(f"the sequence of {self.path} is closed")

    def close(self):
        """Close the dataset file and read no more from it: a thread that
        loads the images into memory stops at its next block (training's
        Ctrl-C waited for the whole load, then ``cli.run`` ended the process
        without the resume line), and a reading thread that Keras left
        running cannot open the file again (HDF5 would then close it in
        the interpreter's teardown). Batches held in memory stay served."""
        self._closed = True
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_file"] = None
        state["_lock"] = None
        state["_images"] = None  # (a worker process reads its own)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()
