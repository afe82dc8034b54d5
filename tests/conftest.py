"""Test-suite set-up: the JAX backend, before any test module imports Keras;
one compile cache for the whole session; and the expensive things several
test files need, made once per session.

The suite runs on two pytest-xdist workers by itself (pyproject.toml's
``addopts``: ``-n 2 --dist loadfile``, each test file on one worker, the
slowest files handed out first (``FIRST``); ``-n 0`` runs it in one
process) and ends with its 20 slowest tests
(``--durations=20``: where the suite's time goes, in every CI log). What the workers share lives in the
session's folder (``shared_folder``), each thing made by the first worker
that needs it, behind a file lock, and read by the other:

* one XLA compile cache (``SESSION_ENV``, set for the session by the
  controlling process and inherited by every worker and every command a test
  starts): a program compiled once in the session is loaded after that,
  in any process. JAX writes its cache under a file lock once a size limit
  is set, so two writers are safe (``JAX_COMPILATION_CACHE_MAX_SIZE``);
  ``CPL_KERAS_CACHE`` points into the session's folder too, so that nothing
  reads or writes the user's own cache. A test whose subject is compilation
  gives its command an empty cache of its own;
* ``tiny_run``: a finished run on 40 rendered cvgl pairs (the files that only
  read a run);
* ``stereo40``: the 40-pair, 32x32 fixture dataset the training, loss-health
  and learning-curve tests train on;
* ``variant_run(name)``: one run of each variant on ``stereo40``, trained at
  first use (the run-directory tests and the learning curves read the same
  MTL-CPL-A run instead of training it twice);
* ``real32``: every shipped real rig built at 32 px, one crop per pair (the
  Table 2 tests and the leave-one-rig-out test);
* ``early(name)``: the result of one of the ``EARLY`` whole commands (the
  quick reproduction, the uninterrupted run the kill-and-resume tests
  compare with, the data-parallel run), run at first use;
* ``train_cache``: the session's compile cache (for the tests that pass one
  to a command explicitly).

Each is read only, on disk too (``made_once``): a test that changes one
changes a copy of it (``helpers.writable_copy``). The helpers that tests
share (the fixture dataset, the ``EARLY`` commands' arguments) are in
helpers.py, which the tests import instead of this file.

Tests marked ``slow`` (the quick reproduction, InceptionV3 builds, data
parallelism, kill-and-resume, every train.py flag, the documented commands,
the benchmark scripts) are left out by ``pytest -m "not slow"``.
"""

import json
import os
import shutil
import subprocess
import sys
import tempfile

import pytest
from filelock import FileLock

from helpers import (
    QUICK_XLA_FLAGS, REPO, RESUME_ARGS, VARIANT_RUN, quick_reproduction_args, set_writable,
    train_py, write_stereo_fixture,
)

os.environ.setdefault("KERAS_BACKEND", "jax")

TINY_SIZE = 32

#: The session folder's variable (set by the controlling process).
SESSION = "CPL_KERAS_TEST_SESSION"
#: A size limit for JAX's compile cache: with one, JAX reads and writes it
#: under a file lock, so that the session's processes can share it.
CACHE_LIMIT = str(64 * 2 ** 30)


def session_env(folder):
    """The environment every process of the session shares: one XLA compile
    cache (every program kept, locked writes) and the package's own cache."""
    return {SESSION: folder,
            "JAX_COMPILATION_CACHE_DIR": os.path.join(folder, "xla"),
            "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
            "JAX_COMPILATION_CACHE_MAX_SIZE": CACHE_LIMIT,
            "CPL_KERAS_CACHE": os.path.join(folder, "cpl_keras")}


def pytest_configure(config):
    """In the controlling process (not an xdist worker): the session's folder
    and ``session_env``, which the workers and their commands inherit."""
    if hasattr(config, "workerinput") or os.environ.get(SESSION):
        return
    folder = tempfile.mkdtemp(prefix="cpl_keras_session_")
    config._cpl_keras_session = folder
    os.environ.update(session_env(folder))


