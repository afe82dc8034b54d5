"""analyses/variant_gaps.py: two variants' test gap, setting by setting,
with the paired bootstrap of each setting's test pairs."""

import json
import os

import numpy as np
import pytest
from helpers import load_script

from cpl_keras.camera import PARAMETERS
from cpl_keras.evaluation import verdicts as v


def _script():
    return load_script("analyses/variant_gaps.py")


def test_arguments():
    script = _script()
    for bad in (["--setting", "A=d.h5,a", "--out", "o.md"],
                ["--setting", "d.h5,a,b", "--out", "o.md"],
                ["--setting", "A=d.h5,a,b", "--out", "o"],
                ["--setting", "A=d.h5,a,b", "--out", "o.md", "--resamples", "5"]):
        with pytest.raises(SystemExit):
            script.parse_args(bad)
    args = script.parse_args(["--setting", "S, 2,000=d.h5,a,b", "--out", "o.md"])
    assert args.setting == [("S, 2,000", "d.h5", "a", "b")]


def test_gap_ratio_and_side_of_one_setting():
    """A off by 1 and B off by 2 on every pair: A lower on every column, by
    (1 - 2) / mean|truth|, at half B's NMAE; equal outputs decide nothing."""
    rng = np.random.default_rng(0)
    indices = np.arange(50)
    truth = {name: rng.uniform(1.0, 3.0, 50) for name in PARAMETERS}
    a = {"indices": indices, "truth": truth, "pred": {n: t + 1.0 for n, t in truth.items()}}
    b = {"indices": indices, "truth": truth, "pred": {n: t - 2.0 for n, t in truth.items()}}
    columns = _script().gap(a, b, seed=0, resamples=200)
    for column, parameter in v.COLUMN_PARAMETER.items():
        cell = columns[column]
        scale = np.abs(truth[parameter]).mean()
        assert cell["gap"] == pytest.approx(-1.0 / scale)
        assert cell["ratio"] == pytest.approx(0.5)
        assert cell["answer"] == "lower" and cell["low"] <= cell["gap"] <= cell["high"] < 0
    same = _script().gap(a, a, seed=0, resamples=200)
    assert {c["answer"] for c in same.values()} == {"="}
    assert {c["ratio"] for c in same.values()} == {1.0}


def test_a_run_against_itself_on_its_test_split(tiny_run, tmp_path):
    """End to end on a trained run: the page and its JSON, the run's test
    split, and no gap between a run and itself."""
    script = _script()
    out = tmp_path / "gaps.md"
    run = tiny_run["run"]
    assert script.main(["--setting", f"tiny={tiny_run['data']},{run},{run}",
                        "--a", "left", "--b", "right", "--out", str(out)]) == 0
    result = json.loads((tmp_path / "gaps.json").read_text())["tiny"]
    split = np.load(os.path.join(run, "split.npz"), allow_pickle=False)
    assert result["test_pairs"] == len(split["test"]) > 0
    assert {c["gap"] for c in result["columns"].values()} == {0.0}
    page = out.read_text()
    assert "# left against right, setting by setting" in page
    assert '--a "left" --b "right"' in page and "| tiny | 0, " in page and "| 0 / 0 |" in page


def test_errors_by_the_depth_of_the_point():
    """Thirds of the test pairs by xCam = fx b / d: A off by 1 on the near
    third and by 3 on the far one, B off by 2 everywhere: ratios 0.5, 1, 1.5
    in every column, the depth ranges in order and every pair counted."""
    n = 30
    truth = {name: np.full(n, 2.0) for name in PARAMETERS}
    truth["disparity"] = np.linspace(60.0, 1.0, n)        # (far last)
    depth = truth["fx"] * truth["baseline"] / truth["disparity"]
    offset = np.repeat([1.0, 2.0, 3.0], n // 3)
    a = {"indices": np.arange(n), "truth": truth,
         "pred": {k: t + offset for k, t in truth.items()}}
    b = {"indices": np.arange(n), "truth": truth,
         "pred": {k: t + 2.0 for k, t in truth.items()}}
    result = _script().by_depth(a, b)
    assert result["pairs"] == [10, 10, 10]
    assert result["depth_m"][0][0] == pytest.approx(depth.min())
    assert result["depth_m"][2][1] == pytest.approx(depth.max())
    assert result["depth_m"][0][1] < result["depth_m"][1][0]
    for column in v.COLUMNS:
        assert result["ratio"][column] == pytest.approx([0.5, 1.0, 1.5])
