"""A training run's faults and bad input (cpl_keras.training and train.py),
on tiny data: a run killed and resumed, a second process on the same run, a
non-finite loss, early stopping, data parallelism, a time budget; bad input
is one line, exit 2, nothing written.
"""

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from helpers import (
    REPO, RESUME_ARGS, epochs_done, load_script, read_log, train_py, wait_for, wait_for_output,
    writable_copy, write_stereo_fixture,
)


def cli(*args, cache, env=None):
    """Run train.py in a subprocess, with its XLA compilation cache in ``cache``."""
    argv, environment = train_py(*args, cache=cache, env=env)
    return subprocess.Popen(argv, cwd=REPO, env=environment, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


# ---------------------------------------------------------------------------
# Faults
# ---------------------------------------------------------------------------
#: train.py's line on a run that has already finished.
FINISHED = "already finished, left as it is: "
#: config.json entries that differ between two runs of one command.
PER_PROCESS = ("wall_time_s", "run_dir", "command")


@pytest.fixture(scope="module")
def uninterrupted(early):
    """The run of RESUME_ARGS on ``stereo40`` made in one go, through
    train.py (started early, conftest's ``EARLY``): its exit status, stdout,
    stderr and run directory."""
    folder, result = early("uninterrupted")
    return {"returncode": result.returncode, "out": result.stdout, "err": result.stderr,
            "run_dir": os.path.join(folder, "run")}


def _ends_like(run_dir, returncode, out, err, uninterrupted):
    """A resumed run ends exactly as the uninterrupted one: exit status, the
    summary line, log.csv, config.json and the files of the run directory."""
    assert returncode == uninterrupted["returncode"] == 0, err
    assert "Traceback" not in err and ": error:" not in err, err

    def summary(text, directory):
        loss = re.search(r"best val_loss (\S+),", text)
        return text.replace(directory, "R").replace(loss.group(1), "L"), float(loss.group(1))

    line, loss = summary(out, run_dir)
    straight_line, straight_loss = summary(uninterrupted["out"], uninterrupted["run_dir"])
    assert line == straight_line and loss == pytest.approx(straight_loss, rel=1e-5)
    rows, straight = read_log(run_dir), read_log(uninterrupted["run_dir"])
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3, 4]
    for resumed_row, straight_row in zip(rows, straight):
        assert float(resumed_row["loss"]) == pytest.approx(float(straight_row["loss"]), rel=1e-5)
        assert float(resumed_row["val_loss"]) == pytest.approx(
            float(straight_row["val_loss"]), rel=1e-5)
    configs = []
    for directory in (run_dir, uninterrupted["run_dir"]):
        with open(os.path.join(directory, "config.json")) as f:
            configs.append({k: v for k, v in json.load(f).items() if k not in PER_PROCESS})
    assert configs[0]["status"] == "finished" and configs[0]["epochs_run"] == 4
    assert configs[0]["best_val_loss"] == pytest.approx(configs[1].pop("best_val_loss"), rel=1e-5)
    configs[0].pop("best_val_loss")
    assert configs[0] == configs[1]
    assert sorted(os.listdir(run_dir)) == sorted(os.listdir(uninterrupted["run_dir"]))
    assert not [n for n in os.listdir(os.path.join(run_dir, "backup")) if n.endswith(".h5")]


