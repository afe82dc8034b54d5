"""evaluate.py end to end: Table 1 and Table 2 on a tiny trained run."""

import json
import os

import numpy as np
import pytest

import evaluate
from cpl_keras import evaluation, metrics, report, runs
from cpl_keras.camera import PARAMETERS
from cpl_keras.data.storage import StereoFile
from cpl_keras.data.writer import StereoWriter
from cpl_keras.models.inference import predict_images
from helpers import REPO, writable_copy

SIZE = 32


@pytest.fixture(scope="module")
def tiny(tiny_run, tmp_path_factory):
    from cpl_keras.real.middlebury import build_middlebury

    root = tmp_path_factory.mktemp("eval")
    real = build_middlebury(root / "middlebury.h5", crops=5, image_size=SIZE, seed=0)
    return dict(tiny_run, root=root, real=real)


def _outputs(directory, stem):
    return [os.path.join(directory, f"{stem}{ext}") for ext in (".md", ".csv", ".json", "_fov.png")]


def test_table1_end_to_end(tiny, tmp_path, capsys):
    assert evaluate.main(["--table", "1", "--runs", tiny["run"], "--out", str(tmp_path),
                          "--geometric-max", "3"]) == 0
    printed = capsys.readouterr().out
    assert "| MTL-Baseline |" in printed and "| Geometric |" in printed
    for path in _outputs(tmp_path, "table1"):
        assert os.path.getsize(path) > 0
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".partial")]
    table = json.load(open(tmp_path / "table1.json"))
    assert list(table["rows"]) == ["Average", "Average (release bug)", "MTL-Baseline", "Geometric"]
    assert "evaluate.py --table 1" in table["command"]
    assert table["rows"]["Geometric"]["num_pairs"] == 3
    assert "few_matches" in table["rows"]["Geometric"]["failures"]
    # the Average row, recomputed by hand from the run's statistics and test split
    split = np.load(os.path.join(tiny["run"], "split.npz"))
    stats = json.load(open(os.path.join(tiny["run"], "train_stats.json")))
    with StereoFile(tiny["data"]) as f:
        fx = f.labels["fx"][split["test"]].astype(np.float64)
    expected = np.mean(np.abs(stats["mean"]["fx"] - fx)) / np.mean(fx)
    assert table["rows"]["Average"]["targets"]["fx"]["nmae_signed"] == pytest.approx(expected, rel=1e-5)
    assert table["num_pairs"] == len(split["test"])
    # the paper's numbers sit beside ours, the best value per column is bold
    md = open(tmp_path / "table1.md").read()
    assert "(94.233)" in md and "**" in md
    csv = open(tmp_path / "table1.csv").read().splitlines()
    assert csv[0] == "method,metric,fx,fy,u0,v0,b,d,tx,ty,tz,theta_p"
    assert len(csv) == 1 + 4 * 3


def test_table2_real_data_forward_pass(tiny, tmp_path):
    assert evaluate.main(["--table", "2", "--runs", tiny["run"], "--data", tiny["real"],
                          "--out", str(tmp_path), "--no-geometric"]) == 0
    table = json.load(open(tmp_path / "table2.json"))
    assert table["num_pairs"] == 5 and "all 5 pairs" in table["data_description"]
    assert "Geometric" not in table["rows"]
    # pitch, tx, tz are 0 on a rectified real rig: NMAE undefined, never inf
    rig = next(iter(table["rigs"].values()))
    row = rig["rows"]["MTL-Baseline"]["targets"]
    assert row["pitch"]["nmae"] is None and row["tz"]["nmae_signed"] is None
    assert row["fx"]["nmae"] is not None and row["pitch"]["mae"] is not None
    # pooled, pitch leaves out the rectified rigs (nothing to measure): here all
    pooled = table["rows"]["MTL-Baseline"]["targets"]
    assert pooled["pitch"]["num_defined"] == 0 and pooled["pitch"]["mae"] is None
    assert pooled["fx"]["num_defined"] == 5 and pooled["fx"]["nmae"] == row["fx"]["nmae"]
    md = open(tmp_path / "table2.md").read()
    assert "n/a" in md and "(2321.338)" in md


