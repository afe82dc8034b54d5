"""The fair fight's analyses of its committed record: the loss split term by term."""

import math

import pytest
from helpers import load_script

from cpl_keras import camera


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