def _on_a_terminal(*args, cache, err_path):
    """train.py as ``cli`` runs it, its stdout a pseudo-terminal (so it draws
    its progress bar) and its stderr ``err_path``; returns the process, the
    thread that reads the terminal into ``seen`` (a list of text chunks)
    and ``seen``. The reader drains the terminal, so the child never blocks."""
    import pty
    import threading

    environment = dict(os.environ, KERAS_BACKEND="jax", JAX_COMPILATION_CACHE_DIR=cache,
                       JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    master, slave = pty.openpty()
    with open(err_path, "w") as err:
        process = subprocess.Popen([sys.executable, os.path.join(REPO, "train.py"), *args],
                                   cwd=REPO, env=environment, stdin=subprocess.DEVNULL,
                                   stdout=slave, stderr=err)
    os.close(slave)
    seen = []

    def read():
        try:
            while chunk := os.read(master, 4096):
                seen.append(chunk.decode(errors="replace"))
        except OSError:  # (EIO: the child has closed the terminal)
            pass
        finally:
            os.close(master)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    return process, reader, seen


#: The progress bar train.py draws on a terminal after a training batch:
#: "epoch 2/4 [====................] 1/5 0s left  loss ...".
BAR = re.compile(r"epoch (\d+)/\d+ \[[=.]+\] (\d+)/(\d+)")


@pytest.mark.slow
@pytest.mark.parametrize("when", ["after an epoch's commit", "in the middle of an epoch"])
def test_killed_run_resumes_and_ends_like_an_uninterrupted_run(
        when, stereo40, tmp_path, train_cache, uninterrupted):
    run_dir = str(tmp_path / "run")
    args = [*RESUME_ARGS, "--data", stereo40, "--run-dir", run_dir]

    if when == "after an epoch's commit":
        process = cli(*args, cache=train_cache)
        # as reported: killed as soon as log.csv has two epoch rows
        assert wait_for(lambda: len(read_log(run_dir)) >= 2)
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=300)
    else:
        # Killed inside the training of epoch N + 1 (N >= 1): the progress bar
        # of a batch of epoch N + 1 is drawn only after epoch N's commit and
        # its publishing (RunState's on_epoch_end, before the epoch line).
        loud = [a for a in args if a != "--quiet"]
        process, reader, seen = _on_a_terminal(*loud, cache=train_cache,
                                               err_path=tmp_path / "killed.err")
        try:
            deadline = time.time() + 120
            while True:  # (the first bar of epoch 2 or later; then kill at once)
                bar = next((m for m in BAR.finditer("".join(seen)) if int(m.group(1)) >= 2),
                           None)
                if bar or process.poll() is not None or time.time() > deadline:
                    break
                time.sleep(0.005)
        finally:
            process.send_signal(signal.SIGKILL)
            process.wait(timeout=300)
            reader.join(timeout=30)
        assert bar is not None, ("".join(seen), (tmp_path / "killed.err").read_text())
        training, batch, steps = (int(g) for g in bar.groups())
        assert 1 <= batch < steps, bar.group(0)  # mid-epoch: batches of it still to train
        committed = training - 1
    done = epochs_done(run_dir)
    assert 1 <= done < 4, f"the run must be killed mid-training ({when})"
    assert len(read_log(run_dir)) == done
    if when == "in the middle of an epoch":
        # epoch N committed, N + 1 not; N's publishing complete: log.csv has
        # its N rows (above) and curves.png was drawn after N's state.json
        assert done == committed, (done, bar.group(0))
        curves = os.path.join(run_dir, "curves.png")
        assert os.path.isfile(curves), "killed before epoch N's curves.png was published"
        state = os.path.join(run_dir, "backup", "state.json")
        assert os.stat(curves).st_mtime_ns >= os.stat(state).st_mtime_ns, \
            "curves.png is older than epoch N's commit: killed during its publishing"

    process = cli(*args, cache=train_cache)
    out, err = process.communicate(timeout=180)
    assert f"Resuming {run_dir} after epoch {done}" in err
    _ends_like(run_dir, process.returncode, out, err, uninterrupted)
    # the same command once more: nothing left to train, the same ending
    process = cli(*args, cache=train_cache)
    out, err = process.communicate(timeout=180)
    assert out.startswith(FINISHED), out
    _ends_like(run_dir, process.returncode, out[len(FINISHED):], err, uninterrupted)


def _waits_for_flock(pid, path):
    """Whether process ``pid`` is blocked waiting for a flock of the file
    ``path``: a "->" line of /proc/locks (its pid, then device:inode)."""
    inode = os.stat(path).st_ino
    with open("/proc/locks") as f:
        return any(fields[1:3] == ["->", "FLOCK"] and int(fields[5]) == pid
                   and int(fields[6].rsplit(":", 1)[1]) == inode
                   for fields in (line.split() for line in f))