def test_single_run_evaluation(tiny, tmp_path):
    out = tmp_path / "new" / "folder"                  # created when missing
    assert evaluate.main(["--run", tiny["run"], "--data", tiny["data"], "--out", str(out)]) == 0
    result = json.load(open(out / "eval_run_baseline.json"))
    split = np.load(os.path.join(tiny["run"], "split.npz"))
    assert result["num_pairs"] == len(split["test"])
    curve = result["rows"]["MTL-Baseline"]["fov_within_deg"]
    assert [float(k) for k in curve] == list(metrics.FOV_THRESHOLDS_DEG)
    # the paths it records are relative to where it was written
    assert not os.path.isabs(result["data"]) and not os.path.isabs(result["runs"][0])
    assert os.path.samefile(os.path.join(out, result["data"]), tiny["data"])
    assert os.path.samefile(os.path.join(out, result["runs"][0]), tiny["run"])


def test_tables_without_out_go_to_runs_tables_not_paper_results():
    """evaluate.py --table writes into runs/tables/ (git-ignored) by default:
    the committed paper_results/ is written only by the reproduction."""
    args = evaluate.parse_args(["--table", "1", "--runs", "runs/x"])
    assert args.out == os.path.join("runs", "tables")
    assert evaluate.parse_args(["--table", "1", "--runs", "runs/x", "--out", "o"]).out == "o"


def test_single_run_writes_next_to_the_run(tiny, tmp_path):
    """Without --out, --run writes beside the run directory, not into paper_results/."""
    run = tmp_path / "runs" / "mine"
    writable_copy(tiny["run"], run)
    paper_results = os.path.join(REPO, "paper_results")
    before = sorted(os.listdir(paper_results))
    assert evaluate.main(["--run", str(run), "--data", tiny["data"]]) == 0
    assert (tmp_path / "runs" / "eval_mine.json").exists()
    assert (tmp_path / "runs" / "eval_mine_fov.png").exists()
    assert sorted(os.listdir(paper_results)) == before


def test_a_published_record_scores_its_test_split_as_its_run_did(tiny, tmp_path):
    """A published record (no weights; its config names the dataset file
    without a folder) scores the run's test split from its stored
    predictions, as the run directory does with its weights."""
    from cpl_keras import published

    run = tmp_path / "run"
    writable_copy(tiny["run"], run)
    evaluation.store_predictions(str(run), [])
    published.publish_run_dir(str(run), str(tmp_path / "record"))
    for source in ("run", "record"):
        assert evaluate.main(["--run", str(tmp_path / source), "--data", tiny["data"],
                              "--no-geometric", "--out", str(tmp_path / "out")]) == 0
    scored = [json.load(open(tmp_path / "out" / f"eval_{source}.json"))
              for source in ("run", "record")]
    assert scored[0]["num_pairs"] == scored[1]["num_pairs"] == len(
        np.load(os.path.join(tiny["run"], "split.npz"))["test"])
    rows = [{row: {k: v for k, v in cells.items() if k != "source"}
             for row, cells in table["rows"].items()} for table in scored]
    assert rows[0] == rows[1] and rows[0]["MTL-Baseline"]["targets"]["fx"]["nmae"] > 0


def _fails(argv, capsys, match):
    assert evaluate.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("evaluate.py: error:") and "\n" not in err and match in err, err


