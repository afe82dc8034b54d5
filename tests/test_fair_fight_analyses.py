"""The fair fight's analyses of its committed record: the records joined to
their test pairs' truths, the loss split term by term, the range weights'
first-order sensitivities."""

import json
import math
import os

import numpy as np
import pytest
from helpers import REPO, load_script

from cpl_keras import camera

FIGHT = os.path.join(REPO, "paper_results", "fair-fight")


def test_the_records_joined_to_their_truths_score_as_the_verdicts_did(tmp_path):
    """The truths taken from inception-2000-ema's files give each seed's NMAE
    that the verdicts computed from the dataset itself; a record whose test
    pairs differ is refused."""
    rows = load_script("analyses/fair_fight_rows.py")
    with open(os.path.join(FIGHT, "inception", "verdicts.json")) as f:
        pair = json.load(f)["pairs"]["MTL-CPL-A vs MTL-Baseline"]
    found = rows.rows(os.path.join(FIGHT, "inception", "runs"), "baseline")
    assert sorted(found) == [0, 1, 2]
    for column in pair["detail"]:
        p = column["parameter"]
        for interval in column["per_seed"]:
            raw = found[interval["seed"]]
            truth = np.asarray(raw["truth"][p], np.float64)
            nmae = np.mean(np.abs(raw["pred"][p] - truth)) / np.mean(np.abs(truth))
            assert nmae == pytest.approx(interval["nmae_b"], rel=1e-9), (p, interval["seed"])
    # a record of other test pairs: refused in one line
    record = tmp_path / "runs" / "cvgl_baseline-s0" / "predictions"
    record.mkdir(parents=True)
    with np.load(os.path.join(FIGHT, "inception", "runs", "cvgl_baseline-s0", "predictions",
                              "cvgl_2000_112px_s0_v3.0.npz")) as stored:
        arrays = {k: stored[k] for k in stored.files}
    arrays["indices"] = arrays["indices"][::-1]
    np.savez(record / "cvgl_2000_112px_s0_v3.0.npz", **arrays)
    with pytest.raises(ValueError, match="not those of"):
        rows.rows(str(tmp_path / "runs"), "baseline")


def test_the_loss_split_adds_up_and_lists_the_jumps():
    jumps = load_script("analyses/loss_jumps.py")
    alpha = {k: 0.5 for k in camera.TARGETS}
    row = {"epoch": 2.0, "loss": 30.0, **{f"alpha_{k}": a for k, a in alpha.items()},
           **{f"{k}_mae": 1.0 for k in camera.TARGETS}}
    row["X_mae"] = 260.0
    parts = jumps.parts(row)
    assert parts["s"] == pytest.approx(13 * math.log(2.0))
    assert parts["points"] == pytest.approx(0.5 * (260 + 1 + 1) / 13)
    assert parts["own"] == pytest.approx(0.5 * 10 / 13)
    assert parts["s"] + parts["points"] + parts["own"] + parts["rest"] == pytest.approx(30.0)
    before = dict(row, epoch=1.0, loss=10.0, X_mae=2.0)
    found = jumps.jumps([before, row], rise=5.0)
    assert [j["epoch"] for j in found] == [2]
    assert found[0]["rises"]["points"] == pytest.approx(0.5 * 258 / 13)
    assert jumps.jumps([before, row], rise=25.0) == []
    # the committed runs: seed 1's epoch 21, its X, Y, Z terms most of the rise
    run = next(r for r in jumps.compute() if r["run"] == "MTL-CPL-A" and r["seed"] == 1)
    worst = max(run["jumps"], key=lambda j: j["rises"]["loss"])
    assert worst["epoch"] == 21 and worst["rises"]["points"] > 0.75 * worst["rises"]["loss"]


def test_the_range_terms_sensitivities_on_the_optical_axis():
    """On the optical axis with no pitch (u = u0, v = v0): the point is
    (xCam, 0, 0) + t with xCam = fx b / d, so dP/dpitch is xCam (in Z),
    dP/dd is xCam / d, dP/dfx and dP/du0 are b / d, dP/db is fx / d,
    dP/dfy is 0 and each translation moves it by 1."""
    script = load_script("analyses/range_sensitivity.py")
    params = {"fx": 50.0, "fy": 40.0, "u0": 56.0, "v0": 56.0, "baseline": 20.0,
              "disparity": 100.0, "tx": 3.0, "ty": -1.0, "tz": 2.0, "pitch": 0.0}
    found = script.point_sensitivities(params, u=56.0, v=56.0)
    xcam = 50.0 * 20.0 / 100.0
    expected = {"fx": 20 / 100, "fy": 0.0, "u0": 20 / 100, "v0": xcam / 40, "baseline": 0.5,
                "disparity": xcam / 100, "tx": 1.0, "ty": 1.0, "tz": 1.0, "pitch": xcam}
    for p, value in expected.items():
        assert found[p] == pytest.approx(value, abs=1e-5), p
    # the reference pair projects the mean point: its implied disparity puts it there
    mean = dict(params, X=13.0, Y=-1.0, Z=2.0)  # (xCam 10 m: d = 50 * 20 / 10)
    pairs = script.reference_pairs(mean)
    (implied, u, v), (at_mean, _, _) = pairs.values()
    assert np.allclose(camera.image_to_world(**implied, u=u, v=v), (13.0, -1.0, 2.0))
    assert implied["disparity"] == pytest.approx(100.0) and at_mean == params
