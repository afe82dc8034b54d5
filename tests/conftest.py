"""Test-suite set-up: the JAX backend, before any test module imports Keras,
and the expensive things several test files need, made once per session:

* ``tiny_run``: a finished run on 40 rendered cvgl pairs (the files that only
  read a run);
* ``stereo40``: the 40-pair, 32x32 fixture dataset the training, loss-health
  and learning-curve tests train on;
* ``variant_run(name)``: one run of each variant on ``stereo40``, trained at
  first use (the run-directory tests and the learning curves read the same
  MTL-CPL-A run instead of training it twice);
* ``real32``: every shipped real rig built at 32 px, one crop per pair (the
  Table 2 tests and the leave-one-rig-out test);
* ``early(name)``: the result of one of the ``EARLY`` commands (the quick
  reproduction, the uninterrupted run the kill-and-resume tests compare
  with, the data-parallel run): whole commands that only tests late in the
  run read, queued when a selected test needs them and run one after
  another in the background from the end of collection on, at a lower
  priority. The tests leave one of the two cores mostly idle (they run one
  at a time, and their floor is XLA's compile time, one thread), so these
  commands run in that idle time instead of holding the suite up
  (paper_results/notes/pipeline-and-suite.md, "The suite on an idle AMD EPYC");
* ``train_cache``: the XLA compile cache of the suite's train.py processes
  of the small backbone, warm from the uninterrupted run.

Each is read only: a test that changes a run copies it first. The helpers
that tests share (the fixture dataset, the ``EARLY`` commands' arguments) are
in helpers.py, which the tests import instead of this file.

Tests marked ``slow`` (the quick reproduction, InceptionV3 builds, data
parallelism, kill-and-resume, every train.py flag, the documented commands,
the benchmark scripts) are left out by ``pytest -m "not slow"``.
"""

import os
import shutil
import subprocess
import sys
import tempfile
import threading

import pytest

from helpers import REPO, RESUME_ARGS, quick_reproduction_args, train_py, write_stereo_fixture

os.environ.setdefault("KERAS_BACKEND", "jax")

