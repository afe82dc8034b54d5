"""Table 2 over several real rigs: per rig, pooled, undefined and degenerate cells."""

import json
import os

import numpy as np
import pytest

import evaluate
from cpl_keras.real import build

SIZE = 32


@pytest.fixture(scope="module")
def setup(tiny_run, tmp_path_factory):
    root = tmp_path_factory.mktemp("t2")
    run = tiny_run["run"]
    real = root / "real"
    real.mkdir()
    assert build.main(["all", "--out-dir", str(real), "--crops", "1", "--image-size",
                       str(SIZE)]) == 0
    return {"run": str(run), "real": real}


def test_table2_per_rig_and_pooled(setup, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    assert evaluate.main(["--table", "2", "--runs", setup["run"], "--data", str(setup["real"]),
                          "--out", str(out), "--geometric-max", "2"]) == 0
    table = json.load(open(out / "table2.json"))
    assert set(table["rigs"]) == {"chessboard", "middlebury"}
    assert table["num_pairs"] == 13 + 1
    assert table["rigs"]["chessboard"]["rectified"] is False
    assert table["rigs"]["middlebury"]["rectified"] is True
    # chessboard: every column defined (unrectified, nonzero pitch / tx / tz)
    cb = table["rigs"]["chessboard"]["rows"]
    assert all(cb["MTL-Baseline"]["targets"][k]["nmae"] is not None for k in ("pitch", "tx", "tz"))
    # Geometric: fx defined on the unrectified rig, degenerate on the rectified one
    assert cb["Geometric"]["degenerate"] == []
    assert cb["Geometric"]["targets"]["fx"]["nmae"] is not None
    mb = table["rigs"]["middlebury"]["rows"]
    assert mb["Geometric"]["degenerate"] == ["fx", "fy"]
    assert mb["Geometric"]["targets"]["fx"]["nmae"] is None
    assert mb["MTL-Baseline"]["targets"]["pitch"]["nmae"] is None       # zero mean
    md = open(out / "table2.md").read()
    assert "## Rig: chessboard (not rectified)" in md and "degenerate" in md
    assert "(2321.338)" in md and "n/a" in md
    csv = open(out / "table2.csv").read().splitlines()
    assert csv[0].startswith("rig,method,metric,fx")
    assert any(line.startswith("middlebury,Geometric,nmae,degenerate") for line in csv)
    for suffix in ("_fov.png", "_fov_scatter.png"):
        assert (out / f"table2{suffix}").read_bytes()[:4] == b"\x89PNG"
    assert not [p for p in os.listdir(out) if p.endswith(".partial")]
    points = table["fov_points"]["chessboard"]["MTL-Baseline"]
    assert len(points["true_deg"]) == 13 and np.all(np.array(points["true_deg"]) > 50)


def test_undefined_disparity_is_left_out(setup, tmp_path):
    """A KITTI frame without ground-truth disparity: disparity, X, Y, Z use the
    other pairs only and are n/a when none is left."""
    import shutil

    from tests.test_real_kitti import _stereo_root

    root = _stereo_root(tmp_path / "kitti")
    os.remove(root / "training" / "disp_occ_0" / "000000_10.png")
    real = tmp_path / "real"
    real.mkdir()
    shutil.copy(setup["real"] / "chessboard.h5", real)
    assert build.main(["kitti", "--root", str(root), "--image-size", str(SIZE), "--out",
                       str(real / "kitti.h5")]) == 0
    out = tmp_path / "out"
    out.mkdir()
    assert evaluate.main(["--table", "2", "--runs", setup["run"], "--data", str(real),
                          "--out", str(out), "--no-geometric"]) == 0
    table = json.load(open(out / "table2.json"))
    kitti = table["rigs"]["kitti"]["rows"]["MTL-Baseline"]["targets"]
    assert kitti["disparity"]["mae"] is None and kitti["X"]["num_defined"] == 0
    assert kitti["fx"]["nmae"] is not None
    pooled = table["rows"]["MTL-Baseline"]["targets"]
    assert pooled["disparity"]["num_defined"] == 13 and pooled["fx"]["num_defined"] == 15
    assert "defined on part of the pairs only" in open(out / "table2.md").read()
