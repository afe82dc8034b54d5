"""Table 2 over several real rigs: per rig, pooled, undefined and degenerate cells."""

import json
import os

import numpy as np
import pytest

import evaluate
from cpl_keras.commands import real_build

SIZE = 32


@pytest.fixture(scope="module")
def setup(tiny_run, real32):
    return {"run": str(tiny_run["run"]), "real": real32}


def test_table2_per_rig_and_pooled(setup, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    assert evaluate.main(["--table", "2", "--runs", setup["run"], "--data", str(setup["real"]),
                          "--out", str(out), "--geometric-max", "2"]) == 0
    table = json.load(open(out / "table2.json"))
    assert set(table["rigs"]) == {"chessboard", "middlebury", "oakd"}
    assert table["num_pairs"] == 13 + 1 + 12
    assert table["rigs"]["oakd"]["rectified"] is True
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

    from helpers import kitti_stereo_root

    root = kitti_stereo_root(tmp_path / "kitti")
    os.remove(root / "training" / "disp_occ_0" / "000000_10.png")
    real = tmp_path / "real"
    real.mkdir()
    shutil.copy(setup["real"] / "chessboard.h5", real)
    assert real_build.main(["kitti", "--root", str(root), "--image-size", str(SIZE), "--out",
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
    assert "Columns scored on part of the pairs only" in open(out / "table2.md").read()


def _rig(name, n, rectified, geometric_pairs, seed):
    """The ``Rig`` of one rig (``table2_from_rigs``' input) with known errors."""
    from cpl_keras.baselines.geometric import FAILURE_FLAGS
    from cpl_keras.camera import TARGETS
    from cpl_keras.table_rows import Rig, Row

    rng = np.random.default_rng(seed)
    truth = {k: rng.uniform(50.0, 150.0, n) for k in TARGETS}
    if rectified:
        truth["pitch"] = np.zeros(n)
    indices = np.arange(n)

    def row(pred_scale, subset=None, **geometric):
        take = indices if subset is None else indices[:subset]
        defined = {k: np.ones(len(take), bool) for k in TARGETS}
        if rectified and geometric:
            defined.update(fx=np.zeros(len(take), bool), fy=np.zeros(len(take), bool))
        return Row(source="x", as_released=False, indices=take,
                   truth={k: v[take] for k, v in truth.items()},
                   pred={k: v[take] * pred_scale for k, v in truth.items()},
                   defined=defined, **geometric)

    rows = {"Average": row(1.5), "MTL-CPL-A": row(1.1), "Geometric": row(
        1.3, geometric_pairs, priors={},
        statuses=[{f: False for f in FAILURE_FLAGS}] * geometric_pairs,
        degenerate=["fx", "fy"] if rectified else [])}
    return Rig(rig=name, data=f"/{name}.h5", data_description=f"all {n}",
               rectified=rectified, width=112, data_source=name, num_pairs=n, rows=rows)


def test_pooled_table_scores_each_row_on_its_pairs_and_shared_on_the_same_pairs():
    """Pooled, every row on every pair it has (Geometric ran on 4 of the 10
    chessboard pairs and is degenerate on the rectified rig); ``shared``,
    every row only on the pairs every row has; pitch only on the rig that is
    not rectified. Values derived by hand from the constructed errors
    (|pred - y| / mean|y| = scale - 1 on any set of pairs)."""
    from cpl_keras.evaluation import table2_from_rigs
    from cpl_keras.report.text import table2_csv, table2_markdown

    rigs = [_rig("chessboard", 10, False, 4, 0), _rig("middlebury", 20, True, 20, 1)]
    table = table2_from_rigs(["run"], rigs)
    fx_pairs = rigs[0].rows["Average"].truth["fx"][:4]
    for row, scale in (("Average", 1.5), ("MTL-CPL-A", 1.1), ("Geometric", 1.3)):
        own, shared = table.rows[row]["targets"], table.shared.rows[row]["targets"]
        assert shared["fx"]["num_defined"] == 4
        assert shared["fx"]["nmae"] == pytest.approx(scale - 1.0)
        assert shared["fx"]["mae"] == pytest.approx((scale - 1.0) * fx_pairs.mean())
        assert shared["pitch"]["num_defined"] == 4       # only the chessboard rig's shared pairs
        assert shared["u0"]["num_defined"] == 24         # the 4 + 20 Geometric has
        assert own["fx"]["nmae"] == pytest.approx(scale - 1.0)
        if row == "Geometric":
            assert own["fx"]["num_defined"] == 4 and own["pitch"]["num_defined"] == 4
            assert own["u0"]["num_defined"] == 24
        else:                                            # every pair with truth
            assert own["fx"]["num_defined"] == 30 and own["pitch"]["num_defined"] == 10
            assert own["u0"]["num_defined"] == 30
    # per rig, each row keeps all of its own pairs
    assert table.rigs["chessboard"].rows["MTL-CPL-A"]["targets"]["fx"]["num_defined"] == 10
    text = table2_markdown(table)
    assert "## Pooled over all rigs, every row on the same pairs" in text
    assert "Rows scored on fewer pairs than the others (pairs per column): Geometric: fx 4," in text
    assert "\npooled on shared pairs,Geometric,nmae," in table2_csv(table)
    # the JSON reads back, the shared table with it
    from cpl_keras.evaluation.tables import table_from_json
    back = table_from_json(table.to_json())
    assert back.shared.rows["Geometric"]["targets"]["fx"]["num_defined"] == 4


def test_pooled_table_has_no_shared_table_when_every_row_has_the_same_pairs():
    from cpl_keras.evaluation import table2_from_rigs

    table = table2_from_rigs(["run"], [_rig("chessboard", 10, False, 10, 0)])
    assert table.shared is None and "shared" not in table.to_json()


def _synthetic_rig(name, n, errors, rectified, subset=None, seed=0):
    """A rig whose rows predict ``truth * (1 + error)`` (an error per pair):
    each row's NMAE on pairs P is then mean(|y| e) / mean(|y|) over P."""
    from cpl_keras.camera import TARGETS
    from cpl_keras.table_rows import Rig, Row

    rng = np.random.default_rng(seed)
    truth = {k: rng.uniform(1.0, 2.0, n) for k in TARGETS}
    rows = {}
    for row, error in errors.items():
        idx = np.arange(n) if subset is None or row != "Average" else np.arange(subset)
        e = np.broadcast_to(np.asarray(error, float), (n,))[idx]
        rows[row] = Row(source=row, as_released=False, indices=idx,
                        truth={k: v[idx] for k, v in truth.items()},
                        pred={k: v[idx] * (1 + e) for k, v in truth.items()},
                        defined={k: np.ones(len(idx), bool) for k in TARGETS})
    return Rig(rig=name, data=f"{name}.h5", data_description="synthetic", rectified=rectified,
               width=64, data_source="test", num_pairs=n, rows=rows), truth


def test_table2_values_per_rig_and_pooled_against_hand_computed_nmae():
    """Table 2's cells from rows with known errors, against NMAE worked out
    here: per rig every pair of each row; pooled, only the pairs every row
    has (Average has the first 10 of rig A's 30), and pitch only on the
    unrectified rig."""
    from cpl_keras.evaluation import table2_from_rigs

    baseline_a = np.where(np.arange(30) < 10, 0.1, 0.5)   # worse off the shared pairs
    rig_a, truth_a = _synthetic_rig("A", 30, {"Average": 0.3, "MTL-Baseline": baseline_a},
                                    rectified=False, subset=10, seed=1)
    rig_b, truth_b = _synthetic_rig("B", 20, {"Average": 0.2, "MTL-Baseline": 0.05},
                                    rectified=True, seed=2)
    table = table2_from_rigs(["run"], [rig_a, rig_b])

    def cell(t, row, name):
        return t.rows[row]["targets"][name]["nmae"]

    # per rig: all of the row's own pairs
    fx_a = truth_a["fx"]
    assert cell(table.rigs["A"], "MTL-Baseline", "fx") == pytest.approx(
        np.sum(fx_a * baseline_a) / np.sum(fx_a), rel=1e-12)
    assert cell(table.rigs["A"], "Average", "fx") == pytest.approx(0.3, rel=1e-12)
    assert cell(table.rigs["B"], "MTL-Baseline", "pitch") == pytest.approx(0.05, rel=1e-12)
    # pooled over the shared pairs: A's first 10 and all of B's 20
    for name in ("fx", "baseline", "Z"):
        y = np.concatenate([truth_a[name][:10], truth_b[name]])
        e = np.concatenate([np.full(10, 0.1), np.full(20, 0.05)])
        assert cell(table.shared, "MTL-Baseline", name) == pytest.approx(
            np.sum(y * e) / np.sum(y), rel=1e-12), name
        assert table.shared.rows["MTL-Baseline"]["targets"][name]["num_defined"] == 30
        # pooled over each row's own pairs: all of A's 30 for MTL-Baseline
        y = np.concatenate([truth_a[name], truth_b[name]])
        e = np.concatenate([baseline_a, np.full(20, 0.05)])
        assert cell(table, "MTL-Baseline", name) == pytest.approx(
            np.sum(y * e) / np.sum(y), rel=1e-12), name
        assert table.rows["MTL-Baseline"]["targets"][name]["num_defined"] == 50
        assert table.rows["Average"]["targets"][name]["num_defined"] == 30
    # pitch pooled only where defined: rig B is rectified
    assert cell(table.shared, "MTL-Baseline", "pitch") == pytest.approx(0.1, rel=1e-12)
    assert cell(table, "MTL-Baseline", "pitch") == pytest.approx(
        np.sum(truth_a["pitch"] * baseline_a) / np.sum(truth_a["pitch"]), rel=1e-12)
    assert cell(table, "Average", "pitch") == pytest.approx(0.3, rel=1e-12)
    assert table.rows["Average"]["targets"]["pitch"]["num_defined"] == 10