TINY_SIZE = 32
#: The shared variant runs' settings: 40 pairs -> 25 train, 3 val, 12 test;
#: batches of 5 keep one shape (one compilation); 2 epochs.
VARIANT_RUN = dict(backbone="small", epochs=2, batch_size=5, seed=1, verbose=0)


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A finished MTL-Baseline run (small backbone, 1 epoch) on 40 rendered
    cvgl pairs of 32x32: ``{"root", "data", "run"}``. Read it, never write
    into it."""
    from cpl_keras.data.generate import generate_dataset
    from cpl_keras.training import train

    root = tmp_path_factory.mktemp("tiny_run")
    data = generate_dataset(root / "cvgl.h5", protocol="cvgl", pairs=40, seed=0,
                            image_size=TINY_SIZE, workers=1, progress=False)
    run = root / "run_baseline"
    train(data, variant="baseline", run_dir=run, epochs=1, batch_size=8, backbone="small",
          verbose=0)
    return {"root": root, "data": str(data), "run": str(run)}


_folders = []


def stereo40_file():
    """``write_stereo_fixture(n=40, image_size=32)`` (random images, labels of
    4 configurations), written once per session: the ``stereo40`` fixture's
    file, and the data of the ``EARLY`` training commands."""
    if not _folders:
        _folders.append(tempfile.mkdtemp(prefix="cpl_keras_stereo40_"))
        write_stereo_fixture(os.path.join(_folders[0], "tiny.h5"), n=40, image_size=32)
    return os.path.join(_folders[0], "tiny.h5")


@pytest.fixture(scope="session")
def stereo40():
    """``stereo40_file()``: a path; read it, never write into it."""
    return stereo40_file()


@pytest.fixture(scope="session")
def variant_run(stereo40, tmp_path_factory):
    """``variant_run(variant)`` -> ``{"run_dir", "summary"}``: that variant
    trained on ``stereo40`` with ``VARIANT_RUN``'s settings, once per session
    (at its first use). Read it; copy the folder to change it."""
    made = {}

    def get(variant):
        if variant not in made:
            from cpl_keras.training import train

            run_dir = str(tmp_path_factory.mktemp("variant_runs") / variant)
            summary = train(stereo40, variant=variant, run_dir=run_dir, **VARIANT_RUN)
            made[variant] = {"run_dir": run_dir, "summary": summary}
        return made[variant]

    return get


@pytest.fixture(scope="session")
def real32(tmp_path_factory):
    """A folder of the shipped real sets (chessboard 13 pairs, Middlebury 1,
    OAK-D 12) at 32x32, ``real.build all --crops 1``. Read only."""
    from cpl_keras.real import build

    real = tmp_path_factory.mktemp("real32")
    assert build.main(["all", "--out-dir", str(real), "--crops", "1", "--image-size",
                       str(TINY_SIZE)]) == 0
    return real


# ---------------------------------------------------------------------------
# Whole commands started early
# ---------------------------------------------------------------------------
def _uninterrupted(root):
    return train_py(*RESUME_ARGS, "--data", stereo40_file(), "--run-dir",
                    os.path.join(root, "run"), cache=os.path.join(root, "xla"))


def _data_parallel(root):
    return train_py("--variant", "cpl-u", "--data", stereo40_file(), "--backbone", "small",
                    "--epochs", "2", "--batch-size", "5", "--data-parallel", "--run-dir",
                    os.path.join(root, "run"), "--quiet", cache=os.path.join(root, "xla"),
                    env={"XLA_FLAGS": "--xla_force_host_platform_device_count=2"})


#: name -> (the fixture whose tests need it, ``(argv, environment)`` given
#: the command's folder), in the order they run (the short ones first).
EARLY = {
    "uninterrupted": ("uninterrupted", _uninterrupted),
    "data_parallel": ("data_parallel_run", _data_parallel),
    # its compile cache a folder of its own (CPL_KERAS_CACHE), not the user's: the
    # processes of the tests that run meanwhile use that one
    "quick": ("quick", lambda root: ([sys.executable, "evaluate.py",
                                      *quick_reproduction_args(root)],
                                     dict(os.environ, KERAS_BACKEND="jax",
                                          CPL_KERAS_CACHE=os.path.join(root, "cache")))),
}


#: The ``EARLY`` commands' niceness: below the tests, which wait for their
#: results only at the end, if ever.
NICENESS = 10


class EarlyCommand:
    """One command of ``EARLY``, to run in a folder of its own; ``result()``
    waits for it and returns ``subprocess.CompletedProcess`` (its output goes
    to files, so a chatty command never blocks on a full pipe)."""

    def __init__(self, name):
        self.name = name
        self.folder = tempfile.mkdtemp(prefix=f"cpl_keras_early_{name}_")
        self.argv, self.environment = EARLY[name][1](self.folder)
        self.process, self._result = None, None
        self.started = threading.Event()

    def start(self):
        self._out = open(os.path.join(self.folder, "stdout.txt"), "w")
        self._err = open(os.path.join(self.folder, "stderr.txt"), "w")
        self.process = subprocess.Popen(self.argv, cwd=REPO, env=self.environment,
                                        stdin=subprocess.DEVNULL, stdout=self._out,
                                        stderr=self._err, text=True)
        try:  # a lower priority: it fills the cores the tests leave idle, and no more
            # (with a second test process no core is idle: the same priority)
            os.setpriority(os.PRIO_PROCESS, self.process.pid,
                           0 if _second.process is not None else NICENESS)
        except (AttributeError, OSError):  # (no such call here, or the process has ended)
            pass
        self.started.set()

    def result(self, timeout=900):
        if not self.started.wait(timeout=timeout):
            raise TimeoutError(f"{self.name}: not started within {timeout} s")
        if self._result is None:
            returncode = self.process.wait(timeout=timeout)
            for f in (self._out, self._err):
                f.close()
            with open(self._out.name) as out, open(self._err.name) as err:
                self._result = subprocess.CompletedProcess(self.argv, returncode, out.read(),
                                                           err.read())
        return self._result

    def stop(self):
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=60)
        shutil.rmtree(self.folder, ignore_errors=True)


class EarlyQueue:
    """The ``EARLY`` commands that the selected tests need, run one after
    another by a background thread from the end of collection on (one at a
    time: several at once would crowd out the tests that run meanwhile)."""

    def __init__(self):
        self.commands, self.stopping, self.thread = {}, False, None
        self.lock = threading.Lock()  # (no command starts once stop() has begun)

    def start(self, names):
        for name in names:
            self.commands[name] = EarlyCommand(name)
        self.thread = threading.Thread(target=self._run, daemon=True, name="early-commands")
        self.thread.start()

    def _run(self):
        for command in list(self.commands.values()):
            with self.lock:
                if self.stopping:
                    return
                command.start()
            try:
                command.process.wait(timeout=900)
            except subprocess.TimeoutExpired:  # (its test fails on it)
                pass

    def get(self, name):
        """The command ``name``, queued or, where it was not, run now."""
        if name not in self.commands:
            self.commands[name] = EarlyCommand(name)
            self.commands[name].start()
        return self.commands[name]

    def stop(self):
        with self.lock:
            self.stopping = True
        for command in self.commands.values():
            command.stop()


_early = EarlyQueue()


def pytest_collection_finish(session):
    """Queue each ``EARLY`` command that a selected test needs."""
    _early.start([name for name, (fixture, _) in EARLY.items()
                  if any(fixture in getattr(item, "fixturenames", ()) for item in session.items)])


# ---------------------------------------------------------------------------
# A second test process
# ---------------------------------------------------------------------------
#: Test files that a second pytest process runs beside this one when the
#: selection holds both them and others. The tests run one at a time and
#: their floor is XLA's compile time, one thread, so one process leaves the
#: second core mostly idle; these files take about half of the suite's time
#: and need no ``EARLY`` command but the uninterrupted run's compile cache
#: (``train_cache``: an empty one there, so test_interrupt's training
#: compiles its own programs) (paper_results/notes/pipeline-and-suite.md).
#: ``CPL_KERAS_TEST_SPLIT=0`` keeps every test in this process.
SECOND_PROCESS_FILES = ("test_bench_diagnostics.py", "test_distributed.py",
                        "test_docs_commands.py", "test_inspect.py", "test_interrupt.py",
                        "test_learning_curves.py", "test_leave_one_rig_out.py",
                        "test_loss_health.py", "test_models.py")
#: Set in the second process (which runs what it is given and splits nothing).
WORKER = "CPL_KERAS_TEST_WORKER"


class SecondProcess:
    """``python -m pytest`` on the given tests (node ids), in the background
    from the end of collection on; its output goes to a file, and its result
    is this session's too (``pytest_sessionfinish``)."""

    def __init__(self):
        self.process, self.folder, self.count = None, None, 0

    def start(self, config, nodeids):
        self.folder, self.count = tempfile.mkdtemp(prefix="cpl_keras_second_"), len(nodeids)
        argv = [sys.executable, "-m", "pytest", "-q", "-rfE", "-p", "no:cacheprovider",
                "--basetemp", os.path.join(self.folder, "tmp")]
        if config.option.durations is not None:
            argv += [f"--durations={config.option.durations}"]
        self._out = open(os.path.join(self.folder, "output.txt"), "w")
        self.process = subprocess.Popen(argv + list(nodeids), cwd=REPO, stdin=subprocess.DEVNULL,
                                        stdout=self._out, stderr=subprocess.STDOUT,
                                        env=dict(os.environ, **{WORKER: "1"}))

    def finish(self, interrupted):
        """``(returncode, output)``; the process is killed when this session
        was interrupted."""
        if interrupted and self.process.poll() is None:
            self.process.kill()
        try:
            returncode = self.process.wait(timeout=1800)
        except subprocess.TimeoutExpired:
            self.process.kill()
            returncode = self.process.wait(timeout=60)
        self._out.close()
        with open(self._out.name) as f:
            output = f.read()
        shutil.rmtree(self.folder, ignore_errors=True)
        return returncode, output


