"""The one-command reproduction pipeline: its quick mode (as CI runs it), the
published predictions and the tables rebuilt from them alone, the presets,
and the checks of its arguments."""

import contextlib
import dataclasses
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cpl_keras import reproduce
from cpl_keras.commands import reproduce as reproduce_command
from cpl_keras.camera import TARGETS
# (REPO: the repository root; no result may name it)
from helpers import QUICK_PAIRS, QUICK_SIZE, REPO, quick_reproduction_args, set_writable, writable_copy


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "cpl_keras.reproduce", *args],
                          capture_output=True, text=True, cwd=cwd, timeout=600)


def rebuild(directory):
    return subprocess.run([sys.executable, "-m", "cpl_keras.reproduce", "--from-predictions",
                           str(directory)], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def quick(early):
    """One quick reproduction, shared by the tests of this module (read only:
    ``lent_to`` the two tests that need it writable). It starts as soon as the
    tests are collected (conftest's ``early``)."""
    folder, result = early("quick")
    assert result.returncode == 0, result.stderr[-3000:]
    root = Path(folder)
    return {"root": root, "out": root / "out", "data": root / "data", "runs": root / "runs",
            "args": quick_reproduction_args(folder)}


@contextlib.contextmanager
def lent_to(quick):
    """The shared reproduction writable for the block, read only again after
    it: for the test that runs its command again in place (a copy would name
    other data than its runs were trained on) and the one that moves its
    datasets and runs away (no copy would show that they are not read)."""
    set_writable(quick["root"], True)
    try:
        yield
    finally:
        set_writable(quick["root"], False)


def _contents(directory):
    """{relative path: bytes} of every file under ``directory``."""
    found = {}
    for folder, _, names in os.walk(directory):
        for name in names:
            path = os.path.join(folder, name)
            with open(path, "rb") as f:
                found[os.path.relpath(path, directory)] = f.read()
    return found


@pytest.mark.slow
def test_quick_reproduction_end_to_end(quick):
    out, tmp_path = quick["out"], quick["root"]
    report = (out / "REPORT.md").read_text()
    for heading in ("Table 1, paper protocol", "Table 1, unseen rigs", "Table 2, real rigs",
                    "Rig: chessboard (not rectified)", "Rig: middlebury (rectified)",
                    "Rig: oakd (rectified)",
                    "Training runs", "MTL-CPL-A (as released)", "Geometric"):
        assert heading in report
    for stem in ("table1_cvgl", "table1_random", "table2"):
        table = json.loads((out / f"{stem}.json").read_text())
        assert {"Average", "Deep-Homo", "MTL-CPL-U", "MTL-Baseline", "MTL-CPL-A"} <= set(table["rows"])
        assert (out / f"{stem}_fov.png").read_bytes()[:4] == b"\x89PNG"
    # Table 2 on every real rig that needs no download, per rig and pooled
    table2 = json.loads((out / "table2.json").read_text())
    assert set(table2["rigs"]) == {"chessboard", "middlebury", "oakd"}
    assert table2["num_pairs"] == sum(r["num_pairs"] for r in table2["rigs"].values())
    assert (out / "table2_fov_scatter.png").read_bytes()[:4] == b"\x89PNG"
    cvgl = json.loads((out / "table1_cvgl.json").read_text())
    assert cvgl["rows"]["MTL-CPL-A (as released)"]["as_released"] is True
    summary = json.loads((out / "reproduce.json").read_text())
    assert len(summary["runs"]) == 9
    assert all(r["epochs_run"] == 1 and r["split"] in ("paper", "held-out-config") for r in summary["runs"])
    assert (out / "runs" / "random_cpl-a_log.csv").exists()
    # every row of every table published its predictions: 13 outputs per test pair
    assert len(summary["predictions"]) == 9 + 3 * 2 + 8 * 3   # runs, baselines, per real rig
    with np.load(out / "runs" / "cvgl_cpl-a_predictions.npz", allow_pickle=False) as f:
        assert list(f["outputs"]) == list(TARGETS) and f["pred"].dtype == np.float32
        assert f["pred"].shape == (cvgl["num_pairs"], 13) == f["truth"].shape
        assert str(f["row"]) == "MTL-CPL-A" and str(f["split"]) == "paper"
        assert str(f["subset"]) == "test" and str(f["dataset"]).startswith(
            f"cvgl_{QUICK_PAIRS}_32px")
        assert all(f[k].dtype != object for k in f.files)
    with np.load(out / "runs" / "cvgl_geometric_on_chessboard_predictions.npz",
                 allow_pickle=False) as f:
        assert str(f["table"]) == "table2" and str(f["rig"]) == "chessboard"
        assert f["failures"].shape == (len(f["indices"]), len(f["failure_flags"]))
    # no machine's absolute paths in the results (but in the command as typed):
    # paths are relative to out/
    command = summary["command"]
    for name in os.listdir(out):
        if name.endswith((".md", ".json", ".csv")):
            text = (out / name).read_text().replace(json.dumps(command)[1:-1], "")
            assert str(tmp_path) not in text.replace(command, ""), name
            assert REPO not in text, name
    assert (out / cvgl["runs"][0] / "config.json").exists()


@pytest.mark.slow
def test_quick_reproduction_reuses_every_stage(quick):
    """The same command again: datasets, runs and predictions are reused,
    and not a byte of the reproduction changes."""
    before = _contents(quick["root"])
    with lent_to(quick):  # (its datasets' folder must be writable)
        again = run(*quick["args"])
    assert again.returncode == 0 and "evaluating" not in again.stderr, again.stderr[-3000:]
    assert "published predictions up to date" in again.stderr
    assert _contents(quick["root"]) == before


@pytest.mark.slow
def test_published_runs_are_restored_not_trained_again(quick, tmp_path):
    """Each run was published the moment it ended (stored predictions, log,
    config and split; no weights). On a machine with the published results
    but no run directories (a later session), the same command restores
    every run from its record, trains none, and scores the same tables."""
    out = tmp_path / "out"
    writable_copy(quick["out"], out)
    records = sorted(p for p in (out / "runs").iterdir() if p.is_dir())
    assert len(records) == 9
    for record in records:
        assert json.loads((record / "config.json").read_text())["status"] == "finished"
        assert list((record / "predictions").glob("*.npz"))
        assert not (record / "model.keras").exists() and not (record / "backup").exists()
    # the cvgl runs also stored their outputs on every real set (Table 2):
    # its test split and the three real rigs
    assert len(list((out / "runs" / "cvgl_cpl-a" / "predictions").glob("*.npz"))) == 1 + 3
    data = writable_copy(quick["data"], tmp_path / "data")  # (where real sets are made)
    args = ["--quick", *QUICK_SIZE, "--out", str(out), "--data-dir", data, "--runs-dir", str(tmp_path / "runs")]
    before = _contents(out)
    result = run(*args)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "training " not in result.stderr
    assert result.stderr.count("restored from its published record") == 9
    # nothing new: the published record is left byte for byte (a rerun of a
    # documented preset once rewrote six of its tracked files)
    assert "the published record is up to date with its runs and data; nothing written" in \
        result.stderr
    assert _contents(out) == before
    for stem in ("table1_cvgl", "table1_random", "table2"):
        again = json.loads((out / f"{stem}.json").read_text())
        first = json.loads((quick["out"] / f"{stem}.json").read_text())
        assert set(again["rows"]) == set(first["rows"])
        for row in first["rows"]:
            assert again["rows"][row]["targets"] == first["rows"][row]["targets"], (stem, row)
    # a restored run has no weights: asking for its model says so in one line
    from cpl_keras import runs
    run_dir = tmp_path / "runs" / "cvgl" / "cpl-a"
    with pytest.raises(runs.RunError, match="no weights"):
        runs.load_model(runs.load_run(run_dir))


@pytest.mark.slow
def test_a_published_prediction_changed_by_hand_is_named_and_the_record_kept(
        quick, tmp_path, capsys):
    """A record rebuilt from its predictions (REPORT.md says so), then one
    predictions file edited by hand and another deleted: the same command
    names the edited file in one line (its arrays' sha256 is not the one in
    reproduce.json), computes its group again, writes the deleted file again
    as recorded and the edited one's arrays as computed beside the record
    (rerun/runs/); REPORT.md (its "rebuilt" paragraph kept), reproduce.json,
    the tables and the edited file are left byte for byte."""
    from cpl_keras import prediction_files
    from cpl_keras.reproduce import pipeline

    out = tmp_path / "out"
    writable_copy(quick["out"], out)
    data = writable_copy(quick["data"], tmp_path / "data")  # (where real sets are made)
    recorded = json.loads((out / "reproduce.json").read_text())["predictions_sha256"]
    assert sorted(recorded) == sorted(json.loads((out / "reproduce.json").read_text())[
        "predictions"]) and all(len(digest) == 64 for digest in recorded.values())
    pipeline.rebuild(str(out), pipeline.rebuild_command(str(out)))
    assert "rebuilt from the published predictions" in (out / "REPORT.md").read_text()
    edited = out / "runs" / "cvgl_cpl-a_predictions.npz"
    with np.load(edited, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    arrays["pred"][0, 0] += 1.0
    np.savez(edited, **arrays)
    deleted = out / "runs" / "cvgl_average_predictions.npz"
    deleted.unlink()
    before = _contents(out)
    capsys.readouterr()
    assert reproduce_command.main(["--quick", *QUICK_SIZE, "--out", str(out), "--data-dir", data,
                                   "--runs-dir", str(tmp_path / "runs")]) == 0
    err = capsys.readouterr().err
    named = [line for line in err.splitlines() if "changed since reproduce.json" in line]
    assert named == ["[reproduce] runs/cvgl_cpl-a_predictions.npz: changed since "
                     "reproduce.json recorded it (its arrays' sha256 differs from the recorded "
                     "one); table1_cvgl computed again"], err[-3000:]
    assert "cvgl_cpl-a_predictions.npz: 1 of " in err and "(by up to 1) from the published" in err
    assert "the published record left as it is; 1 predictions file it lacked written again " \
        "as recorded; 1 computed again differs from it: beside it in" in err, err[-3000:]
    after = _contents(out)
    after.pop("runs/cvgl_average_predictions.npz")
    assert prediction_files.checksum(deleted) == recorded["runs/cvgl_average_predictions.npz"]
    beside = after.pop("rerun/runs/cvgl_cpl-a_predictions.npz")
    assert after == before   # REPORT.md, reproduce.json, tables, the edited file: as they were
    with np.load(io.BytesIO(beside), allow_pickle=False) as f, \
            np.load(quick["out"] / "runs" / "cvgl_cpl-a_predictions.npz") as published:
        assert np.array_equal(f["pred"], published["pred"])


@pytest.mark.slow
def test_partial_tables_of_the_seeds_whose_runs_have_all_finished(quick, tmp_path):
    """--partial trains nothing: with one cvgl run not finished (its record
    gone), the cvgl table and Table 2 are left out, the random table is the
    full reproduction's, and REPORT.md names what was left out."""
    out = tmp_path / "out"
    writable_copy(quick["out"], out)
    shutil.rmtree(out / "runs" / "cvgl_cpl-u")
    args = ["--quick", *QUICK_SIZE, "--partial", "--out", str(out), "--data-dir",
            writable_copy(quick["data"], tmp_path / "data"), "--runs-dir", str(tmp_path / "runs")]
    result = run(*args)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "training " not in result.stderr
    partial = out / "partial"
    assert not (partial / "table1_cvgl.json").exists() and not (partial / "table2.json").exists()
    again = json.loads((partial / "table1_random.json").read_text())
    first = json.loads((quick["out"] / "table1_random.json").read_text())
    assert set(again["rows"]) == set(first["rows"])
    for row in first["rows"]:
        assert again["rows"][row]["targets"] == first["rows"][row]["targets"], row
    text = (partial / "REPORT.md").read_text()
    assert "**Partial**: the tables of the seeds whose runs have all finished (random: seed 0)" \
        in text and "left out: cvgl seed 0 (not finished: cpl-u)." in text
    # the full tables in OUT are the reproduction's, untouched
    assert (out / "table1_cvgl.json").read_bytes() == (quick["out"] / "table1_cvgl.json").read_bytes()


def test_complete_seeds_keeps_a_seed_only_with_all_its_runs():
    from cpl_keras.reproduce import pipeline
    config = reproduce.settings(preset="inception-2000-ema")
    trained = {"cvgl": {0: ["r/cpl-a-s0", "r/baseline-s0"], 1: ["r/cpl-a-s1", "r/baseline-s1"],
                        2: ["r/cpl-a-s2"]}}
    kept, left_out = pipeline.complete_seeds(config, trained, seed=0)
    assert kept == {"cvgl": {0: ["r/cpl-a-s0", "r/baseline-s0"],
                             1: ["r/cpl-a-s1", "r/baseline-s1"]}}
    assert left_out == ["cvgl seed 2 (not finished: baseline-s2)"]
    kept, left_out = pipeline.complete_seeds(config, {}, seed=0)
    assert kept == {} and len(left_out) == 3


def test_partial_goes_with_a_reproduction_that_trains():
    with pytest.raises(SystemExit):
        _parsed("--from-predictions", "x", "--partial")
    assert _parsed("--preset", "compact-2000-ema", "--partial").partial is True


@pytest.mark.slow
def test_tables_rebuilt_from_predictions_alone(quick, tmp_path):
    """Weights and datasets moved away, --from-predictions rebuilds every table
    and REPORT.md exactly as the reproduction made them."""
    original = _contents(quick["out"])
    copy = tmp_path / "results"
    writable_copy(quick["out"], copy)
    away = {quick["data"]: tmp_path / "data_away", quick["runs"]: tmp_path / "runs_away"}
    with lent_to(quick):
        for path, moved in away.items():
            shutil.move(str(path), str(moved))
        try:
            for name in list(original):
                if name.endswith((".md", ".csv", ".json", ".png")) and \
                        not name.startswith("runs") and name != "reproduce.json":
                    os.remove(copy / name)          # every table is written anew
            result = rebuild(copy)
        finally:
            for path, moved in away.items():
                shutil.move(str(moved), str(path))
    assert result.returncode == 0, result.stderr[-3000:]
    rebuilt = _contents(copy)
    assert set(rebuilt) == set(original)
    note = ("The tables and this page were rebuilt from the published predictions "
            "(`runs/*_predictions.npz`), without weights or datasets, by:\n\n```\n"
            f"python -m cpl_keras.reproduce --from-predictions {copy}\n```\n\n")
    report = rebuilt.pop("REPORT.md").decode()
    assert note in report and report.replace(note, "") == original.pop("REPORT.md").decode()
    for name, data in original.items():
        assert rebuilt[name] == data, name


@pytest.mark.slow
def test_rebuild_with_a_new_discussion(quick, tmp_path):
    """--from-predictions DIR --discussion FILE: the comparison with the paper,
    written after the tables were seen, replaces the stored one (REPORT.md and
    reproduce.json); the tables are untouched. A missing FILE: exit 2."""
    copy = tmp_path / "results"
    writable_copy(quick["out"], copy)
    tables = {k: v for k, v in _contents(copy).items() if k.startswith("table")}
    (tmp_path / "comparison.md").write_text("MTL-CPL-A beats MTL-Baseline on fx.\n")
    result = subprocess.run([sys.executable, "-m", "cpl_keras.reproduce", "--from-predictions",
                             str(copy), "--discussion", str(tmp_path / "comparison.md")],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    report = (copy / "REPORT.md").read_text()
    assert report.rstrip().endswith("## Comparison with the paper\n\nMTL-CPL-A beats "
                                    "MTL-Baseline on fx.")
    assert json.loads((copy / "reproduce.json").read_text())["discussion"].startswith("MTL-CPL-A")
    assert {k: v for k, v in _contents(copy).items() if k.startswith("table")} == tables
    assert rebuild(copy).returncode == 0                   # kept for later rebuilds
    assert (copy / "REPORT.md").read_text().rstrip().endswith("on fx.")
    before = _contents(copy)
    result = subprocess.run([sys.executable, "-m", "cpl_keras.reproduce", "--from-predictions",
                             str(copy), "--discussion", str(tmp_path / "missing.md")],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert "--discussion: file not found" in result.stderr and _contents(copy) == before


@pytest.mark.slow
def test_rebuild_refuses_bad_predictions(quick, tmp_path):
    """A corrupt or missing predictions file, or a folder that is not a
    reproduction's: one line, exit 2, nothing written."""
    copy = tmp_path / "results"
    writable_copy(quick["out"], copy)
    target = copy / "runs" / "cvgl_cpl-u_predictions.npz"
    data = target.read_bytes()
    for damage, expected in ((lambda: target.write_bytes(data[: len(data) // 2]),
                              "cvgl_cpl-u_predictions.npz: not a readable predictions file"),
                             (lambda: target.unlink(), "predictions file not found")):
        damage()
        before = _contents(copy)
        result = rebuild(copy)
        assert result.returncode == 2, result.stderr
        err = result.stderr.strip()
        assert err.startswith("python -m cpl_keras.reproduce: error: ") and "\n" not in err, err
        assert expected in err, err
        assert _contents(copy) == before                    # no partial output
    (tmp_path / "empty").mkdir()
    result = rebuild(tmp_path / "empty")
    assert result.returncode == 2 and "reproduce.json not found" in result.stderr
    assert os.listdir(tmp_path / "empty") == []


def test_reproduce_bad_arguments_exit_2(tmp_path):
    for args in (["--pairs", "0"], ["--table", "1"], ["--quick", "--preset", "cpu"],
                 ["--from-predictions", str(tmp_path), "--epochs", "3"]):
        result = run(*args, "--out", str(tmp_path / "out"), "--data-dir", str(tmp_path / "d"))
        assert result.returncode == 2, args
        assert result.stderr.startswith("python -m cpl_keras.reproduce: error: ") and \
            result.stderr.count("\n") == 1, result.stderr
    result = run("--pairs", "0", "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    assert result.stderr == ("python -m cpl_keras.reproduce: error: argument --pairs: must be "
                             "a positive integer, got 0\n")
    # evaluate.py --reproduce is no second way in: one line naming the command
    # with the same arguments, exit 2, nothing made
    out = tmp_path / "out"
    result = subprocess.run([sys.executable, "evaluate.py", "--reproduce", "--quick", "--out",
                             str(out)], capture_output=True, text=True, cwd=REPO, timeout=600)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr == (f"evaluate.py: error: --reproduce moved: run cpl-reproduce --quick "
                             f"--out {out} (or python -m cpl_keras.reproduce --quick --out {out})"
                             f"\n")
    assert not out.exists()


#: Numeric flags of the reproduction, a bad value and what the line says.
BAD_NUMBERS = [
    ("--pairs", "0", "argument --pairs: must be a positive integer, got 0"),
    ("--random-pairs", "-5", "argument --random-pairs: must be a positive integer, got -5"),
    ("--epochs", "two", "argument --epochs: must be a positive integer, got 'two'"),
    ("--patience", "-1", "argument --patience: must be a non-negative integer, got -1"),
    ("--image-size", "0", "argument --image-size: must be a positive integer, got 0"),
    ("--image-size", "24", "image-size must be at least 75"),
    ("--crops", "0", "argument --crops: must be a positive integer, got 0"),
    ("--chessboard-crops", "0", "argument --chessboard-crops: must be a positive integer"),
    ("--seeds", "0", "argument --seeds: must be a positive integer, got 0"),
    ("--random-seeds", "1.5", "argument --random-seeds: must be a positive integer, got '1.5'"),
    ("--workers", "0", "argument --workers: must be a positive integer, got 0"),
    ("--seed", "-1", "argument --seed: must be a non-negative integer, got -1"),
    ("--geometric-max", "0", "argument --geometric-max: must be a positive integer, got 0"),
    ("--run-budget", "inf", "argument --run-budget: must be a positive number, got inf"),
]


def test_gpu_sized_settings_refused_on_a_cpu(tmp_path, capsys):
    """The paper's scale and paper-gpu on a machine whose JAX sees no GPU:
    one line with their cost and the flag that goes on anyway, exit 2,
    nothing made; the same settings at a CPU's size pass."""
    if reproduce.has_accelerator():
        pytest.skip("this machine has a GPU")
    folders = ["--out", str(tmp_path / "out"), "--data-dir", str(tmp_path / "data"),
               "--runs-dir", str(tmp_path / "runs")]
    for argv in ([], ["--preset", "paper-gpu"], ["--preset", "cpu", "--backbone", "inception_v3",
                                                  "--pairs", "10000"]):
        with pytest.raises(SystemExit) as exit_info:
            _parsed(*argv, *folders)
        assert exit_info.value.code == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "sized for a GPU" in err and "--allow-cpu" in err, err
        assert "JAX sees no GPU" in err and " h on this CPU" in err, err
    assert "2 runs" in reproduce.cpu_cost(reproduce.settings(preset="paper-gpu"))
    for argv in (["--preset", "paper-gpu", "--allow-cpu"], ["--preset", "paper-gpu",
                                                           "--pairs", "9999"]):
        assert _parsed(*argv, *folders).config.pairs
    assert os.listdir(tmp_path) == []


def test_reproduce_numbers_checked_when_parsed(tmp_path, capsys):
    """Every numeric flag of the reproduction is checked by the parser:
    one line naming it, exit 2, before any folder is made."""
    folders = ["--out", str(tmp_path / "out"), "--data-dir", str(tmp_path / "data"),
               "--runs-dir", str(tmp_path / "runs")]
    for flag, value, message in BAD_NUMBERS:
        with pytest.raises(SystemExit) as exit_info:
            _parsed(flag, value, *folders)
        assert exit_info.value.code == 2, flag
        err = capsys.readouterr().err
        assert err.startswith(f"{reproduce.PROG}: error: ") and err.count("\n") == 1, err
        assert message in err, (flag, err)
    # the same through the command line, in a fresh process
    for flag, value, message in (BAD_NUMBERS[2], BAD_NUMBERS[5], BAD_NUMBERS[10]):
        result = run(flag, value, *folders)
        assert result.returncode == 2 and result.stdout == ""
        assert result.stderr.startswith(f"{reproduce.PROG}: error: ") and message in result.stderr
        assert result.stderr.count("\n") == 1, result.stderr
    assert os.listdir(tmp_path) == []


def _parsed(*argv):
    return reproduce_command.parse_args(list(argv))


def test_a_preset_is_a_frozen_checked_record():
    import dataclasses

    cpu = reproduce.PRESETS["cpu"]
    assert isinstance(cpu, reproduce.Preset) and cpu.pairs == 1000
    with pytest.raises(dataclasses.FrozenInstanceError):
        cpu.pairs = 5
    # every check runs when a preset is made or changed, with the same one line
    with pytest.raises(ValueError, match="pairs must be positive, got 0"):
        dataclasses.replace(cpu, pairs=0)
    with pytest.raises(ValueError, match="unknown backbone 'resnet'"):
        dataclasses.replace(cpu, backbone="resnet")
    with pytest.raises(ValueError, match="image-size must be at least 32"):
        dataclasses.replace(cpu, image_size=16)
    with pytest.raises(ValueError, match="unknown setting 'pear'"):
        reproduce.settings(preset="cpu", pear=3)
    # lists given as settings become tuples; the JSON form has every field, in order
    config = reproduce.settings(preset="cpu", variants=["baseline", "cpl-a", "cpl-u"])
    assert config.variants == ("baseline", "cpl-a", "cpl-u") and config.preset == "cpu"
    assert list(config.to_dict()) == [f.name for f in dataclasses.fields(reproduce.Preset)] + [
        "preset", "quick"]
    assert reproduce.Settings.from_dict(config.to_dict()) == config
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.pairs = 5
    with pytest.raises(ValueError, match="quick must be True with preset 'quick'"):
        dataclasses.replace(reproduce.settings(quick=True), quick=False)
    # an older reproduce.json: the settings added since take their defaults
    old = {k: v for k, v in config.to_dict().items() if k not in ("real_sets", "monitor")}
    assert reproduce.Settings.from_dict(old) == dataclasses.replace(
        config, real_sets=reproduce.REAL_SETS, monitor=None)
    # ... except the averaged weights: every summary written before them
    # describes runs trained without them
    quick = reproduce.settings(quick=True)
    assert quick.weight_ema is None
    assert reproduce.Settings.from_dict({k: v for k, v in quick.to_dict().items()
                                         if k != "weight_ema"}).weight_ema == 0.0
    with pytest.raises(ValueError, match="moving-average momentum must be in"):
        dataclasses.replace(quick, weight_ema=1.0)
    with pytest.raises(ValueError, match="unknown setting 'pear'"):
        reproduce.Settings.from_dict(dict(old, pear=3))
    with pytest.raises(ValueError, match="setting 'pairs' missing"):
        reproduce.Settings.from_dict({k: v for k, v in old.items() if k != "pairs"})


def test_presets_resolve():
    cpu = _parsed("--preset", "cpu").config
    assert cpu.backbone == "small_resnet" and cpu.image_size == 112
    assert cpu.variants == ("deep-homo", "cpl-u", "baseline", "cpl-a") and cpu.released
    assert cpu.seeded_variants == ("cpl-u", "baseline", "cpl-a")
    assert (cpu.pairs, cpu.random_pairs, cpu.epochs, cpu.patience) == (1000, 1000, 60, 5)
    assert (cpu.seeds, cpu.random_seeds, cpu.geometric_max) == (3, 1, 200)
    # every row of both tables: the MTL variants on every cvgl seed (split and
    # initial weights), Deep-Homo and MTL-CPL-A as released once, on seed 0
    jobs = reproduce.run_jobs(cpu, seed=0)
    assert len(jobs) == 15
    cvgl = [(j.seed, j.variant, j.released, j.name) for j in jobs if j.key == "cvgl"]
    assert cvgl == [(0, "deep-homo", False, "deep-homo-s0"), (0, "cpl-u", False, "cpl-u-s0"),
                    (0, "baseline", False, "baseline-s0"), (0, "cpl-a", False, "cpl-a-s0"),
                    (0, "cpl-a", True, "cpl-a-released-s0")] + [
        (s, v, False, f"{v}-s{s}") for s in (1, 2) for v in ("cpl-u", "baseline", "cpl-a")]
    assert all((j.protocol, j.split) == ("cvgl", "paper") for j in jobs if j.key == "cvgl")
    assert [(j.seed, j.variant, j.released, j.name) for j in jobs if j.key == "random"] == [
        (0, v, False, v) for v in ("deep-homo", "cpl-u", "baseline", "cpl-a")]
    assert all((j.protocol, j.split) == ("random", "held-out-config") for j in jobs
               if j.key == "random")
    # --seed S shifts every run seed; more random seeds: the MTL variants on each
    shifted = reproduce.run_jobs(reproduce.settings(preset="cpu", random_seeds=2), seed=5)
    assert [j.name for j in shifted if j.key == "random"] == [
        "deep-homo-s5", "cpl-u-s5", "baseline-s5", "cpl-a-s5", "cpl-u-s6", "baseline-s6",
        "cpl-a-s6"]
    assert {j.seed for j in shifted if j.key == "cvgl"} == {5, 6, 7}
    # the decision preset: the MTL variants on 8,000 cvgl pairs, 3 seeds, both splits
    decide = _parsed("--preset", "cpu-8000").config
    assert (decide.pairs, decide.seeds, decide.backbone) == (8000, 3, "small_resnet")
    assert decide.tables == ("cvgl", "cvgl_drive") and not decide.released
    assert decide.geometric_max is None                 # every baseline on every test pair
    jobs = reproduce.run_jobs(decide, seed=0)
    assert len(jobs) == 18
    assert {(j.key, j.split) for j in jobs} == {("cvgl", "paper"), ("cvgl_drive", "drive")}
    assert {j.protocol for j in jobs} == {"cvgl"}          # one dataset for both tables
    # the deciding pair on every seed before MTL-CPL-U, in each table
    assert [j.name for j in jobs if j.key == "cvgl_drive"] == [
        f"{v}-s{s}" for s in (0, 1, 2) for v in ("cpl-a", "baseline")] + [
        f"cpl-u-s{s}" for s in (0, 1, 2)]
    assert [j.name for j in jobs if j.key == "cvgl"][:6] == [
        "cpl-a-s0", "baseline-s0", "cpl-a-s1", "baseline-s1", "cpl-a-s2", "baseline-s2"]
    with pytest.raises(ValueError, match="first variant 'baseline' is not trained"):
        reproduce.settings(preset="cpu-8000", variants=("cpl-a", "cpl-u"))
    assert "Seeds per table: cvgl 3, cvgl_drive 3" in reproduce.scale_text(decide)
    with pytest.raises(ValueError, match="unknown table 'kitti'"):
        reproduce.settings(preset="cpu", tables=("cvgl", "kitti"))
    with pytest.raises(ValueError, match="seeded variant 'baseline' is not trained"):
        reproduce.settings(preset="cpu", variants=("deep-homo", "cpl-u", "cpl-a"))
    # the report says which rows are of one seed
    assert "on the first seed only: Deep-Homo, MTL-CPL-A (as released)" in \
        reproduce.scale_text(cpu)
    # the paper's scale: every row, into paper_results/paper/ (no preset: paper_results/)
    paper = _parsed("--preset", "paper", "--allow-cpu")
    config = paper.config
    assert (config.pairs, config.random_pairs, config.epochs) == (123017, 123017, 200)
    assert config.backbone == "inception_v3" and config.run_budget_s is None
    assert config.variants == ("deep-homo", "cpl-u", "baseline", "cpl-a") and config.released
    assert config.geometric_max is None and config.seeds == 1
    assert config.seeded_variants is None                     # everything on every seed
    assert [j.name for j in reproduce.run_jobs(config, 0)] == [
        "deep-homo", "cpl-u", "baseline", "cpl-a", "cpl-a-released"] + [
        "deep-homo", "cpl-u", "baseline", "cpl-a"]
    assert paper.out.endswith(os.path.join("paper_results", "paper"))
    default = _parsed("--allow-cpu")
    assert os.path.basename(default.out) == "paper_results" and default.discussion
    assert default.config.preset is None
    assert dataclasses.replace(default.config, preset="paper") == config
    # ten minutes of one GPU: the deciding pair first, each run under a time budget
    gpu = _parsed("--preset", "paper-gpu", "--allow-cpu")
    config = gpu.config
    assert config.backbone == "inception_v3" and config.image_size == 112
    assert config.run_budget_s == 150 and config.tables == ("cvgl",)
    assert [j.name for j in reproduce.run_jobs(config, 0)] == ["cpl-a", "baseline"]
    assert all(j.split == "paper" for j in reproduce.run_jobs(config, 0))
    assert gpu.out.endswith(os.path.join("paper_results", "paper-gpu"))
    assert gpu.runs_dir == os.path.join("runs", "reproduce-paper-gpu")
    assert "a budget of 150 s of training per run" in reproduce.scale_text(config)
    assert _parsed("--preset", "paper-gpu", "--allow-cpu",
                   "--run-budget", "2.5").config.run_budget_s == 2.5
    # the disparity head's ceiling: training's default, except cpu-8000, whose
    # first runs were made before it (all its runs keep one setting)
    from cpl_keras.reproduce.jobs import training_arguments

    job = reproduce.Job("cvgl", "cvgl", "paper", 0, "cpl-a", False, "cpl-a")
    assert config.disparity_ceiling == "auto"
    cpu_8000 = reproduce.settings(preset="cpu-8000")
    assert cpu_8000.disparity_ceiling is None
    assert training_arguments(cpu_8000, "r", job)[
        "disparity_ceiling"] is None
    assert training_arguments(config, "r", job)[
        "disparity_ceiling"] == "auto"
    # the averaged weights: training's default, except the presets whose
    # published runs were trained without them
    for name in ("cpu", "cpu-8000", "compact-2000", "inception-2000"):
        assert training_arguments(reproduce.settings(preset=name), "r", job)["weight_ema"] == 0.0
    for name in ("inception-2000-ema", "compact-2000-ema", "paper", "paper-gpu"):
        assert training_arguments(reproduce.settings(preset=name), "r", job)["weight_ema"] is None
    before = {k: v for k, v in config.to_dict().items() if k != "disparity_ceiling"}
    assert training_arguments(reproduce.Settings.from_dict(before), "r", job)[
        "disparity_ceiling"] == "auto"
    with pytest.raises(ValueError, match="disparity.ceiling"):
        dataclasses.replace(reproduce.PRESETS["cpu"], disparity_ceiling="high")
    # explicit flags override the preset's values
    mine = _parsed("--preset", "cpu", "--epochs", "7", "--seeds", "2", "--out", "x").config
    assert (mine.epochs, mine.seeds, mine.pairs) == (7, 2, 1000)
    # the paper's recipe at --quick's values is --quick's pipeline (what CI runs)
    quick = reproduce.settings(quick=True)
    scaled = reproduce.settings(preset="paper", **{
        k: getattr(quick, k) for k in ("pairs", "random_pairs", "epochs", "image_size",
                                       "backbone", "crops", "chessboard_crops",
                                       "geometric_max")}, workers=1)
    assert reproduce.run_jobs(scaled, 0) == reproduce.run_jobs(quick, 0)
    assert dataclasses.replace(scaled, preset="quick", quick=True, workers=None) == quick


def _tiny_plan(run_dir, seed=0, variant="baseline"):
    return dict(variant=variant, run_dir=str(run_dir), epochs=1, batch_size=8, backbone="small",
                split="paper", as_released=False, seed=seed, patience=5)


def test_two_runs_of_one_model_do_not_compile_side_by_side():
    """The next job is the first whose model no running process is compiling
    (so the later one loads its programs from the compile cache), else the
    first; the slow variants' order is otherwise kept."""
    from cpl_keras.training import parallel

    def job(variant, released=False):
        return (variant, "data.h5", dict(variant=variant, as_released=released,
                                         backbone="small", batch_size=16))

    queue = [job("deep-homo"), job("deep-homo"), job("cpl-u"), job("cpl-a"),
             job("cpl-a", released=True)]
    assert parallel.next_job(queue, set()) == 0
    running = {parallel.model_key(queue[0][2])}
    assert parallel.next_job(queue, running) == 2
    running.add(parallel.model_key(queue[2][2]))
    assert parallel.next_job(queue[3:], running) == 0
    assert parallel.next_job(queue[:2], running) == 0  # nothing else to run: the first
    assert parallel.model_key(queue[3][2]) != parallel.model_key(queue[4][2])


@pytest.mark.slow
def test_parallel_training_makes_the_same_runs(tiny_run, tmp_path):
    """``--jobs 2``: runs trained two at a time, each in a spawned process,
    end as the same run trained here; a run that fails stops the rest with
    one error naming its directory."""
    from cpl_keras import runs, training
    from cpl_keras.training import parallel

    data = tiny_run["data"]
    pending = [(f"cvgl/{name}", data, _tiny_plan(tmp_path / name, seed))
               for name, seed in (("a", 0), ("b", 1))]
    finished = []
    parallel.train_parallel(pending, 2, on_finished=lambda label, _: finished.append(label))
    assert sorted(finished) == ["cvgl/a", "cvgl/b"]
    for name in ("a", "b"):
        assert runs.read_run_config(str(tmp_path / name)).status == "finished"

    def val_loss(run_dir):
        return [row["val_loss"] for row in runs.read_log(str(run_dir))]

    # "a" has the shared tiny run's settings (trained in this process)
    here = val_loss(tiny_run["run"])
    np.testing.assert_allclose(val_loss(tmp_path / "a"), here, rtol=1e-5)
    assert not np.allclose(val_loss(tmp_path / "b"), here)  # another seed, another run

    missing = str(tmp_path / "missing.h5")
    bad = [("cvgl/bad", missing, _tiny_plan(tmp_path / "bad")),
           ("cvgl/c", data, _tiny_plan(tmp_path / "c"))]
    with pytest.raises(training.TrainingError, match="bad: training ended with exit status 2"):
        parallel.train_parallel(bad, 1)
    assert not (tmp_path / "c").exists()  # nothing started after the failure


def test_settings_without_real_sets_make_table_1_alone(tmp_path, monkeypatch):
    """inception-2000-ema has no real sets: stage 1 builds none and stage 3
    makes Table 1 only (a Table 2 group would need the runs' weights)."""
    from cpl_keras.reproduce import pipeline, record
    config = reproduce.settings(preset="inception-2000-ema")
    assert config.real_sets == () and config.tables == ("cvgl",)
    tiny = dataclasses.replace(config, pairs=4, workers=1)
    paths = pipeline.make_datasets(tiny, str(tmp_path), seed=0)
    assert paths["real"] == [] and os.path.exists(paths["cvgl"])
    assert sorted(os.listdir(tmp_path)) == [os.path.basename(paths["cvgl"])]
    groups = []
    monkeypatch.setattr(record, "_group_predictions",
                        lambda number, stem, *rest: groups.append((number, stem)) or [])
    trained = {"cvgl": {0: ["cpl-a-s0", "baseline-s0"], 1: ["cpl-a-s1", "baseline-s1"]}}
    pipeline.make_predictions(config, paths, trained, str(tmp_path))
    assert groups == [(1, "table1_cvgl"), (1, "table1_cvgl")]
    # with real sets the same runs make Table 2 on each seed as well
    pipeline.make_predictions(config, dict(paths, real=["x.h5"]), trained, str(tmp_path))
    assert groups[2:] == [(1, "table1_cvgl")] * 2 + [(2, "table2")] * 2


def test_a_rerun_over_a_published_record_writes_what_differs_beside_it(tmp_path, capsys):
    """In a published folder, predictions files whose arrays are unchanged
    are left byte for byte, a new one is added, and one whose arrays differ
    is written into rerun/ beside the folder's runs/, with one line saying
    how many values differ; the published file stays."""
    from cpl_keras import prediction_files

    folder = tmp_path / "out" / "runs"
    pred = np.arange(26, dtype=np.float32).reshape(2, 13)
    prediction_files.write_files(str(folder), {"a.npz": {"pred": pred, "key": np.array("k")},
                                               "b.npz": {"pred": pred, "key": np.array("k")}})
    before = _contents(folder)
    changed = pred.copy()
    changed[1, 3] += 0.5
    paths, wrote = prediction_files.write_group(str(folder), {
        "a.npz": {"pred": pred, "key": np.array("k")},
        "b.npz": {"pred": changed, "key": np.array("k")},
        "c.npz": {"pred": pred, "key": np.array("k")}}, published=True)
    assert paths == [str(folder / name) for name in ("a.npz", "b.npz", "c.npz")] and wrote
    after = _contents(folder)
    assert {name: after[name] for name in before} == before  # (a unchanged, b published kept)
    assert "c.npz" in after
    with np.load(tmp_path / "out" / "rerun" / "runs" / "b.npz") as f:
        assert np.array_equal(f["pred"], changed)
    err = capsys.readouterr().err
    assert "b.npz: 1 of 26 predicted values differ (by up to 0.5) from the published file" in err
    # made elsewhere (other relative paths) but the same predictions: nothing written
    _, wrote = prediction_files.write_group(str(folder), {
        "a.npz": {"pred": pred, "key": np.array("made elsewhere")}}, published=True)
    assert not wrote and _contents(folder)["a.npz"] == before["a.npz"]
    # outside a published record a changed file is written in place
    prediction_files.write_group(str(folder), {"b.npz": {"pred": changed, "key": np.array("k")}})
    with np.load(folder / "b.npz") as f:
        assert np.array_equal(f["pred"], changed)


@pytest.mark.slow
def test_rerunning_a_documented_preset_leaves_the_published_record_untouched(tmp_path):
    """``python -m cpl_keras.reproduce --preset inception-2000-ema`` over
    the committed folder, in a fresh clone: its runs restored from their
    records, nothing trained, nothing written into paper_results/ (it once
    rewrote six tracked files), ``git status`` empty."""
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "--quiet", "--shared", REPO, str(clone)], check=True,
                   capture_output=True, timeout=120)
    done = subprocess.run([sys.executable, "-m", "cpl_keras.reproduce", "--preset",
                           "inception-2000-ema", "--workers", "2"], cwd=clone,
                          capture_output=True, text=True, timeout=900,
                          env=dict(os.environ, KERAS_BACKEND="jax", PYTHONPATH=str(clone)))
    assert done.returncode == 0, done.stderr[-3000:]
    assert "training " not in done.stderr
    assert "nothing written" in done.stderr, done.stderr[-3000:]
    status = subprocess.run(["git", "status", "--porcelain"], cwd=clone, capture_output=True,
                            text=True, timeout=60).stdout
    assert status == "", status
