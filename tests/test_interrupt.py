"""Ctrl-C (SIGINT to the process group, as a terminal sends it) stops a
command promptly: one line on stderr, exit 130, nothing half-written, and a
training run that the same command resumes (cpl_keras.cli.interruptible)."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from test_datasets import write_stereo_fixture

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


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


def _wait_for(condition, timeout=120):
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            if condition():
                return True
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.02)
    return False


def _one_line_130(process, prog, timeout=30):
    out, err = process.communicate(timeout=timeout)
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
    state = os.path.join(run_dir, "backup", "state.json")

    def epochs_done():
        with open(state) as f:
            return json.load(f)["epoch"]

    process = _start(args, cache)
    assert _wait_for(lambda: epochs_done() >= 1)
    _ctrl_c(process)
    line = _one_line_130(process, "train.py")
    assert "run the same command again" in line and run_dir in line
    done = epochs_done()
    assert 1 <= done < 6, "the run must be stopped mid-training"
    process = _start(args, cache)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, err
    assert f"Resuming {run_dir} after epoch {done}" in err
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    assert config["status"] == "finished" and config["epochs_run"] == 6


def test_ctrl_c_stops_generation_and_leaves_no_partial_file(tmp_path):
    out = tmp_path / "cvgl.h5"
    process = _start(["-m", "cpl_keras.data.generate", "--pairs", "4000", "--image-size", "32",
                      "--workers", "2", "--no-progress", "--out", str(out)])
    assert _wait_for(lambda: os.path.exists(str(out) + ".partial"))
    time.sleep(0.5)
    _ctrl_c(process)
    _one_line_130(process, "python -m cpl_keras.data.generate")
    assert os.listdir(tmp_path) == []


def test_a_ctrl_c_swallowed_during_generation_stops_it_before_the_file_is_written(
        tmp_path, monkeypatch, capsys):
    """A SIGINT that lands where an exception is swallowed (an h5py
    callback, say: the unraisable hook leaves it pending) still stops the
    generator at its next block: one line, exit 130, no file."""
    from cpl_keras import cli
    from cpl_keras.data import generate, storage

    write = storage.StereoWriter.write

    def write_then_swallowed_ctrl_c(self, *args):
        write(self, *args)
        cli._pending.set()  # what the unraisable hook leaves behind

    monkeypatch.setattr(storage.StereoWriter, "write", write_then_swallowed_ctrl_c)
    out = tmp_path / "cvgl.h5"
    assert generate.main(["--pairs", "40", "--image-size", "32", "--workers", "1",
                          "--no-progress", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "data.generate: interrupted" in err, err
    assert os.listdir(tmp_path) == []


def test_ctrl_c_stops_the_reproduction_resumably(tmp_path):
    data_dir, runs_dir = tmp_path / "data", tmp_path / "runs"
    command = ["evaluate.py", "--reproduce", "--quick", "--out", str(tmp_path / "out"),
               "--data-dir", str(data_dir), "--runs-dir", str(runs_dir)]
    process = _start(command)
    assert _wait_for(lambda: os.listdir(data_dir))  # generating its first dataset
    time.sleep(0.3)
    _ctrl_c(process)
    line = _one_line_130(process, "evaluate.py")
    assert "run the same command again: python evaluate.py --reproduce --quick" in line
    assert not [n for n in os.listdir(data_dir) if n.endswith(".partial")]


def test_a_ctrl_c_swallowed_by_a_callback_prints_nothing_and_stays_pending(capsys):
    """A SIGINT inside a callback whose exceptions Python ignores (JAX's
    garbage-collection callback) must not print a traceback; the next
    check_interrupt() stops the command."""
    import types

    from cpl_keras import cli

    with cli.interruptible():
        cli._pending.set()
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
