"""The analyses of analyses/ and the diagnostics of bench/ on the shared tiny run.

analyses/diagnose_inference_mode.py: every row of statistics is printed, the saved
statistics give the validation loss that training recorded, and the figures
are finite. analyses/fy_from_aspect.py: its errors are the ones worked out here from
the run's own predictions."""

import json
import math
import os

import numpy as np
import pytest

from helpers import REPO, load_script

BENCH = os.path.join(REPO, "bench")


def _script(name):
    return load_script(os.path.join("analyses", name + ".py"))


diagnose = _script("diagnose_inference_mode")


@pytest.mark.slow
def test_every_statistics_row_is_reported(tiny_run, capsys):
    diagnose.main(["--run", tiny_run["run"], "--batches", "2", "--draws", "1",
                   "--epoch-order", "0"])
    lines = capsys.readouterr().out.splitlines()
    rows = {}
    for line in lines[2:]:
        label, values = line[:18].strip(), line[18:].split("(")[0].split()
        rows[label] = [float(v) for v in values]
    assert list(rows) == ["saved", "epoch 0's first 2", "recompute 2 #1", "population 2 #1",
                          "recompute all 4", "population all 4", "batch stats"]
    columns = 2 + len(diagnose.COLUMNS)  # the loss, the loss with the ceiling, the MAEs
    assert all(len(v) == columns and all(math.isfinite(x) for x in v) for v in rows.values())
    # the saved statistics are training's; MTL-Baseline's linear disparity
    # head, clipped at twice its largest training label, changes no loss here
    assert all(v[0] == v[1] for v in rows.values())
    # the saved statistics give the validation loss training recorded
    config = json.load(open(os.path.join(tiny_run["run"], "config.json")))
    assert rows["saved"][0] == pytest.approx(config["best_val_loss"], rel=1e-3)


def test_fy_from_aspect_reports_the_runs_errors(tiny_run, capsys):
    import numpy as np

    from cpl_keras import runs
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import targets_from_labels
    from cpl_keras.models.inference import predict_images

    _script("fy_from_aspect").main(["--data", tiny_run["data"], "--split-of", tiny_run["run"],
                                    "--runs", tiny_run["run"]])
    line = capsys.readouterr().out.splitlines()[1]
    run = runs.load_run(tiny_run["run"])
    test = run.split["test"]
    with StereoFile(tiny_run["data"]) as f:
        truth = targets_from_labels(f.labels)
        out = predict_images(runs.load_model(run), *f.read_pairs(test))
    fy = np.median(np.abs(out["fy"] - truth["fy"][test]) / truth["fy"][test])
    assert f"fy {fy:.3f}," in line


@pytest.mark.parametrize("script", ["diagnose_heads.py", "bench_batchnorm.py"])
def test_a_missing_data_file_is_one_line_and_exit_2(script, tmp_path):
    """The documented bench commands on a fresh clone (no data/ yet): one
    line that names the file, exit status 2 (``cli.run``), not a traceback."""
    import subprocess
    import sys

    missing = tmp_path / "cvgl-8000-112px-v2.1.h5"
    done = subprocess.run([sys.executable, os.path.join(BENCH, script), "--data", str(missing)],
                          env=dict(os.environ, KERAS_BACKEND="jax"), text=True,
                          capture_output=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"bench/{script}: error: dataset not found: {missing}"], done.stderr


@pytest.mark.parametrize("script, args, message", [
    ("bench_generate.py", ["--pairs", "0"], "argument --pairs: must be a positive integer, got 0"),
    ("bench_train.py", ["--steps", "-1"], "argument --steps: must be a positive integer, got -1"),
    ("calibrate_held_out.py", ["--runs-dir", "{tmp}/none"], "--runs-dir is not a directory: "
     "{tmp}/none"),
    ("calibrate_held_out.py", ["--runs-dir", "{tmp}"],
     "no without-<rig> run (chessboard, middlebury, oakd) in {tmp}"),
])
def test_bench_commands_refuse_bad_arguments_in_one_line(script, args, message, tmp_path):
    """A count that is not positive, or a folder of held-out runs that is
    missing or holds none: one line, exit status 2, no traceback and no
    empty table, nothing written to --out."""
    import subprocess
    import sys

    out = tmp_path / "out"
    args = [a.format(tmp=tmp_path) for a in args]
    if script == "calibrate_held_out.py":
        args += ["--out", str(out)]
    done = subprocess.run([sys.executable, os.path.join(BENCH, script), *args],
                          env=dict(os.environ, KERAS_BACKEND="jax", PYTHONPATH=REPO), text=True,
                          capture_output=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"bench/{script}: error: " + message.format(tmp=tmp_path)], done.stderr
    assert done.stdout == "" and not out.exists()