@pytest.mark.slow
def test_second_process_waits_for_the_first_and_ends_like_it(
        stereo40, tmp_path, train_cache, uninterrupted):
    """A kill that missed: the command run again while the first process still
    trains waits for it, then finds the run finished (exit 0, no error)."""
    run_dir = str(tmp_path / "run")
    lock = os.path.join(run_dir, "backup", "lock")
    args = [*RESUME_ARGS, "--data", stereo40, "--run-dir", run_dir]
    first = cli(*args, cache=train_cache)
    assert wait_for(lambda: os.path.exists(lock)
                     and os.path.exists(os.path.join(run_dir, "config.json")))
    os.kill(first.pid, signal.SIGSTOP)  # the first holds the lock, frozen mid-run
    try:
        second = cli(*args, cache=train_cache)
        waiting = wait_for_output(second.stderr, "Waiting for the training process")
        assert "Waiting for the training process" in waiting, waiting  # it waits
        # ... and goes on waiting: blocked in flock on the lock the first holds
        assert wait_for(lambda: _waits_for_flock(second.pid, lock)), open("/proc/locks").read()
        assert second.poll() is None
    finally:
        os.kill(first.pid, signal.SIGCONT)
    first_out, first_err = first.communicate(timeout=180)
    out, err = second.communicate(timeout=180)
    err = waiting + err
    _ends_like(run_dir, first.returncode, first_out, first_err, uninterrupted)
    assert "Resuming" not in err and out.startswith(FINISHED)  # it found the run finished
    _ends_like(run_dir, second.returncode, out[len(FINISHED):], err.replace("Waiting for the training process "
                                                            f"that is using {run_dir}", ""),
               uninterrupted)


def test_a_different_run_begun_meanwhile_is_refused_not_called_finished(
        stereo40, tmp_path, monkeypatch, capsys):
    """Two train.py started at once on one run directory with other learning
    rates: the one that planned while the directory was empty finds the
    other's run there later (before its finished-run check, or once it has
    built its model and takes the lock, free or held by the other). Each
    time: refused in one line naming the other's learning rate, exit 2,
    without waiting for the lock, the other's run left as it is; never
    "already finished" about the other's run."""
    import fcntl
    import shutil
    import threading

    from cpl_keras import runs
    from cpl_keras.training import planning, trainer

    run_dir = tmp_path / "run"
    args = ["--variant", "baseline", "--backbone", "small", "--epochs", "1", "--batch-size", "5",
            "--lr", "0.002", "--quiet", "--data", stereo40, "--run-dir", str(run_dir)]
    other = planning.plan_run(stereo40, variant="baseline", run_dir=str(run_dir),
                              backbone="small", epochs=1, batch_size=5, learning_rate=5e-4)
    originals = {name: getattr(trainer, name) for name in ("plan_run", "finished_run")}

    def other_begins_after(name):  # (the other's config.json, right after ``name``)
        def step(*a, **k):
            result = originals[name](*a, **k)
            if not (run_dir / "config.json").exists():
                runs.write_config(str(run_dir), dataclasses.replace(other.config, status=status))
            return result
        return step

    for when, status, held in (("plan_run", "finished", False),
                               ("finished_run", "finished", False),
                               ("finished_run", "running", True)):
        monkeypatch.setattr(trainer, when, other_begins_after(when))
        if run_dir.exists():
            shutil.rmtree(run_dir)
        (run_dir / "backup").mkdir(parents=True)
        handle = open(run_dir / "backup" / "lock", "a+")
        if held:  # the other process holds the lock while it trains
            fcntl.flock(handle, fcntl.LOCK_EX)
        release = threading.Timer(60, handle.close)  # (a waiter would never end without it)
        release.start()
        start = time.time()
        try:
            code = load_script("train.py").main(args)
        finally:
            release.cancel()
            handle.close()
            monkeypatch.undo()
        captured = capsys.readouterr()
        assert FINISHED not in captured.out, (when, status, captured.out)
        err = captured.err.strip()
        assert code == 2 and "\n" not in err, (when, status, err)
        assert err.startswith("train.py: error: ") and "holds a different run" in err
        assert "learning_rate: 0.0005 there, 0.002 now" in err, err
        assert time.time() - start < 50, status  # refused, not after a wait for the lock
        kept = runs.read_run_config(str(run_dir))
        assert (kept.training.learning_rate, kept.status) == (5e-4, status)
        assert sorted(os.listdir(run_dir)) == ["backup", "config.json"]


