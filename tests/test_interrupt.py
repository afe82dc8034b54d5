"""Ctrl-C (SIGINT to the process group, as a terminal sends it) stops a
command promptly: one line on stderr, exit 130, nothing half-written, and a
training run that the same command resumes (cpl_keras.cli.interruptible)."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from cpl_keras.data.storage import StereoFile
from helpers import REPO, epochs_done, wait_for, wait_for_output, write_stereo_fixture


@pytest.fixture(autouse=True)
def ctrl_c_not_ignored():
    """A test run started in the background (nohup, ``&`` in a script)
    inherits SIGINT ignored, and so would every command started here; these
    tests are about a terminal's Ctrl-C, so they restore Python's default
    (a handled signal is reset to its default in a started command, an
    ignored one would stay ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _start(args, cache=None):
    env = dict(os.environ, KERAS_BACKEND="jax")
    if cache:
        env["JAX_COMPILATION_CACHE_DIR"] = cache
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    return subprocess.Popen([sys.executable, *args], cwd=REPO, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)


def _ctrl_c(process):
    os.killpg(process.pid, signal.SIGINT)


def _one_line_130(process, prog, timeout=30):
    out, err = process.communicate(timeout=timeout)
    process.stderr_text = err
    assert process.returncode == 130, err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if "interrupted" in line]
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: interrupted"), err
    return lines[0]


def test_interruptible_raises_once_and_remembers():
    from cpl_keras import cli

    with pytest.raises(cli.Interrupted), cli.interruptible():
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
        except KeyboardInterrupt:
            pass  # a library that swallows it: the next check stops
        cli.check_interrupt()
    cli.check_interrupt()  # outside the block: nothing pending
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


@pytest.mark.slow
def test_ctrl_c_stops_training_resumably(tmp_path, train_cache):
    data = write_stereo_fixture(tmp_path / "tiny.h5", n=40, image_size=32)
    run_dir = str(tmp_path / "run")
    args = ["train.py", "--variant", "baseline", "--backbone", "small", "--epochs", "6",
            "--batch-size", "5", "--patience", "10", "--quiet", "--data", str(data),
            "--run-dir", run_dir]
    cache = train_cache  # (warm: the same programs as the kill-and-resume runs)

    process = _start(args, cache)
    assert wait_for(lambda: epochs_done(run_dir) >= 1)
    _ctrl_c(process)
    line = _one_line_130(process, "train.py")
    assert "run the same command again" in line and run_dir in line
    done = epochs_done(run_dir)
    assert 1 <= done < 6, "the run must be stopped mid-training"
    process = _start(args, cache)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, err
    assert f"Resuming {run_dir} after epoch {done}" in err
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    assert config["status"] == "finished" and config["epochs_run"] == 6


@pytest.mark.slow
def test_sigterm_stops_training_resumably_with_its_own_line(tmp_path, train_cache):
    """SIGTERM (a kill, a scheduler) ended train.py with 143 and no line;
    now it stops as Ctrl-C does, says so in one line, and exits 143."""
    data = write_stereo_fixture(tmp_path / "tiny.h5", n=40, image_size=32)
    run_dir = str(tmp_path / "run")
    args = ["train.py", "--variant", "baseline", "--backbone", "small", "--epochs", "6",
            "--batch-size", "5", "--patience", "10", "--quiet", "--data", str(data),
            "--run-dir", run_dir]
    process = _start(args, train_cache)
    assert wait_for(lambda: epochs_done(run_dir) >= 1)
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 143, err
    lines = [line for line in err.splitlines() if "terminated" in line]
    assert len(lines) == 1 and lines[0].startswith("train.py: terminated (SIGTERM); to "
                                                   "resume, run the same command again"), err
    assert "Traceback" not in err, err
    with open(os.path.join(run_dir, "config.json")) as f:
        assert json.load(f)["status"] == "running"  # (resumable, not finished)


