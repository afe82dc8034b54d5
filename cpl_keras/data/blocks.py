"""Rendering a dataset's pairs in blocks, in worker processes, in order.

``iter_blocks`` yields the blocks of pairs ``first .. pairs`` in order
(``render_block`` each), rendered by a pool of ``spawn`` worker processes
that ignore Ctrl-C (the parent stops them; one line, no traceback per
worker) and ended, their queues released, however the iteration ends. Pair i
depends only on (seed, i), so neither the number of workers nor where a
resumed file starts changes a pair.
"""

from __future__ import annotations

import contextlib
import gc
import math
import multiprocessing as mp
import signal
import sys
import threading
import traceback
import types
from multiprocessing import resource_tracker

import numpy as np

from cpl_keras.data.pair import FLOAT_LABELS, INT_LABELS, render_pair

BLOCK = 32


def render_block(protocol, seed, pairs, image_size, start, stop):
    """Pairs ``start .. stop``: (left, right, labels) with labels as arrays."""
    lefts, rights, rows = [], [], []
    for i in range(start, stop):
        left, right, labels = render_pair(protocol, seed, pairs, image_size, i)
        lefts.append(left)
        rights.append(right)
        rows.append(labels)
    labels = {k: np.array([r[k] for r in rows], np.float32) for k in FLOAT_LABELS}
    labels.update({k: np.array([r[k] for r in rows], np.int32) for k in INT_LABELS})
    return np.stack(lefts), np.stack(rights), labels


@contextlib.contextmanager
def _sigint_deferred():
    """A Ctrl-C while the block runs (the worker pool's start) is held back
    and delivered to the handler in place when the block ends, so none is
    lost; and the processes started in the block begin with SIGINT blocked
    (a process keeps its signal mask across exec), so a Ctrl-C while a
    worker starts Python or imports cannot print its traceback. The
    resource tracker is started first: starting it unblocks SIGINT in the
    thread that starts it (multiprocessing's own ``ensure_running``), which
    had let the workers start with Ctrl-C live. In the main thread;
    elsewhere (or where Python did not set SIGINT's handler) a no-op."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is None:
        yield
        return
    masks = hasattr(signal, "pthread_sigmask")
    if masks:
        resource_tracker.ensure_running()
    came = []
    # (one that another thread receives runs this in the main thread)
    previous = signal.signal(signal.SIGINT, lambda signum, frame: came.append(signum))
    if masks:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if masks:  # (one held pending by the mask reaches ``previous`` here)
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        if came:
            signal.raise_signal(signal.SIGINT)


def _ignore_sigint():
    """Workers leave Ctrl-C to the parent, which stops the pool (one line, no
    traceback per worker): ignored from here on (a Ctrl-C held back by the
    mask they started with is dropped), and the mask lifted."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _render_block_task(args):
    return args[4], render_block(*args)


def _blocks(pairs, workers, first=0):
    """Blocks of at most BLOCK pairs, small enough to keep every worker
    busy, from pair ``first`` (a block boundary of the same ``pairs`` and
    ``workers``, where a resumed file stopped): (count, iterator)."""
    size = max(1, min(BLOCK, math.ceil(pairs / (2 * workers))))
    starts = range(first, pairs, size)
    return len(starts), ((s, min(s + size, pairs)) for s in starts)


def iter_blocks(protocol, seed, pairs, image_size, workers, first=0):
    """(start, (left, right, labels)) for every block from pair ``first``,
    in order, memory bounded."""
    count, blocks = _blocks(pairs, workers, first)
    if workers == 1 or count <= 1:
        for start, stop in blocks:
            yield start, render_block(protocol, seed, pairs, image_size, start, stop)
        return

    # (the task is this module's, never ``__main__``'s: the workers need not
    # re-import the caller's script)
    task = _render_block_task
    window = 2 * workers
    pool, pending = None, []
    try:
        # spawn: safe even when the caller has started threads (e.g. JAX);
        # a Ctrl-C during the start is delivered once the pool is there
        # (and ends it, below)
        with _without_main_module(), _sigint_deferred():
            pool = mp.get_context("spawn").Pool(min(workers, count),
                                                initializer=_ignore_sigint)
        for block in blocks:
            pending.append(pool.apply_async(task, ((protocol, seed, pairs, image_size) + block,)))
            if len(pending) >= window:
                break
        while pending:
            result = pending.pop(0).get()
            block = next(blocks, None)
            if block is not None:
                pending.append(pool.apply_async(
                    task, ((protocol, seed, pairs, image_size) + block,)))
            yield result
    except BaseException as error:
        # (the frames of a Ctrl-C that came in ``get`` hold the pool)
        traceback.clear_frames(error.__traceback__)
        raise
    finally:
        # The workers stopped and the pool's queues released now: their
        # semaphores are unlinked when the queues are collected, which a
        # process that ends by ``os._exit`` (``cli.run`` after a Ctrl-C)
        # never does (the resource tracker then warned of leaked semaphores).
        if pool is not None:
            pool.terminate()
            pool.join()
        pending.clear()  # (each unfinished result holds the pool)
        del pool
        gc.collect()


@contextlib.contextmanager
def _without_main_module():
    """Hide the caller's ``__main__`` while workers start, so that ``spawn``
    does not re-run a script that calls ``generate_dataset`` without an
    ``if __name__ == "__main__"`` guard."""
    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if main is not None:
            sys.modules["__main__"] = main

