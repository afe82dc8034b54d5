"""bench/leave_one_rig_out.py at tiny scale: with the real crops, every
model is trained without the rig it is scored on, and the summary reports
each held-out rig once with the field's metrics."""

import importlib.util
import json
import os

import pytest

BENCH = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench")


@pytest.mark.slow
def test_each_rig_is_scored_by_a_model_that_never_saw_it(tiny_run, real32, tmp_path):
    from cpl_keras.data.storage import StereoFile

    real = tmp_path / "real"  # two of the three rigs: two models
    real.mkdir()
    for rig in ("chessboard", "oakd"):
        os.symlink(real32 / f"{rig}.h5", real / f"{rig}.h5")
    spec = importlib.util.spec_from_file_location(
        "leave_one_rig_out", os.path.join(BENCH, "leave_one_rig_out.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out, runs = tmp_path / "out", tmp_path / "runs"
    assert script.main(["--synthetic", tiny_run["data"], "--real-dir", str(real), "--out", str(out),
                        "--runs-dir", str(runs), "--with-real-crops", "--backbone", "small",
                        "--epochs", "1", "--augment", "none"]) == 0
    rigs = sorted(script.real_sets(str(real)))
    assert rigs == ["chessboard", "oakd"]
    for rig in rigs:
        config = json.loads((runs / f"without-{rig}" / "config.json").read_text())
        assert config["training_rigs"] == [r for r in rigs if r != rig]
        with StereoFile(runs / f"mix_without_{rig}.h5") as f:
            assert f.metadata["rigs"] == config["training_rigs"]
        published = json.loads((out / "runs" / f"without-{rig}_config.json").read_text())
        assert published["training_rigs"] == config["training_rigs"]
        assert published["data"] == f"mix_without_{rig}.h5"
        assert (out / "runs" / f"without-{rig}_log.csv").read_text() == \
            (runs / f"without-{rig}" / "log.csv").read_text()
        table = json.loads((out / f"without-{rig}" / "table2.json").read_text())
        assert list(table["rigs"]) == [rig]
    summary = (out / "summary.md").read_text()
    rows = [line for line in summary.splitlines() if line.startswith("| ") and "without-" in line]
    assert [row.split(" | ")[0][2:] for row in rows] == rigs
    assert all(row.endswith("| no |") or row.endswith("| yes |") for row in rows)
