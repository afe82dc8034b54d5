"""analyses/collapsed_heads.py: the test pairs on which a head puts out one
value, what they cost, and (with the weights) the heads' first-layer units
at zero."""

import json
import os
import shutil

import numpy as np
import pytest
from helpers import load_script, writable_copy

from cpl_keras.camera import PARAMETERS


def _script():
    return load_script("analyses/collapsed_heads.py")


def test_arguments():
    script = _script()
    for bad in (["--data", "d.h5", "--run", "A", "--out", "o.md"],
                ["--data", "d.h5", "--run", "A=a,b,c", "--out", "o.md"],
                ["--data", "d.h5", "--run", "A=a", "--out", "o"],
                ["--data", "d.h5", "--run", "A=a", "--out", "o.md", "--min-share", "0"]):
        with pytest.raises(SystemExit):
            script.parse_args(bad)
    args = script.parse_args(["--data", "d.h5", "--run", "A, 1=a", "--run", "B=b,r",
                              "--out", "o.md"])
    assert args.run == [("A, 1", "a", None), ("B", "b", "r")]


def test_one_value_on_part_of_the_pairs():
    """The pitch on one value (to float rounding) for the 40 pairs of the
    upper truth, spread elsewhere: its share, truth, error share and MAEs
    on and off those pairs, and the reference's on the same pairs."""
    n = 100
    truth = {name: np.linspace(1.0, 2.0, n) for name in PARAMETERS}
    truth["pitch"] = np.linspace(-0.8, 0.2, n)
    pred = {name: t + 0.01 for name, t in truth.items()}
    on = np.arange(n) >= 60
    pred["pitch"] = np.where(on, -0.2 * (1 + 1e-9 * np.arange(n)), truth["pitch"] + 0.01)
    reference = {"pred": {name: t - 0.02 for name, t in truth.items()}}
    cells = _script().collapse({"truth": truth, "pred": pred}, reference)
    pitch = cells["pitch"]
    assert pitch["share"] == pytest.approx(0.4) and pitch["pairs"] == 40
    assert pitch["value"] == pytest.approx(-0.2)
    assert pitch["truth_min"] == pytest.approx(truth["pitch"][60])
    assert pitch["truth_max"] == pytest.approx(0.2)
    assert pitch["others_min"] == pytest.approx(-0.8)
    assert pitch["others_max"] == pytest.approx(truth["pitch"][59])
    assert pitch["others_inside"] == 0
    error = np.abs(pred["pitch"] - truth["pitch"])
    assert pitch["mae_on"] == pytest.approx(error[on].mean())
    assert pitch["mae_off"] == pytest.approx(0.01)
    assert pitch["error_share"] == pytest.approx(error[on].sum() / error.sum())
    assert pitch["reference_on"] == pytest.approx(0.02)
    assert pitch["reference_slope_on"] == pytest.approx(1.0)
    flat = {"pred": dict(reference["pred"], pitch=np.full(n, -0.3))}
    assert _script().collapse({"truth": truth, "pred": pred}, flat)["pitch"][
        "reference_slope_on"] == pytest.approx(0.0, abs=1e-9)
    for column, cell in cells.items():
        if column != "pitch":
            assert cell["share"] == 0.0 and cell["pairs"] == 0
    # One value on every other pair instead: the others lie inside its range.
    pred["pitch"] = np.where(np.arange(n) % 2 == 0, -0.2, truth["pitch"] + 0.01)
    spread = _script().collapse({"truth": truth, "pred": pred})["pitch"]
    assert spread["pairs"] == 50 and spread["others_inside"] == 49


def test_a_head_switched_off_puts_out_one_value(tiny_run, tmp_path):
    """End to end with the weights: a run whose pitch head's first layer is
    set below zero for every input puts out one pitch on every test pair,
    and --units finds every one of its pairs with every unit at zero, no
    unit active; the other heads are as trained."""
    from cpl_keras.saving import load_model

    run = str(tmp_path / "run")
    writable_copy(tiny_run["run"], run)
    shutil.rmtree(os.path.join(run, "predictions"), ignore_errors=True)
    model = load_model(os.path.join(run, "model.keras"))
    layer = model.get_layer("pitch_dense_120")
    kernel, bias = layer.get_weights()
    layer.set_weights([np.zeros_like(kernel), np.full_like(bias, -1.0)])
    model.save(os.path.join(run, "model.keras"))
    out = tmp_path / "collapsed.md"
    assert _script().main(["--data", tiny_run["data"], "--run", f"off={run},{tiny_run['run']}",
                           "--units", "--out", str(out)]) == 0
    result = json.loads((tmp_path / "collapsed.json").read_text())["off"]
    split = np.load(os.path.join(run, "split.npz"), allow_pickle=False)
    assert result["test_pairs"] == len(split["test"]) > 1
    assert result["columns"]["pitch"]["share"] == 1.0
    assert result["units"]["pitch"] == {"pairs_all_zero": 1.0, "units_active": 0, "units": 120}
    assert result["units"]["fx"]["units_active"] > 0
    assert result["units"]["fx"]["pairs_all_zero"] < 1.0
    page = out.read_text()
    assert "python analyses/collapsed_heads.py --data" in page and "--units" in page
    rows = [line for line in page.splitlines() if line.startswith("| off |")]
    assert rows[-1].endswith("| 1.00, 0 |")      # the units table's pitch (its last head)