def test_ctrl_c_stops_generation_and_the_same_command_continues_it_to_the_same_bytes(tmp_path):
    """Ctrl-C once the first block is written (the progress bar says so):
    the bar's line ended, one line, exit 130, the worker pool ended without
    a leaked semaphore, ``.partial`` kept; the same command says where it
    resumes and makes the very file that a run never interrupted makes."""
    import threading

    command = ["-m", "cpl_keras.data.generate", "--pairs", "480", "--image-size", "16",
               "--workers", "2", "--out", "x.h5"]
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    env = dict(os.environ, KERAS_BACKEND="jax", PYTHONPATH=REPO)
    process = subprocess.Popen([sys.executable, *command], cwd=tmp_path / "a", env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               start_new_session=True)
    err = bytearray()
    reader = threading.Thread(target=lambda: err.extend(process.stderr.read()), daemon=True)
    chunks = iter(lambda: os.read(process.stderr.fileno(), 4096), b"")
    for chunk in chunks:                   # until the bar shows the first block
        err.extend(chunk)
        if b"/480 pairs" in err:
            break
    assert b"/480 pairs" in err, err
    _ctrl_c(process)
    reader.start()
    assert process.wait(timeout=60) == 130
    reader.join(timeout=60)
    text = err.decode()
    assert "Traceback" not in text and "leaked" not in text, text
    last = text.split("\n")[-2]           # (its own line, not after the bar's \r)
    kept = int(re.fullmatch(r"python -m cpl_keras\.data\.generate: interrupted; x\.h5\.partial "
                            r"keeps the first (\d+) of 480 pairs; the same command continues it",
                            last).group(1))
    assert os.listdir(tmp_path / "a") == ["x.h5.partial"]

    resumed = subprocess.run([sys.executable, *command], cwd=tmp_path / "a", env=env,
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    start = int(re.search(r"^resuming x\.h5\.partial at pair (\d+) of 480$",
                          resumed.stderr, re.M).group(1))
    assert start == kept and 32 <= start < 480 and start % 32 == 0
    whole = subprocess.run([sys.executable, *command], cwd=tmp_path / "b", env=env,
                           capture_output=True, text=True, timeout=300)
    assert whole.returncode == 0 and "resuming" not in whole.stderr, whole.stderr
    assert os.listdir(tmp_path / "a") == ["x.h5"]
    assert (tmp_path / "a" / "x.h5").read_bytes() == (tmp_path / "b" / "x.h5").read_bytes()


def _children(pid):
    """The processes that ``pid``'s main thread has started and that run."""
    with open(f"/proc/{pid}/task/{pid}/children") as f:
        return f.read().split()


@pytest.mark.skipif(not os.path.exists(f"/proc/{os.getpid()}/task/{os.getpid()}/children"),
                    reason="needs Linux's /proc/PID/task/TID/children")
@pytest.mark.parametrize("delay", [0.0, 0.05, 0.1, 0.2])
def test_ctrl_c_while_generations_workers_start_is_one_line(tmp_path, delay):
    """A Ctrl-C ``delay`` seconds after generation's worker processes appear
    (while they start Python and import the renderer): one line, exit 130,
    no file. Their start unblocked SIGINT (multiprocessing's resource
    tracker lifts the mask of the thread that starts it), and each worker
    printed its KeyboardInterrupt traceback (11 to 38 lines) before the
    command's line, in 12 of 26 tries 0.2 to 0.33 s after the start."""
    out = tmp_path / "x.h5"
    process = _start(["-m", "cpl_keras.data.generate", "--pairs", "64", "--image-size", "16",
                      "--workers", "2", "--no-progress", "--out", str(out)])
    try:
        # (the resource tracker, then the two workers)
        assert wait_for(lambda: len(_children(process.pid)) >= 3 or process.poll() is not None,
                        timeout=30)
        time.sleep(delay)
        _ctrl_c(process)
        _, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, err
    assert err == (f"python -m cpl_keras.data.generate: interrupted; {out} was not written; "
                   "the same command starts again from the first pair\n"), err
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("module", ["cpl_keras.calibrate", "cpl_keras.real.build",
                                    "cpl_keras.reproduce"])
def test_ctrl_c_during_the_imports_of_python_m_is_one_line(tmp_path, module):
    """``python -m cpl_keras.X`` interrupted while X's module (and the
    packages above it, NumPy and h5py for ``cpl_keras.real``) are imported:
    one line, exit 130, no file (Python's handler printed a KeyboardInterrupt
    traceback from inside those imports, exit 1, when a Ctrl-C came 0.2 to
    0.7 s after the start). The Ctrl-C is sent as soon as ``-X importtime``
    says the package ``cpl_keras`` is imported, the rest of the imports
    still to come."""
    out = tmp_path / "out.json"
    args = {"cpl_keras.calibrate": ["l.png", "r.png", "--run", str(tmp_path / "run"),
                                    "--json-out", str(out)],
            "cpl_keras.real.build": ["middlebury", "--out", str(out)],
            "cpl_keras.reproduce": ["--quick", "--out", str(tmp_path / "paper")]}[module]
    process = _start(["-X", "importtime", "-m", module, *args])
    try:
        # (read from the pipe itself: a readline() reads ahead into a buffer
        # that communicate(), which reads the pipe, never sees)
        seen = wait_for_output(process.stderr, " cpl_keras\n")  # (the package imported)
        assert " cpl_keras\n" in seen, seen
        _ctrl_c(process)
        _, err = process.communicate(timeout=60)
        err = seen + err
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, err
    assert "Traceback" not in err, err
    assert [line for line in err.splitlines() if not line.startswith("import time:")] == [
        f"python -m {module}: interrupted"], err
    assert os.listdir(tmp_path) == []


#: A ``sitecustomize`` (found through PYTHONPATH during Python's start-up)
#: that sends this process a SIGINT the moment the package asks for its first
#: module, ``cpl_keras.backend``: a Ctrl-C at the package's first import.
SIGINT_AT_FIRST_IMPORT = """\
import os, signal, sys


class CtrlCAtFirstImport:
    def find_spec(self, fullname, path=None, target=None):
        if fullname == "cpl_keras.backend":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None


sys.meta_path.insert(0, CtrlCAtFirstImport())
"""


def test_ctrl_c_at_the_packages_first_import_is_one_line(tmp_path):
    """A Ctrl-C as soon as ``cpl_keras/__init__.py`` imports its first module
    (sent by the process itself, so the moment is exact): one line, exit 130
    (the guard was set only after the package's own imports, and such a
    Ctrl-C ended in a KeyboardInterrupt traceback and death by SIGINT)."""
    (tmp_path / "sitecustomize.py").write_text(SIGINT_AT_FIRST_IMPORT)
    env = dict(os.environ, KERAS_BACKEND="jax", PYTHONPATH=str(tmp_path))
    done = subprocess.run([sys.executable, "-m", "cpl_keras.calibrate", "l.png", "r.png"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stderr) == (130, "python -m cpl_keras.calibrate: interrupted\n")


def _ctrl_c_inside(monkeypatch, owner, name):
    """``owner.name`` sends this process a SIGINT, then does its work."""
    original = getattr(owner, name)

    def ctrl_c_then(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, ctrl_c_then)


@pytest.mark.parametrize("moment", ["the new file's layout", "the worker pool's start"])
def test_the_first_ctrl_c_of_generation_is_never_lost(tmp_path, monkeypatch, capsys, moment):
    """A Ctrl-C just after ``.partial`` appears (the file's datasets being
    made) or while the worker processes start: exit 130, a line that says
    no pair was kept, no file. (The first left a half-made ``.partial`` that
    the line said "keeps the blocks written in full" and the next run could
    not read; the second was ignored, and generation ended with exit 0.)"""
    import multiprocessing.pool

    from cpl_keras.commands import generate
    from cpl_keras.data import writer

    if moment == "the new file's layout":
        _ctrl_c_inside(monkeypatch, writer.StereoWriter, "_lay_out")
    else:
        _ctrl_c_inside(monkeypatch, multiprocessing.pool.Pool, "_repopulate_pool")
    out = tmp_path / "x.h5"
    assert generate.main(["--pairs", "40", "--image-size", "16", "--workers", "2",
                          "--no-progress", "--out", str(out)]) == 130
    assert capsys.readouterr().err == (
        f"python -m cpl_keras.data.generate: interrupted; {out} was not written; the same "
        "command starts again from the first pair\n")
    assert os.listdir(tmp_path) == []


def test_a_ctrl_c_swallowed_during_generation_stops_it_before_the_file_is_written(
        tmp_path, monkeypatch, capsys):
    """A SIGINT that lands where an exception is swallowed (an h5py
    callback, say: the unraisable hook leaves it pending) still stops the
    generator at its next block: one line, exit 130, no file."""
    from cpl_keras import interrupts
    from cpl_keras.commands import generate
    from cpl_keras.data import writer

    write = writer.StereoWriter.write

    def write_then_swallowed_ctrl_c(self, *args):
        write(self, *args)
        interrupts._pending.set()  # what the unraisable hook leaves behind

    monkeypatch.setattr(writer.StereoWriter, "write", write_then_swallowed_ctrl_c)
    out = tmp_path / "cvgl.h5"
    assert generate.main(["--pairs", "40", "--image-size", "32", "--workers", "1",
                          "--no-progress", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "data.generate: interrupted" in err, err
    assert os.listdir(tmp_path) == ["cvgl.h5.partial"]  # (its first block, to be continued)


def test_ctrl_c_stops_the_reproduction_resumably(tmp_path):
    data_dir, runs_dir = tmp_path / "data", tmp_path / "runs"
    command = ["-m", "cpl_keras.reproduce", "--quick", "--out", str(tmp_path / "out"),
               "--data-dir", str(data_dir), "--runs-dir", str(runs_dir)]
    process = _start(command)
    # generating its first dataset: its progress bar shows the first block written
    seen = wait_for_output(process.stderr, " pairs/s ")
    assert " pairs/s " in seen, seen
    _ctrl_c(process)
    line = _one_line_130(process, "python -m cpl_keras.reproduce")
    assert "run the same command again: python -m cpl_keras.reproduce --quick" in line
    for name in os.listdir(data_dir):  # (a .partial file is continued by the same command)
        if not name.endswith((".partial", ".lock")):  # (the cache's lock: no data)
            StereoFile(data_dir / name).close()  # whole, or it would not be there


def test_an_error_after_a_ctrl_c_is_taken_for_the_ctrl_c():
    """An exception that ends an ``interruptible()`` block once a Ctrl-C has
    come is what the Ctrl-C stopped half-way (Keras's TypeError from a
    variable it was initialising, seen at 1 of 3 Ctrl-Cs of train.py at
    40 s: a traceback, then Python's teardown): ``Interrupted``, from it.
    Without a Ctrl-C it is left as it is."""
    from cpl_keras import cli, interrupts

    with pytest.raises(cli.Interrupted) as caught, cli.interruptible():
        interrupts._pending.set()
        raise TypeError("'NoneType' object is not callable")
    assert isinstance(caught.value.__cause__, TypeError)
    with pytest.raises(TypeError), cli.interruptible():
        raise TypeError("a bug")


def test_a_ctrl_c_swallowed_by_a_callback_prints_nothing_and_stays_pending(capsys):
    """A SIGINT inside a callback whose exceptions Python ignores (JAX's
    garbage-collection callback) must not print a traceback; the next
    check_interrupt() stops the command."""
    import types

    from cpl_keras import cli, interrupts

    with cli.interruptible():
        interrupts._pending.set()
        sys.unraisablehook(types.SimpleNamespace(
            exc_type=cli.Interrupted, exc_value=cli.Interrupted(), exc_traceback=None,
            err_msg="Exception ignored in", object=None))
        assert capsys.readouterr().err == ""
        with pytest.raises(cli.Interrupted):
            cli.check_interrupt()


@pytest.mark.parametrize("moment", ["forward pass", "geometric baseline"])
def test_ctrl_c_during_evaluate_is_one_line(tiny_run, tmp_path, moment):
    """Ctrl-C while evaluate.py scores a table (at the line that says it
    has reached ``moment``): one line, exit 130, no table written."""
    out = tmp_path / "out"
    process = _start(["evaluate.py", "--table", "1", "--runs", tiny_run["run"],
                      "--out", str(out)])
    seen = []
    try:
        while True:
            line = process.stderr.readline()
            assert line, "evaluate.py ended before " + moment + ": " + "".join(seen)
            seen.append(line)
            if line.startswith(moment):
                break
        _ctrl_c(process)
        rest, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    err = "".join(seen) + err
    assert process.returncode == 130, err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if "interrupted" in line]
    assert lines == ["evaluate.py: interrupted; nothing was written"], err
    assert not out.exists() or not any(out.iterdir())


def _interrupt_at(args, moment, cache):
    """Start ``args`` with an empty compile cache of its own (so that it
    compiles), send Ctrl-C as soon as its stderr shows ``moment`` (its
    imports reported by ``-X importtime``, its compilations by
    ``JAX_LOG_COMPILES``); (exit status, stderr, whether ``moment`` came)."""
    env = dict(os.environ, KERAS_BACKEND="jax", CPL_KERAS_CACHE=cache,
               JAX_COMPILATION_CACHE_DIR=os.path.join(cache, "xla"), JAX_LOG_COMPILES="1")
    process = subprocess.Popen([sys.executable, "-X", "importtime", *args], cwd=REPO, env=env,
                               text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               start_new_session=True)
    try:
        seen = wait_for_output(process.stderr, moment)
        try:
            _ctrl_c(process)
        except ProcessLookupError:
            pass
        _, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    return process.returncode, seen + err, moment in seen


#: Moments to interrupt evaluate.py at, each for what it exercises, and the
#: line on its stderr that marks it: the start of the command (cli.run's
#: guard set, the command's imports begun), the imports (NumPy and JAX done,
#: Keras's own under way), the model's load (Keras imported, the custom
#: objects registered) and XLA's compilation (of the prediction step, an
#: empty cache).
MOMENTS = {"start-up": " cpl_keras.commands\n", "imports": " jax\n",
           "model load": " cpl_keras.models.factory\n",
           "compilation": "Compiling jit(predict_step)"}


@pytest.mark.slow
def test_ctrl_c_of_evaluate_at_four_moments_exits_130_with_one_line(tiny_run, tmp_path):
    """Ctrl-C at start-up, during the imports, the model's load and XLA's
    compilation: exit 130 and one line every time, nothing written. (Python's
    teardown with XLA's compilation still in flight crashed 4 of 10 such
    interrupts with a segmentation fault, exit -11 / 139; ``cli.run`` ends
    an interrupted process with ``os._exit(130)``.) Each command has an
    empty compile cache of its own, so that it compiles; two at a time, on
    2 cores. Each Ctrl-C is sent when the command's stderr says it has
    reached its moment, whatever the machine's speed."""
    from concurrent.futures import ThreadPoolExecutor

    def one(name):
        out = tmp_path / f"out-{name}"
        status, err, came = _interrupt_at(["evaluate.py", "--run", tiny_run["run"], "--data",
                                           tiny_run["data"], "--out", str(out)],
                                          MOMENTS[name], str(tmp_path / f"cache-{name}"))
        return name, status, err, came, sorted(os.listdir(out)) if out.exists() else []

    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(one, MOMENTS))
    for name, status, err, came, written in results:
        assert came, f"evaluate.py never reached {name}: {err[-3000:]}"
        assert status == 130, f"at {name}: exit {status}: {err}"
        assert "Traceback" not in err and "Segmentation" not in err, err
        lines = [line for line in err.strip().splitlines() if "interrupted" in line]
        assert lines == ["evaluate.py: interrupted; nothing was written"], err
        assert written == [], f"at {name} it wrote {written}"


@pytest.mark.slow
@pytest.mark.parametrize("moment", ["Compiling jit(", "Compiling jit(train_step)"],
                         ids=["its first compilation", "the training step's compilation"])
def test_ctrl_c_of_a_benchmark_while_it_compiles_exits_130_with_one_line(tmp_path, moment):
    """The benchmark scripts go through the same exit path (``cli.run``):
    no traceback, no crash."""
    status, err, came = _interrupt_at(["bench/bench_variants.py", "--variants", "baseline",
                                       "--image-size", "32", "--rounds", "50"],
                                      moment, str(tmp_path / "cache"))
    assert came, err[-3000:]
    assert status == 130, err
    assert "Traceback" not in err, err
    assert [line for line in err.splitlines() if "interrupted" in line] == [
        "bench/bench_variants.py: interrupted"], err


def test_every_command_leaves_through_cli_run():
    """One exit path: the ``__main__`` block of every module of the package,
    of bench/, of analyses/ and of the top-level commands calls ``cli.run`` (a bare
    ``sys.exit(main())`` is what crashed on Ctrl-C)."""
    import glob
    import re

    files = (glob.glob(os.path.join(REPO, "cpl_keras", "**", "*.py"), recursive=True)
             + glob.glob(os.path.join(REPO, "bench", "*.py"))
             + glob.glob(os.path.join(REPO, "analyses", "*.py"))
             + [os.path.join(REPO, name) for name in ("train.py", "evaluate.py")])
    checked = 0
    for path in files:
        with open(path) as f:
            text = f.read()
        block = re.search(r'\nif __name__ == "__main__":\n((?:    .*\n|\n)+)', text)
        if not block:
            continue
        checked += 1
        # (a library module's python -m form runs its command, whose block calls cli.run)
        assert "cli.run(" in block.group(1) or 'runpy.run_module("cpl_keras.commands.' in \
            block.group(1), f"{os.path.relpath(path, REPO)}: {block.group(1)}"
    assert checked >= 25


def console_scripts():
    """``{name: (module, function)}``: pyproject.toml's ``[project.scripts]``."""
    import re

    with open(os.path.join(REPO, "pyproject.toml")) as f:
        table = re.search(r"^\[project\.scripts\]\n(.*?)(?:^\[|\Z)", f.read(), re.M | re.S)
    found = re.findall(r'^([\w-]+) = "([\w.]+):(\w+)"$', table.group(1), re.M)
    return {name: (module, function) for name, module, function in found}


def test_every_installed_command_leaves_through_cli_run():
    """The same exit path for the installed commands (``cpl-train``, ...):
    each entry point's function calls ``cli.run``, or is made by a function
    of the module that does (``console._command``)."""
    import ast
    import importlib

    scripts = console_scripts()
    assert {"cpl-train", "cpl-evaluate", "cpl-reproduce", "cpl-calibrate", "cpl-graph",
            "cpl-generate", "cpl-real-build"} <= set(scripts), scripts
    for name, (module, function) in scripts.items():
        with open(importlib.import_module(module).__file__) as f:
            tree = ast.parse(f.read())
        functions = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}
        made_by = {t.id: n.value.func.id for n in tree.body if isinstance(n, ast.Assign)
                   and isinstance(n.value, ast.Call) and isinstance(n.value.func, ast.Name)
                   for t in n.targets if isinstance(t, ast.Name)}
        node = functions.get(function) or functions[made_by[function]]
        calls = [ast.unparse(c.func) for c in ast.walk(node) if isinstance(c, ast.Call)]
        assert "cli.run" in calls, (name, calls)
        assert callable(getattr(importlib.import_module(module), function)), name


def test_cli_run_exit_statuses(tmp_path):
    """``cli.run``: main's status; a KeyboardInterrupt -> one line and 130;
    a package error or OSError -> one line and 2; a SystemExit with a
    message -> the message and 1, as Python gives it; any exception after a
    Ctrl-C -> the Ctrl-C's line and 130."""
    script = tmp_path / "command.py"
    script.write_text(
        "import sys\n"
        "from cpl_keras import cli, interrupts\n"
        "from cpl_keras.errors import Error\n"
        "def main():\n"
        "    what = sys.argv[1]\n"
        "    if what == 'ok': return 0\n"
        "    if what == 'ctrl-c': raise KeyboardInterrupt\n"
        "    if what == 'error': raise Error('dataset not found: x.h5')\n"
        "    if what == 'oserror': open('/nonexistent/x')\n"
        "    if what == 'exit': raise SystemExit('prog: error: said by main')\n"
        "    if what == 'ctrl-c-then-bug': interrupts._pending.set(); raise TypeError('half-way')\n"
        "    return 3\n"
        "cli.run(main, 'prog')\n")
    env = dict(os.environ, PYTHONPATH=REPO)
    expected = {"ok": (0, []), "ctrl-c": (130, ["prog: interrupted"]),
                "error": (2, ["prog: error: dataset not found: x.h5"]),
                "oserror": (2, None), "other": (3, []), "exit": (1, ["prog: error: said by main"]),
                "ctrl-c-then-bug": (130, ["prog: interrupted"])}
    for what, (status, lines) in expected.items():
        done = subprocess.run([sys.executable, str(script), what], env=env, text=True,
                              capture_output=True, timeout=60)
        assert done.returncode == status, (what, done.stderr)
        err = done.stderr.strip().splitlines()
        if lines is None:
            assert len(err) == 1 and err[0].startswith("prog: error: "), done.stderr
        else:
            assert err == lines, (what, done.stderr)


_BOTH_PATHS = """
import sys, threading, time
from cpl_keras import cli, interrupts

interrupts.GRACE_S = 0.5
first = sys.argv[1]
cli.on_interrupt(lambda: time.sleep(0.6))  # the first caller is slow to print


def swallowing(until):
    # a command whose callbacks swallow the Ctrl-C (and its redeliveries)
    while True:
        try:
            while not until():
                time.sleep(0.005)
            return
        except KeyboardInterrupt:
            pass


def main():
    interrupts._pending.set()  # a Ctrl-C that a callback swallowed
    start = time.monotonic()
    if first == "main":
        # the command prints its line while the watchdog's grace runs out
        swallowing(lambda: time.monotonic() - start > 0.3)
        return cli.interrupted("prog", note="main")
    if first == "watchdog":
        # the watchdog has claimed the line; the command ends beside it
        swallowing(interrupts._announced.is_set)
        raise KeyboardInterrupt
    barrier = threading.Barrier(8)

    def call():
        barrier.wait()
        cli.interrupted("prog", note="threads")

    threads = [threading.Thread(target=call) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return 130


cli.run(main, "prog", note="watchdog")
"""


@pytest.mark.parametrize("first, line", [("main", "prog: interrupted; main"),
                                         ("watchdog", "prog: interrupted; watchdog"),
                                         ("threads", "prog: interrupted; threads")])
def test_the_interrupted_line_is_printed_once_whichever_paths_end_the_command(
        tmp_path, first, line):
    """The command's own handler and ``cli.run``'s watchdog (or 8 threads
    at once) all end the same interrupted command: exactly one line, not
    two glued together and not none (a path that found the line claimed
    used to end the process before the other had printed it), exit 130."""
    script = tmp_path / "both.py"
    script.write_text(_BOTH_PATHS)
    done = subprocess.run([sys.executable, str(script), first], text=True, capture_output=True,
                          env=dict(os.environ, PYTHONPATH=REPO), timeout=60)
    assert done.returncode == 130, done.stderr
    assert done.stderr.splitlines() == [line], done.stderr


@pytest.mark.parametrize("end", ["return 0", "raise SystemExit(0)"])
def test_a_ctrl_c_after_the_command_is_done_is_ignored(tmp_path, end):
    """A Ctrl-C that lands once ``main`` has returned, or left through
    ``SystemExit`` (argparse's ``--help``), in the interpreter's teardown
    (an atexit callback here) leaves the finished command's exit status as
    it was; it used to end it by SIGINT (exit -2, no line)."""
    script = tmp_path / "done.py"
    script.write_text(
        "import atexit, sys, time\n"
        "from cpl_keras import cli\n"
        "def teardown():  # (slow)\n"
        "    print('teardown', flush=True)\n"
        "    time.sleep(1.5)\n"
        "def main():\n"
        "    atexit.register(teardown)\n"
        "    print('done', flush=True)\n"
        f"    {end}\n"
        "cli.run(main, 'prog')\n")
    process = subprocess.Popen([sys.executable, str(script)], text=True, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, env=dict(os.environ, PYTHONPATH=REPO),
                               start_new_session=True)
    seen = wait_for_output(process.stdout, "teardown\n")  # (main has returned)
    assert seen == "done\nteardown\n", seen
    _ctrl_c(process)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 0, (process.returncode, err)
    assert err == "", err
