"""Training end to end (cpl_keras.training and train.py), on tiny data.

Small backbone, 32x32 images, a few dozen pairs, two or three epochs.
"""

import csv
import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from cpl_keras.camera import TARGETS
from helpers import (
    REPO, RESUME_ARGS, epochs_done, train_py, wait_for, write_stereo_fixture,
)

RUN_FILES = ("config.json", "model.keras", "best.weights.h5", "log.csv", "curves.png",
             "train_stats.json", "split.npz")
# 40 pairs -> 25 train, 3 val, 12 test: batches of 5 keep one shape (one compile).
TINY = dict(backbone="small", epochs=2, batch_size=5, verbose=0)


@pytest.fixture(scope="module")
def dataset(stereo40):
    return stereo40


def read_log(run_dir):
    with open(os.path.join(run_dir, "log.csv")) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def xla_cache(train_cache):
    """The XLA compile cache of this module's train.py processes (conftest's
    ``train_cache``)."""
    return train_cache


def cli(*args, cache, env=None):
    """Run train.py in a subprocess, with its XLA compilation cache in ``cache``."""
    argv, environment = train_py(*args, cache=cache, env=env)
    return subprocess.Popen(argv, cwd=REPO, env=environment, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


# ---------------------------------------------------------------------------
# Every variant: the whole run directory, a model that reloads and agrees
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("variant", ["baseline", "cpl-u", "cpl-a", "deep-homo"])
def test_every_variant_writes_the_run_directory(variant, dataset, variant_run, tmp_path):
    """The shared run of each variant (conftest's VARIANT_RUN: these
    settings, seed 1) on this module's dataset."""
    import keras

    import cpl_keras.models.factory  # noqa: F401  (registers the custom objects)
    from cpl_keras.camera import TARGETS
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import load_split
    from cpl_keras.training import train

    run_dir, summary = variant_run(variant)["run_dir"], variant_run(variant)["summary"]
    for name in RUN_FILES:
        assert os.path.isfile(os.path.join(run_dir, name)), name
    assert summary["status"] == "finished" and summary["epochs_run"] == 2
    assert summary["best_epoch"] in (1, 2) and np.isfinite(summary["best_val_loss"])

    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    assert config["variant"] == variant and config["data"] == os.path.abspath(dataset)
    assert config["build"]["image_size"] == [32, 32] and config["build"]["backbone"] == "small"
    assert config["epochs_run"] == 2 and config["best_epoch"] == summary["best_epoch"]
    assert config["learning_rate_used"] == (1.5e-3 if variant == "deep-homo" else 1e-3)
    for key in ("seed", "batch_size", "split", "data_parallel", "wall_time_s"):
        assert key in config
    # each fact once: as_released is a build argument, not also a top-level key
    assert config["build"]["as_released"] is False and "as_released" not in config
    # the machine it trained on: one entry, this process's cores and versions
    (machine,) = config["machines"]
    assert machine["cpu_count"] == os.cpu_count() and machine["cpu"]
    assert machine["keras"] == keras.__version__ and machine["keras_backend"] == "jax"
    assert machine["devices"] and all(d.startswith("cpu:") for d in machine["devices"])

    rows = read_log(run_dir)
    assert [int(r["epoch"]) for r in rows] == [1, 2]  # numbered from 1
    best_row = rows[summary["best_epoch"] - 1]
    assert float(best_row["val_loss"]) == pytest.approx(summary["best_val_loss"], rel=1e-6)

    split = load_split(os.path.join(run_dir, "split.npz"))
    assert sum(len(v) for v in split.values()) == 40
    assert not set(split["val"]) & set(split["test"])
    with open(os.path.join(run_dir, "train_stats.json")) as f:
        stats = json.load(f)
    assert stats["num_train"] == len(split["train"]) and stats["targets"] == list(TARGETS)

    # The saved model reloads safely and predicts exactly what the kept
    # epoch's weights (best.weights.h5) in a model built anew predict.
    from cpl_keras.models import build_model

    model = keras.saving.load_model(os.path.join(run_dir, "model.keras"), safe_mode=True)
    trained = build_model(variant, **config["build"])
    trained.load_weights(os.path.join(run_dir, "best.weights.h5"))
    with StereoFile(dataset) as f:
        left, right = f.read_pairs(split["test"][:5])
    x = {"left_image": left.astype("float32"), "right_image": right.astype("float32")}
    for a, b in zip(model.predict(x, verbose=0), trained.predict(x, verbose=0)):
        assert np.all(np.isfinite(a))
        np.testing.assert_array_equal(a, b)
    assert not [n for n in os.listdir(os.path.join(run_dir, "backup")) if n.endswith(".h5")]
    if variant in ("baseline", "cpl-a"):
        # A run directory of the older config.json layouts (as_released also
        # at the top level; no disparity ceiling) still loads and resumes.
        from cpl_keras import runs

        run_dir = str(tmp_path / "run")
        shutil.copytree(variant_run(variant)["run_dir"], run_dir)

        assert (config["build"]["disparity_ceiling"] is None) == (variant == "baseline")
        old_build = {k: v for k, v in config["build"].items() if k != "disparity_ceiling"}
        with open(os.path.join(run_dir, "config.json"), "w") as f:
            json.dump(dict(config, as_released=False, build=old_build), f)
        assert runs.load_run(run_dir).as_released is False
        assert runs.load_run(run_dir).config.build["disparity_ceiling"] is None
        # Running the same command on a finished run trains nothing more.
        again = train(dataset, variant=variant, run_dir=run_dir, seed=1, **TINY)
        assert again.config.epochs_run == 2 and again.config.best_epoch == summary["best_epoch"]
        assert len(read_log(run_dir)) == 2


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
        when, dataset, tmp_path, xla_cache, uninterrupted):
    run_dir = str(tmp_path / "run")
    args = [*RESUME_ARGS, "--data", dataset, "--run-dir", run_dir]

    if when == "after an epoch's commit":
        process = cli(*args, cache=xla_cache)
        # as reported: killed as soon as log.csv has two epoch rows
        assert wait_for(lambda: len(read_log(run_dir)) >= 2)
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=300)
    else:
        # Killed inside the training of epoch N + 1 (N >= 1): the progress bar
        # of a batch of epoch N + 1 is drawn only after epoch N's commit and
        # its publishing (RunState's on_epoch_end, before the epoch line).
        loud = [a for a in args if a != "--quiet"]
        process, reader, seen = _on_a_terminal(*loud, cache=xla_cache,
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

    process = cli(*args, cache=xla_cache)
    out, err = process.communicate(timeout=180)
    assert f"Resuming {run_dir} after epoch {done}" in err
    _ends_like(run_dir, process.returncode, out, err, uninterrupted)
    # the same command once more: nothing left to train, the same ending
    process = cli(*args, cache=xla_cache)
    out, err = process.communicate(timeout=180)
    assert out.startswith(FINISHED), out
    _ends_like(run_dir, process.returncode, out[len(FINISHED):], err, uninterrupted)


@pytest.mark.slow
def test_second_process_waits_for_the_first_and_ends_like_it(
        dataset, tmp_path, xla_cache, uninterrupted):
    """A kill that missed: the command run again while the first process still
    trains waits for it, then finds the run finished (exit 0, no error)."""
    import select

    run_dir = str(tmp_path / "run")
    args = [*RESUME_ARGS, "--data", dataset, "--run-dir", run_dir]
    first = cli(*args, cache=xla_cache)
    assert wait_for(lambda: os.path.exists(os.path.join(run_dir, "backup", "lock"))
                     and os.path.exists(os.path.join(run_dir, "config.json")))
    os.kill(first.pid, signal.SIGSTOP)  # the first holds the lock, frozen mid-run
    try:
        second = cli(*args, cache=xla_cache)
        waiting, deadline = b"", time.time() + 120
        while b"Waiting for the training process" not in waiting and time.time() < deadline:
            ready, _, _ = select.select([second.stderr], [], [], 1.0)
            if ready:
                waiting += os.read(second.stderr.fileno(), 4096)
        assert b"Waiting for the training process" in waiting, waiting  # it waits
        time.sleep(1.0)
        assert second.poll() is None  # ... and goes on waiting while the first holds the lock
    finally:
        os.kill(first.pid, signal.SIGCONT)
    first_out, first_err = first.communicate(timeout=180)
    out, err = second.communicate(timeout=180)
    err = waiting.decode() + err
    _ends_like(run_dir, first.returncode, first_out, first_err, uninterrupted)
    assert "Resuming" not in err and out.startswith(FINISHED)  # it found the run finished
    _ends_like(run_dir, second.returncode, out[len(FINISHED):], err.replace("Waiting for the training process "
                                                            f"that is using {run_dir}", ""),
               uninterrupted)


def test_nan_loss_stops_and_keeps_the_best_weights(dataset, tmp_path, monkeypatch):
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
    summary = train(dataset, variant="baseline", run_dir=str(run_dir), epochs=4, batch_size=8,
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
    predictions = model.predict(_images(dataset), verbose=0)
    outputs = predictions.values() if isinstance(predictions, dict) else predictions
    assert all(np.isfinite(np.asarray(v)).all() for v in outputs)


def _images(path, count=4):
    from cpl_keras.data.storage import StereoFile

    with StereoFile(path) as f:
        left, right = f.read_pairs(np.arange(count))
    return {"left_image": left.astype(np.float32), "right_image": right.astype(np.float32)}


def test_early_stopping_ends_the_run_and_model_keras_holds_the_best_epoch(
        dataset, tmp_path, monkeypatch):
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
    summary = train(dataset, variant="baseline", run_dir=str(run_dir), epochs=6, batch_size=8,
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


def test_bad_arguments_from_the_shell(tmp_path, xla_cache):
    run_dir = tmp_path / "run"
    for args, message in (
        (["--variant", "cpl-x"], "invalid choice"),
        (["--variant", "cpl-a", "--data", str(tmp_path / "missing.h5"), "--run-dir", str(run_dir)],
         "dataset not found"),
    ):
        process = cli(*args, cache=xla_cache)
        out, err = process.communicate(timeout=60)
        assert process.returncode == 2
        assert message in err and len(err.strip().splitlines()) == 1, err
        assert "Traceback" not in err
        assert not run_dir.exists()


def test_finished_run_is_left_untouched(tiny_run, tmp_path, xla_cache):
    """The same command on a finished run (a copy of the shared tiny run)
    changes no file (model.keras keeps its optimizer state) and says so in
    one line, exit 0, without importing Keras or JAX (it returns at once)."""
    run_dir = str(tmp_path / "run")
    shutil.copytree(tiny_run["run"], run_dir)
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
    process = cli(*args, cache=xla_cache)
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


def _train_script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_script", os.path.join(REPO, "train.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


@pytest.mark.parametrize("flag, value", [
    ("--steps-per-execution", "0"), ("--steps-per-execution", "-1"), ("--seed", "-1"),
    ("--epochs", "0"), ("--batch-size", "0"), ("--workers", "0"), ("--patience", "-1"),
    ("--bn-recompute-batches", "-2"), ("--image-size", "0"), ("--lr", "0"), ("--lr", "-1"), ("--lr", "nan"),
    ("--time-budget", "0"), ("--time-budget", "nan"),
])
def test_numeric_arguments_are_checked_before_anything_is_written(
        flag, value, dataset, tmp_path, capsys):
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_info:
        _train_script().main(["--variant", "baseline", "--backbone", "small", "--data", dataset,
                              "--run-dir", str(run_dir), flag, value])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"train.py: error: argument {flag}: must be") and "\n" not in err
    assert not run_dir.exists()


def test_library_checks_steps_per_execution_and_seed(dataset, tmp_path):
    from cpl_keras.training import TrainingError, train

    for kwargs, needle in (({"steps_per_execution": 0}, "steps per execution"),
                           ({"seed": -1}, "seed"), ({"time_budget_s": -1.0}, "time budget"),
                           ({"time_budget_s": True}, "time budget")):
        with pytest.raises(TrainingError, match=needle):
            train(dataset, variant="baseline", run_dir=tmp_path / "run", backbone="small",
                  verbose=0, **kwargs)
    assert not (tmp_path / "run").exists()


def test_time_budget_ends_the_run_after_the_epoch_that_would_overrun_it(
        dataset, tmp_path, capsys):
    """--time-budget: after an epoch, when another as long would pass the
    budget, the run ends as finished with its best epoch and says why; a
    budget that is not reached changes nothing."""
    run_dir = tmp_path / "run"
    args = ["--variant", "baseline", "--backbone", "small", "--data", dataset, "--epochs", "3",
            "--batch-size", "8", "--quiet", "--run-dir", str(run_dir)]
    assert _train_script().main(args + ["--time-budget", "0.001"]) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["status"] == "finished" and config["time_budget_s"] == 0.001
    assert (config["epochs_run"], config["best_epoch"]) == (1, 1)
    assert config["stopped"] == "time budget: another epoch would end after 0.001 s of training"
    assert (run_dir / "model.keras").is_file()
    assert "best epoch 1 of 1" in capsys.readouterr().out
    roomy = tmp_path / "roomy"
    args[-1] = str(roomy)
    assert _train_script().main(args + ["--epochs", "2", "--time-budget", "1e6"]) == 0
    config = json.loads((roomy / "config.json").read_text())
    assert (config["epochs_run"], config["stopped"]) == (2, None)


def test_diverged_run_is_exit_2_and_replaced_by_the_next_run(dataset, tmp_path, capsys):
    """A non-finite loss: one error line, exit 2, the run directory marked
    failed; the same command again replaces it (and fails again, alike),
    and a command with sane settings trains a new run in its place."""
    run_dir = tmp_path / "run"
    args = ["--variant", "baseline", "--backbone", "small", "--data", dataset, "--epochs", "2",
            "--batch-size", "5", "--quiet", "--run-dir", str(run_dir)]
    for attempt in range(2):
        assert _train_script().main(args + ["--lr", "1e35"]) == 2
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert captured.out == "" and len(lines) == 1 + attempt, captured.err
        assert lines[-1].startswith("train.py: error: ") and "non-finite" in lines[-1]
        assert ("Replacing the failed run" in captured.err) == (attempt == 1), captured.err
        config = json.loads((run_dir / "config.json").read_text())
        assert config["status"] == "failed" and config["learning_rate"] == 1e35
    assert _train_script().main(args + ["--epochs", "1"]) == 0
    assert "Replacing the failed run" in capsys.readouterr().err
    config = json.loads((run_dir / "config.json").read_text())
    assert config["status"] == "finished" and config["learning_rate"] is None
    assert config["epochs_run"] == 1


def test_resume_after_a_kill_during_the_final_save_keeps_the_optimizer_state(dataset, tmp_path):
    """A run killed while it wrote model.keras (its state says it ended, its
    config says running) is finished by the same command: model.keras again,
    with the optimizer's state and without Keras's skipped-variables warning."""
    import warnings

    import keras

    from cpl_keras.training import train

    run_dir = tmp_path / "run"
    kwargs = dict(variant="baseline", run_dir=str(run_dir), epochs=1, batch_size=8,
                  backbone="small", verbose=0)
    train(dataset, **kwargs)
    first = keras.saving.load_model(run_dir / "model.keras", safe_mode=True)
    steps = int(first.optimizer.iterations.numpy())
    assert steps > 0
    # what a kill in the middle of the final save leaves behind
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps(dict(config, status="running")))
    (run_dir / "model.keras").unlink()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = train(dataset, **kwargs)
    assert summary.config.status == "finished" and not summary.finished_before
    assert not [w for w in caught if "Skipping variable loading" in str(w.message)]
    again = keras.saving.load_model(run_dir / "model.keras", safe_mode=True)
    assert int(again.optimizer.iterations.numpy()) == steps
    for a, b in zip(first.optimizer.variables, again.optimizer.variables):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_truncated_files_are_called_truncated(dataset, tmp_path, tiny_run):
    from cpl_keras import runs
    from cpl_keras.data.storage import DatasetError, StereoFile

    data = tmp_path / "cut.h5"
    with open(dataset, "rb") as f:
        data.write_bytes(f.read()[: os.path.getsize(dataset) // 2])
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


# ---------------------------------------------------------------------------
# Readable output: short epoch lines, every metric in log.csv, curves titled
# ---------------------------------------------------------------------------
def test_epoch_lines_are_short_and_log_csv_keeps_every_metric(dataset, tmp_path, capsys):
    from cpl_keras import runs
    from cpl_keras.training import checkpointing, progress
    from cpl_keras.training.state import read_state
    from cpl_keras.camera import PARAMETERS, TARGETS

    run_dir = str(tmp_path / "run")
    status = _train_script().main(["--variant", "cpl-a", "--backbone", "small", "--data", dataset,
                                   "--run-dir", run_dir, "--epochs", "2", "--batch-size", "5"])
    out = capsys.readouterr().out
    assert status == 0
    lines = out.splitlines()
    assert "\r" not in out  # not a terminal: no bar, one line per epoch
    assert [line.split("  ")[0] for line in lines[:2]] == ["epoch 1/2", "epoch 2/2"]
    assert lines[2].startswith("best epoch ") and len(lines) == 3
    assert all(len(line) <= progress.WIDTH for line in lines[:2]), lines
    # (the monitored sum of validation NMAEs in place of the validation loss)
    assert all(key in lines[0] for key in ("loss ", "val_nmae ", "val MAE fx ", " b ", " pitch "))
    # log.csv: every metric of every epoch, epochs numbered from 1
    with open(os.path.join(run_dir, "log.csv")) as f:
        header = next(csv.reader(f))
    expected = {"epoch", "loss", "val_loss", "wall_time_s", "load_average"}
    expected |= {f"{prefix}{name}_mae" for prefix in ("", "val_") for name in TARGETS}
    expected |= {f"alpha_{name}" for name in TARGETS}
    expected |= {"val_nmae"} | {f"val_nmae_{name}" for name in PARAMETERS}
    assert set(header) == expected and len(header) > 40
    rows = read_log(run_dir)
    assert [int(row["epoch"]) for row in rows] == [1, 2]
    assert float(rows[1]["val_nmae"]) == pytest.approx(
        float(lines[1].split("val_nmae ")[1].split()[0]), rel=1e-3)
    # curves.png names the run and how far it got
    config = runs.read_run_config(run_dir)
    state = read_state(run_dir)
    title = checkpointing.curves_title(config, state)
    assert title == "cpl-a, small, tiny.h5, split paper\n2 of 2 epochs, finished"
    first = dataclasses.replace(state, rows=state.rows[:1])
    assert checkpointing.curves_title(config, first).endswith("\n1 of at most 2 epochs so far")
    stopped = dataclasses.replace(
        state, stopped="early stopping: no improvement of val_loss for 5 epochs")
    assert checkpointing.curves_title(config, stopped).endswith(
        "\n2 epochs, finished: early stopping: no improvement of val_loss for 5 epochs")
    assert PARAMETERS[0] == "fx"


def test_progress_bar_on_a_terminal_stays_within_the_width():
    import io

    from cpl_keras.training import progress

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    screen = Terminal()
    lines = progress.EpochLines(200, stream=screen)
    assert lines.live
    lines.set_params({"steps": 315, "epochs": 200})
    huge = {"loss": -1.234567e12, "val_loss": 9.87654e-9, "val_fx_mae": 123456.7,
            "val_baseline_mae": -0.000123456, "val_pitch_mae": float("nan"),
            **{f"val_{name}_mae": 1e9 for name in ("X", "Y", "Z", "fy", "tx", "ty", "tz")}}
    lines.on_epoch_begin(199)
    lines.on_train_batch_end(99, {"loss": 1.5e33})
    lines.on_test_begin()
    lines.on_epoch_end(199, huge)
    text = screen.getvalue()
    assert text.count("\n") == 1 and text.count("\r") == 3
    shown = [part for line in text.split("\n") for part in line.split("\r")]
    assert all(len(part) <= progress.WIDTH for part in shown), shown
    assert "[======" in shown[1] and "100/315" in shown[1] and "validating" in shown[2]
    assert shown[3].startswith("epoch 200/200  ") and "val MAE fx 1.23e+05 b -0.000123 pitch nan" in shown[3]
    # written to a file: the epoch line alone
    log = io.StringIO()
    lines = progress.EpochLines(200, stream=log)
    lines.set_params({"steps": 315})
    lines.on_epoch_begin(0)
    lines.on_train_batch_end(0, {"loss": 3.0})
    lines.on_test_begin()
    lines.on_epoch_end(0, {"loss": 3.0, "val_loss": 2.0})
    assert log.getvalue() == "epoch 1/200  0s  loss 3.000  val_loss 2.000\n"


def test_old_zero_based_log_is_read_alike_and_renumbered_on_resume(dataset, tmp_path, monkeypatch):
    """A run begun by the code that numbered log.csv's epochs from 0 (Keras's
    CSVLogger convention) and resumed by this code: both logs read alike, and
    the resumed run's log.csv is numbered from 1 throughout."""
    from cpl_keras import learning_curves, runs
    from cpl_keras.training import train
    from helpers import interrupt_after_epoch

    run_dir = str(tmp_path / "run")
    interrupt_after_epoch(monkeypatch, 2)
    with pytest.raises(KeyboardInterrupt):
        train(dataset, variant="baseline", run_dir=run_dir, **dict(TINY, epochs=3))
    monkeypatch.undo()
    log = os.path.join(run_dir, "log.csv")
    with open(log) as f:
        new_text = f.read()
    # the older code's file: the same rows, the epoch column from 0
    lines = new_text.splitlines(keepends=True)
    old_text = lines[0] + "".join(f"{k}{line[line.index(','):]}" for k, line in enumerate(lines[1:]))
    assert old_text != new_text and old_text.splitlines()[1].startswith("0,")
    with open(log, "w") as f:
        f.write(old_text)
    assert runs.read_log(log) == runs.read_log(run_dir) == learning_curves.read_log(run_dir)
    assert [row["epoch"] for row in runs.read_log(log)] == [1.0, 2.0]
    with open(os.path.join(tmp_path, "new.csv"), "w") as f:
        f.write(new_text)
    assert runs.read_log(os.path.join(tmp_path, "new.csv")) == runs.read_log(log)

    summary = train(dataset, variant="baseline", run_dir=run_dir, **dict(TINY, epochs=3))
    assert summary.config.status == "finished" and summary.config.epochs_run == 3
    with open(log) as f:
        resumed = f.read()
    assert resumed.startswith(new_text)  # the first two rows as before, renumbered
    assert [int(row["epoch"]) for row in read_log(run_dir)] == [1, 2, 3]


FLAG_CASES = {
    "as released": (["--as-released"], "cpl-a", lambda c: c["build"]["as_released"]
                    and c["bn_recompute_batches"] == 0 and c["weight_ema"] == 0.0
                    and c["build"]["disparity_ceiling"] is None
                    and not c["build"]["positive_focal_head"]
                    and not c["build"]["bounded_pitch_head"]),
    "cpl-u heads": (["--disentangle", "partial", "--linear-pitch-head",
                     "--disparity-ceiling", "300", "--point-errors", "relative"], "cpl-u",
                    lambda c: c["build"]["disentangle"] == "partial"
                    and c["build"]["point_errors"] == "relative"
                    and c["build"]["disparity_ceiling"] == 300.0
                    and c["build"]["bounded_pitch_head"] is False),
    "cpl-a heads": (["--linear-focal-head", "--alpha-rate", "3", "--weight-ema", "0.9",
                     "--head-activation", "leaky_relu_0.01", "--head-units"], "cpl-a",
                    lambda c: c["build"]["positive_focal_head"] is False
                    and c["build"]["head_activation"] == "leaky_relu_0.01"
                    and c["build"]["alpha_rate"] == 3.0 and c["weight_ema"] == 0.9),
    "cpl-a recipe": (["--recipe", "sound", "--adaptive-weights", "range", "--weight-decay",
                      "1e-4", "--head-activation", "relu"], "cpl-a",
                     lambda c: c["build"]["head_norm"] is True
                     and c["build"]["disparity_head"] == "softplus"
                     and c["build"]["disparity_start"] > 0 and c["build"]["clip_norm"] == 1.0
                     and "head_activation" not in c["build"]  # (given: the recipe's overridden)
                     and c["build"]["adaptive_weights"] == "range"
                     and c["build"]["alpha_rate"] == 0.0 and c["build"]["weight_decay"] == 1e-4
                     and set(c["build"]["range_scales"]) == set(TARGETS)),
    "baseline steps": (["--target-scaling", "std", "--steps-per-execution", "2",
                        "--bn-recompute-batches", "0", "--split", "held-out-config",
                        "--augment", "photometric", "--exp-disparity-head"], "baseline",
                       lambda c: c["target_scaling"] == "std" and c["augment"] == "photometric"
                       and c["build"]["exp_disparity_head"] is True
                       and c["build"]["disparity_ceiling"] > 0
                       and c["bn_recompute_batches"] == 0 and c["split"] == "held-out-config"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(FLAG_CASES))
def test_every_training_flag_reaches_the_run(case, tiny_run, tmp_path):
    """The train.py options at tiny scale (several per run): the run
    finishes, its config records them, and model.keras loads (safe mode)
    as the model they ask for."""
    import keras

    flags, variant, check = FLAG_CASES[case]
    run_dir = tmp_path / "run"
    assert _train_script().main(["--variant", variant, "--backbone", "small", "--data",
                                 tiny_run["data"], "--epochs", "1", "--batch-size", "4",
                                 "--quiet", "--run-dir", str(run_dir)] + flags) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["status"] == "finished" and config["epochs_run"] == 1
    assert check(config), config
    if config["split"] == "held-out-config":  # no rig of the test set in training
        from cpl_keras.data.storage import StereoFile
        from cpl_keras.datasets import load_split

        with StereoFile(tiny_run["data"]) as f:
            rig = np.asarray(f.labels["config_id"])
        split = load_split(str(run_dir / "split.npz"))
        assert not set(rig[split["test"]]) & set(rig[split["train"]])
    model = keras.saving.load_model(run_dir / "model.keras", safe_mode=True)
    assert model.build_settings["as_released"] == config["build"]["as_released"]
    ceiling = config["build"]["disparity_ceiling"]
    if ceiling is not None:
        assert model.get_layer("disparity").activation.ceiling == ceiling
    if case == "cpl-a heads":  # the default: twice the largest training disparity
        from cpl_keras.data.storage import StereoFile
        from cpl_keras.datasets import load_split

        with StereoFile(tiny_run["data"]) as f:
            disparity = np.asarray(f.labels["disparity"], np.float64)
        train_pairs = load_split(str(run_dir / "split.npz"))["train"]
        assert ceiling == pytest.approx(2 * disparity[train_pairs].max(), abs=1e-3)
    if "alpha_rate" in config["build"]:
        assert model.alpha_rate == config["build"]["alpha_rate"]
    assert model.build_settings.get("head_activation") == config["build"].get("head_activation")
    if case == "cpl-a recipe":  # (the softplus head and range weights, in safe mode)
        assert model.get_layer("head_norm") is not None
        assert type(model.get_layer("disparity").activation).__name__ == "SoftplusDisparity"
        assert model.adaptive_weights()["u0"] == pytest.approx(
            1 / config["build"]["range_scales"]["u0"], rel=1e-5)
    if case == "cpl-a heads":  # (a registered activation, loaded in safe mode)
        slope = model.get_layer("pitch_dense_120").activation(np.array([-1.0], "float32"))
        np.testing.assert_allclose(np.asarray(slope), [-0.01], rtol=1e-6)
        log = (run_dir / "log.csv").read_text().splitlines()[0].split(",")  # --head-units
        assert {"dead_pitch", "units_pitch", "dead_fx"} <= set(log) and "grad_fx" not in log
    # metres, the default, is recorded by its absence, as in every run before the choice
    assert model.build_settings.get("point_errors") == config["build"].get("point_errors")
    assert config["build"].get("point_errors") == ("relative" if case == "cpl-u heads" else None)


def test_ablation_switches_are_refused_where_they_do_not_apply(tiny_run, tmp_path):
    from cpl_keras.training import TrainingError, plan_run

    for variant in ("baseline", "deep-homo"):
        with pytest.raises(TrainingError, match="point errors 'relative' apply to the camera "
                           f"projection loss, which {variant} does not train with"):
            plan_run(tiny_run["data"], variant=variant, run_dir=str(tmp_path / variant),
                     backbone="small", point_errors="relative")
    with pytest.raises(TrainingError, match="point errors"):
        plan_run(tiny_run["data"], variant="cpl-a", run_dir=str(tmp_path / "c"),
                 backbone="small", point_errors="depth")
    plan = plan_run(tiny_run["data"], variant="cpl-a", run_dir=str(tmp_path / "a"),
                    backbone="small", point_errors="relative")
    assert plan.config.build["point_errors"] == "relative"
    for variant in ("cpl-a", "deep-homo"):
        with pytest.raises(TrainingError, match="an exp disparity head is MTL-Baseline's "
                           f"ablation; {variant} has its own disparity head"):
            plan_run(tiny_run["data"], variant=variant, run_dir=str(tmp_path / variant),
                     backbone="small", exp_disparity_head=True)
    plain = plan_run(tiny_run["data"], variant="baseline", run_dir=str(tmp_path / "b"),
                     backbone="small")
    assert "exp_disparity_head" not in plain.config.build  # (as in every run before it)
    assert "head_activation" not in plain.config.build
    with pytest.raises(TrainingError, match="head activation 'leaky_relu' applies to the "
                       "regression heads; deep-homo has its own"):
        plan_run(tiny_run["data"], variant="deep-homo", run_dir=str(tmp_path / "h"),
                 head_activation="leaky_relu")
    with pytest.raises(TrainingError, match="head activation"):
        plan_run(tiny_run["data"], variant="cpl-a", run_dir=str(tmp_path / "h"),
                 backbone="small", head_activation="gelu")
    assert plain.config.build["disparity_ceiling"] is None
    assert not any(tmp_path.iterdir())


def test_drive_split_flag_reaches_the_split(tiny_run, tmp_path, capsys):
    """--split drive is the drive split: on 40 cvgl pairs of nearly as many
    rigs it has no validation frames, and says so (exit 2, nothing written)."""
    assert _train_script().main(["--variant", "baseline", "--backbone", "small", "--data",
                                 tiny_run["data"], "--quiet", "--run-dir", str(tmp_path / "run"),
                                 "--split", "drive"]) == 2
    assert "drive split of 40 pairs leaves the val set empty" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_target_scaling_and_steps_per_execution_reach_the_compiled_model(tiny_run, tmp_path,
                                                                         monkeypatch):
    """train.py --target-scaling std --steps-per-execution 2: the model is
    compiled with two steps per call, and its validation loss is the sum of
    the per-output MAEs each divided by the target's standard deviation over
    the training split (worked out here), not their plain sum."""
    from cpl_keras import models
    from cpl_keras.camera import TARGETS
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import load_split, targets_from_labels

    compiled = []
    compile_model = models.compile_model

    def recording(model, **kwargs):
        compiled.append(model)
        return compile_model(model, **kwargs)

    monkeypatch.setattr(models, "compile_model", recording)
    run_dir = tmp_path / "run"
    assert _train_script().main(["--variant", "baseline", "--backbone", "small", "--data",
                                 tiny_run["data"], "--epochs", "1", "--batch-size", "4",
                                 "--quiet", "--run-dir", str(run_dir), "--target-scaling", "std",
                                 "--steps-per-execution", "2"]) == 0
    assert len(compiled) == 1 and compiled[0].steps_per_execution == 2
    with StereoFile(tiny_run["data"]) as f:
        targets = targets_from_labels(f.labels)
    train_pairs = load_split(str(run_dir / "split.npz"))["train"]
    std = {name: float(np.std(np.asarray(targets[name], np.float64)[train_pairs]))
           for name in TARGETS}
    (row,) = read_log(run_dir)
    scaled = sum(float(row[f"val_{name}_mae"]) / (std[name] if std[name] > 1e-6 else 1.0)
                 for name in TARGETS)
    plain = sum(float(row[f"val_{name}_mae"]) for name in TARGETS)
    assert abs(scaled - plain) > 0.1 * plain  # (a test that can tell)
    assert float(row["val_loss"]) == pytest.approx(scaled, rel=1e-4)


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


# ---------------------------------------------------------------------------
# Steady validation: fixed BatchNorm statistics, the NMAE monitor
# ---------------------------------------------------------------------------
def test_the_nmae_monitor_keeps_the_epoch_of_the_lowest_validation_nmae(dataset, tmp_path):
    """The default monitor: log.csv has val_nmae_<p> = val MAE of p / the
    training split's mean |p| and val_nmae their sum; the kept epoch is the
    lowest val_nmae's, whatever val_loss did; config.json says so."""
    from cpl_keras.camera import PARAMETERS
    from cpl_keras.datasets import load_split, targets_from_labels
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.training import train

    run_dir = str(tmp_path / "run")
    summary = train(dataset, variant="cpl-u", run_dir=run_dir, epochs=3, batch_size=5,
                    backbone="small", verbose=0, patience=10, seed=2)
    rows = read_log(run_dir)
    split = load_split(os.path.join(run_dir, "split.npz"))
    with StereoFile(dataset) as f:
        targets = targets_from_labels(f.labels)
    for row in rows:
        parts = {}
        for name in PARAMETERS:
            scale = float(np.mean(np.abs(targets[name][split["train"]].astype(np.float64))))
            parts[name] = float(row[f"val_{name}_mae"]) / (scale if scale > 1e-9 else 1.0)
            assert float(row[f"val_nmae_{name}"]) == pytest.approx(parts[name], rel=1e-6)
        assert float(row["val_nmae"]) == pytest.approx(sum(parts.values()), rel=1e-6)
    scores = [float(row["val_nmae"]) for row in rows]
    assert summary.config.best_epoch == 1 + int(np.argmin(scores))
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    assert config["monitor"] == "nmae" and config["bn_statistics"] == "fixed"
    assert config["best_score"] == pytest.approx(min(scores), rel=1e-6)
    best_row = rows[summary.config.best_epoch - 1]
    assert config["best_val_loss"] == pytest.approx(float(best_row["val_loss"]), rel=1e-6)


def test_fixed_batchnorm_statistics_do_not_depend_on_the_epoch(dataset, tmp_path):
    """With ``bn_statistics="fixed"`` validation sees the same statistics for
    the same weights at every epoch (the same training pairs, population
    variance); the first batches of each epoch's order ("epoch", the
    earlier default) change with the epoch."""
    import keras

    from cpl_keras import models
    from cpl_keras.training.checkpointing import RunState
    from cpl_keras.models.batchnorm import batchnorm_layers
    from cpl_keras.training.planning import plan_run
    from cpl_keras.training.sequence import StereoSequence
    from cpl_keras.training.trainer import batchnorm_pairs

    plan = plan_run(dataset, variant="baseline", run_dir=str(tmp_path / "r"), backbone="small",
                    batch_size=5, bn_recompute_batches=2)
    config = plan.config

    def with_config(**changes):
        return dataclasses.replace(plan, config=dataclasses.replace(config, **changes))

    pairs = batchnorm_pairs(plan)
    assert len(pairs) == 10 and set(pairs) <= set(plan.split["train"])
    np.testing.assert_array_equal(pairs, batchnorm_pairs(plan))
    other_seed = batchnorm_pairs(with_config(seed=config.seed + 1))
    assert not np.array_equal(pairs, other_seed)
    capped = batchnorm_pairs(with_config(bn_recompute_batches=1000))
    assert len(capped) == len(plan.split["train"]) // 5 * 5
    # shuffled, so that each batch mixes frames as training's do (file order
    # put neighbouring frames of one drive together)
    assert not np.array_equal(capped, np.sort(capped))

    model = models.build_model("baseline", backbone="small_resnet", image_size=32)
    train_seq = StereoSequence(dataset, plan.split["train"], targets=plan.targets,
                               batch_size=5, shuffle=True, seed=0)
    fixed = StereoSequence(dataset, pairs, targets=plan.targets, batch_size=5)
    layer = batchnorm_layers(model)[0]

    def statistics(state, epoch):
        train_seq.set_epoch(epoch)
        state.set_model(model)
        state.on_test_begin()
        return [np.array(keras.ops.convert_to_numpy(v))
                for v in (layer.moving_mean, layer.moving_variance)]

    steady = RunState(str(tmp_path / "a"), 5, train_seq, 2, bn_sequence=fixed)
    for a, b in zip(statistics(steady, 0), statistics(steady, 7)):
        np.testing.assert_array_equal(a, b)
    drawn = RunState(str(tmp_path / "b"), 5, train_seq, 2)
    first, later = statistics(drawn, 0), statistics(drawn, 7)
    assert not np.allclose(first[0], later[0])


def test_nmae_scores_read_either_mae_name_and_sum_the_parameters():
    from cpl_keras.training.checkpointing import nmae_scores

    logs = {"val_fx_mae": 2.0, "val_baseline_loss": 6.0, "val_loss": 9.0}
    scores = nmae_scores(logs, {"fx": 4.0, "baseline": 3.0, "pitch": 1.0})
    assert scores == {"val_nmae_fx": 0.5, "val_nmae_baseline": 2.0, "val_nmae": 2.5}
    assert nmae_scores({"val_loss": 1.0}, {"fx": 1.0}) == {}


def test_a_run_made_before_the_new_defaults_resumes_with_its_own(dataset, tmp_path):
    """A run directory of before ``bn_statistics`` and ``monitor`` (its
    config.json has neither) is resumed with what it ran with, unless the
    call names other settings."""
    from cpl_keras.training.planning import TrainingError, plan_run
    from cpl_keras.training import train

    run_dir = str(tmp_path / "old")
    train(dataset, variant="baseline", run_dir=run_dir, epochs=1, batch_size=5,
          backbone="small", verbose=0, bn_statistics="epoch", monitor="loss")
    path = os.path.join(run_dir, "config.json")
    with open(path) as f:
        config = json.load(f)
    for key in ("bn_statistics", "monitor", "best_score"):
        config.pop(key)
    config["bn_recompute_batches"] = 16
    with open(path, "w") as f:
        json.dump(config, f)
    plan = plan_run(dataset, variant="baseline", run_dir=run_dir, epochs=1, batch_size=5,
                    backbone="small")
    assert (plan.config.bn_statistics, plan.config.monitor,
            plan.config.bn_recompute_batches) == ("epoch", "loss", 16)
    with pytest.raises(TrainingError, match="holds a different run .monitor"):
        plan_run(dataset, variant="baseline", run_dir=run_dir, epochs=1, batch_size=5,
                 backbone="small", monitor="nmae")
