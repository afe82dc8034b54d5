"""The project's cache directory and JAX's persistent compile cache.

``cache_dir()`` holds generated demonstration data and compiled XLA
programs; ``enable_compile_cache()`` keeps compiled training steps there, so
a resumed or repeated run (or another of the same model shape) skips most of
XLA's compile time.
"""

from __future__ import annotations

import os
import sys

from cpl_keras import files
from cpl_keras.backend import keras_backend
from cpl_keras.errors import Error


class CacheError(Error):
    """The cache directory cannot be one (one-line message)."""


def cache_dir():
    """The project's cache directory: ``$CPL_KERAS_CACHE`` or
    ``~/.cache/cpl_keras``; CacheError when that names something that is
    not a folder, or one where no file can be made (``/proc/self``: the
    demonstration run waited there "for another process" for ever, its lock
    file never made)."""
    path = os.environ.get("CPL_KERAS_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "cpl_keras"
    )
    where = "CPL_KERAS_CACHE" if os.environ.get("CPL_KERAS_CACHE") else "the cache directory"
    if os.path.exists(path) and not os.path.isdir(path):
        raise CacheError(f"{where} names a file, not a folder: {path}; point CPL_KERAS_CACHE "
                         f"at a folder")
    problem = files.cannot_write(path)
    if problem:
        raise CacheError(f"{where} cannot hold files: {path} ({problem}); point "
                         "CPL_KERAS_CACHE at a folder you can write")
    return path


def _writable(path):
    """Whether ``path`` is (or can be made) a folder this process can write in."""
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return False
    return os.path.isdir(path) and os.access(path, os.W_OK | os.X_OK)


def enable_compile_cache():
    """Keep compiled training steps on disk (JAX), so a resumed or repeated run,
    or another run of the same model shape, skips most of XLA's compile time.

    ``$JAX_COMPILATION_CACHE_DIR`` wins when set; otherwise ``<cache_dir>/xla``.
    Every compiled program is kept, not only those that took JAX's default
    second to compile (``$JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`` wins
    when set): a run makes about a hundred programs of under a second each
    (initialisers, metrics, the optimizer's set-up), which the next process
    of the same model then loads instead of compiling. The quick reproduction
    (nine runs in processes of their own, two at a time) took 90 and 91 s
    with this against 100 and 103 s with JAX's default, from an empty cache
    (paper_results/notes/pipeline-and-suite.md). Returns the directory, or None on other
    backends and where it cannot be written (a read-only one: compiling goes on without it).
    """
    if keras_backend() != "jax":
        return None
    path = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if not path:
        try:
            path = os.path.join(cache_dir(), "xla")
        except CacheError:  # (no cache to keep programs in: compiling goes on)
            return None
    if not _writable(path):
        # (a read-only cache: compiling goes on without it, and without
        # JAX's warning of every program it could not write)
        return None
    keep_all = "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ
    jax = sys.modules.get("jax")
    if jax is None:
        # Not imported yet (a finished run's train.py never imports it): JAX
        # reads these when it is, here and in the processes started from here.
        os.environ["JAX_COMPILATION_CACHE_DIR"] = path
        if keep_all:
            os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
        return path
    jax.config.update("jax_compilation_cache_dir", path)
    if keep_all:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path

