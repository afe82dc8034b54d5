"""bench/leave_one_rig_out.py at tiny scale: with the real crops, every
model is trained without the rig it is scored on, and the summary reports
each held-out rig once with the field's metrics."""

import importlib.util
import json
import os

import numpy as np
import pytest

BENCH = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench")


@pytest.mark.slow
def test_each_rig_is_scored_by_a_model_that_never_saw_it(tiny_run, real32, tmp_path):
    """``--only oakd``: one model, trained with the other two rigs' crops,
    scored on the OAK-D rig alone."""
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import load_split

    spec = importlib.util.spec_from_file_location(
        "leave_one_rig_out", os.path.join(BENCH, "leave_one_rig_out.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out, runs = tmp_path / "out", tmp_path / "runs"
    assert script.main(["--synthetic", tiny_run["data"], "--real-dir", str(real32), "--out",
                        str(out), "--runs-dir", str(runs), "--with-real-crops", "--only", "oakd",
                        "--backbone", "small", "--epochs", "1", "--augment", "none"]) == 0
    assert sorted(script.real_sets(str(real32))) == ["chessboard", "middlebury", "oakd"]
    assert sorted(os.listdir(runs)) == ["mix_without_oakd.h5", "without-oakd"]
    config = json.loads((runs / "without-oakd" / "config.json").read_text())
    assert config["training_rigs"] == ["chessboard", "middlebury"]
    with StereoFile(runs / "mix_without_oakd.h5") as f:
        assert f.metadata["rigs"] == config["training_rigs"]
        assert f.num_pairs == 40 + 13 + 1  # the rendered pairs and the two rigs' crops
        source = f.labels["source_index"]
    # the frame-level split: the chessboard rig (one configuration) is trained on,
    # not held out whole as held-out-config would
    assert config["split"] == "paper"
    train = load_split(runs / "without-oakd" / "split.npz")["train"]
    assert np.count_nonzero(source[train] == 1) >= 5
    published = json.loads((out / "runs" / "without-oakd_config.json").read_text())
    assert published["training_rigs"] == config["training_rigs"]
    assert published["data"] == "mix_without_oakd.h5"
    assert (out / "runs" / "without-oakd_log.csv").read_text() == \
        (runs / "without-oakd" / "log.csv").read_text()
    table = json.loads((out / "without-oakd" / "table2.json").read_text())
    assert list(table["rigs"]) == ["oakd"]
    summary = (out / "summary.md").read_text()
    rows = [line for line in summary.splitlines() if line.startswith("| oakd | ")]
    assert len(rows) == 1 and rows[0].startswith("| oakd | without-oakd | 12 |")
    assert rows[0].endswith("| no |") or rows[0].endswith("| yes |")
    # fy from square pixels, by hand from the stored predictions of fx and the
    # crops' sides (fy / fx of a square-pixel crop is its width / height)
    from cpl_keras import evaluation
    from cpl_keras.runs import load_model, load_run
    with StereoFile(real32 / "oakd.h5") as f:
        labels = f.labels
        run = load_run(str(runs / "without-oakd"))
        fx = evaluation.predict_run(load_model(run), f, np.arange(12))
    expected = np.median(np.abs(fx["fx"] * labels["crop_width"] / labels["crop_height"]
                                / labels["fy"] - 1.0))
    assert f"| {expected:.3f} |" in rows[0]
    assert script.square_pixel_fy_error(str(runs / "without-oakd"), str(real32 / "oakd.h5")) == \
        pytest.approx(expected, rel=1e-5)
    # the model's own test split, per source of its training file: the counts
    # add up to the split's test part, the rendered row's fx error by hand
    test = load_split(runs / "without-oakd" / "split.npz")["test"]
    own = [line for line in summary.split("own test split")[1].splitlines()
           if line.startswith("| without-oakd |")]
    counts = {line.split(" | ")[1]: int(line.split(" | ")[2]) for line in own}
    assert sum(counts.values()) == len(test) and "rendered" in counts
    assert set(counts) <= {"rendered", "chessboard", "middlebury"}
    with StereoFile(runs / "mix_without_oakd.h5") as f:
        pred = evaluation.predict_run(load_model(run), f, test)
        rendered = f.labels["source_index"][test] == 0
        fx_true = f.labels["fx"][test]
    fx_error = np.median(np.abs(pred["fx"][rendered] / fx_true[rendered] - 1.0))
    assert f"| without-oakd | rendered | {rendered.sum()} | {fx_error:.3f} |" in own[0]
    # summary.json holds what the page shows: the page and the model's table
    # render again from the written files alone
    stored = json.loads((out / "summary.json").read_text())
    assert [r["rig"] for r in stored["held_out"]] == ["oakd"]
    assert stored["held_out"][0]["fy_square_pixels_relative_median"] == pytest.approx(
        expected, rel=1e-5)
    for page in (out / "summary.md", out / "without-oakd" / "table2.md"):
        assert script.regenerate(str(page)) == page.read_text()


def test_calibrate_held_out_writes_each_rigs_calibration_against_its_truth(tiny_run, tmp_path):
    """bench/calibrate_held_out.py with a without-oakd run only: the OAK-D
    rig's 12 whole pairs calibrated as calibrate --folder does, the row's
    errors worked out from the written JSON and the true 451.03 px, the YAML
    read back by OpenCV, the other rigs skipped."""
    import cv2

    spec = importlib.util.spec_from_file_location(
        "calibrate_held_out", os.path.join(BENCH, "calibrate_held_out.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    runs, out = tmp_path / "runs", tmp_path / "out"
    runs.mkdir()
    os.symlink(tiny_run["run"], runs / "without-oakd")
    assert script.main(["--runs-dir", str(runs), "--out", str(out)]) == 0
    assert sorted(os.listdir(out)) == ["oakd.json", "oakd_opencv.yml", "oakd_ros",
                                       "oakd_warnings.txt", "summary.md"]
    result = json.loads((out / "oakd.json").read_text())
    rig = result["rig"]
    assert rig["num_pairs"] == 12 and rig["folder"] == "oakd_stereo"
    assert all("/" not in p["left"] for p in result["pairs"])
    fx = rig["parameters"]["fx"]
    assert rig["parameters"]["fy"] == fx       # square pixels
    row = [l for l in (out / "summary.md").read_text().splitlines() if l.startswith("| oakd")]
    assert len(row) == 1
    assert f"| 451.0 / {fx:.1f} ({abs(fx / 451.03 - 1):.3f}) |" in row[0]
    assert "| 640 x 480 |" in row[0]
    warnings = (out / "oakd_warnings.txt").read_text().splitlines()
    assert any("is grey" in w for w in warnings) and row[0].endswith(f"| {len(warnings)} |")
    fs = cv2.FileStorage(str(out / "oakd_opencv.yml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("M1").mat()[0, 0] == pytest.approx(fx)
    fs.release()
    # the page renders again from the files written beside it
    assert script.regenerate(str(out / "summary.md")) == (out / "summary.md").read_text()