def test_nan_loss_stops_and_keeps_the_best_weights(stereo40, tmp_path, monkeypatch):
    """A loss that turns non-finite in epoch 2 (NaN targets from then on)
    stops the run there, marked failed, and model.keras holds epoch 1's
    weights: finite, predicting finite values, equal to best.weights.h5."""
    import keras

    from cpl_keras.training.checkpointing import RunState
    from cpl_keras.training.sequence import StereoSequence
    from cpl_keras.training import summary_line, train

    getitem = StereoSequence.__getitem__

    def nan_from_epoch_2(self, index):
        x, y = getitem(self, index)
        if self.shuffle and self.epoch >= 1:  # (the training sequence)
            y = {name: value * np.nan for name, value in y.items()}
        return x, y

    kept = {}
    on_epoch_end = RunState.on_epoch_end

    def remember(self, epoch, logs=None):
        kept.setdefault(epoch, [np.array(w) for w in self.model.get_weights()])
        return on_epoch_end(self, epoch, logs)

    monkeypatch.setattr(StereoSequence, "__getitem__", nan_from_epoch_2)
    monkeypatch.setattr(RunState, "on_epoch_end", remember)
    run_dir = tmp_path / "run"
    summary = train(stereo40, variant="baseline", run_dir=str(run_dir), epochs=4, batch_size=8,
                    backbone="small", verbose=0, patience=10)
    assert summary.config.status == "failed" and summary.config.best_epoch == 1
    assert summary.config.stopped == "non-finite training loss at epoch 2, batch 1"
    assert "non-finite" in summary_line(summary) and summary.config.epochs_run == 1
    assert json.loads((run_dir / "config.json").read_text())["status"] == "failed"
    model = keras.saving.load_model(run_dir / "model.keras", safe_mode=True)
    saved = model.get_weights()
    assert all(np.isfinite(w).all() for w in saved)
    for a, b in zip(saved, kept[0]):
        np.testing.assert_array_equal(a, b)
    predictions = model.predict(_images(stereo40), verbose=0)
    outputs = predictions.values() if isinstance(predictions, dict) else predictions
    assert all(np.isfinite(np.asarray(v)).all() for v in outputs)


def _images(path, count=4):
    from cpl_keras.data.storage import StereoFile

    with StereoFile(path) as f:
        left, right = f.read_pairs(np.arange(count))
    return {"left_image": left.astype(np.float32), "right_image": right.astype(np.float32)}


