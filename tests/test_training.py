"""Training end to end (cpl_keras.training and train.py), on tiny data: the
run directory of every variant, and what a run prints and logs.

Small backbone, 32x32 images, a few dozen pairs, two or three epochs. A
run's faults and bad input are in test_training_faults.py, the settings it
is planned with (train.py's flags) in test_planning.py, and validation's
fixed BatchNorm statistics and NMAE monitor in test_checkpointing.py.
"""

import csv
import dataclasses
import json
import os

import numpy as np
import pytest

from helpers import load_script, read_log, writable_copy

RUN_FILES = ("config.json", "model.keras", "best.weights.h5", "log.csv", "curves.png",
             "train_stats.json", "split.npz")
# 40 pairs -> 25 train, 3 val, 12 test: batches of 5 keep one shape (one compile).
TINY = dict(backbone="small", epochs=2, batch_size=5, verbose=0)


# ---------------------------------------------------------------------------
# Every variant: the whole run directory, a model that reloads and agrees
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("variant", ["baseline", "cpl-u", "cpl-a", "deep-homo"])
def test_every_variant_writes_the_run_directory(variant, stereo40, variant_run, tmp_path):
    """The shared run of each variant (helpers' VARIANT_RUN: these
    settings, seed 1) on ``stereo40``."""
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
    assert config["variant"] == variant and config["data"] == os.path.abspath(stereo40)
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
    # (its backend: the suite's, JAX, or another one's: tests/test_other_backends.py)
    assert machine["keras"] == keras.__version__
    assert machine["keras_backend"] == config["keras_backend"] == keras.backend.backend()
    if keras.backend.backend() == "jax":  # (the devices JAX sees; other backends list none)
        assert machine["devices"] and all(d.startswith("cpu:") for d in machine["devices"])
    else:
        assert "devices" not in machine

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
    with StereoFile(stereo40) as f:
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
        writable_copy(variant_run(variant)["run_dir"], run_dir)

        assert (config["build"]["disparity_ceiling"] is None) == (variant == "baseline")
        old_build = {k: v for k, v in config["build"].items() if k != "disparity_ceiling"}
        with open(os.path.join(run_dir, "config.json"), "w") as f:
            json.dump(dict(config, as_released=False, build=old_build), f)
        assert runs.load_run(run_dir).as_released is False
        assert runs.load_run(run_dir).config.build["disparity_ceiling"] is None
        # Running the same command on a finished run trains nothing more.
        again = train(stereo40, variant=variant, run_dir=run_dir, seed=1, **TINY)
        assert again.config.epochs_run == 2 and again.config.best_epoch == summary["best_epoch"]
        assert len(read_log(run_dir)) == 2




# ---------------------------------------------------------------------------
# Readable output: short epoch lines, every metric in log.csv, curves titled
# ---------------------------------------------------------------------------
def test_epoch_lines_are_short_and_log_csv_keeps_every_metric(stereo40, tmp_path, capsys):
    from cpl_keras import runs
    from cpl_keras.training import checkpointing, progress
    from cpl_keras.training.state import read_state
    from cpl_keras.camera import PARAMETERS, TARGETS

    run_dir = str(tmp_path / "run")
    status = load_script("train.py").main(["--variant", "cpl-a", "--backbone", "small", "--data", stereo40,
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


def test_old_zero_based_log_is_read_alike_and_renumbered_on_resume(stereo40, tmp_path, monkeypatch):
    """A run begun by the code that numbered log.csv's epochs from 0 (Keras's
    CSVLogger convention) and resumed by this code: both logs read alike, and
    the resumed run's log.csv is numbered from 1 throughout."""
    from cpl_keras import learning_curves, runs
    from cpl_keras.training import train
    from helpers import interrupt_after_epoch

    run_dir = str(tmp_path / "run")
    interrupt_after_epoch(monkeypatch, 2)
    with pytest.raises(KeyboardInterrupt):
        train(stereo40, variant="baseline", run_dir=run_dir, **dict(TINY, epochs=3))
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

    summary = train(stereo40, variant="baseline", run_dir=run_dir, **dict(TINY, epochs=3))
    assert summary.config.status == "finished" and summary.config.epochs_run == 3
    with open(log) as f:
        resumed = f.read()
    assert resumed.startswith(new_text)  # the first two rows as before, renumbered
    assert [int(row["epoch"]) for row in read_log(run_dir)] == [1, 2, 3]