#: The test files that take longest (the --durations of CI's logs), slowest
#: first. pytest-xdist hands out whole files (``--dist loadfile``) in the
#: order of ``pytest_collection_modifyitems``: these first, then the others
#: by their number of tests, most first, as xdist itself would order them
#: (pyproject.toml's ``--no-loadscope-reorder`` keeps this order). A heavy
#: file with few tests (two process groups, an InceptionV3 run) handed out
#: last would run alone while the other worker had nothing left to do.
FIRST = ("test_reproduce.py", "test_distributed.py", "test_backbone_weights.py",
         "test_planning.py", "test_training_faults.py", "test_release_import.py",
         "test_docs_commands.py", "test_interrupt.py", "test_checkpointing.py",
         "test_leave_one_rig_out.py", "test_collapsed_heads.py")


def pytest_collection_modifyitems(config, items):
    """Whole files in ``FIRST``'s order, then by number of tests (most
    first); within a file, the tests keep their order."""
    counts = {}
    for item in items:
        counts[item.path.name] = counts.get(item.path.name, 0) + 1

    def rank(item):
        name = item.path.name
        return (FIRST.index(name), 0) if name in FIRST else (len(FIRST), -counts[name])

    items.sort(key=rank)  # (stable: files stay whole, in collection order on a tie)


def pytest_unconfigure(config):
    folder = getattr(config, "_cpl_keras_session", None)
    if folder:
        set_writable(folder, True)  # (made_once's files, read only)
        shutil.rmtree(folder, ignore_errors=True)
        for name in session_env(folder):
            os.environ.pop(name, None)


@pytest.fixture(scope="session")
def shared_folder():
    """The session's folder, the same in every worker."""
    return os.environ[SESSION]


def made_once(folder, name, make):
    """``make(path)`` for ``folder/name`` by the first process of the
    session that asks, behind a file lock; the others wait and get the same
    path. ``make`` writes ``path`` (a file or a folder); ``path.done`` marks
    it complete. Once made, ``path`` is read only (files 0o444, folders
    0o555), so that a test that writes into it fails at once rather than
    changing what the tests after it read (``helpers.writable_copy`` makes
    a copy to change). (Root writes through file modes: run as root, the
    suite catches such a test only without CAP_DAC_OVERRIDE, e.g. under
    ``setpriv --bounding-set -dac_override,-dac_read_search,-fowner``.)"""
    path = os.path.join(folder, name)
    done = path + ".done"
    with FileLock(path + ".lock"):
        if not os.path.exists(done):
            if os.path.lexists(path):  # (an attempt that failed half-way)
                set_writable(path, True)
                if os.path.isdir(path):
                    shutil.rmtree(path)
            make(path)
            set_writable(path, False)
            with open(done, "w"):
                pass
    return path


@pytest.fixture(scope="session")
def tiny_run(shared_folder):
    """A finished MTL-Baseline run (small backbone, 1 epoch) on 40 rendered
    cvgl pairs of 32x32: ``{"root", "data", "run"}``. Read it, never write
    into it."""
    def make(root):
        from cpl_keras.data.generate import generate_dataset
        from cpl_keras.training import train

        os.makedirs(root)
        data = generate_dataset(os.path.join(root, "cvgl.h5"), protocol="cvgl", pairs=40,
                                seed=0, image_size=TINY_SIZE, workers=1, progress=False)
        train(data, variant="baseline", run_dir=os.path.join(root, "run_baseline"), epochs=1,
              batch_size=8, backbone="small", verbose=0)

    root = made_once(shared_folder, "tiny_run", make)
    return {"root": root, "data": os.path.join(root, "cvgl.h5"),
            "run": os.path.join(root, "run_baseline")}


def stereo40_file(folder):
    """``write_stereo_fixture(n=40, image_size=32)`` (random images, labels of
    4 configurations) in the session's ``folder``, written once: the
    ``stereo40`` fixture's file, and the data of the ``EARLY`` training
    commands."""
    return made_once(folder, "tiny.h5",
                     lambda path: write_stereo_fixture(path, n=40, image_size=32))


@pytest.fixture(scope="session")
def stereo40(shared_folder):
    """``stereo40_file()``: a path; read it, never write into it."""
    return stereo40_file(shared_folder)