@pytest.mark.parametrize("jobs,message", [
    (None, "no jobs file {jobs}"),
    ("cvgl_baseline-s2 --variant baseline\n", "{jobs}: no line 'data PROTOCOL PAIRS SEED'"),
    ("data cvgl 2000\nrun --variant baseline\n", "{jobs}: no line 'data PROTOCOL PAIRS SEED'"),
    ("# only a comment\ndata cvgl 2000 0\n", "{jobs}: no run (a line 'NAME train.py arguments')"),
])
def test_gpu_train_refuses_a_bad_jobs_file_in_one_line(tmp_path, jobs, message):
    """bench/gpu_train.sh: a missing or incomplete jobs file is one line and
    exit status 2, before anything is written to OUT."""
    import subprocess

    path = tmp_path / "jobs.txt"
    if jobs is not None:
        path.write_text(jobs)
    out = tmp_path / "out"
    done = subprocess.run(["bash", os.path.join(BENCH, "gpu_train.sh"), str(out), str(path)],
                          text=True, capture_output=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == ["gpu_train: " + message.format(jobs=path)]
    assert not out.exists()


def test_disparity_depth_is_eq_4a_with_fx_and_b_at_their_truth(capsys):
    import numpy as np

    script = _script("disparity_depth")
    ones = np.ones(4)
    raw = {"truth": {"fx": 100 * ones, "baseline": ones, "disparity": 10 * ones},
           "pred": {"fx": 50 * ones, "baseline": 3 * ones,  # (not used: at their truth)
                    "disparity": np.array([20.0, 20.0, 10.0, 5.0])}}
    # depths 10 m; implied 5, 5, 10, 20 m: errors 5, 5, 0, 10 m
    d, depth, median = script.disparity_and_depth(raw["truth"], raw["pred"])
    assert (d, depth, median) == (pytest.approx(6.25 / 10), pytest.approx(5.0 / 10), 0.5)

    # the committed compact-2000 folder: each network row, seeds 0-2, once
    rows = script.folder_rows(os.path.join(REPO, "paper_results", "compact-2000"))
    assert list(rows) == ["table1_cvgl"]
    assert {v: sorted(s for s, _ in r) for v, r in rows["table1_cvgl"].items()} == \
        {v: [0, 1, 2] for v in script.VARIANTS}
    assert script.main(["--folders", os.path.join(REPO, "paper_results", "compact-2000")]) == 0
    out = capsys.readouterr().out
    assert out.count("| mean |") == 3 and "| cpl-a | 2 | " in out

    from cpl_keras.evaluation import EvaluationError
    with pytest.raises(EvaluationError, match="no Table 1 network rows"):
        script.folder_rows(os.path.join(REPO, "paper_results", "notes"))


def test_monitor_steadiness_reads_the_swings_and_the_shared_training(tmp_path, capsys):
    script = _script("monitor_steadiness")
    val = np.array([4.0, 2.0, 3.0, 1.5, 1.5])
    assert script.steadiness(val, 2) == (pytest.approx(0.5), pytest.approx(0.5), 1)
    losses = [np.array([3.0, 2.0, 1.0]), np.array([3.0, 2.0, 1.5, 1.0])]
    assert script.same_training(losses) == 2
    assert script.same_training([losses[0], losses[0][:2]]) == 2
    for name, rows in (("a", val), ("b", val / 2)):
        with open(tmp_path / f"{name}.csv", "w") as f:
            f.write("epoch,loss,val_nmae\n" + "".join(
                f"{k + 1},{10 - k},{v}\n" for k, v in enumerate(rows)))
    assert script.main(["--from-epoch", "2", str(tmp_path / "a.csv"),
                        str(tmp_path / "b.csv")]) == 0
    out = capsys.readouterr().out
    assert "| 5 | 4 (1.500) | 50.0% | 50.0% | 1 of 3 |" in out
    assert "| 5 | 4 (0.750) |" in out and "equal over the first 5 epochs" in out
    (tmp_path / "c.csv").write_text("epoch,loss\n1,2\n")
    from cpl_keras.evaluation import EvaluationError
    with pytest.raises(EvaluationError, match="no val_nmae column"):
        script.read(str(tmp_path / "c.csv"))


def _nmae_log(path, rows):
    """A log.csv of train.py's nmae monitor: ``rows``, the ten validation
    NMAEs of each epoch (their sum the monitor). Returns its path."""
    from cpl_keras.camera import PARAMETERS

    header = "epoch,loss,val_nmae," + ",".join(f"val_nmae_{p}" for p in PARAMETERS)
    path.write_text(header + "\n" + "".join(
        f"{epoch},1.0,{sum(nmae)},{','.join(map(str, nmae))}\n"
        for epoch, nmae in enumerate(rows, 1)))
    return str(path)


def test_equal_epochs_compares_two_runs_column_by_column(tmp_path, capsys):
    from cpl_keras.evaluation import EvaluationError

    script = _script("equal_epochs")

    def log(name, rows):
        return _nmae_log(tmp_path / f"{name}.csv", rows)

    # A: lower on fx..v0 at every epoch, far higher on the disparity; B
    # runs longer and its monitor falls below A's from epoch 2 on.
    a = log("a", [[0.1] * 4 + [0.2, 0.9, 0.2, 0.2, 0.2, 0.2],
                  [0.1] * 4 + [0.2, 1.5, 0.2, 0.2, 0.2, 0.2]])
    b = log("b", [[0.2] * 4 + [0.2, 0.5, 0.2, 0.2, 0.2, 0.2],
                  [0.2] * 4 + [0.1, 0.4, 0.1, 0.1, 0.1, 0.1],
                  [0.2] * 4 + [0.1, 0.3, 0.1, 0.1, 0.1, 0.1]])
    assert script.main([a, b]) == 0
    out = capsys.readouterr().out
    assert "2 epochs, kept 1 (val_nmae 2.300)" in out
    assert "3 epochs, kept 3 (val_nmae 1.600)" in out
    assert "| 1 | A | 2.300 |" in out and "| 4 (fx, fy, u0, v0) |" in out
    assert "| 1 | B | 2.300 |" in out and "| 1 (disparity) |" in out
    assert "| 2 | B | 1.700 |" in out and "| 6 (baseline, disparity, tx, ty, tz, pitch) |" in out
    assert "| 3 |" not in out  # B's epoch 3: A never ran it
    assert "A's val_nmae is lower at 0." in out  # 2.3 against 2.3, 2.9 against 1.7
    (tmp_path / "c.csv").write_text("epoch,loss,val_nmae\n1,2,3\n")
    with pytest.raises(EvaluationError, match="no per-parameter val_nmae columns"):
        script.validation(str(tmp_path / "c.csv"))


def test_equal_epochs_writes_its_page_and_regenerates_it(tmp_path, capsys):
    """--out: the page is the title, the command in a code block and what it
    printed; --pair: a section per pair under its heading, each with its own
    command. ``regenerate`` rebuilds both from the logs their first line names."""
    from cpl_keras import files

    script = _script("equal_epochs")
    a = _nmae_log(tmp_path / "a.csv", [[0.1] * 10, [0.05] * 10])
    b = _nmae_log(tmp_path / "b.csv", [[0.2] * 10, [0.01] * 10, [0.01] * 10])
    page = tmp_path / "pages" / "equal.md"
    page.parent.mkdir()
    assert script.main([a, b, "--epochs", "1", "2", "--title", "A's and B's, seed 0",
                        "--out", str(page)]) == 0
    printed = capsys.readouterr().out
    text = page.read_text()
    command = files.generated_command(text)
    assert command.startswith("python analyses/equal_epochs.py ") and "--out " in command
    head = text.split("\n\n```\n", 1)[0]
    assert head.endswith("\n\n# A's and B's, seed 0")
    block, report = text.split("\n```\n\n", 1)
    assert block.endswith("b.csv --epochs 1 2") and "--title" not in block.split("```")[-1]
    assert printed == report + f"wrote {os.path.relpath(page, REPO)}\n"
    assert "A: " in report and "A's val_nmae is lower at 1 (1)." in report
    assert script.regenerate(str(page)) == text

    # Two pairs under their headings, an introduction under the title.
    assert script.main(["--pair", "Seed 0", a, b, "--pair", "Seed 1", b, a, "--title", "Both",
                        "--intro", "Two seeds.", "--out", str(page)]) == 0
    text = page.read_text()
    assert text.split("\n", 2)[2].startswith("# Both\n\nTwo seeds.\n\n## Seed 0\n\n```\n")
    assert text.count("\n```\npython analyses/equal_epochs.py ") == 2
    assert "\n\n## Seed 1\n\n```\n" in text
    assert "lower at 1 (1).\n\n## Seed 1" in text and text.endswith("lower at 1 (2).\n")
    assert script.regenerate(str(page)) == text
    for bad in (["--title", "T", a, b], [a, b, "--out", str(page)], [a],
                ["--pair", "S", a, b, a, b, "--title", "T", "--out", str(page)]):
        with pytest.raises(SystemExit):
            script.parse_args(bad)
