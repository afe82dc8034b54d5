"""Learning curves: validation NMAE per parameter from a run directory, and
the regression tests that fail if learning breaks."""

import json
import math
import os

import numpy as np
import pytest

from cpl_keras import learning_curves
from cpl_keras.commands import learning_curves as learning_curves_command
from cpl_keras.camera import PARAMETERS
from cpl_keras.data.storage import StereoFile
from cpl_keras.datasets import load_split, targets_from_labels



@pytest.fixture(scope="module")
def tiny(stereo40):
    return stereo40


@pytest.fixture(scope="module")
def tiny_run(variant_run):
    """The session's MTL-CPL-A run on ``tiny`` (2 epochs, batches of 5)."""
    return variant_run("cpl-a")["run_dir"]


def test_curves_are_the_logged_validation_mae_over_mean_abs_truth(tiny, tiny_run):
    curve = learning_curves.curves(tiny_run)
    rows = learning_curves.read_log(tiny_run)
    split = load_split(os.path.join(tiny_run, "split.npz"))
    with StereoFile(tiny) as f:
        targets = targets_from_labels(f.labels)
    assert curve["samples_seen"] == [25 * (k + 1) for k in range(len(rows))]
    for name in PARAMETERS:
        scale = np.mean(np.abs(targets[name][split["val"]].astype(np.float64)))
        expected = [row[f"val_{name}_mae"] / scale for row in rows]
        assert curve["nmae"][name] == pytest.approx(expected, rel=1e-6)
        assert math.isfinite(curve["average"][name])


def test_outputs_figures_and_tables(tiny_run, tmp_path):
    out = str(tmp_path / "new" / "folder")
    assert learning_curves_command.main([tiny_run, "--out", out]) == 0
    name = os.path.basename(tiny_run)
    assert os.path.getsize(os.path.join(out, f"{name}.png")) > 10_000
    # the run's own log and curves are published beside the figures
    with open(os.path.join(tiny_run, "log.csv"), "rb") as f, \
            open(os.path.join(out, "runs", f"{name}_log.csv"), "rb") as g:
        assert f.read() == g.read()
    assert os.path.getsize(os.path.join(out, "runs", f"{name}_curves.png")) > 10_000
    with open(os.path.join(out, "learning_curves.json")) as f:
        payload = json.load(f)
    assert payload[0]["run"] == name and set(payload[0]["nmae"]) == set(PARAMETERS)
    with open(os.path.join(out, "learning_curves.md")) as f:
        assert "| cpl-a, small" in f.read()


def test_keep_earlier_keeps_rows_of_runs_not_given(tiny_run, tmp_path):
    out = str(tmp_path / "out")
    earlier = [{"run": "gone-run", "label": "baseline, small, old.h5, split paper",
                "num_train": 10, "num_val": 2, "epochs_run": 7, "best_epoch": 4,
                "stopped": "early stopping", "wall_time_s": 120.0, "load_average": 2.0,
                "best_epoch_nmae": {p: 0.5 for p in PARAMETERS},
                "average_nmae": {p: 1.0 for p in PARAMETERS},
                "samples_seen": [10, 20], "nmae": {p: [0.6, 0.5] for p in PARAMETERS}}]
    os.makedirs(out)
    with open(os.path.join(out, "learning_curves.json"), "w") as f:
        json.dump(earlier, f)
    assert learning_curves_command.main([tiny_run, "--out", out, "--keep-earlier"]) == 0
    with open(os.path.join(out, "learning_curves.json")) as f:
        payload = json.load(f)
    assert [row["run"] for row in payload] == ["gone-run", os.path.basename(tiny_run)]
    assert payload[0]["kept_from_earlier"] and payload[0]["nmae"]["fx"] == [0.6, 0.5]
    with open(os.path.join(out, "learning_curves.md")) as f:
        text = f.read()
    assert "| baseline, small, old.h5, split paper | 10/2 | 7 (4) |" in text
    assert "Kept from an earlier drawing (run directory not given this time): gone-run." in text
    # the equal-budget table: NMAE after 2 epochs, a run with fewer epochs said so
    assert learning_curves_command.main([tiny_run, "--out", out, "--keep-earlier", "--at-epoch", "2"]) == 0
    with open(os.path.join(out, "learning_curves.json")) as f:
        mine = json.load(f)[1]
    with open(os.path.join(out, "learning_curves.md")) as f:
        text = f.read()
    cells = [f"{mine['nmae'][p][1]:.3f}" for p in learning_curves.KEY_PARAMETERS]
    mean = np.mean([mine["nmae"][p][1] for p in PARAMETERS])
    assert "## Validation NMAE after 2 epochs" in text
    assert f"| {mine['label']} | {mean:.3f} | " + " | ".join(cells) in text
    assert "| baseline, small, old.h5, split paper | 0.500 | 0.500 |" in text
    assert learning_curves_command.main([tiny_run, "--out", out, "--keep-earlier", "--at-epoch", "9"]) == 0
    with open(os.path.join(out, "learning_curves.md")) as f:
        assert "| fewer than 9 epochs |" in f.read()
    # without the flag the table holds only the runs given
    assert learning_curves_command.main([tiny_run, "--out", out]) == 0
    with open(os.path.join(out, "learning_curves.json")) as f:
        assert [row["run"] for row in json.load(f)] == [os.path.basename(tiny_run)]