def test_early_stopping_ends_the_run_and_model_keras_holds_the_best_epoch(
        stereo40, tmp_path, monkeypatch):
    """Validation losses 3, 2, 5, 6 (scripted) with patience 2: the run stops
    after epoch 4 by early stopping, best epoch 2, and model.keras holds the
    weights of epoch 2, not those of the last epoch."""
    import keras

    from cpl_keras.training.checkpointing import RunState
    from cpl_keras.training import train

    scripted = [3.0, 2.0, 5.0, 6.0, 7.0, 8.0]
    kept = {}
    on_epoch_end = RunState.on_epoch_end

    def scripted_val_loss(self, epoch, logs=None):
        kept[epoch] = [np.array(w) for w in self.model.get_weights()]
        return on_epoch_end(self, epoch, dict(logs or {}, val_loss=scripted[epoch]))

    monkeypatch.setattr(RunState, "on_epoch_end", scripted_val_loss)
    run_dir = tmp_path / "run"
    summary = train(stereo40, variant="baseline", run_dir=str(run_dir), epochs=6, batch_size=8,
                    backbone="small", verbose=0, patience=2, monitor="loss")
    assert (summary.config.epochs_run, summary.config.best_epoch) == (4, 2)
    assert summary.config.stopped == "early stopping: no improvement of val_loss for 2 epochs"
    assert summary.config.status == "finished" and summary.config.best_val_loss == 2.0
    saved = keras.saving.load_model(run_dir / "model.keras", safe_mode=True).get_weights()
    for a, b in zip(saved, kept[1]):
        np.testing.assert_array_equal(a, b)
    assert any(not np.array_equal(a, b) for a, b in zip(saved, kept[3]))
    rows = (run_dir / "log.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 4

@pytest.fixture(scope="module")
def data_parallel_run(early):
    """``train.py --data-parallel`` of MTL-CPL-U on ``stereo40`` on two
    (forced) host devices, batch 5, two epochs (started early, conftest's
    ``EARLY``): ``(run directory, subprocess.CompletedProcess)``."""
    folder, result = early("data_parallel")
    return os.path.join(folder, "run"), result


@pytest.mark.slow
def test_data_parallel_on_two_devices_with_uneven_batches(data_parallel_run):
    run_dir, process = data_parallel_run
    assert process.returncode == 0, process.stderr
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    # 25 training pairs, batch 5 -> 6 (2 devices): 5 batches, the last one padded.
    assert config["num_devices"] == 2 and config["device_batch_size"] == 6
    assert config["num_train"] % 6 != 0
    assert config["epochs_run"] == 2 and len(read_log(run_dir)) == 2




# ---------------------------------------------------------------------------
# Bad input: one line, exit 2, nothing written
# ---------------------------------------------------------------------------
def _bad_files(tmp_path):
    not_h5 = tmp_path / "notes.h5"
    not_h5.write_text("not a dataset")
    no_label = write_stereo_fixture(tmp_path / "no_label.h5", n=30, drop=("tz",))
    small = write_stereo_fixture(tmp_path / "small.h5", n=30, image_size=8)
    nan = write_stereo_fixture(tmp_path / "nan.h5", n=30)
    with h5py.File(nan, "a") as f:
        f["labels/fx"][3] = np.nan
    return {
        "missing": ([str(tmp_path / "nope.h5")], "dataset not found"),
        "not hdf5": ([str(not_h5)], "not an HDF5 file"),
        "no label": ([no_label], "missing label(s) tz"),
        "wrong size": ([small], "below the minimum"),
        "mismatch": ([small, "--image-size", "32"], "images are 8x8"),
        "nan": ([nan], "label 'fx' has 1 non-finite"),
    }


def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    import train as train_cli

    cases = _bad_files(tmp_path)
    good = write_stereo_fixture(tmp_path / "good.h5", n=30)
    # (bad numbers are refused by the parser: test_numeric_arguments_are_checked_...)
    cases["few pairs"] = ([write_stereo_fixture(tmp_path / "few.h5", n=12)], "training pairs")
    for name, (data_args, message) in cases.items():
        run_dir = tmp_path / f"run-{name}"
        code = train_cli.main(["--variant", "cpl-a", "--backbone", "small", "--data", *data_args,
                               "--run-dir", str(run_dir)])
        err = capsys.readouterr().err.strip()
        assert code == 2, name
        assert message in err and "\n" not in err, (name, err)
        assert err.startswith("train.py: error:")
        assert not run_dir.exists(), name

    # A batch larger than the training split (30 pairs: 19 for training) is refused.
    code = train_cli.main(["--variant", "cpl-a", "--backbone", "small", "--data", good,
                           "--batch-size", "20", "--run-dir", str(tmp_path / "big-batch")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    assert "batch size 20 is larger than the training split (19 pairs" in err
    assert not (tmp_path / "big-batch").exists()

    # A run directory holding another run is refused before anything changes.
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "config.json").write_text(json.dumps({"variant": "baseline"}))
    code = train_cli.main(["--variant", "cpl-a", "--backbone", "small", "--data", good,
                           "--run-dir", str(occupied)])
    assert code == 2 and "holds a different run" in capsys.readouterr().err
    assert os.listdir(occupied) == ["config.json"]
    # and so is one whose config.json is damaged or no JSON object, naming why
    for text, why in (('{"variant": "base', "cannot read"), ("[1, 2]", "not a JSON object")):
        (occupied / "config.json").write_text(text)
        code = train_cli.main(["--variant", "cpl-a", "--backbone", "small", "--data", good,
                               "--run-dir", str(occupied)])
        err = capsys.readouterr().err.strip()
        assert code == 2 and "\n" not in err and "an unreadable one" in err and why in err, err
        assert (occupied / "config.json").read_text() == text


def test_bad_arguments_from_the_shell(tmp_path, train_cache):
    run_dir = tmp_path / "run"
    for args, message in (
        (["--variant", "cpl-x"], "invalid choice"),
        (["--variant", "cpl-a", "--data", str(tmp_path / "missing.h5"), "--run-dir", str(run_dir)],
         "dataset not found"),
    ):
        process = cli(*args, cache=train_cache)
        out, err = process.communicate(timeout=60)
        assert process.returncode == 2
        assert message in err and len(err.strip().splitlines()) == 1, err
        assert "Traceback" not in err
        assert not run_dir.exists()


def test_finished_run_is_left_untouched(tiny_run, tmp_path, train_cache):
    """The same command on a finished run (a copy of the shared tiny run)
    changes no file (model.keras keeps its optimizer state) and says so in
    one line, exit 0, without importing Keras or JAX (it returns at once)."""
    run_dir = str(tmp_path / "run")
    writable_copy(tiny_run["run"], run_dir)
    assert json.loads(open(os.path.join(run_dir, "config.json")).read())["status"] == "finished"
    args = ["--variant", "baseline", "--backbone", "small", "--epochs", "1", "--batch-size",
            "8", "--quiet", "--data", tiny_run["data"], "--run-dir", run_dir]

    def snapshot():
        found = {}
        for root, _, names in os.walk(run_dir):
            for name in names:
                path = os.path.join(root, name)
                with open(path, "rb") as f:
                    found[path] = (os.stat(path).st_mtime_ns, f.read())
        return found

    before = snapshot()
    process = cli(*args, cache=train_cache)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, err
    assert out.startswith(FINISHED) and len(out.strip().splitlines()) == 1, out
    assert "Traceback" not in err
    assert snapshot() == before
    # train.py's main, then what it imported
    code = ("import runpy, sys\n"
            "status = runpy.run_path('train.py')['main'](sys.argv[1:])\n"
            "print(status, 'keras' in sys.modules, 'jax' in sys.modules, file=sys.stderr)\n")
    done = subprocess.run([sys.executable, "-c", code, *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env=dict(os.environ, KERAS_BACKEND="jax"))
    assert done.stdout.startswith(FINISHED) and done.stderr.split() == ["0", "False", "False"], \
        done.stderr[-2000:]
    assert snapshot() == before


@pytest.mark.parametrize("flag, value", [
    ("--steps-per-execution", "0"), ("--steps-per-execution", "-1"), ("--seed", "-1"),
    ("--epochs", "0"), ("--batch-size", "0"), ("--workers", "0"), ("--patience", "-1"),
    ("--bn-recompute-batches", "-2"), ("--image-size", "0"), ("--lr", "0"), ("--lr", "-1"), ("--lr", "nan"),
    ("--time-budget", "0"), ("--time-budget", "nan"),
])
def test_numeric_arguments_are_checked_before_anything_is_written(
        flag, value, stereo40, tmp_path, capsys):
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_info:
        load_script("train.py").main(["--variant", "baseline", "--backbone", "small", "--data", stereo40,
                              "--run-dir", str(run_dir), flag, value])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"train.py: error: argument {flag}: must be") and "\n" not in err
    assert not run_dir.exists()


def test_library_checks_steps_per_execution_and_seed(stereo40, tmp_path):
    from cpl_keras.training import TrainingError, train

    for kwargs, needle in (({"steps_per_execution": 0}, "steps per execution"),
                           ({"seed": -1}, "seed"), ({"time_budget_s": -1.0}, "time budget"),
                           ({"time_budget_s": True}, "time budget")):
        with pytest.raises(TrainingError, match=needle):
            train(stereo40, variant="baseline", run_dir=tmp_path / "run", backbone="small",
                  verbose=0, **kwargs)
    assert not (tmp_path / "run").exists()


def test_time_budget_ends_the_run_after_the_epoch_that_would_overrun_it(
        stereo40, tmp_path, capsys):
    """--time-budget: after an epoch, when another as long would pass the
    budget, the run ends as finished with its best epoch and says why; a
    budget that is not reached changes nothing."""
    run_dir = tmp_path / "run"
    args = ["--variant", "baseline", "--backbone", "small", "--data", stereo40, "--epochs", "3",
            "--batch-size", "8", "--quiet", "--run-dir", str(run_dir)]
    assert load_script("train.py").main(args + ["--time-budget", "0.001"]) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["status"] == "finished" and config["time_budget_s"] == 0.001
    assert (config["epochs_run"], config["best_epoch"]) == (1, 1)
    assert config["stopped"] == "time budget: another epoch would end after 0.001 s of training"
    assert (run_dir / "model.keras").is_file()
    assert "best epoch 1 of 1" in capsys.readouterr().out
    roomy = tmp_path / "roomy"
    args[-1] = str(roomy)
    assert load_script("train.py").main(args + ["--epochs", "2", "--time-budget", "1e6"]) == 0
    config = json.loads((roomy / "config.json").read_text())
    assert (config["epochs_run"], config["stopped"]) == (2, None)


def test_diverged_run_is_exit_2_and_replaced_by_the_next_run(stereo40, tmp_path, capsys):
    """A non-finite loss: one error line, exit 2, the run directory marked
    failed; the same command again replaces it (and fails again, alike),
    and a command with sane settings trains a new run in its place."""
    run_dir = tmp_path / "run"
    args = ["--variant", "baseline", "--backbone", "small", "--data", stereo40, "--epochs", "2",
            "--batch-size", "5", "--quiet", "--run-dir", str(run_dir)]
    for attempt in range(2):
        assert load_script("train.py").main(args + ["--lr", "1e35"]) == 2
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert captured.out == "" and len(lines) == 1 + attempt, captured.err
        assert lines[-1].startswith("train.py: error: ") and "non-finite" in lines[-1]
        assert ("Replacing the failed run" in captured.err) == (attempt == 1), captured.err
        config = json.loads((run_dir / "config.json").read_text())
        assert config["status"] == "failed" and config["learning_rate"] == 1e35
    assert load_script("train.py").main(args + ["--epochs", "1"]) == 0
    assert "Replacing the failed run" in capsys.readouterr().err
    config = json.loads((run_dir / "config.json").read_text())
    assert config["status"] == "finished" and config["learning_rate"] is None
    assert config["epochs_run"] == 1


def test_resume_after_a_kill_during_the_final_save_keeps_the_optimizer_state(stereo40, tmp_path):
    """A run killed while it wrote model.keras (its state says it ended, its
    config says running) is finished by the same command: model.keras again,
    with the optimizer's state and without Keras's skipped-variables warning."""
    import warnings

    import keras

    from cpl_keras.training import train

    run_dir = tmp_path / "run"
    kwargs = dict(variant="baseline", run_dir=str(run_dir), epochs=1, batch_size=8,
                  backbone="small", verbose=0)
    train(stereo40, **kwargs)
    first = keras.saving.load_model(run_dir / "model.keras", safe_mode=True)
    steps = int(first.optimizer.iterations.numpy())
    assert steps > 0
    # what a kill in the middle of the final save leaves behind
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps(dict(config, status="running")))
    (run_dir / "model.keras").unlink()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = train(stereo40, **kwargs)
    assert summary.config.status == "finished" and not summary.finished_before
    assert not [w for w in caught if "Skipping variable loading" in str(w.message)]
    again = keras.saving.load_model(run_dir / "model.keras", safe_mode=True)
    assert int(again.optimizer.iterations.numpy()) == steps
    for a, b in zip(first.optimizer.variables, again.optimizer.variables):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_truncated_files_are_called_truncated(stereo40, tmp_path, tiny_run):
    from cpl_keras import runs
    from cpl_keras.data.storage import DatasetError, StereoFile

    data = tmp_path / "cut.h5"
    with open(stereo40, "rb") as f:
        data.write_bytes(f.read()[: os.path.getsize(stereo40) // 2])
    with pytest.raises(DatasetError, match="truncated or corrupt"):
        StereoFile(data)
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(DatasetError, match="not an HDF5 file"):
        StereoFile(tmp_path / "text.h5")
    model = os.path.join(tiny_run["run"], "model.keras")
    run = runs.load_run(tiny_run["run"])
    for size in (os.path.getsize(model) // 2, os.path.getsize(model) - 100):
        cut = tmp_path / f"cut{size}.keras"
        with open(model, "rb") as f:
            cut.write_bytes(f.read()[:size])
        with pytest.raises(runs.RunError, match="truncated or corrupt"):
            runs.load_model(dataclasses.replace(run, model_path=str(cut)))