@pytest.fixture(scope="session")
def variant_run(stereo40, shared_folder):
    """``variant_run(variant)`` -> ``{"run_dir", "summary"}``: that variant
    trained on ``stereo40`` with ``VARIANT_RUN``'s settings, once per session
    (at its first use; the summary without its model). Read it; copy the
    folder to change it."""
    def get(variant):
        def make(folder):
            from cpl_keras.training import train

            os.makedirs(folder)
            result = train(stereo40, variant=variant, run_dir=os.path.join(folder, "run"),
                           return_model=False, **VARIANT_RUN)
            summary = result.config.to_dict()   # (the run's final config.json)
            with open(os.path.join(folder, "summary.json"), "w") as f:
                json.dump(summary, f)

        folder = made_once(shared_folder, f"variant_{variant}", make)
        with open(os.path.join(folder, "summary.json")) as f:
            return {"run_dir": os.path.join(folder, "run"), "summary": json.load(f)}

    return get


@pytest.fixture(scope="session")
def real32(shared_folder):
    """A folder of the shipped real sets (chessboard 13 pairs, Middlebury 1,
    OAK-D 12) at 32x32, ``real.build all --crops 1``. Read only."""
    from pathlib import Path

    def make(real):
        from cpl_keras.commands import real_build

        assert real_build.main(["all", "--out-dir", real, "--crops", "1", "--image-size",
                           str(TINY_SIZE)]) == 0

    return Path(made_once(shared_folder, "real32", make))


# ---------------------------------------------------------------------------
# Whole commands
# ---------------------------------------------------------------------------
def _uninterrupted(root, data):
    return train_py(*RESUME_ARGS, "--data", data, "--run-dir", os.path.join(root, "run"))


def _data_parallel(root, data):
    # (XLA's level 0, as the quick reproduction's: two epochs of 5 steps are
    # start-up and compilation; its programs are no other command's)
    return train_py("--variant", "cpl-u", "--data", data, "--backbone", "small",
                    "--epochs", "2", "--batch-size", "5", "--data-parallel", "--run-dir",
                    os.path.join(root, "run"), "--quiet",
                    env={"XLA_FLAGS": QUICK_XLA_FLAGS +
                         " --xla_force_host_platform_device_count=2"})


def _quick(root, data):
    return [sys.executable, "-m", "cpl_keras.reproduce", *quick_reproduction_args(root)], \
        dict(os.environ, KERAS_BACKEND="jax", XLA_FLAGS=QUICK_XLA_FLAGS)


#: name -> ``(argv, environment)`` given the command's folder and the
#: ``stereo40`` file.
EARLY = {"uninterrupted": _uninterrupted, "data_parallel": _data_parallel, "quick": _quick}


@pytest.fixture(scope="session")
def early(shared_folder, stereo40):
    """``early(name)`` -> ``(folder, subprocess.CompletedProcess)`` of the
    ``EARLY`` command ``name``, run once per session at its first use (its
    output in files, so a chatty command never blocks on a full pipe). Read
    only."""
    def get(name):
        def make(folder):
            os.makedirs(folder)
            argv, environment = EARLY[name](folder, stereo40)
            with open(os.path.join(folder, "stdout.txt"), "w") as out, \
                    open(os.path.join(folder, "stderr.txt"), "w") as err:
                returncode = subprocess.run(argv, cwd=REPO, env=environment,
                                            stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                            text=True, timeout=1800).returncode
            with open(os.path.join(folder, "returncode"), "w") as f:
                f.write(str(returncode))

        folder = made_once(shared_folder, f"early_{name}", make)
        argv, _ = EARLY[name](folder, stereo40)
        with open(os.path.join(folder, "returncode")) as f:
            returncode = int(f.read())
        with open(os.path.join(folder, "stdout.txt")) as out, \
                open(os.path.join(folder, "stderr.txt")) as err:
            return folder, subprocess.CompletedProcess(argv, returncode, out.read(), err.read())

    return get


@pytest.fixture(scope="session")
def train_cache():
    """The session's XLA compile cache (``session_env``), for the tests that
    give a command its cache explicitly."""
    return os.environ["JAX_COMPILATION_CACHE_DIR"]
