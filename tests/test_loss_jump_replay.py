"""``analyses/loss_jump_replay.py``: an epoch replayed step by step from a
run trained again and stopped after the epoch before it."""

import os

import numpy as np
import pytest
from helpers import VARIANT_RUN, interrupt_after_epoch, load_script

from cpl_keras import files
from cpl_keras.training_options import TrainingError


@pytest.fixture(scope="module")
def stopped(stereo40, variant_run, tmp_path_factory):
    """MTL-CPL-A trained again as ``variant_run``'s, stopped after epoch 1
    as a kill would leave it: ``(its run directory, the finished run's log)``."""
    from cpl_keras.training import train

    run_dir = str(tmp_path_factory.mktemp("replay") / "run")
    with pytest.MonkeyPatch.context() as monkeypatch:
        interrupt_after_epoch(monkeypatch, 1)
        with pytest.raises(KeyboardInterrupt):
            train(stereo40, variant="cpl-a", run_dir=run_dir, **VARIANT_RUN)
    return run_dir, os.path.join(variant_run("cpl-a")["run_dir"], "log.csv")


def test_the_replayed_epoch_is_the_logged_one(stereo40, stopped, tmp_path):
    """Epoch 2 replayed one step at a time gives the finished run's logged
    loss and X MAE for that epoch; every pair of the training split is met
    once, with its outputs; the page regenerates from its JSON."""
    script = load_script("analyses/loss_jump_replay.py")
    run_dir, log = stopped
    out = str(tmp_path / "replay")
    assert script.main(["--run-dir", run_dir, "--data", stereo40, "--log", log,
                        "--out", out]) == 0
    found = files.read_json(out + ".json")
    assert found["epoch"] == 2 and found["replay_loss"] == pytest.approx(found["log_loss"],
                                                                           rel=1e-4)
    assert found["replay_X_mae"] == pytest.approx(found["log_X_mae"], rel=1e-4)
    with np.load(out + "-pairs.npz", allow_pickle=False) as pairs:
        split = np.load(os.path.join(run_dir, "split.npz"))["train"]
        assert sorted(pairs["index"]) == sorted(split)
        worst = np.argmax(np.abs(pairs["pred_X"] - pairs["true_X"]))
        assert int(pairs["index"][worst]) == found["top_pairs"][0]["pair"]
    assert script.regenerate(out + ".md") == open(out + ".md").read()


def test_a_run_that_does_not_repeat_the_log_is_refused(stopped, tmp_path):
    script = load_script("analyses/loss_jump_replay.py")
    run_dir, log = stopped
    other = tmp_path / "log.csv"
    lines = open(log).read().splitlines()
    header, first = lines[0].split(","), lines[1].split(",")
    first[header.index("loss")] = "123.0"
    other.write_text("\n".join([lines[0], ",".join(first)] + lines[2:]) + "\n")
    with pytest.raises(TrainingError, match="repeats .* over 0 of its 1 epochs") as error:
        script.check_repeats(run_dir, str(other))
    assert "\n" not in str(error.value)