def test_bad_inputs(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    no_weights = tmp_path / "no_weights"
    writable_copy(tiny["run"], no_weights)
    os.remove(no_weights / "model.keras")
    _fails(["--run", str(no_weights), "--data", tiny["data"], "--out", str(out)], capsys,
           "weights")
    # a dataset without labels
    unlabeled = tmp_path / "unlabeled.h5"
    with StereoWriter(unlabeled, 2, SIZE) as writer:
        images = np.zeros((2, SIZE, SIZE, 3), np.uint8)
        writer.write(0, images, images, {"fx": np.ones(2)})
    _fails(["--run", tiny["run"], "--data", str(unlabeled), "--out", str(out)], capsys,
           "missing label")
    _fails(["--table", "2", "--runs", tiny["run"], "--out", str(out)], capsys, "--data")
    _fails(["--run", tiny["run"], "--data", str(tmp_path / "none.h5"), "--out", str(out)],
           capsys, "not found")
    (tmp_path / "a_file").write_text("")
    _fails(["--run", tiny["run"], "--data", tiny["data"], "--out", str(tmp_path / "a_file")],
           capsys, "output directory")
    _fails(["--run", str(tmp_path / "a_file"), "--data", tiny["data"], "--out", str(out)],
           capsys, "not a directory")
    _fails(["--run", str(tmp_path / "no_run"), "--data", tiny["data"], "--out", str(out)],
           capsys, "run directory not found")
    with pytest.raises(SystemExit) as exit_info:
        evaluate.main(["--table", "3", "--runs", tiny["run"]])
    assert exit_info.value.code == 2
    assert os.listdir(out) == []                 # nothing partial was left behind


def test_the_reproduction_is_its_own_command(tmp_path, capsys):
    """--reproduce (and the reproduction's options) are not evaluate.py's: one
    line naming ``cpl-reproduce`` with the same arguments (or the option),
    exit 2, nothing made. evaluate.py's own --batch-size is checked when parsed."""
    out = tmp_path / "out"
    for argv, line in (
            (["--reproduce", "--preset", "cpu", "--out", str(out)],
             f"evaluate.py: error: --reproduce moved: run cpl-reproduce --preset cpu --out {out} "
             f"(or python -m cpl_keras.reproduce --preset cpu --out {out})"),
            (["--quick", "--out", str(out)], "evaluate.py: error: unrecognized arguments: --quick"),
            (["--table", "1", "--runs", "x", "--batch-size", "0", "--out", str(out)],
             "evaluate.py: error: argument --batch-size: must be a positive integer, got 0")):
        with pytest.raises(SystemExit) as exit_info:
            evaluate.main(argv)
        assert exit_info.value.code == 2
        assert capsys.readouterr().err == line + "\n"
    assert os.listdir(tmp_path) == []


def test_best_marks_smallest_magnitude_and_ties():
    def row(value):
        return {"targets": {p: {"nmae_signed": value} for p in PARAMETERS}}
    rows = {"A": row(-1.9), "B": row(0.09), "C": row(-0.09), "D": row(None)}
    best = report.best_rows(rows, "nmae_signed")
    assert best["fx"] == {"B", "C"}


def test_forward_pass_sees_one_batch_shape_and_drops_the_filled_rows(tiny):
    """predict_images gives the model full batches only (a set of 7 and of 3
    pairs at batch 4: every call 4 pairs, so one compilation), and its
    outputs are the model's on each pair alone: the filled-up rows change
    nothing and are dropped."""
    model = runs.load_model(runs.load_run(tiny["run"]))
    with StereoFile(tiny["data"]) as f:
        left, right = f.read_pairs(np.arange(7))
    seen, call = [], model.predict_on_batch

    def recording(inputs):
        seen.append(inputs["left_image"].shape[0])
        return call(inputs)

    model.predict_on_batch = recording
    seven = predict_images(model, left, right, batch_size=4)
    three = predict_images(model, left[4:], right[4:], batch_size=4)
    assert seen == [4, 4, 4]
    del model.predict_on_batch
    for i in range(7):  # each pair through the model on its own
        alone = model.predict_on_batch({"left_image": left[i:i + 1].astype(np.float32),
                                        "right_image": right[i:i + 1].astype(np.float32)})
        alone = dict(zip(model.output_names, alone))
        for name in PARAMETERS:
            value = float(np.asarray(alone[name]).reshape(-1)[0])
            assert seven[name].shape == (7,) and three[name].shape == (3,)
            assert seven[name][i] == pytest.approx(value, rel=1e-5, abs=1e-5)
            if i >= 4:
                assert three[name][i - 4] == seven[name][i]


def test_predict_images_has_one_home():
    """The forward pass on image arrays is imported from
    ``cpl_keras.models.inference`` alone: no module of ``cpl_keras.evaluation``
    hands it out as a second door."""
    import importlib
    import pkgutil

    import cpl_keras.evaluation
    from cpl_keras.models import inference

    assert hasattr(inference, "predict_images")
    assert not hasattr(cpl_keras.evaluation, "predict_images")
    assert "predict_images" not in cpl_keras.evaluation.__all__
    for module in pkgutil.iter_modules(cpl_keras.evaluation.__path__):
        loaded = importlib.import_module(f"cpl_keras.evaluation.{module.name}")
        assert not hasattr(loaded, "predict_images"), loaded.__name__


def test_runs_are_loaded_from_their_own_home():
    """A run and its model are read through ``cpl_keras.runs`` and a model's
    input size through ``cpl_keras.models.inference``; the evaluation
    package uses them but does not hand them out."""
    import cpl_keras.evaluation
    from cpl_keras.models import inference

    for name, home in (("load_run", runs), ("load_model", runs),
                       ("model_image_shape", inference)):
        assert hasattr(home, name)
        assert not hasattr(cpl_keras.evaluation, name), name
        assert name not in cpl_keras.evaluation.__all__