_second = SecondProcess()
_second_result = []


@pytest.hookimpl(trylast=True)  # (after -m and -k have deselected)
def pytest_collection_modifyitems(session, config, items):
    """Hand ``SECOND_PROCESS_FILES``' tests to a second process when the
    selection also holds others."""
    if os.environ.get(WORKER) or os.environ.get("CPL_KERAS_TEST_SPLIT") == "0" \
            or config.option.collectonly:
        return
    second = [item for item in items if item.path.name in SECOND_PROCESS_FILES]
    if not second or len(second) == len(items):
        return
    items[:] = [item for item in items if item.path.name not in SECOND_PROCESS_FILES]
    _second.start(config, [item.nodeid for item in second])


def pytest_sessionfinish(session):
    if _second.process is not None:
        returncode, output = _second.finish(
            interrupted=session.exitstatus == pytest.ExitCode.INTERRUPTED)
        _second_result.append((returncode, output))
        if returncode not in (0, pytest.ExitCode.NO_TESTS_COLLECTED):
            session.exitstatus = pytest.ExitCode.TESTS_FAILED
    _early.stop()
    for folder in _folders:
        shutil.rmtree(folder, ignore_errors=True)


def pytest_terminal_summary(terminalreporter):
    """The second process's result: its last line, and all of its output
    when it failed."""
    if not _second_result:
        return
    returncode, output = _second_result[0]
    lines = output.rstrip().splitlines() or ["(no output)"]
    terminalreporter.section(f"second process ({_second.count} tests of "
                             f"{', '.join(SECOND_PROCESS_FILES)})")
    for line in (lines if returncode not in (0, pytest.ExitCode.NO_TESTS_COLLECTED)
                 else lines[-1:]):
        terminalreporter.write_line(line)


def started_early(name):
    """Whether the ``EARLY`` command ``name`` was queued at collection."""
    return name in _early.commands


@pytest.fixture(scope="session")
def train_cache(early, tmp_path_factory):
    """The XLA compile cache of the suite's train.py processes of the small
    backbone on ``stereo40``-like data (batch 5): that of the uninterrupted
    run (``RESUME_ARGS``) once it has ended, where it was queued (its
    programs are theirs, so they load instead of compiling), else an empty
    folder. One process writes to it at a time."""
    if started_early("uninterrupted"):
        return os.path.join(early("uninterrupted")[0], "xla")
    return str(tmp_path_factory.mktemp("xla"))


@pytest.fixture(scope="session")
def early():
    """``early(name)`` -> ``(folder, subprocess.CompletedProcess)`` of the
    ``EARLY`` command ``name`` (started now if it was not yet). Read only."""
    def get(name):
        command = _early.get(name)
        return command.folder, command.result()

    return get
