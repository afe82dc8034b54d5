"""``cpl_keras/cache.py``: the cache directory and the compile cache."""

import os

import pytest

from cpl_keras import cache


def test_a_cache_directory_that_is_a_file_is_one_line(tmp_path, monkeypatch):
    """CPL_KERAS_CACHE naming a file said ``[Errno 17] File exists``."""
    path = tmp_path / "a-file"
    path.write_text("x")
    monkeypatch.setenv("CPL_KERAS_CACHE", str(path))
    with pytest.raises(cache.CacheError, match=f"CPL_KERAS_CACHE names a file, not a folder: "
                       f"{path}; point CPL_KERAS_CACHE at a folder"):
        cache.cache_dir()
    monkeypatch.setenv("CPL_KERAS_CACHE", str(tmp_path / "new"))
    assert cache.cache_dir() == str(tmp_path / "new")


def test_a_compile_cache_that_cannot_be_written_is_left_off(tmp_path, monkeypatch):
    """A compile cache that cannot be written (here under a file) is not
    handed to JAX, whose warning for every program it could not write
    reached the user; compiling goes on without it."""
    (tmp_path / "a-file").write_text("x")
    monkeypatch.setenv("KERAS_BACKEND", "jax")
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "a-file" / "xla"))
    assert cache.enable_compile_cache() is None
    # (a folder that can be: made and taken; not handed to this process's JAX,
    # whose cache the other tests share)
    assert cache._writable(str(tmp_path / "xla")) and os.path.isdir(tmp_path / "xla")