def test_a_missing_run_is_one_line_and_exit_2(tmp_path, capsys):
    assert learning_curves_command.main([str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error:" in err[0]


# ---------------------------------------------------------------------------
# Regression tests: learning must not break
# ---------------------------------------------------------------------------
def _nmae_sum(model, x, y):
    """Sum over the 10 parameters of MAE / mean|y| on (x, y), inference mode."""
    predictions = dict(zip(model.output_names, model.predict(x, verbose=0)))
    return sum(float(np.mean(np.abs(predictions[n] - y[n])) / np.mean(np.abs(y[n])))
               for n in PARAMETERS)


# Deep-Homo's fit is the heaviest case (its step costs 15-18x the compact
# tower's): it runs in the full suite, not under -m "not slow".
@pytest.mark.parametrize("variant", ["baseline", "cpl-u", "cpl-a",
                                     pytest.param("deep-homo", marks=pytest.mark.slow)])
def test_a_tiny_run_learns_and_its_pitch_stays_bounded(variant, tiny):
    """Sixteen pairs fitted for 80 steps: the error on them must fall by a
    clear factor, and every pitch prediction stays a plausible angle.

    The MTL variants are judged by the summed NMAE of the 10 parameters in
    inference mode; Deep-Homo (Dropout 0.75 before its last layers keeps its
    inference-mode fit of 16 pairs loose) by its training loss."""
    from cpl_keras import build_model, compile_model
    from cpl_keras.training.sequence import StereoSequence
    from cpl_keras.models.batchnorm import recompute_batchnorm_statistics

    with StereoFile(tiny) as f:
        targets = targets_from_labels(f.labels)
    seq = StereoSequence(tiny, np.arange(16), targets=targets, batch_size=16)
    x, y = seq[0]
    seq.close()
    model = compile_model(build_model(variant, backbone="small", image_size=32, seed=0))
    model.initialise_adaptive_weights(y)
    before = _nmae_sum(model, x, y)
    history = model.fit(x, y, epochs=80, batch_size=16, verbose=0)
    recompute_batchnorm_statistics(model, [x])  # Deep-Homo's BatchNorm, as training does
    after = _nmae_sum(model, x, y)
    assert np.all(np.isfinite(history.history["loss"]))
    loss = history.history["loss"]
    if variant == "deep-homo":
        assert np.mean(loss[-10:]) < loss[0] / 2.5, loss
    else:
        assert after < before / 2, (before, after)
    pitch = model.predict(x, verbose=0)[list(model.output_names).index("pitch")]
    if variant != "deep-homo":  # Deep-Homo's 13 outputs are linear, as in the release
        assert np.all(np.abs(pitch) <= np.pi / 2)
        # fitted, not bounded by construction: well below what predicting the
        # pairs' mean pitch (or 0) would give (measured 0.018-0.088 rad
        # against 0.179)
        spread = np.abs(y["pitch"] - y["pitch"].mean()).mean()
        assert np.abs(pitch - y["pitch"]).mean() < 0.75 * spread, (pitch, y["pitch"])
