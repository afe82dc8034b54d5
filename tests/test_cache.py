"""``cpl_keras/cache.py``: the cache directory and the compile cache."""

import os
import subprocess
import sys

import pytest

from cpl_keras import cache
from helpers import REPO


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


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_a_cache_directory_where_no_file_can_be_made_is_one_line_and_no_wait(
        tmp_path, monkeypatch, capsys):
    """CPL_KERAS_CACHE=/proc/self (a folder, but no file can be made in it,
    root or not): the demonstration run waited "for another process" for
    ever (the lock of its dataset never made); now one line, exit 2, nothing
    made, and the compile cache is left off rather than refused."""
    from cpl_keras.commands import train
    from cpl_keras.data.generate import cached_dataset

    for folder in ("/proc/self", "/proc/self/cache"):
        monkeypatch.setenv("CPL_KERAS_CACHE", folder)
        with pytest.raises(cache.CacheError) as error:
            cache.cache_dir()
        assert str(error.value) == (f"CPL_KERAS_CACHE cannot hold files: {folder} (No such "
                                    "file or directory); point CPL_KERAS_CACHE at a folder "
                                    "you can write")
    monkeypatch.setenv("KERAS_BACKEND", "jax")
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    assert cache.enable_compile_cache() is None
    run_dir = tmp_path / "demo"
    assert train.main(["--variant", "cpl-a", "--run-dir", str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "CPL_KERAS_CACHE cannot hold files: /proc/self/cache" in err
    assert os.listdir(tmp_path) == []
    # (a folder given to the project's datasets directly: one line, no wait)
    with pytest.raises(OSError, match=r"cannot make /proc/self/cvgl_8_16px_s0_v\S+\.h5: no "
                       r"file can be made in /proc/self \(No such file or directory\)"):
        cached_dataset("/proc/self", protocol="cvgl", pairs=8, seed=0, image_size=16)


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


@pytest.mark.parametrize("jax_first", [True, False], ids=["jax imported", "jax not yet"])
@pytest.mark.parametrize("setting", [None, "2.5"])
def test_compile_cache_keeps_every_program_unless_told_otherwise(setting, jax_first, tmp_path):
    """enable_compile_cache: the directory from $JAX_COMPILATION_CACHE_DIR,
    programs kept whatever their compile time (0 s), and a
    $JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS the user set left as set; a
    small program compiled after it lands in the directory; alike whether
    JAX was imported before it or is after it (nor does it import Keras). In
    a process of its own: the setting is global to JAX."""
    enable = ("from cpl_keras.cache import enable_compile_cache\n"
              "print(enable_compile_cache())\n"
              "import sys; assert 'keras' not in sys.modules\n")
    code = (("import jax, jax.numpy as jnp\n" + enable) if jax_first else
            (enable + "import jax, jax.numpy as jnp\n")) + (
            "print(jax.config.jax_persistent_cache_min_compile_time_secs)\n"
            "jax.jit(lambda x: jnp.sin(x) * 3)(jnp.ones(7)).block_until_ready()\n")
    env = dict(os.environ, KERAS_BACKEND="jax", JAX_COMPILATION_CACHE_DIR=str(tmp_path / "xla"))
    env.pop("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", None)
    env.pop("JAX_COMPILATION_CACHE_MAX_SIZE", None)  # (the suite's: a lock file)
    if setting is not None:
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = setting
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    directory, minimum = done.stdout.split()
    assert directory == str(tmp_path / "xla")
    assert float(minimum) == (0.0 if setting is None else 2.5)
    kept = os.listdir(tmp_path / "xla") if os.path.isdir(tmp_path / "xla") else []
    assert bool(kept) == (setting is None), kept
